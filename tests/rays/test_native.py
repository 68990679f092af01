"""The native ray engine (jaxbvh.rays.native): the JAX walk's hits and counters, ray by ray.

Checked against the NumPy twin (jaxbvh.rays.traversal_reference) under hypothesis (small
random trees binary and wide, every mode, float32 and float64, stacks that spill and climb,
skip flags, ties, zero direction components: hits, distances and counters bit for bit, as
neither numba nor NumPy contracts multiply-adds), against the JAX walk on the shapes
test_rays.py compiles (counters and hits exact, distances to the last bits), on a deep
chain, on a broken tree (the step bound), and for the engine choice and the import cost.
"""

from __future__ import annotations

import gc
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_rays import (
    BATCH,
    CAP,
    COUNTERS,
    assert_t_close,
    chain_tree,
    fixed,
    median_tree,
    mixed_rays,
    padded,
    random_triangles,
    widen,
)

from jaxbvh import native as engines
from jaxbvh import rays
from jaxbvh.rays import native
from jaxbvh.rays import traversal as traverse
from jaxbvh.rays import traversal_reference as ref
from jaxbvh.tree.layout import BVH
from jaxbvh.tree.validate import InvalidTreeError

pytest.importorskip("numba")

LISTS = ("hit_count", "hit_prims", "hit_t", "hits_overflow")


def twin_arrays(twin, name, mode, max_hits):
    """The twin's field ``name`` [R] (lists padded to ``max_hits`` as the engines pad them)."""
    if name == "hit_prims":
        return np.array([r[name] + [-1] * (max_hits - len(r[name])) for r in twin])
    if name == "hit_t":
        return np.array([r[name] + [np.inf] * (max_hits - len(r[name])) for r in twin])
    return np.array([r[name] for r in twin])


def assert_equal_to_twin(hits, twin, mode, max_hits, exact_t=True):
    names = COUNTERS + ("prim", "step_limit", "stack_overflow") + (("t", "u", "v") if exact_t else ())
    names += LISTS if mode == "all" else ()
    for name in names:
        expected = twin_arrays(twin, name, mode, max_hits)
        got = np.asarray(getattr(hits, name))
        if name in ("t", "u", "v", "hit_t"):
            expected = expected.astype(got.dtype)
        assert got.shape == expected.shape, name
        bad = np.flatnonzero((got != expected).reshape(len(got), -1).any(axis=1))
        assert bad.size == 0, f"{mode}: {name} differs on rays {bad[:5]}: {got[bad[:5]]} vs {expected[bad[:5]]}"


def with_ties_and_axis_rays(rng, tri, origin, direction):
    """Triangles with a copy of some (equal ``t`` on two ids: ties go to the lower id)
    and rays along the axes (zero direction components)."""
    copies = tri[rng.integers(0, len(tri), max(1, len(tri) // 4))]
    tri = np.concatenate([tri, copies])
    n = len(origin) // 4
    axis_dir = np.zeros((n, 3), direction.dtype)
    axis_dir[np.arange(n), np.arange(n) % 3] = np.where(np.arange(n) % 2, 1, -1)
    direction = np.concatenate([direction[: len(direction) - n], axis_dir])
    return tri, origin, direction


def as_dtype(tree, dtype):
    return tree.replace(lo=np.asarray(tree.lo, dtype), hi=np.asarray(tree.hi, dtype))


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), max_leaf=st.sampled_from([1, 3]),
       shape=st.sampled_from(["binary-axis", "binary-distance", "wide4"]),
       mode=st.sampled_from(["closest", "any", "all"]), dtype=st.sampled_from(["float32", "float64"]),
       short_stack=st.booleans(), flags=st.booleans())
def test_native_equals_twin(seed, n, max_leaf, shape, mode, dtype, short_stack, flags):
    """Hits, distances, barycentrics, counters and hit lists of the twin, ray by ray."""
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n, size=0.4)
    origin, direction = mixed_rays(rng, tri, 48)
    tri, origin, direction = with_ties_and_axis_rays(rng, tri, origin, direction)
    tree = median_tree(tri, max_leaf)
    if shape == "binary-distance":
        tree = tree.replace(axis=np.full(tree.capacity, -1, np.int32))
    elif shape == "wide4":
        tree = widen(tree, 4)
    k = 4 if shape == "wide4" else 2
    capacity = k if short_stack else CAP
    # skip flags on random nodes (the root's box is always tested): any flags are a valid
    # "assume hit" input, and both walks must honour them alike
    skip = (rng.random(tree.capacity) < 0.3) & (np.arange(tree.capacity) != int(tree.root)) if flags else None
    max_hits = 4  # short: lists overflow too
    with jax.enable_x64(dtype == "float64"):
        tree = as_dtype(tree, dtype)
        tri = tri.astype(dtype)
        origin, direction = origin.astype(dtype), direction.astype(dtype)
        hits = traverse.trace(tree, tri, origin, direction, mode=mode, capacity=capacity, max_hits=max_hits,
                              skip=skip, engine="native")
    assert hits.t.dtype == np.dtype(dtype)
    twin = ref.trace(tree, tri, origin, direction, mode=mode, capacity=capacity, max_hits=max_hits, skip=skip)
    assert_equal_to_twin(hits, twin, mode, max_hits)
    if mode == "closest":
        _, prim = ref.brute_force_closest(tri, origin, direction)
        assert np.array_equal(hits.prim, prim)


@pytest.mark.parametrize("shape,mode,capacity", [
    (shape, mode, capacity) for shape in ("binary-axis", "binary-distance", "wide4")
    for mode in ("closest", "any", "all") for capacity in (CAP, 2) if capacity == CAP or shape == "binary-axis"])
def test_native_equals_jax_walk(shape, mode, capacity):
    """The same Hits as the JAX walk (the shapes test_rays.py compiles): counters, hits and
    lists exact, distances up to the JAX walk's fused multiply-adds; the same dtypes."""
    rng = np.random.default_rng(17)
    tri = random_triangles(rng, 120, size=0.3)
    tree = median_tree(tri, max_leaf=3)
    if shape == "binary-distance":
        tree = tree.replace(axis=np.full(tree.capacity, -1, np.int32))
    elif shape == "wide4":
        tree = widen(tree, 4)
    origin, direction = mixed_rays(rng, tri, 96)
    kwargs = dict(mode=mode, capacity=capacity, max_hits=16, batch=BATCH)
    jax_hits = traverse.trace(fixed(tree), padded(tri), origin, direction, engine="jax", **kwargs)
    hits = traverse.trace(fixed(tree), padded(tri), origin, direction, engine="native", **kwargs)
    assert jax.tree_util.tree_structure(hits) == jax.tree_util.tree_structure(jax_hits)
    for name in COUNTERS + ("prim", "step_limit", "stack_overflow") + (("hit_count", "hit_prims", "hits_overflow")
                                                                       if mode == "all" else ()):
        a, b = np.asarray(getattr(hits, name)), np.asarray(getattr(jax_hits, name))
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert hits.t.dtype == jax_hits.t.dtype
    assert_t_close(hits.t, jax_hits.t, tri, direction, hits.prim)
    assert (hits.prim >= 0).any() and (hits.prim < 0).any()


def test_deep_chain_climbs_like_the_twin():
    """A 199-deep chain on a stack of 2 entries: the twin's counters (climbs included) and
    brute force's hits; rays climb."""
    rng = np.random.default_rng(12)
    tri = random_triangles(rng, 200, spread=3.0, size=0.2)
    tri = tri[np.argsort(tri.mean(axis=1)[:, 0])]
    tree = chain_tree(tri)
    origin, direction = mixed_rays(rng, tri, 96)
    hits = traverse.trace(tree, tri, origin, direction, capacity=2, engine="native")
    twin = ref.trace(tree, tri, origin, direction, capacity=2)
    assert_equal_to_twin(hits, twin, "closest", 16)
    unbounded = np.array([r["box_tests"] for r in ref.trace(tree, tri, origin, direction)])
    assert (hits.box_tests > unbounded).mean() > 0.1  # the climbs' box tests
    assert (hits.nodes_visited + hits.prim_tests).max() > 100


@pytest.mark.parametrize("engine", ["native", "jax"])
def test_broken_tree_reaches_the_step_bound(engine):
    """A cycle (the root listed as its own child) ends at the step bound and raises, on
    both engines; it does not hang. Sound trees of the same shapes do not."""
    rng = np.random.default_rng(3)
    tri = random_triangles(rng, 30)
    tree = median_tree(tri)
    origin, direction = mixed_rays(rng, tri, 8)
    traverse.trace(fixed(tree), padded(tri), origin, direction, mode="all", capacity=CAP, batch=BATCH,
                   engine=engine)
    left = np.asarray(tree.left).copy()
    left[int(tree.root)] = int(tree.root)
    broken = tree.replace(left=left)
    with pytest.raises(InvalidTreeError, match="did not end"):
        traverse.trace(fixed(broken), padded(tri), origin, direction, mode="all", capacity=CAP, batch=BATCH,
                       engine=engine)


def test_engine_choice_and_errors():
    """auto picks native on concrete CPU arrays with triangles, jax for another intersector;
    native under jit says to use jax; an unknown engine is refused; measure reports the
    engine that ran."""
    rng = np.random.default_rng(1)
    tri = random_triangles(rng, 10)
    tree = median_tree(tri)
    origin, direction = mixed_rays(rng, tri, 8)
    assert engines.choose("auto", tree, tri, origin, direction) == "native"
    assert engines.choose("auto", tree, tri, origin, direction, supported=False) == "jax"
    assert engines.choose("jax", tree, tri, origin, direction) == "jax"
    with pytest.raises(ValueError, match="engine must be one of"):
        rays.closest_hit(tree, tri, origin, direction, engine="embree")

    @jax.jit
    def inside(o):
        return rays.closest_hit(tree, tri, o, direction, engine="native").t

    with pytest.raises(TypeError, match="engine='jax'"):
        inside(jnp.asarray(origin))
    with pytest.raises(TypeError, match="custom intersector"):
        traverse.trace(tree, tri, origin, direction, engine="native", intersect=lambda *a: None)
    # measure names the engine that ran, not the one asked for
    for asked, ran in (("auto", "native"), ("jax", "jax"), ("native", "native")):
        assert rays.measure(tree, tri, origin, direction, engine=asked)[1]["engine"] == ran


def test_numba_cache_folder_follows_jaxbvh_cache(monkeypatch, tmp_path):
    from jaxbvh import compile_cache

    monkeypatch.delenv("JAXBVH_CACHE", raising=False)
    monkeypatch.setattr(compile_cache, "status", lambda: {"folder": str(tmp_path / "jax"), "owner": "jaxbvh"})
    assert engines.cache_folder() == tmp_path / "jax" / "numba"
    monkeypatch.setattr(compile_cache, "status", lambda: {"folder": str(tmp_path / "mine"), "owner": "user"})
    assert engines.cache_folder() is None
    monkeypatch.setattr(compile_cache, "status", lambda: {"folder": None, "owner": None})
    assert engines.cache_folder() is None


def test_binary_and_wide_inputs_as_jax_arrays():
    """Trees and rays given as JAX arrays (read-only NumPy views) trace alike."""
    rng = np.random.default_rng(5)
    tri = random_triangles(rng, 30)
    tree = median_tree(tri, max_leaf=2)
    assert isinstance(tree, BVH)
    origin, direction = mixed_rays(rng, tri, 32)
    a = rays.closest_hit(tree, tri, origin, direction, engine="native")
    b = rays.closest_hit(jax.tree_util.tree_map(jnp.asarray, tree), jnp.asarray(tri), jnp.asarray(origin),
                         jnp.asarray(direction), engine="native")
    for name in COUNTERS + ("prim", "t"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    none = rays.all_hits(tree, tri, origin[:0], direction[:0], max_hits=3, engine="native")
    assert none.prim.shape == (0,) and none.hit_prims.shape == (0, 3)


def test_packed_trees_are_reused_only_while_right():
    """A tree of JAX arrays is packed once and reused; another tree (JAX arrays of the same
    shapes) or a NumPy tree changed in place between calls is traced as it is now, never
    through a stale packed copy (the cache, and the rows reused between uncached calls)."""
    rng = np.random.default_rng(8)
    tri = random_triangles(rng, 40, size=0.3)
    tree = median_tree(tri, max_leaf=2)
    origin, direction = mixed_rays(rng, tri, 64)
    jtree = jax.tree_util.tree_map(jnp.asarray, tree)
    jtri = jnp.asarray(tri)
    first = rays.closest_hit(jtree, jtri, origin, direction, engine="native")
    dtype = np.dtype(np.float32)
    packed, cached = native.packed(native.kernels(), jtree, jtri, None, dtype)
    assert cached and native.packed(native.kernels(), jtree, jtri, None, dtype)[0] is packed  # packed once, reused
    assert not native.packed(native.kernels(), tree, tri, None, dtype)[1]  # NumPy: packed per call
    again = rays.closest_hit(jtree, jtri, origin, direction, engine="native")
    # the same shapes, other boxes and triangles: mirrored in x
    flipped_tri = tri * np.array([-1, 1, 1], tri.dtype)
    flipped = median_tree(flipped_tri, max_leaf=2)
    assert flipped.lo.shape == tree.lo.shape
    other = rays.closest_hit(jax.tree_util.tree_map(jnp.asarray, flipped), jnp.asarray(flipped_tri), origin,
                             direction, engine="native")
    twin = ref.trace(tree, tri, origin, direction)
    assert_equal_to_twin(first, twin, "closest", 16)
    assert_equal_to_twin(again, twin, "closest", 16)
    assert_equal_to_twin(other, ref.trace(flipped, flipped_tri, origin, direction), "closest", 16)
    assert not np.array_equal(other.prim, first.prim)
    # a NumPy tree and triangles changed in place: the next call sees the change
    np_tree = jax.tree_util.tree_map(np.array, tree)
    np_tri = tri.copy()
    assert_equal_to_twin(rays.closest_hit(np_tree, np_tri, origin, direction, engine="native"), twin, "closest", 16)
    for name in ("lo", "hi"):
        getattr(np_tree, name)[...] = getattr(flipped, name)
    for name in ("left", "right", "parent", "prim_start", "prim_count", "prim_index", "axis"):
        getattr(np_tree, name)[...] = getattr(flipped, name)
    np_tri[...] = flipped_tri
    assert_equal_to_twin(rays.closest_hit(np_tree, np_tri, origin, direction, engine="native"),
                         ref.trace(flipped, flipped_tri, origin, direction), "closest", 16)
    # a tree that dies leaves the cache (its packed copy is freed)
    probe, probe_tri = jax.tree_util.tree_map(jnp.asarray, tree), jnp.asarray(tri)
    arrays, cached = native.packed(native.kernels(), probe, probe_tri, None, dtype)
    assert cached
    gone = weakref.ref(arrays)
    del arrays, probe, probe_tri
    gc.collect()
    assert gone() is None


@pytest.mark.parametrize("shape", ["binary", "wide4"])
@pytest.mark.parametrize("broken", ["cycle", "parent"])
@pytest.mark.parametrize("arrays", ["numpy", "jax"])
def test_broken_trees_raise_on_every_packed_path(shape, broken, arrays):
    """A child cycle, or a parent link to itself met by a climb (a stack of ``k``
    entries), ends at the step bound and raises on the written-out binary and 4-wide
    branches, packed per call (NumPy) or cached (JAX arrays): no hang, no stale pack."""
    rng = np.random.default_rng(4)
    tri = random_triangles(rng, 60, size=0.3)
    tree = median_tree(tri)
    origin, direction = mixed_rays(rng, tri, 32)
    if shape == "wide4":
        tree = widen(tree, 4)
    k = 4 if shape == "wide4" else 2
    as_arrays = (lambda t: jax.tree_util.tree_map(jnp.asarray, t)) if arrays == "jax" else (lambda t: t)
    sound = rays.closest_hit(as_arrays(tree), tri, origin, direction, capacity=k, engine="native")
    assert_equal_to_twin(sound, ref.trace(tree, tri, origin, direction, capacity=k), "closest", 16)
    root = int(np.asarray(tree.root))
    if broken == "cycle":
        if shape == "binary":
            left = np.asarray(tree.left).copy()
            left[root] = root
            bad = tree.replace(left=left)
        else:
            child = np.asarray(tree.child).copy()
            child[root, 0] = root
            bad = tree.replace(child=child)
    else:
        # every node below the root names itself as parent: the first climb never ends
        parent = np.asarray(tree.parent).copy()
        nodes = np.flatnonzero(parent >= 0)
        parent[nodes] = nodes
        bad = tree.replace(parent=parent)
    with pytest.raises(InvalidTreeError, match="did not end"):
        rays.closest_hit(as_arrays(bad), tri, origin, direction, capacity=k, engine="native")


@pytest.mark.parametrize("shape", ["binary", "wide4"])
def test_capacity_padding_shares_one_packed_row(shape):
    """A tree padded to a capacity packs its padding into one shared row; the walk is the
    twin's on the padded tree (a stack of ``k``: climbs), and on a broken one whose root's
    child points into the padding (the middle of it and its last node)."""
    rng = np.random.default_rng(6)
    tri = random_triangles(rng, 50, size=0.3)
    tree = median_tree(tri, max_leaf=2)
    padded_tree = fixed(tree) if shape == "binary" else widen(tree, 4)
    k = 2 if shape == "binary" else 4
    n = padded_tree.capacity
    module = native.kernels()
    packed = native.PackedTree(module, padded_tree, tri, None, np.float32)
    assert packed.rows.shape[0] < n  # the padding shares a row
    # pack (every row, for other kernels): each node's own children ids and count in its row
    child = (np.stack([padded_tree.left, padded_tree.right], 1) if k == 2 else np.asarray(padded_tree.child))
    child = child.astype(np.int32)
    width = native.row_width(k, np.float32)
    rows = np.zeros((n, width), np.float32)
    flags = np.zeros(n, np.int32)
    slots = np.zeros((padded_tree.prim_index.shape[0], 10), np.float32)
    i32 = np.int32
    axis = np.asarray(padded_tree.axis, i32) if k == 2 else np.full(n, -1, i32)
    module.pack(child, np.asarray(padded_tree.lo, np.float32), np.asarray(padded_tree.hi, np.float32),
                np.asarray(padded_tree.prim_start, i32), np.asarray(padded_tree.prim_count, i32), axis,
                np.zeros(n, i32), np.asarray(padded_tree.prim_index, i32), tri.astype(np.float32), rows,
                rows.view(i32), flags, slots, slots.view(i32))
    assert np.array_equal(rows.view(i32)[:, 6 * k:7 * k], child)
    assert np.array_equal(rows.view(i32)[:, 7 * k], np.asarray(padded_tree.prim_count))
    assert np.array_equal(rows.view(i32)[: packed.rows.shape[0], : 7 * k + 2], packed.irows[:, : 7 * k + 2])
    origin, direction = mixed_rays(rng, tri, 64)
    root = int(np.asarray(padded_tree.root))
    for target in (None, packed.rows.shape[0] + (n - packed.rows.shape[0]) // 2, n - 1):
        tree_now = padded_tree
        if target is not None:
            if shape == "binary":
                right = np.asarray(padded_tree.right).copy()
                right[root] = target
                tree_now = padded_tree.replace(right=right)
            else:
                child = np.asarray(padded_tree.child).copy()
                child[root, 1] = target
                tree_now = padded_tree.replace(child=child)
        # (the twin climbs sound trees only)
        for capacity in (k, CAP) if target is None else (CAP,):
            hits = native.trace(tree_now, tri, origin, direction, 0.0, np.inf, dtype=np.dtype(np.float32),
                                mode="closest", capacity=capacity, max_hits=16,
                                step_limit=traverse.max_steps(tree_now))
            twin = ref.trace(tree_now, tri, origin, direction, capacity=capacity)
            assert_equal_to_twin(hits, twin, "closest", 16)
