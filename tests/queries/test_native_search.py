"""The native engine of closest_point, overlap and within (jaxbvh.queries.native_search).

Held equal, query by query, to the NumPy twin (every field: the walk's choices and
counters, and the closest point's geometry bit for bit: both evaluate the same scalar
formulas in the tree's dtype) and to the JAX engine (the choices, lists and counters
exactly; the closest point's distance, barycentrics and point to rounding: XLA may fuse
a multiply and an add where NumPy and numba round twice). Random small trees (binary,
4-wide, chains), float32 and float64, points on corners (ties), near and far.
"""

from __future__ import annotations

import sys

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxbvh import queries
from jaxbvh.queries import native_search
from jaxbvh.queries import search_reference as ref

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from test_queries import COUNTERS, chain_tree, make_tree, padded, random_triangles  # noqa: E402

pytest.importorskip("numba")

KINDS = ("binned", "wide", "chain")
DTYPES = (np.float32, np.float64)


def host(result):
    return jax.tree_util.tree_map(np.asarray, result)


def assert_same_dtypes_and_shapes(a, b):
    for name in a._fields:
        x, y = getattr(a, name), getattr(b, name)
        assert isinstance(x, jax.Array), name
        assert x.dtype == y.dtype and x.shape == y.shape, (name, x.dtype, y.dtype, x.shape, y.shape)


def in_dtype(dtype):
    """float64 trees need JAX's x64 switched on while they exist."""
    return jax.enable_x64(dtype == np.float64)


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), kind=st.sampled_from(KINDS),
       dtype=st.sampled_from(DTYPES))
def test_native_closest_point_equals_twin_and_jax(seed, n, kind, dtype):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n).astype(dtype)
    tri[n // 2:] = tri[: n - n // 2]  # copies at higher ids: exact ties, to the lower id
    points = rng.uniform(-1.6, 1.6, (12, 3)).astype(dtype)
    points[:4] = tri[rng.integers(0, n, 4), rng.integers(0, 3, 4)]  # on a corner
    points[4:6] = tri[rng.integers(0, n, 2)].mean(axis=1) + rng.normal(0, 1e-3, (2, 3))  # near the surface
    points[6:8] *= 40  # far: every box kept until the first triangle
    radius = np.where(np.arange(12) % 3 == 0, np.inf, rng.uniform(0, 1, 12)).astype(dtype)
    with in_dtype(dtype):
        tree = make_tree(tri, kind)
        assert np.asarray(tree.lo).dtype == dtype
        nat = queries.closest_point(tree, padded(tri), points, max_distance=radius, engine="native")
        jx = queries.closest_point(tree, padded(tri), points, max_distance=radius, engine="jax")
        assert_same_dtypes_and_shapes(nat, jx)
        nat, jx = host(nat), host(jx)
        for i, p in enumerate(points):
            prim, dist, counts, limit = ref.closest_point(tree, tri, p, radius[i])
            assert nat.prim[i] == prim == jx.prim[i] and nat.step_limit[i] == limit == jx.step_limit[i]
            for name in COUNTERS:
                assert getattr(nat, name)[i] == counts[name] == getattr(jx, name)[i], name
            if prim < 0:
                assert np.isinf(nat.distance[i]) and nat.u[i] == nat.v[i] == 0 and nat.feature[i] == -1
                assert np.isnan(nat.point[i]).all()
                continue
            d2, q, u, v, feature = ref.closest_on_triangle(p, *tri[prim])
            assert nat.distance[i] == dist and nat.u[i] == u and nat.v[i] == v and nat.feature[i] == feature
            assert np.array_equal(nat.point[i], q)
        scale = 1e-5 if dtype == np.float32 else 1e-12
        hit = nat.prim >= 0
        for name in ("distance", "u", "v", "point"):
            assert np.allclose(getattr(nat, name)[hit], getattr(jx, name)[hit], rtol=scale, atol=scale), name


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), kind=st.sampled_from(KINDS),
       dtype=st.sampled_from(DTYPES), capacity=st.sampled_from([3, 64]), as_boxes=st.booleans())
def test_native_overlap_and_within_equal_twin_and_jax(seed, n, kind, dtype, capacity, as_boxes):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n).astype(dtype)
    t_lo, t_hi = tri.min(axis=1), tri.max(axis=1)
    prims = (padded(t_lo[:, None])[:, 0], padded(t_hi[:, None])[:, 0]) if as_boxes else padded(tri)
    twin_prims = (t_lo, t_hi) if as_boxes else tri
    centre = rng.uniform(-1.3, 1.3, (2, 4, 3)).astype(dtype)  # a [2, 4] batch
    centre[0, 0] = tri[0, 0]  # on a corner: the ball and box touch
    half = rng.uniform(0, 0.6, (2, 4, 3)).astype(dtype)
    radius = rng.uniform(0, 0.8, (2, 4)).astype(dtype)
    radius[0, 1] = 0
    with in_dtype(dtype):
        tree = make_tree(tri, kind)
        for query, args, twin in (
                (queries.overlap, (centre - half, centre + half),
                 lambda j: ref.overlap(tree, twin_prims, (centre - half)[j], (centre + half)[j], capacity)),
                (queries.within, (centre, radius),
                 lambda j: ref.within(tree, twin_prims, centre[j], radius[j], capacity))):
            nat = query(tree, prims, *args, capacity=capacity, engine="native")
            jx = query(tree, prims, *args, capacity=capacity, engine="jax")
            assert_same_dtypes_and_shapes(nat, jx)
            assert nat.prims.shape == (2, 4, capacity)
            nat, jx = host(nat), host(jx)
            for name in nat._fields:
                assert np.array_equal(getattr(nat, name), getattr(jx, name)), name
            for j in np.ndindex(2, 4):
                listed, count, counts, limit = twin(j)
                assert nat.prims[j].tolist() == listed and nat.count[j] == count
                assert nat.overflow[j] == (count > capacity) and nat.step_limit[j] == limit
                for name in COUNTERS:
                    assert getattr(nat, name)[j] == counts[name], name


def test_signed_native_distance_equals_jax(bundled_mesh):
    """The sign from pseudonormals: native and jax agree on every point near a closed mesh."""
    import jaxbvh

    lo, hi = bundled_mesh.local_boxes()
    tri = np.asarray(bundled_mesh.local_triangles())
    tree = jaxbvh.build(lo, hi, method="binned")
    normals = queries.pseudonormals(tri)
    rng = np.random.default_rng(3)
    # face centres moved a little along their normals, in or out
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pick = rng.integers(0, len(tri), 64)
    step = 1e-3 * np.linalg.norm(hi.max(0) - lo.min(0))
    points = (tri[pick].mean(axis=1) + rng.choice([-1, 1], (64, 1)) * step * normal[pick]).astype(np.float32)
    nat = host(queries.closest_point(tree, tri, points, normals, engine="native"))
    jx = host(queries.closest_point(tree, tri, points, normals, engine="jax"))
    assert np.array_equal(nat.prim, jx.prim)
    assert np.array_equal(np.sign(nat.distance), np.sign(jx.distance))
    assert 5 < (nat.distance < 0).sum() < 59
    assert np.allclose(nat.distance, jx.distance, rtol=1e-5, atol=1e-7)


def broken_chain(n=6):
    """A chain whose last interior node's right child is the root: a cycle."""
    rng = np.random.default_rng(0)
    tri = random_triangles(rng, n)
    tree = chain_tree(tri.min(axis=1), tri.max(axis=1))
    right = np.asarray(tree.right).copy()
    right[n - 2] = int(tree.root)
    return tree.replace(right=jax.numpy.asarray(right)), tri


def test_a_broken_tree_stops_at_the_step_bound_and_says_so():
    tree, tri = broken_chain()
    everywhere = np.array([[-9.0, -9, -9]], np.float32), np.array([[9.0, 9, 9]], np.float32)
    for engine in ("native", "jax"):
        got = queries.closest_point(tree, tri, np.zeros((2, 3), np.float32), engine=engine)
        assert np.asarray(got.step_limit).all(), engine
        box = queries.overlap(tree, tri, *everywhere, capacity=8, engine=engine)
        ball = queries.within(tree, tri, np.zeros((1, 3), np.float32), 50.0, capacity=8, engine=engine)
        assert np.asarray(box.step_limit).all() and np.asarray(ball.step_limit).all(), engine
    native = host(queries.closest_point(tree, tri, np.zeros((2, 3), np.float32), engine="native"))
    jx = host(queries.closest_point(tree, tri, np.zeros((2, 3), np.float32), engine="jax"))
    for name in ("prim", "step_limit") + COUNTERS:
        assert np.array_equal(getattr(native, name), getattr(jx, name)), name


def test_engines_under_jit_and_the_engine_argument():
    rng = np.random.default_rng(1)
    tri = random_triangles(rng, 10)
    tree = make_tree(tri, "binned")
    points = rng.uniform(-1, 1, (5, 3)).astype(np.float32)

    with pytest.raises(TypeError, match="cannot run inside"):
        jax.jit(lambda p: queries.closest_point(tree, padded(tri), p, engine="native").distance)(points)
    with pytest.raises(TypeError, match="cannot run inside"):
        jax.jit(lambda p: queries.within(tree, padded(tri), p, 0.5, capacity=4, engine="native").count)(points)
    # "auto" inside jit and grad takes the jax engine: it runs and differentiates
    inside = jax.jit(lambda p: queries.closest_point(tree, padded(tri), p).distance)(points)
    outside = queries.closest_point(tree, padded(tri), points).distance  # auto: native here
    assert np.allclose(inside, outside, rtol=1e-5)
    grad = jax.grad(lambda p: queries.closest_point(tree, padded(tri), p).distance.sum())(points)
    assert np.isfinite(np.asarray(grad)).all() and np.abs(np.asarray(grad)).sum() > 0
    with pytest.raises(ValueError, match="engine"):
        queries.closest_point(tree, padded(tri), points, engine="numba")


def test_a_tree_the_kernels_do_not_take_goes_to_the_jax_engine():
    """A float16 tree: "auto" answers on the JAX engine, "native" refuses it plainly."""
    rng = np.random.default_rng(3)
    tri = random_triangles(rng, 10)
    tree = make_tree(tri, "binned")
    half = tree.replace(lo=np.asarray(tree.lo).astype(np.float16), hi=np.asarray(tree.hi).astype(np.float16))
    points = rng.uniform(-1, 1, (4, 3)).astype(np.float16)
    assert native_search.supports(tree) and not native_search.supports(half)
    auto = queries.closest_point(half, padded(tri).astype(np.float16), points)
    jax_engine = queries.closest_point(half, padded(tri).astype(np.float16), points, engine="jax")
    np.testing.assert_array_equal(np.asarray(auto.prim), np.asarray(jax_engine.prim))
    with pytest.raises(TypeError, match="does not cover"):
        queries.closest_point(half, padded(tri).astype(np.float16), points, engine="native")
