"""What several test modules share: paths, the command line run in-process, optimizer
results checked; trees, strategies and assertions come from the public kit
(:mod:`jaxbvh.testing`), re-exported here under the names test modules import."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st

import jaxbvh
import jaxbvh.testing as kit
from jaxbvh import cli
from jaxbvh.testing import assert_costs_close, assert_valid_tree, random_tree  # noqa: F401
from jaxbvh.testing.strategies import boxes
from jaxbvh.tree.frame import Frame

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"  # meshes, scenes, reference trees (../shared beside the clone)
# XLA's flags for cheap compiles (conftest sets them for the suite): LLVM's optimizations
# off, and the older loop emitters for fusions instead of the MLIR fusion emitters
UNOPTIMIZED_XLA = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
NODES, PRIMS = 128, 64  # random_tree's one capacity: one compiled program for all its trees
CAPACITY = 64  # padded()'s primitive capacity

# canonical forms recurse once per level in some callers; set at import, not inside a
# test, so hypothesis does not warn that the limit changed under it
sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))

# Trees to compare: the kit's canonical form, here with the split axis unless asked not to
canonical = functools.partial(kit.canonical, with_axis=True)



def assert_same_tree(a, b, fields=("left", "right", "parent", "lo", "hi", "root")):
    """Exactly the same arrays ``fields`` (node ids included): an optimizer against its twin,
    which number nodes alike. Up to node numbering: :func:`jaxbvh.testing.assert_same_tree`."""
    a, b = jaxbvh.to_numpy(a), jaxbvh.to_numpy(b)
    for field in fields:
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)),
                                      err_msg=field)


def assert_same_costs(a, b, err_msg=""):
    """Costs (SAH figures, histories; NaN past the end) of the same trees from two different
    compiled programs, e.g. a vmapped batch against single runs: equal but for the last bits
    of a float sum, whose order each program may choose (with the suite's XLA flags the
    loop emitters sum a few figures in another order: 1-2 ulps in float32)."""
    a, b = np.asarray(a), np.asarray(b)
    eps = max(np.finfo(a.dtype).eps, np.finfo(b.dtype).eps)  # of the coarser one
    np.testing.assert_allclose(a, b, rtol=8 * eps, atol=0, equal_nan=True, err_msg=err_msg)


# Random tree cases: (seed, n, max_leaf, kind) for random_tree
tree_cases = st.builds(lambda seed, n, leaf, grid: (seed, n, leaf, grid),
                       st.integers(0, 2**31), st.integers(2, 40), st.integers(1, 3),
                       st.sampled_from(["random", "grid"]))


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


def crossing_slivers(rows: int = 6, offset: float = 0.0) -> np.ndarray:
    """[2 rows, 3, 3] float32: long slivers along x and along y crossing on a grid in one
    slab, object splits overlap and spatial splits pay (an SBVH of them has references)."""
    tri = []
    for i in range(rows):
        y = i / rows + offset
        tri.append([[0, y, 0], [1, y + 0.01, 0.01], [1, y, 0.02]])  # along x
        tri.append([[y, 0, 0.01], [y + 0.01, 1, 0.0], [y, 1, 0.02]])  # along y, in the same slab
    return np.asarray(tri, np.float32)


#: Python source for a child process, after ``import jax.monitoring``: counts what XLA
#: compiled (``len(compiles) - len(hits)``) and what was loaded instead, from JAX's
#: persistent cache (``hits``) or from jaxbvh's program store (``stored``)
COUNT_COMPILES = """
hits, compiles, stored = [], [], []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(1) if event == "/jax/compilation_cache/cache_hits" else None)
def on_duration(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":  # JAX records this for cache hits too
        compiles.append(1)
    elif event == "/jaxbvh/program_store/executable_load_sec":  # program_store.EXECUTABLE_LOAD_EVENT
        stored.append(1)  # compiled code loaded from jaxbvh's program store: not compiled either
jax.monitoring.register_event_duration_secs_listener(on_duration)
"""
