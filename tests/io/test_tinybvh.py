"""jaxbvh.io.tinybvh: trees written as tinybvh's node file, read back, and traced by tinybvh.

The writer's promises (module docstring of :mod:`jaxbvh.io.tinybvh`) are checked on the
bytes: node 0 the root, node 1 zeros, ``BVH::Compact``'s numbering, every subtree's
primitives one run, float32 world boxes holding float32 world triangles, the triangles
bit-identical to the peer harness's ``dump_tris.py``. The tracer test compiles
``../shared/peer/tinybvh_trace`` (g++, about 15 CPU seconds, once per session) and
checks tinybvh's hits on our trees against ``jaxbvh.rays`` and brute force.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from helpers import REPO, assert_one_line_error, run_cli, run_json
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.builders import BinnedConfig, SBVHConfig
from jaxbvh.builders import sbvh_reference, topdown_reference
from jaxbvh.io import bundled_mesh_path, export_tinybvh, load_mesh, read_tinybvh
from jaxbvh.io.tinybvh import FLAG_REFERENCES, NODE_DTYPE, TINYBVH_MAGIC, tinybvh_arrays
from jaxbvh.testing import canonical
from jaxbvh.testing.oracles import closest_hits
from jaxbvh.testing.plugin import examples
from jaxbvh.testing.strategies import triangle_soups, trees
from jaxbvh.testing.trees import Choices, make_tree
from jaxbvh.tree.frame import Frame

PEER = REPO.parent / "shared" / "peer"
needs_peer = pytest.mark.skipif(not (PEER / "tinybvh_trace.cpp").exists(),
                                reason=f"the peer harness is not at {PEER} (clone without ../shared)")


# ----------------------------------------------------------------------------------
# The file, read independently of the reader under test
# ----------------------------------------------------------------------------------


def raw(path):
    """``(nodes, prim_idx, triangles, flags)`` straight from the bytes."""
    data = open(path, "rb").read()
    assert data[:8] == TINYBVH_MAGIC
    used, idx, tris, flags = np.frombuffer(data, "<u4", 4, 8)
    nodes = np.frombuffer(data, NODE_DTYPE, used, 24)
    prim = np.frombuffer(data, "<u4", idx, 24 + 32 * used)
    tri = np.frombuffer(data, "<f4", 9 * tris, 24 + 32 * used + 4 * idx).reshape(tris, 3, 3)
    assert len(data) == 24 + 32 * int(used) + 4 * int(idx) + 36 * int(tris)
    return nodes, prim, tri, int(flags)


def compact_order(nodes, prim):
    """tinybvh_trace's ``Canonical``: BVH::Compact's numbering and primIdx packing."""
    out_nodes, out_prim = [nodes[0].copy(), np.zeros((), NODE_DTYPE)], []
    stack = [(0, 0)]
    while stack:
        s, d = stack.pop()
        n = nodes[s].copy()
        if n["tri_count"] > 0:
            out_nodes[d] = n
            out_nodes[d]["left_first"] = len(out_prim)
            out_prim += prim[n["left_first"]: n["left_first"] + n["tri_count"]].tolist()
            continue
        slot = len(out_nodes)
        out_nodes += [None, None]
        out_nodes[d] = n
        out_nodes[d]["left_first"] = slot
        stack += [(int(n["left_first"]) + 1, slot + 1), (int(n["left_first"]), slot)]
    return np.array(out_nodes, NODE_DTYPE), np.array(out_prim, np.uint32)


def assert_file_promises(path, triangles):
    """Every promise of the module docstring, on the bytes; returns them."""
    nodes, prim, tri, flags = raw(path)
    np.testing.assert_array_equal(tri, np.asarray(triangles).astype(np.float32))
    assert nodes[1].tobytes() == bytes(32)  # node 1 unused
    want_nodes, want_prim = compact_order(nodes, prim)
    assert nodes.tobytes() == want_nodes.tobytes() and np.array_equal(prim, want_prim)
    lo, hi = nodes["lo"], nodes["hi"]
    count, first = nodes["tri_count"].astype(np.int64), nodes["left_first"].astype(np.int64)
    # bottom-up over the slots (children after parents): run of each subtree, containment
    run_lo, run_hi = first.copy(), first + count
    tri_lo, tri_hi = tri.min(axis=1), tri.max(axis=1)
    uses = np.zeros(tri.shape[0], np.int64)
    for i in range(nodes.size - 1, -1, -1):
        if i == 1:
            continue
        if count[i] > 0:
            ids = prim[first[i]: first[i] + count[i]].astype(np.int64)
            np.add.at(uses, ids, 1)
            for p in ids:
                if flags & FLAG_REFERENCES:  # a piece's leaf meets its triangle
                    assert (lo[i] <= tri_hi[p]).all() and (hi[i] >= tri_lo[p]).all()
                else:
                    assert (lo[i] <= tri_lo[p]).all() and (hi[i] >= tri_hi[p]).all(), (i, p)
            continue
        a, b = first[i], first[i] + 1
        assert a >= 2 and b < nodes.size
        for c in (a, b):
            assert (lo[i] <= lo[c]).all() and (hi[i] >= hi[c]).all()
        assert run_hi[a] == run_lo[b] or run_hi[b] == run_lo[a]  # the two runs adjoin: one run
        run_lo[i], run_hi[i] = min(run_lo[a], run_lo[b]), max(run_hi[a], run_hi[b])
    assert (run_lo[0], run_hi[0]) == (0, prim.size)
    assert (uses >= 1).all()  # every triangle in a leaf
    assert (uses == 1).all() or flags & FLAG_REFERENCES  # a triangle twice: flagged
    return nodes, prim, tri, flags


def world_tree_boxes(tree, frame):
    """The tree's boxes in world space, float64 [N, 3] each."""
    t = jaxbvh.to_numpy(tree)
    return frame.to_world(np.asarray(t.lo, np.float64)), frame.to_world(np.asarray(t.hi, np.float64))


# ----------------------------------------------------------------------------------
# Round trip on a real tree
# ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spot():
    mesh = load_mesh(bundled_mesh_path())
    lo, hi = mesh.local_boxes()
    tree = topdown_reference.build(lo, hi, BinnedConfig(bins=8, max_leaf=4))
    return mesh, tree


def test_round_trip(spot, tmp_path):
    mesh, tree = spot
    path = tmp_path / "spot.bin"
    written = export_tinybvh(path, tree, mesh.triangles, mesh.frame)
    assert written["bytes"] == path.stat().st_size and written["flags"] == 0
    assert_file_promises(path, mesh.triangles)
    got = read_tinybvh(path)
    assert not got.references and got.frame.is_identity
    assert got.triangles.dtype == np.float32
    np.testing.assert_array_equal(got.triangles, mesh.triangles.astype(np.float32))
    # the same tree, node for node; its boxes the world boxes, rounded outward and tight
    assert canonical(got.tree, boxes=False) == canonical(tree, boxes=False)
    jaxbvh.validate(got.tree, got.triangles.min(1), got.triangles.max(1))
    order = np.asarray([n for n in _bfs(tree)])
    w_lo, w_hi = world_tree_boxes(tree, mesh.frame)
    lo, hi = got.tree.lo.astype(np.float64), got.tree.hi.astype(np.float64)
    slack = 4 * (np.spacing(np.abs(w_lo[order]).astype(np.float32)) + mesh.frame.scale * np.spacing(np.float32(1)))
    assert (lo <= w_lo[order]).all() and (hi >= w_hi[order]).all()
    assert (lo >= w_lo[order] - slack).all() and (hi <= w_hi[order] + slack).all()
    # the tree read back writes the same bytes
    again = tmp_path / "again.bin"
    export_tinybvh(again, got.tree, got.triangles)
    assert again.read_bytes() == path.read_bytes()


def _bfs(tree):
    """Node ids breadth first, children left then right (the reader's order)."""
    t = jaxbvh.to_numpy(tree)
    order, i = [int(t.root)], 0
    while i < len(order):
        n = order[i]
        i += 1
        if t.left[n] >= 0:
            order += [int(t.left[n]), int(t.right[n])]
    return order


@needs_peer
def test_triangles_are_dump_tris_bytes(spot, tmp_path):
    """The triangles in the file are, bit for bit, those of the harness's TRIS.bin."""
    sys.path.insert(0, str(PEER))
    try:
        from dump_tris import load_triangles
    finally:
        sys.path.remove(str(PEER))
    mesh, tree = spot
    export_tinybvh(tmp_path / "t.bin", tree, mesh.triangles, mesh.frame)
    _, _, tri, _ = raw(tmp_path / "t.bin")
    assert tri.tobytes() == load_triangles(str(bundled_mesh_path())).astype("<f4").tobytes()


# ----------------------------------------------------------------------------------
# Properties: any tree, any soup (scales 1e-30 .. 1e30, far from the origin)
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(40), deadline=None)
@given(data=st.data(), tri=triangle_soups(max_size=30))
def test_exported_boxes_contain_their_float32_triangles(data, tri, tmp_path_factory):
    frame = Frame.fit(tri.min(1), tri.max(1))
    local = frame.to_local(tri).astype(np.float32)  # as Mesh.local_boxes rounds them
    built = data.draw(trees(boxes=st.just((local.min(1), local.max(1)))))
    path = tmp_path_factory.mktemp("soup") / "t.bin"
    export_tinybvh(path, built.tree, tri, frame)
    nodes, prim, tri32, flags = assert_file_promises(path, tri)
    assert flags == 0 and prim.size == tri.shape[0] and np.array_equal(np.sort(prim), np.arange(tri.shape[0]))
    got = read_tinybvh(path)
    assert canonical(got.tree, boxes=False) == canonical(built.tree, boxes=False)
    assert jaxbvh.check(got.tree, tri32.min(1), tri32.max(1)) == []


@settings(max_examples=examples(6), deadline=None)  # the NumPy SBVH takes ~1 s a soup
@given(tri=triangle_soups(max_size=24), max_leaf=st.sampled_from([1, 3]))
def test_spatial_split_trees_cover_every_float32_triangle(tri, max_leaf, tmp_path_factory):
    """With references each leaf may hold a clipped piece; in float32 world space the
    pieces together still cover every triangle (the check's coverage test)."""
    frame = Frame.fit(tri.min(1), tri.max(1))
    local = frame.to_local(tri).astype(np.float32)
    tree = sbvh_reference.build(local, SBVHConfig(alpha=0.0, max_leaf=max_leaf, bins=8), capacity=640).tree
    path = tmp_path_factory.mktemp("sbvh") / "t.bin"
    export_tinybvh(path, tree, tri, frame, references=True)
    _, _, tri32, flags = assert_file_promises(path, tri)
    assert flags == FLAG_REFERENCES
    got = read_tinybvh(path)
    assert got.references
    assert canonical(got.tree, boxes=False) == canonical(tree, boxes=False)
    assert jaxbvh.check(got.tree, tri32.min(1), tri32.max(1), references=True, triangles=tri32) == []


def straddlers(seed: int = 0, n: int = 80):
    """Long triangles at random angles among small ones: SBVH splits many (test_sbvh)."""
    rng = np.random.default_rng(seed)
    size = np.where(rng.random((n, 1, 1)) < 0.2, 1.0, 0.1)
    return rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(size=(n, 3, 3)) * size


def test_spatial_splits_are_flagged_by_themselves(tmp_path):
    tri = straddlers()
    frame = Frame.fit(tri.min(1), tri.max(1))
    built = sbvh_reference.build(frame.to_local(tri).astype(np.float32), SBVHConfig(alpha=0.0, max_leaf=2, bins=8),
                                 capacity=640)
    assert built.spatial_splits > 0
    written = export_tinybvh(tmp_path / "t.bin", built.tree, tri, frame)  # references=None: found
    assert written["flags"] == FLAG_REFERENCES and written["primitive_ids"] > tri.shape[0]
    assert_file_promises(tmp_path / "t.bin", tri)


# ----------------------------------------------------------------------------------
# Refusals
# ----------------------------------------------------------------------------------


def small(n=6, seed=0, **kwargs):
    rng = np.random.default_rng(seed)
    tri = rng.normal(size=(n, 3, 3))
    built = make_tree(tri.min(1), tri.max(1), Choices(rng), **kwargs)
    return tri, built.tree


def test_refuses_wide_trees():
    tri, tree = small(arity=4)
    with pytest.raises(ValueError, match="4-wide.*binary tree"):
        tinybvh_arrays(tree, tri)


def test_refuses_a_tree_of_another_mesh():
    tri, tree = small()
    with pytest.raises(ValueError, match="names primitive.*5 triangles"):
        tinybvh_arrays(tree, tri[:5])
    with pytest.raises(ValueError, match="1 of the 7 triangles are in no leaf"):
        tinybvh_arrays(tree, np.concatenate([tri, tri[:1]]))
    with pytest.raises(ValueError, match="does not contain its triangle"):
        tinybvh_arrays(tree, tri + 10.0)
    with pytest.raises(ValueError, match="does not contain its triangle"):  # boxes in another frame
        tinybvh_arrays(tree, tri, Frame(np.ones(3), 2.0))


def test_refuses_bad_triangles():
    tri, tree = small()
    with pytest.raises(ValueError, match=r"\[n >= 1, 3, 3\]"):
        tinybvh_arrays(tree, tri[:, :2])
    big = tri.copy()
    big[2] *= 1e39  # finite in float64, not in float32
    with pytest.raises(ValueError, match=r"triangle\(s\) 2 are not finite in float32"):
        tinybvh_arrays(tree, big)


def test_refuses_a_broken_tree():
    tri, tree = small()
    t = jaxbvh.to_numpy(tree)
    root = int(t.root)
    bad = t.replace(left=np.where(np.arange(t.left.size) == t.left[root], root, t.left))  # a cycle
    with pytest.raises(ValueError, match="invalid tree"):
        tinybvh_arrays(bad, tri)


def good_file(tmp_path):
    tri, tree = small(n=5, seed=3)
    path = tmp_path / "good.bin"
    export_tinybvh(path, tree, tri)
    return path, bytearray(path.read_bytes())


def node_offset(i, field):
    return 24 + 32 * i + NODE_DTYPE.fields[field][1]


def test_reader_refuses_malformed_files(tmp_path):
    path, data = good_file(tmp_path)
    read_tinybvh(path)  # the file itself is fine
    used = int(np.frombuffer(bytes(data[8:12]), "<u4")[0])
    cases = {
        "magic": (b"TBVHNOD2" + data[8:], "not a tinybvh node file"),
        "short": (data[:-1], "cut short"),
        "long": (data + b"\0", "longer than its header says"),
        "empty": (b"", "not a tinybvh node file"),
    }
    cycle = bytearray(data)  # the root's children: 0 and 1, the root itself
    cycle[node_offset(0, "left_first"): node_offset(0, "left_first") + 4] = np.uint32(0).tobytes()
    cases["cycle"] = (cycle, "outside nodes")
    outside = bytearray(data)
    outside[node_offset(0, "left_first"): node_offset(0, "left_first") + 4] = np.uint32(used - 1).tobytes()
    cases["outside"] = (outside, "outside nodes")
    nodes = np.frombuffer(bytes(data), NODE_DTYPE, used, 24)
    leaf = int(np.flatnonzero(nodes["tri_count"] > 0)[0])
    run = bytearray(data)
    run[node_offset(leaf, "left_first"): node_offset(leaf, "left_first") + 4] = np.uint32(1000).tobytes()
    cases["run"] = (run, f"leaf node {leaf} covers primIdx")
    twice = bytearray(data)  # an interior node that links to the root's children again
    inner = [i for i in range(2, used) if nodes["tri_count"][i] == 0]
    if inner:
        twice[node_offset(inner[0], "left_first"): node_offset(inner[0], "left_first") + 4] = \
            data[node_offset(0, "left_first"): node_offset(0, "left_first") + 4]
        cases["twice"] = (twice, "reached twice")
    ids = bytearray(data)
    at = 24 + 32 * used
    ids[at: at + 4] = np.uint32(99).tobytes()
    cases["ids"] = (ids, "primIdx names triangle")
    for name, (content, message) in cases.items():
        bad = tmp_path / f"{name}.bin"
        bad.write_bytes(bytes(content))
        with pytest.raises(ValueError, match=message) as info:
            read_tinybvh(bad)
        assert str(bad) in str(info.value), name
    with pytest.raises(FileNotFoundError):
        read_tinybvh(tmp_path / "missing.bin")
    with pytest.raises(ValueError, match="is a directory"):
        read_tinybvh(tmp_path)


# ----------------------------------------------------------------------------------
# The command line
# ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spot_tree_file(spot, tmp_path_factory):
    mesh, tree = spot
    path = tmp_path_factory.mktemp("cli") / "spot.npz"
    jaxbvh.save(path, tree, frame=mesh.frame)
    return path


def test_cli_export(spot, spot_tree_file, tmp_path, capsys):
    mesh, tree = spot
    out = tmp_path / "spot.bin"
    result = run_json(capsys, "export", spot_tree_file, bundled_mesh_path(), "--format", "tinybvh", "-o", out)
    assert result["output"] == str(out) and result["triangles"] == mesh.n_triangles
    assert not result["spatial_splits"] and result["bytes"] == out.stat().st_size
    export_tinybvh(tmp_path / "library.bin", tree, mesh.triangles, mesh.frame)
    assert out.read_bytes() == (tmp_path / "library.bin").read_bytes()
    # an existing output is kept, unless --overwrite
    out.write_bytes(b"keep me")
    assert_one_line_error(*run_cli(capsys, "export", spot_tree_file, bundled_mesh_path(), "-o", out),
                          "exists", "--overwrite")
    assert out.read_bytes() == b"keep me"
    run_json(capsys, "export", spot_tree_file, bundled_mesh_path(), "-o", out, "--overwrite")
    assert out.read_bytes() == (tmp_path / "library.bin").read_bytes()
    assert_one_line_error(*run_cli(capsys, "export", spot_tree_file, bundled_mesh_path(), "-o", tmp_path),
                          "is a folder")


def test_cli_export_refuses_a_mesh_that_is_not_the_trees(spot_tree_file, tmp_path, capsys):
    other = tmp_path / "other.obj"
    mesh = load_mesh(bundled_mesh_path())
    moved = mesh.vertices + 1.0  # the same triangles, elsewhere: the leaves miss them
    other.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in moved.tolist())
                     + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in mesh.faces.tolist()))
    out = tmp_path / "x.bin"
    assert_one_line_error(*run_cli(capsys, "export", spot_tree_file, other, "-o", out), "invalid BVH")
    assert not out.exists()


def test_cli_export_refuses_wide_trees(tmp_path, capsys):
    mesh = load_mesh(bundled_mesh_path())
    lo, hi = mesh.local_boxes()
    wide = make_tree(lo, hi, Choices(np.random.default_rng(0)), arity=4).tree
    jaxbvh.save(tmp_path / "wide.npz", wide, frame=mesh.frame)
    assert_one_line_error(*run_cli(capsys, "export", tmp_path / "wide.npz", bundled_mesh_path(), "-o",
                                   tmp_path / "x.bin"), "4-wide", "binary tree")


# ----------------------------------------------------------------------------------
# tinybvh traces the file: its hits against jaxbvh.rays and brute force
# ----------------------------------------------------------------------------------

#: the compile took 15-18 CPU seconds on the 2-core machine; past this it is skipped
BUILD_SECONDS = 300


@pytest.fixture(scope="session")
def tracer(tmp_path_factory):
    """``tinybvh_trace`` compiled into a temporary folder (skipped without g++ or the harness)."""
    if not (PEER / "build_trace.sh").exists():
        pytest.skip(f"the peer harness is not at {PEER}")
    if shutil.which(os.environ.get("CXX", "g++")) is None:
        pytest.skip("no C++ compiler (g++, or $CXX)")
    folder = tmp_path_factory.mktemp("peer")
    try:
        subprocess.run(["bash", str(PEER / "build_trace.sh")], env={**os.environ, "PEER_BUILD": str(folder)},
                       check=True, capture_output=True, timeout=BUILD_SECONDS)
    except subprocess.TimeoutExpired:
        pytest.skip(f"compiling tinybvh_trace took over {BUILD_SECONDS} s")
    except subprocess.CalledProcessError as exc:
        pytest.skip(f"tinybvh_trace does not compile here: {exc.stderr.decode()[-300:]}")
    return folder / "tinybvh_trace"


def normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def primary_rays(tri32, res):
    """tinybvh_trace's primary rays (pinhole, float32), as its source makes them."""
    f = np.float32
    verts = tri32.reshape(-1, 3)
    bmin, bmax = verts.min(0), verts.max(0)
    centre, ext = (bmin + bmax) * f(0.5), bmax - bmin
    radius = f(0.5) * np.linalg.norm(ext).astype(f)
    axis = normalize(np.array([0.62, 0.45, 0.64], f))
    eye = centre + axis * (f(1.5) * radius)
    fwd = normalize(centre - eye)
    right = normalize(np.cross(fwd, np.array([0, 1, 0], f)))
    up = np.cross(right, fwd)
    h = np.tan(f(0.5 * 60.0) * f(3.14159265) / f(180.0)).astype(f)
    y, x = np.meshgrid(np.arange(res, dtype=f), np.arange(res, dtype=f), indexing="ij")
    sx = ((f(2) * (x + f(0.5)) / f(res) - f(1)) * h).reshape(-1, 1)
    sy = ((f(1) - f(2) * (y + f(0.5)) / f(res)) * h).reshape(-1, 1)
    direction = normalize(fwd + right * sx + up * sy).astype(f)
    return np.broadcast_to(eye, direction.shape).astype(f), direction


def random_rays(tri32, res, seed):
    """tinybvh_trace's random rays: its PCG32 stream (seed, sequence 1). The origin's
    three draws are arguments of one constructor call, an order C++ leaves open: g++ on
    x86-64 evaluates them last to first (and a wrong guess fails the hit counts)."""
    mask = (1 << 64) - 1
    state, inc = 0, (1 << 1) | 1

    def step():
        nonlocal state
        old = state
        state = (old * 6364136223846793005 + inc) & mask
        xs, rot = (((old >> 18) ^ old) >> 27) & 0xFFFFFFFF, old >> 59
        return ((xs >> rot) | (xs << ((-rot) & 31))) & 0xFFFFFFFF

    step()
    state = (state + seed) & mask
    step()
    u = np.array([(step() >> 8) for _ in range(5 * res * res)], np.float32).reshape(-1, 5) * np.float32(2 ** -24)
    verts = tri32.reshape(-1, 3)
    bmin, bmax = verts.min(0), verts.max(0)
    origin = bmin + u[:, 2::-1] * (bmax - bmin)
    z = np.float32(1) - np.float32(2) * u[:, 3]
    phi = np.float32(6.2831853) * u[:, 4]
    r = np.sqrt(np.maximum(np.float32(0), np.float32(1) - z * z))
    return origin.astype(np.float32), np.stack([r * np.cos(phi), r * np.sin(phi), z], 1).astype(np.float32)


RES = 24  # rays per set: RES^2


def test_tinybvh_traces_our_trees_as_we_do(tracer, tmp_path):
    tri = straddlers(seed=1)  # spatial splits happen on it
    frame = Frame.fit(tri.min(1), tri.max(1))
    local = frame.to_local(tri).astype(np.float32)
    trees_ = {
        "binned": topdown_reference.build(local.min(1), local.max(1), BinnedConfig(bins=8, max_leaf=4)),
        "sbvh": sbvh_reference.build(local, SBVHConfig(alpha=0.0, max_leaf=2, bins=8), capacity=640).tree,
    }
    tri32 = tri.astype(np.float32)
    (tmp_path / "tris.bin").write_bytes(np.uint32(tri.shape[0]).tobytes() + tri32.astype("<f4").tobytes())
    args = [str(tracer), str(tmp_path / "tris.bin"), "--peer", "build", "--res", str(RES), "--repeats", "1"]
    for name, tree in trees_.items():
        export_tinybvh(tmp_path / f"{name}.bin", tree, tri, frame)
        args += ["--tree", f"{name}={tmp_path / name}.bin"]
    done = subprocess.run(args, capture_output=True, text=True, timeout=120, check=True)
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    for line in (x for x in lines if x["kind"] == "tree" and x["tree"] in trees_):
        assert line["references"] == (line["tree"] == "sbvh") and line["file_in_compact_order"]
        # with references a leaf may bound a piece of a triangle that other leaves hold too
        allowed = ("leaf_box_not_containing_tri", "multi_referenced_tris") if line["references"] else ()
        assert {k: v for k, v in line["check"].items() if k not in allowed and v}  == {}, line
        assert all(layout["traced"] for layout in line["layouts"].values()), line
    traced = [x for x in lines if x["kind"] == "trace" and x["tree"] in trees_]
    assert len(traced) == len(trees_) * 4 * 3  # 4 layouts, 3 ray sets
    for line in traced:  # every ray: the same hit as tinybvh's own tree, in every layout
        assert set(line["vs_ref_same_layout"].values()) == {0} and set(line["vs_ref_bvh"].values()) == {0}, line
    hits = {(x["tree"], x["set"]): x["hits"] for x in traced if x["layout"] == "bvh"}
    rays = {"primary": primary_rays(tri32, RES), "random": random_rays(tri32, RES, seed=1)}
    for name in trees_:
        got = read_tinybvh(tmp_path / f"{name}.bin")
        for kind, (origin, direction) in rays.items():
            ours = jaxbvh.rays.closest_hit(got.tree, got.triangles, origin, direction)
            brute_t, brute_prim = closest_hits(got.triangles, origin, direction)
            np.testing.assert_array_equal(np.asarray(ours.prim), brute_prim)
            assert hits[(name, kind)] == int((brute_prim >= 0).sum()) > 0, (name, kind)
