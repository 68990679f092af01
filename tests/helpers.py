"""What several test modules share: paths, trees to compare, random trees, the command line run in-process."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st
from strategies import boxes

import jaxbvh
from jaxbvh import cli
from jaxbvh.tree.frame import Frame

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"  # meshes, scenes, reference trees (../shared beside the clone)
NODES, PRIMS = 128, 64  # random_tree's one capacity: one compiled program for all its trees
CAPACITY = 64  # padded()'s primitive capacity

# canonical() recurses once per level; set at import, not inside a test, so hypothesis
# does not warn that the limit changed under it
sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))


def canonical(tree, with_axis: bool = True):
    """Tree as nested tuples from the root: node ids and prim order inside leaves ignored.

    Interior: ``(axis, left, right, lo, hi)``; leaf: ``("leaf", sorted prims, lo, hi)``.
    """
    t = jaxbvh.to_numpy(tree)

    def rec(n):
        box = (tuple(np.asarray(t.lo[n]).tolist()), tuple(np.asarray(t.hi[n]).tolist()))
        if t.prim_count[n] > 0:
            s, c = int(t.prim_start[n]), int(t.prim_count[n])
            return ("leaf", tuple(sorted(t.prim_index[s:s + c].tolist())), box)
        return (int(t.axis[n]) if with_axis else None, rec(int(t.left[n])), rec(int(t.right[n])), box)

    return rec(int(t.root))


def random_tree(seed: int, n: int, max_leaf: int = 1, kind: str = "random", *, dtype=np.float32,
                nodes: int = NODES, prims: int = PRIMS):
    """Binary tree over ``n`` random boxes by recursive random splits of a permutation (a
    poor tree, with much to gain), node ids shuffled so they say nothing about the
    structure, root not 0; padded to ``nodes`` / ``prims`` (one capacity: one compile).

    ``kind``: "random" boxes; "grid" (snapped to a coarse grid: duplicates, flat boxes,
    many exact ties, exact arithmetic); "point" (every box one point: all areas zero).
    Leaves hold up to ``max_leaf`` primitives. Returns ``(tree, prim_lo, prim_hi)``.
    """
    rng = np.random.default_rng(seed)
    if kind == "grid":
        lo = rng.integers(0, 3, (n, 3)).astype(dtype)
        hi = lo + rng.integers(0, 2, (n, 3)).astype(dtype)
    elif kind == "point":
        lo = hi = np.broadcast_to(rng.normal(size=3), (n, 3)).astype(dtype)
    elif kind == "random":
        lo = rng.uniform(-5, 5, (n, 3)).astype(dtype)
        hi = lo + rng.exponential(1.0, (n, 3)).astype(dtype)
    else:
        raise ValueError(f"kind must be random, grid or point, got {kind!r}")
    child, start, count, box_lo, box_hi, prim_index = [], [], [], [], [], []

    def make(ids):
        i = len(child)
        child.append([-1, -1]), start.append(0), count.append(0), box_lo.append(None), box_hi.append(None)
        if len(ids) == 1 or (len(ids) <= max_leaf and rng.random() < 0.5):
            start[i], count[i] = len(prim_index), len(ids)
            prim_index.extend(ids)
            box_lo[i], box_hi[i] = lo[ids].min(0), hi[ids].max(0)
        else:
            k = int(rng.integers(1, len(ids)))
            a, b = make(ids[:k]), make(ids[k:])
            child[i] = [a, b]
            box_lo[i], box_hi[i] = np.minimum(box_lo[a], box_lo[b]), np.maximum(box_hi[a], box_hi[b])
        return i

    make([int(p) for p in rng.permutation(n)])
    m = len(child)
    new = rng.permutation(m)
    old_child = np.array(child)
    ids = np.full((m, 2), -1, np.int32)
    for old in range(m):
        for side in range(2):
            c = old_child[old, side]
            ids[new[old], side] = new[c] if c >= 0 else -1
    inv = np.argsort(new)
    arrays = dict(child=ids, prim_start=np.array(start, np.int32)[inv],
                  prim_count=np.array(count, np.int32)[inv], prim_index=np.array(prim_index, np.int32),
                  lo=np.array(box_lo, dtype)[inv], hi=np.array(box_hi, dtype)[inv],
                  root=np.int32(new[0]))
    tree = jaxbvh.from_interchange(arrays, pad=False)
    return jaxbvh.tree.pad_to(tree, nodes, prims), lo, hi


# Random tree cases: (seed, n, max_leaf, kind) for random_tree
tree_cases = st.builds(lambda seed, n, leaf, grid: (seed, n, leaf, grid),
                  st.integers(0, 2**31), st.integers(2, 40), st.integers(1, 3),
                  st.sampled_from(["random", "grid"]))


def assert_same_tree(a, b, fields=("left", "right", "parent", "lo", "hi", "root")):
    a, b = jaxbvh.to_numpy(a), jaxbvh.to_numpy(b)
    for field in fields:
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)),
                                      err_msg=field)


def check_result(tree, result, prim_lo, prim_hi, ct=1.0):
    """Valid, leaves untouched, SAH as reported and never worse than the start."""
    jaxbvh.validate(result.tree, prim_lo, prim_hi)
    t, out = jaxbvh.to_numpy(tree), jaxbvh.to_numpy(result.tree)
    leaf = t.prim_count > 0
    for field in ("prim_start", "prim_count", "prim_index"):
        np.testing.assert_array_equal(getattr(out, field), getattr(t, field))
    np.testing.assert_array_equal(out.lo[leaf], t.lo[leaf])
    np.testing.assert_array_equal(out.hi[leaf], t.hi[leaf])
    assert out.left.shape == t.left.shape  # same capacity
    sah = float(jaxbvh.sah(jaxbvh.to_jax(out), ct))
    assert float(result.sah) == pytest.approx(sah, rel=1e-6)
    assert sah <= float(result.sah_start) * (1 + 1e-6)
    return sah


# Primitive boxes in the scene frame, padded to one capacity

def local_boxes(tri, dtype=np.float32):
    lo, hi = boxes(tri)
    frame = Frame.fit(lo, hi)
    return frame.to_local(lo).astype(dtype), frame.to_local(hi).astype(dtype)


def padded(lo, hi, cap=CAPACITY):
    n = lo.shape[0]
    lo_p = np.full((cap, 3), np.inf, lo.dtype)
    hi_p = np.full((cap, 3), -np.inf, hi.dtype)
    lo_p[:n], hi_p[:n] = lo, hi
    return lo_p, hi_p


# The command line, in-process

def run_cli(capsys, *argv):
    """``(exit status, stdout, stderr)`` of ``jaxbvh ARGV``."""
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def run_json(capsys, *argv, status: int = 0) -> dict:
    """The JSON result of ``jaxbvh ARGV --json``, which must exit with ``status``."""
    got, out, err = run_cli(capsys, *argv, "--json")
    assert got == status, err
    lines = out.strip().splitlines()
    assert len(lines) == 1, out  # one JSON object, nothing else on stdout
    return json.loads(lines[0])


def assert_one_line_error(status, out, err, *fragments):
    assert status == 2
    assert out == ""
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("jaxbvh: error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def grid_obj(path: Path, n: int = 3, seed: int = 0) -> Path:
    """A bumpy n x n grid of 2 n^2 triangles."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij")
    zs = rng.random(xs.shape)
    vertices = np.stack([xs, ys, zs], -1).reshape(-1, 3)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            faces += [(a, b, c), (a, c, d)]
    text = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist())
    text += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
    path.write_text(text)
    return path


def three_triangle_files(tmp_path):
    """An OBJ of three triangles and a valid world-space tree over them.

    Nodes: 0 root (1, 2); 1 interior (3, 4); leaves 2, 3, 4 hold triangles 2, 0, 1.
    Returns ``(mesh path, interchange arrays)``.
    """
    mesh = tmp_path / "three.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nv 4 0 0\nv 4 1 1\n"
                    "f 1 2 3\nf 2 4 5\nf 4 6 7\n")
    tri_lo = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], np.float32)
    tri_hi = np.array([[1, 1, 0], [2, 1, 0], [4, 1, 1]], np.float32)
    arrays = {
        "child": np.array([[1, 2], [3, 4], [-1, -1], [-1, -1], [-1, -1]], np.int32),
        "prim_start": np.array([0, 0, 0, 1, 2], np.int32),
        "prim_count": np.array([0, 0, 1, 1, 1], np.int32),
        "prim_index": np.array([2, 0, 1], np.int32),
        "lo": np.stack([tri_lo.min(0), tri_lo[:2].min(0), tri_lo[2], tri_lo[0], tri_lo[1]]),
        "hi": np.stack([tri_hi.max(0), tri_hi[:2].max(0), tri_hi[2], tri_hi[0], tri_hi[1]]),
        "root": np.int32(0),
    }
    return mesh, arrays


def broken_arrays(arrays, **changes):
    out = {k: np.array(v) for k, v in arrays.items()}
    for key, (index, value) in changes.items():
        out[key][index] = value
    return out


BROKEN = {
    "self-loop": dict(child=((0,), [0, 2])),           # the root lists itself as a child
    "cycle": dict(child=((1,), [3, 0])),               # node 1 lists the root
    "shared-child": dict(child=((1,), [3, 2])),        # leaf 2 under the root and under 1
    "nan-box": dict(lo=((0,), [np.nan, 0, 0])),        # NaN in the root box
}


def broken_tree_file(tmp_path, kind):
    mesh, arrays = three_triangle_files(tmp_path)
    path = tmp_path / f"{kind}.npz"
    np.savez(path, **broken_arrays(arrays, **BROKEN[kind]))
    return mesh, path
