"""Ray sets, traversal and ray measurement (jaxbvh.rays / raygen / traverse).

Checked three ways: closest hits against brute force over every triangle (hypothesis,
small random meshes), every counter against the NumPy twin ray by ray, and closest hits
against Embree (embreex, optional) on the shared real meshes.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from helpers import SHARED_DATA
from hypothesis import given
from hypothesis import strategies as st

from jaxbvh import rays
from jaxbvh.rays import traversal as traverse
from jaxbvh.rays import traversal_reference as ref
from jaxbvh.tree import BVH, depth, from_interchange
from jaxbvh.wide import collapse

COUNTERS = ("box_tests", "prim_tests", "nodes_visited", "leaves_visited")

def assert_t_close(got, expected, triangles, direction, prim):
    """Hit distances agree up to the rounding of the ray-triangle test.

    XLA on CPU contracts ``a * b + c`` into fused multiply-adds and NumPy does not, so a
    distance may differ from the twin's or brute force's in its last bits; Möller–Trumbore's
    error grows like ``1 / |cos|`` of the angle between ray and normal, so the tolerance
    (1e-5 of our few-unit scenes at normal incidence) does too.
    """
    got, expected = np.asarray(got), np.asarray(expected)
    assert np.array_equal(np.isfinite(got), np.isfinite(expected))
    fin = np.flatnonzero(np.isfinite(expected))
    tri = np.asarray(triangles, np.float64)[np.asarray(prim)[fin]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d = np.asarray(direction, np.float64)[fin]
    cos = np.abs(np.sum(normal * d, axis=1)) / np.linalg.norm(d, axis=1)
    tol = 1e-5 * (1 + np.abs(expected[fin])) / np.maximum(cos, 1e-4)
    err = np.abs(got[fin].astype(np.float64) - expected[fin])
    assert (err <= tol).all(), f"t differs on rays {fin[err > tol][:5]}: {got[fin][err > tol][:5]} " \
                               f"vs {expected[fin][err > tol][:5]} (cos {cos[err > tol][:5]})"


# ----------------------------------------------------------------------------------
# Small trees of our own (independent of jaxbvh.build)
# ----------------------------------------------------------------------------------


def random_triangles(rng, n, spread=1.0, size=0.3):
    """``n`` random triangles [n, 3, 3] float32 scattered in a cube."""
    centre = rng.uniform(-spread, spread, (n, 1, 3))
    return (centre + rng.normal(0, size, (n, 3, 3))).astype(np.float32)


def median_tree(triangles, max_leaf=1):
    """Binary BVH by median split of centroids on the widest axis, with ``axis`` set."""
    lo_p, hi_p = triangles.min(axis=1), triangles.max(axis=1)
    centroid = triangles.mean(axis=1)
    child, start, count, lo, hi, axis, order = [], [], [], [], [], [], []

    def node(ids):
        me = len(child)
        child.append([-1, -1])
        start.append(0)
        count.append(0)
        lo.append(lo_p[ids].min(axis=0))
        hi.append(hi_p[ids].max(axis=0))
        axis.append(-1)
        if len(ids) <= max_leaf:
            start[me], count[me] = len(order), len(ids)
            order.extend(ids.tolist())
            return me
        c = centroid[ids]
        split = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        ids = ids[np.argsort(c[:, split], kind="stable")]
        half = len(ids) // 2
        axis[me] = split
        left = node(ids[:half])
        right = node(ids[half:])
        child[me] = [left, right]
        return me

    node(np.arange(triangles.shape[0]))
    arrays = dict(child=np.array(child, np.int32), prim_start=np.array(start, np.int32),
                  prim_count=np.array(count, np.int32), prim_index=np.array(order, np.int32),
                  lo=np.array(lo, np.float32), hi=np.array(hi, np.float32), root=np.int32(0))
    tree = from_interchange(arrays)
    full_axis = np.full(tree.capacity, -1, np.int32)
    full_axis[: len(axis)] = axis
    return tree.replace(axis=full_axis)


# Every test traces with the same array shapes, so each (mode, arity) compiles once:
# trees padded to NODES / PRIMS entries, triangles to PRIMS, batches of BATCH rays, a
# stack of CAP entries (more than any test tree needs).
NODES, PRIMS, BATCH, CAP = 512, 256, 64, 24


def padded(triangles):
    """Triangles padded with degenerate (never hit) ones to PRIMS."""
    out = np.zeros((max(PRIMS, triangles.shape[0]), 3, 3), np.float32)
    out[: triangles.shape[0]] = triangles
    return out


def fixed(tree):
    """``tree`` with inert padding up to NODES nodes and PRIMS primitive slots."""
    grow = NODES - tree.capacity
    slots = PRIMS - tree.prim_index.shape[0]
    assert grow >= 0 and slots >= 0

    def pad(a, fill):
        return np.concatenate([a, np.full((grow,) + a.shape[1:], fill, a.dtype)])

    fields = dict(parent=pad(tree.parent, -1), lo=pad(tree.lo, np.inf), hi=pad(tree.hi, -np.inf),
                  prim_start=pad(tree.prim_start, 0), prim_count=pad(tree.prim_count, 0),
                  prim_index=np.concatenate([tree.prim_index, np.full(slots, -1, np.int32)]))
    if isinstance(tree, BVH):
        fields.update(left=pad(tree.left, -1), right=pad(tree.right, -1), axis=pad(tree.axis, -1))
    else:
        fields.update(child=pad(tree.child, -1))
    return tree.replace(**fields)


def widen(tree, k):
    """A k-wide tree: the optimal collapse (jaxbvh.collapse) with at most k children.

    Collapsed at the fixed capacity (see NODES), so each k compiles once.
    """
    return collapse.optimal(fixed(tree), max_children=k).tree


def run(kind, tree, tri, origin, direction, **kwargs):
    """``rays.<kind>`` with the shared shapes (see NODES), on the JAX walk (this module's
    subject; the native engine is held equal to it in test_native.py)."""
    kwargs.setdefault("capacity", CAP)
    kwargs.setdefault("engine", "jax")
    return getattr(rays, kind)(fixed(tree), padded(tri), origin, direction, batch=BATCH, **kwargs)


def mixed_rays(rng, triangles, n):
    """Half random rays in the scene box, half aimed at triangle interiors."""
    lo, hi = triangles.reshape(-1, 3).min(0), triangles.reshape(-1, 3).max(0)
    m = n // 2
    origin = rng.uniform(lo - 0.5, hi + 0.5, (n, 3)).astype(np.float32)
    direction = rng.normal(size=(n, 3))
    target_tri = triangles[rng.integers(0, triangles.shape[0], n - m)]
    bary = rng.dirichlet([1, 1, 1], n - m)
    target = np.einsum("rc,rcx->rx", bary, target_tri)
    direction[m:] = target - origin[m:]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return origin, direction.astype(np.float32)


def assert_same_as_reference(tree, triangles, origin, direction, mode, **kwargs):
    kwargs.setdefault("capacity", CAP)
    kwargs.setdefault("engine", "jax")
    hits = traverse.trace(fixed(tree), padded(triangles), origin, direction, mode=mode,
                          batch=BATCH, **kwargs)
    for walk_only in ("allow_overflow", "lanes", "leaf_width", "engine"):
        kwargs.pop(walk_only, None)
    twin = ref.trace(tree, triangles, origin, direction, mode=mode, **kwargs)
    for name in COUNTERS + ("prim", "stack_overflow"):
        expected = np.array([r[name] for r in twin])
        got = np.asarray(getattr(hits, name))
        bad = np.flatnonzero(expected != got)
        assert bad.size == 0, f"{mode}: {name} differs on rays {bad[:5]}: {got[bad[:5]]} vs {expected[bad[:5]]}"
    expected_t = np.array([r["t"] for r in twin], np.float32)
    assert_t_close(hits.t, expected_t, triangles, direction, hits.prim)
    if mode == "all":
        assert np.array_equal(hits.hit_count, [r["hit_count"] for r in twin])
        for i, r in enumerate(twin):
            n = len(r["hit_prims"])
            assert hits.hit_prims[i, :n].tolist() == r["hit_prims"]
            assert (hits.hit_prims[i, n:] == -1).all()
        assert np.array_equal(hits.hits_overflow, [r["hits_overflow"] for r in twin])
    return hits


# ----------------------------------------------------------------------------------
# Traversal against brute force and against the NumPy twin
# ----------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 48), max_leaf=st.sampled_from([1, 3]),
       arity=st.sampled_from([2, 4]))
def test_closest_hit_equals_brute_force(seed, n, max_leaf, arity):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n)
    tree = median_tree(tri, max_leaf)
    if arity > 2:
        tree = widen(tree, arity)
    origin, direction = mixed_rays(rng, tri, 64)
    assert traverse.stack_capacity(tree) <= CAP
    hits = run("closest_hit", tree, tri, origin, direction)
    t, prim = ref.brute_force_closest(tri, origin, direction)
    assert np.array_equal(hits.prim, prim), np.flatnonzero(hits.prim != prim)
    assert_t_close(hits.t, t, tri, direction, prim)
    assert not hits.stack_overflow.any()
    assert (prim >= 0).mean() > 0.3  # the aimed half mostly hits


@pytest.mark.parametrize("shape,mode", [
    (shape, mode) for shape in ("binary-axis", "binary-distance", "wide4", "wide8")
    for mode in ("closest", "any", "all") if shape != "wide8" or mode == "closest"])
def test_counts_equal_reference_ray_by_ray(shape, mode):
    rng = np.random.default_rng(7)
    tri = random_triangles(rng, 150, size=0.2)
    tree = median_tree(tri, max_leaf=3)
    if shape == "binary-distance":
        tree = tree.replace(axis=np.full(tree.capacity, -1, np.int32))
    elif shape.startswith("wide"):
        tree = widen(tree, int(shape[4:]))
    origin, direction = mixed_rays(rng, tri, 96)
    hits = assert_same_as_reference(tree, tri, origin, direction, mode, max_hits=16)
    if mode == "closest":
        t, prim = ref.brute_force_closest(tri, origin, direction)
        assert np.array_equal(hits.prim, prim)
    assert hits.box_tests.min() >= 1 and hits.prim_tests.max() > 0


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), max_leaf=st.sampled_from([1, 5]),
       arity=st.sampled_from([2, 4]), mode=st.sampled_from(["closest", "any"]))
def test_wavefront_lanes_and_leaf_chunks_equal_twin(seed, n, max_leaf, arity, mode):
    """Few lanes (each traces several rays in turn, refilled as rays end) and leaves
    tested 3 slots at a time give the twin's hits and counters, ray by ray."""
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n)
    tree = median_tree(tri, max_leaf)
    if arity > 2:
        tree = widen(tree, arity)
    origin, direction = mixed_rays(rng, tri, 64)
    hits = assert_same_as_reference(tree, tri, origin, direction, mode, lanes=5, leaf_width=3)
    if mode == "closest":
        _, prim = ref.brute_force_closest(tri, origin, direction)
        assert np.array_equal(hits.prim, prim)


def chain_tree(triangles):
    """A binary tree that peels one triangle per level (depth T - 1): interior node j
    holds triangles j..T-1, its children are the leaf of triangle j and node j + 1."""
    n = triangles.shape[0]
    n_int = n - 1
    leaf = n_int + np.arange(n)
    child = np.full((n_int + n, 2), -1, np.int32)
    child[:n_int, 0] = leaf[:n_int]
    child[:n_int, 1] = np.arange(1, n_int + 1)
    child[n_int - 1, 1] = leaf[n - 1]
    lo_p, hi_p = triangles.min(axis=1), triangles.max(axis=1)
    lo = np.concatenate([np.minimum.accumulate(lo_p[::-1])[::-1][:n_int], lo_p])
    hi = np.concatenate([np.maximum.accumulate(hi_p[::-1])[::-1][:n_int], hi_p])
    start = np.concatenate([np.zeros(n_int, np.int32), np.arange(n, dtype=np.int32)])
    count = np.concatenate([np.zeros(n_int, np.int32), np.ones(n, np.int32)])
    return from_interchange(dict(child=child, prim_start=start, prim_count=count,
                                 prim_index=np.arange(n, dtype=np.int32), lo=lo, hi=hi, root=np.int32(0)))


def test_deep_chain_traces_with_a_bounded_state():
    """A 199-deep chain traced with a stack of 2 entries (a lane's whole state is a few
    scalars and 2 entries; the program is the one a shallow tree of the same shapes
    compiles): hits equal brute force, counters equal the twin's with the same stack, and
    the unbounded walk's but for the climbs' box tests; every ray stays within the step
    bound, and deep rays do climb."""
    rng = np.random.default_rng(12)
    tri = random_triangles(rng, 200, spread=3.0, size=0.2)
    tri = tri[np.argsort(tri.mean(axis=1)[:, 0])]  # a sweep along x: deep rays
    tree = chain_tree(tri)
    assert int(np.max(depth(tree))) == 199 and traverse.stack_capacity(tree) == 200
    origin, direction = mixed_rays(rng, tri, 96)
    shallow = median_tree(tri)
    run("closest_hit", shallow, tri, origin, direction, capacity=2)
    programs = traverse.trace_batch._cache_size()
    hits = assert_same_as_reference(tree, tri, origin, direction, "closest", capacity=2)
    assert traverse.trace_batch._cache_size() == programs  # depth is not part of the program
    _, prim = ref.brute_force_closest(tri, origin, direction)
    assert np.array_equal(hits.prim, prim)
    climbed = assert_climbs_like_unbounded(hits, tree, tri, origin, direction, "closest")
    assert climbed.mean() > 0.1
    assert (hits.nodes_visited + hits.prim_tests).max() > 100  # some rays do walk deep


def test_front_to_back_orders_differ_but_hits_agree():
    """Axis order and distance order visit differently and find the same hits."""
    rng = np.random.default_rng(3)
    tri = random_triangles(rng, 200, size=0.15)
    tree = median_tree(tri, max_leaf=2)
    origin, direction = mixed_rays(rng, tri, 128)
    by_axis = run("closest_hit", tree, tri, origin, direction)
    by_distance = run("closest_hit", tree.replace(axis=np.full(tree.capacity, -1, np.int32)),
                      tri, origin, direction)
    assert np.array_equal(by_axis.prim, by_distance.prim)
    assert not np.array_equal(by_axis.box_tests, by_distance.box_tests)


def test_any_hit_and_all_hits_agree_with_closest():
    rng = np.random.default_rng(11)
    tri = random_triangles(rng, 120, size=0.3)
    tree = widen(median_tree(tri, max_leaf=2), 4)
    origin, direction = mixed_rays(rng, tri, 128)
    closest = run("closest_hit", tree, tri, origin, direction)
    anyhit = run("any_hit", tree, tri, origin, direction)
    allhits = run("all_hits", tree, tri, origin, direction, max_hits=16)
    assert np.array_equal(anyhit.prim >= 0, closest.prim >= 0)
    # the same triangle's t from two programs may differ in its last bit (FMA
    # contraction, see assert_t_close): compare up to that
    same = anyhit.prim == closest.prim
    assert_t_close(anyhit.t[same], closest.t[same], tri, direction[same], closest.prim[same])
    assert (anyhit.t[~same] >= closest.t[~same]).all()
    assert (anyhit.prim_tests <= allhits.prim_tests).all()
    assert np.array_equal(allhits.prim, closest.prim)  # all-hits also reports the closest
    # hit counts equal the brute-force count of triangles each ray crosses
    tt, _, _ = jax.vmap(lambda o, d: traverse.moller_trumbore(tri[:, 0], tri[:, 1], tri[:, 2],
                                                               o, d))(origin, direction)
    crossed = np.isfinite(tt) & (np.asarray(tt) > 0)
    assert np.array_equal(allhits.hit_count, crossed.sum(axis=1))
    assert not allhits.hits_overflow.any()
    listed = allhits.hit_prims
    for i in range(len(origin)):
        got = sorted(listed[i, : allhits.hit_count[i]].tolist())
        assert got == np.flatnonzero(crossed[i]).tolist()


def test_all_hits_list_overflow_is_flagged():
    rng = np.random.default_rng(5)
    tri = random_triangles(rng, 200, spread=0.1, size=0.5)  # piled up: many hits per ray
    tree = median_tree(tri)
    origin, direction = mixed_rays(rng, tri, 64)
    hits = assert_same_as_reference(tree, tri, origin, direction, "all", max_hits=16)
    assert hits.hits_overflow.any()
    assert np.array_equal(hits.hits_overflow, hits.hit_count > 16)


UNBOUNDED_EQUAL = ("prim", "prim_tests", "nodes_visited", "leaves_visited")
"""What a stack that spills and climbs keeps of an unbounded stack's walk (the climbs add
box tests and steps)."""


def assert_climbs_like_unbounded(hits, tree, triangles, origin, direction, mode, **kwargs):
    """``hits`` (a short stack) against the twin with an unbounded stack: the same hits,
    visits, primitive tests and lists; no fewer box tests. Returns the rays that climbed."""
    twin = ref.trace(tree, triangles, origin, direction, mode=mode, **kwargs)
    for name in UNBOUNDED_EQUAL:
        np.testing.assert_array_equal(getattr(hits, name), [r[name] for r in twin], err_msg=name)
    if mode == "all":
        np.testing.assert_array_equal(hits.hit_count, [r["hit_count"] for r in twin])
        for i, r in enumerate(twin):
            assert hits.hit_prims[i, :len(r["hit_prims"])].tolist() == r["hit_prims"]
    unbounded_box = np.array([r["box_tests"] for r in twin])
    assert (hits.box_tests >= unbounded_box).all()
    assert not hits.stack_overflow.any() and not hits.step_limit.any()
    return hits.box_tests > unbounded_box


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 60), max_leaf=st.sampled_from([1, 3]),
       shape=st.sampled_from(["binary-axis", "binary-distance", "wide4"]),
       mode=st.sampled_from(["closest", "all"]))
def test_short_stack_climbs_to_the_unbounded_walk(seed, n, max_leaf, shape, mode):
    """A stack of k entries (the least allowed) spills on most trees; the climb by parent
    links gives the twin's counters with the same stack, ray by ray, and the hits,
    visits, primitive tests and hit lists of an unbounded stack."""
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n, size=0.4)
    tree = median_tree(tri, max_leaf)
    if shape == "binary-distance":
        tree = tree.replace(axis=np.full(tree.capacity, -1, np.int32))
    elif shape == "wide4":
        tree = widen(tree, 4)
    k = 4 if shape == "wide4" else 2
    origin, direction = mixed_rays(rng, tri, 64)
    hits = assert_same_as_reference(tree, tri, origin, direction, mode, capacity=k, max_hits=16)
    assert_climbs_like_unbounded(hits, tree, tri, origin, direction, mode, max_hits=16)
    if mode == "closest":
        _, prim = ref.brute_force_closest(tri, origin, direction)
        assert np.array_equal(hits.prim, prim)


def test_climbs_happen_and_honour_skip_flags():
    """A distance-ordered tree with skip flags (a collapse's) on a stack of 2 entries: rays
    do climb, and hits and counters still equal the twin's and the unbounded walk's."""
    rng = np.random.default_rng(9)
    tri = random_triangles(rng, 64, size=0.4)
    tree = fixed(median_tree(tri)).replace(axis=np.full(NODES, -1, np.int32))
    skip = collapse.optimal(tree, max_children=4).skip
    assert np.asarray(skip).any()
    origin, direction = mixed_rays(rng, tri, 64)
    for mode in ("closest", "all"):
        hits = assert_same_as_reference(tree, tri, origin, direction, mode, capacity=2, skip=skip)
        climbed = assert_climbs_like_unbounded(hits, tree, tri, origin, direction, mode, skip=skip)
        assert climbed.any()
    with pytest.raises(ValueError, match="children per node"):
        run("closest_hit", widen(median_tree(tri), 4), tri, origin, direction, capacity=3)


def test_stack_capacity_bound():
    tri = random_triangles(np.random.default_rng(0), 33)
    tree = median_tree(tri)  # height 6 (33 leaves, median split)
    assert traverse.stack_capacity(tree) == 7
    wide = widen(tree, 4)
    assert traverse.stack_capacity(wide) == 3 * int(np.max(depth(wide))) + 1


def test_zero_direction_components_and_axis_aligned_rays():
    """Rays along the axes (0 components: no 0 * inf) find the same hits as brute force."""
    rng = np.random.default_rng(2)
    tri = random_triangles(rng, 60)
    tree = median_tree(tri, max_leaf=2)
    origin = rng.uniform(-1.5, 1.5, (BATCH, 3)).astype(np.float32)
    direction = np.zeros((BATCH, 3), np.float32)
    direction[np.arange(BATCH), np.arange(BATCH) % 3] = np.where(np.arange(BATCH) % 2, 1, -1)
    hits = assert_same_as_reference(tree, tri, origin, direction, "closest")
    _, prim = ref.brute_force_closest(tri, origin, direction)
    assert np.array_equal(hits.prim, prim)


def test_no_retrace_for_same_shapes():
    rng = np.random.default_rng(4)
    tri = random_triangles(rng, 40)
    tree = median_tree(tri)
    origin, direction = mixed_rays(rng, tri, 100)
    run("closest_hit", tree, tri, origin, direction)
    before = traverse.trace_batch._cache_size()
    other_o, other_d = mixed_rays(np.random.default_rng(5), tri, 70)  # last batch padded
    run("closest_hit", tree, tri, other_o, other_d)
    assert traverse.trace_batch._cache_size() == before


# ----------------------------------------------------------------------------------
# Ray sets
# ----------------------------------------------------------------------------------


def test_random_rays_fill_box_with_unit_directions_and_keys_repeat():
    lo, hi = np.array([-1, 0, 2], np.float32), np.array([1, 3, 2.5], np.float32)
    origin, direction = rays.random_rays(jax.random.key(0), lo, hi, 4000)
    origin, direction = np.asarray(origin), np.asarray(direction)
    assert origin.shape == direction.shape == (4000, 3)
    assert (origin >= lo).all() and (origin <= hi).all()
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1, atol=1e-5)
    assert np.abs(direction.mean(axis=0)).max() < 0.05  # uniform on the sphere
    again = np.asarray(rays.random_rays(jax.random.key(0), lo, hi, 4000)[0])
    other = np.asarray(rays.random_rays(jax.random.key(1), lo, hi, 4000)[0])
    assert np.array_equal(origin, again) and not np.array_equal(origin, other)


def test_camera_rays_frame_the_box():
    lo, hi = np.zeros(3, np.float32), np.ones(3, np.float32)
    origin, direction = rays.camera_rays(lo, hi, 32, 24)
    assert origin.shape == direction.shape == (32 * 24, 3)
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1, atol=1e-5)
    # the eye is outside the box and the central ray points at the box centre
    assert (np.abs(origin[0] - 0.5) > 0.5).any()
    to_centre = 0.5 - origin[0]
    to_centre /= np.linalg.norm(to_centre)
    mid = direction.reshape(24, 32, 3)[11:13, 15:17].mean(axis=(0, 1))
    assert np.dot(mid / np.linalg.norm(mid), to_centre) > 0.999
    # every corner of the box is in view: inside the image's angular extent
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 1]], [[1, 1, 1], [0, 1, 0], [1, 0, 1]]], np.float32)
    tree = median_tree(tri)
    hits = run("closest_hit", tree, tri, origin, direction)
    border = np.ones((24, 32), bool)
    border[1:-1, 1:-1] = False
    assert (hits.prim >= 0).any() and (hits.prim.reshape(24, 32)[border] < 0).all()


def test_bounce_rays_leave_the_surface_cosine_weighted():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 1], [0, 2, 1], [2, 0, 1]]],
                   np.float32)  # normals +z and -z; the second has 4x the area
    origin, direction = rays.bounce_rays(jax.random.key(3), tri, 20000)
    origin, direction = np.asarray(origin), np.asarray(direction)
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1, atol=1e-5)
    on_second = origin[:, 2] > 0.5
    assert abs(on_second.mean() - 0.8) < 0.02  # chosen by area
    assert (direction[~on_second, 2] > 0).all() and (direction[on_second, 2] < 0).all()
    cos = np.abs(direction[:, 2])
    assert abs(cos.mean() - 2 / 3) < 0.01  # E[cos] = 2/3 for cosine weighting
    assert (origin[~on_second, 2] > 0).all()  # lifted off the surface
    two = np.asarray(rays.bounce_rays(jax.random.key(3), tri, 4000, two_sided=True)[1])
    assert (two[:, 2] > 0).any() and (two[:, 2] < 0).any()


def test_measure_reports_costs_with_intervals():
    rng = np.random.default_rng(6)
    tri = random_triangles(rng, 100)
    tree = median_tree(tri, max_leaf=2)
    origin, direction = rays.make_rays(jax.random.key(0), "random", tree, tri, 500)
    hits, summary = rays.measure(fixed(tree), padded(tri), origin, direction, batch=BATCH,
                                 capacity=CAP)
    assert summary["rays"] == 500
    for name in ("box_tests", "prim_tests", "nodes_visited", "cost"):
        assert summary[name] > 0 and 0 < summary[name + "_ci"] < summary[name]
    assert summary["box_tests"] == pytest.approx(float(np.mean(hits.box_tests)))
    assert summary["sah"] > 1
    interior = hits.nodes_visited - hits.leaves_visited
    assert (hits.box_tests == 1 + 2 * interior).all()  # binary: two box tests per interior
    mean, half = rays.mean_ci([1.0, 3.0] * 50)
    assert mean == 2.0 and half == pytest.approx(1.96 * np.std([1.0, 3.0] * 50, ddof=1) / 10)


@pytest.mark.parametrize("kind", rays.KINDS)
def test_make_rays_kinds(kind):
    tri = random_triangles(np.random.default_rng(1), 30)
    tree = median_tree(tri)
    origin, direction = rays.make_rays(jax.random.key(2), kind, tree, tri, 300)
    assert origin.shape == direction.shape and origin.shape[0] >= 250
    with pytest.raises(ValueError, match="ray kind"):
        rays.make_rays(jax.random.key(2), "laser", tree, tri, 10)


def test_builder_trees():
    """Trees from jaxbvh.build (axis-ordered) trace like brute force."""
    import jaxbvh

    tri = random_triangles(np.random.default_rng(8), 90)
    tree = jaxbvh.build(tri.min(axis=1), tri.max(axis=1), method="sweep", max_leaf=2)
    origin, direction = mixed_rays(np.random.default_rng(1), tri, 64)
    hits = assert_same_as_reference(tree, tri, origin, direction, "closest")
    _, prim = ref.brute_force_closest(tri, origin, direction)
    assert np.array_equal(hits.prim, prim)


# ----------------------------------------------------------------------------------
# Embree on the real meshes (optional)
# ----------------------------------------------------------------------------------

REAL = [("bunny", "meshes/stanford-bunny.obj"), ("legocar", "meshes/legocar.obj"),
        ("drone", "scenes/drone/scene.gltf")]


def _real_scene(name, mesh):
    if not (SHARED_DATA / "trees" / f"{name}_binned_ref.npz").exists():
        pytest.skip(f"shared data not found at {SHARED_DATA} (reference trees and meshes)")
    import trimesh

    import jaxbvh

    tree, frame = jaxbvh.load(SHARED_DATA / "trees" / f"{name}_binned_ref.npz")
    assert frame.is_identity
    loaded = trimesh.load(SHARED_DATA / mesh, process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()
    tri = np.asarray(loaded.vertices, np.float64)[np.asarray(loaded.faces)].astype(np.float32)
    return tree, tri


def _embree_closest(tri, origin, direction):
    embreex = pytest.importorskip("embreex", reason="embreex (Embree bindings) is not installed: "
                                                    "pip install embreex")
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, tri)
    out = scene.run(origin.astype(np.float32), direction.astype(np.float32), output=1)
    del embreex
    t = np.where(out["primID"] >= 0, out["tfar"], np.inf)
    return t, out["primID"].astype(np.int32)


@pytest.mark.parametrize("name,mesh", REAL, ids=[n for n, _ in REAL])
@pytest.mark.parametrize("kind", rays.KINDS)
def test_closest_hits_equal_embree(name, mesh, kind):
    """Tolerance: hit distances agree to 1e-4 of the scene diagonal; a different
    triangle is accepted only at (numerically) the same distance (a shared edge or
    vertex); hit/miss may differ for at most 0.5% of rays (grazing rays through edges
    and silhouettes, where Möller–Trumbore and Embree's test round differently)."""
    tree, tri = _real_scene(name, mesh)
    origin, direction = rays.make_rays(jax.random.key(0), kind, tree, tri, 2000)
    hits = rays.closest_hit(tree, tri, origin, direction)
    t_e, prim_e = _embree_closest(tri, origin, direction)
    diag = float(np.linalg.norm(tri.reshape(-1, 3).max(0) - tri.reshape(-1, 3).min(0)))
    tol = 1e-4 * diag
    both = (hits.prim >= 0) & (prim_e >= 0)
    disagree = (hits.prim >= 0) != (prim_e >= 0)
    assert disagree.mean() <= 0.005, f"{disagree.sum()} of {len(origin)} rays disagree on hit/miss"
    assert np.all(np.abs(hits.t[both] - t_e[both]) <= tol)
    other = both & (hits.prim != prim_e)
    assert other.mean() <= 0.005
    assert (hits.prim >= 0).mean() > 0.05  # the drone scene is sparse: ~10% of camera rays hit


# ----------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------


def test_cli_trace(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="--image needs matplotlib (the plot extra)")
    import trimesh

    import jaxbvh
    from jaxbvh import cli

    rng = np.random.default_rng(12)
    tri = random_triangles(rng, 60).astype(np.float64)
    mesh_path = tmp_path / "soup.obj"
    trimesh.Trimesh(tri.reshape(-1, 3), np.arange(180).reshape(60, 3), process=False).export(mesh_path)
    tri = jaxbvh.load_mesh(mesh_path).triangles  # the OBJ rounds coordinates: use what it holds
    tree = median_tree(tri.astype(np.float32))
    tree_path = tmp_path / "soup.npz"
    jaxbvh.save(tree_path, tree)
    hits_path, image_path = tmp_path / "hits.npz", tmp_path / "view.png"
    status = cli.main(["trace", str(tree_path), str(mesh_path), "--rays", "400", "--kind",
                       "camera", "--seed", "3", "--json", "--save", str(hits_path),
                       "--image", str(image_path)])
    assert status == 0
    result = json.loads(capsys.readouterr().out)
    assert result["rays"] > 300 and result["box_tests"] > 0 and "rays_per_second" in result
    with np.load(hits_path) as saved:
        assert set(saved.files) >= {"origin", "direction", "t", "prim"}
        # the saved hits check out against brute force in world space
        t, prim = ref.brute_force_closest(tri.astype(np.float32), saved["origin"], saved["direction"])
        assert np.array_equal(saved["prim"], prim)
        np.testing.assert_allclose(saved["t"], t, rtol=1e-4)
    assert image_path.exists() and image_path.stat().st_size > 0
    status = cli.main(["trace", str(tree_path), str(mesh_path), "--kind", "nonsense"])
    assert status == 2
