"""Queries (jaxbvh.queries): closest point, box overlap, radius, gradients.

Checked against brute force over every triangle (hypothesis, small random meshes, binary,
wide and 2,000-deep chain trees), against the NumPy twin query by query (results and
every counter), and gradients against central finite differences in float64.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh import queries
from jaxbvh.queries import search_reference as ref
from jaxbvh.rays import traversal_reference as ray_twin
from jaxbvh.rays.stack_walk import STACK
from jaxbvh.tree import from_interchange, pad_to, validate
from jaxbvh.wide import collapse

COUNTERS = ("box_tests", "prim_tests", "nodes_visited", "leaves_visited")
# one shape for every test tree and triangle array, so each query compiles once per arity
NODES, PRIMS = 128, 64


def random_triangles(rng, n, spread=1.0, size=0.3):
    centre = rng.uniform(-spread, spread, (n, 1, 3))
    return (centre + rng.normal(0, size, (n, 3, 3))).astype(np.float32)


def padded(triangles, rows=PRIMS):
    out = np.zeros((rows, 3, 3), triangles.dtype)
    out[: triangles.shape[0]] = triangles
    return out


def make_tree(triangles, kind):
    """``"binned"`` (jaxbvh.build, leaves up to 3), ``"wide"`` (its 4-wide collapse) or
    ``"chain"`` (every interior node has a leaf on the left: depth n - 1), at NODES/PRIMS."""
    n = triangles.shape[0]
    lo, hi = triangles.min(axis=1), triangles.max(axis=1)
    if kind == "chain":
        return pad_to(chain_tree(lo, hi), NODES, PRIMS)
    tree = pad_to(jaxbvh.build(lo, hi, method="binned", max_leaf=3, capacity=PRIMS), NODES, PRIMS)
    if kind == "wide":
        tree = collapse.optimal(tree, max_children=4).tree
    validate(tree, lo, hi, n)
    return tree


def chain_tree(lo, hi):
    """The deepest binary tree over ``n`` boxes: interior node ``i`` has leaf ``i`` left
    and the rest of the chain right (interchange arrays; node ids: interior 0..n-2, then leaves)."""
    n = lo.shape[0]
    if n == 1:
        arrays = dict(child=np.array([[-1, -1]], np.int32), prim_start=np.array([0], np.int32),
                      prim_count=np.array([1], np.int32), prim_index=np.array([0], np.int32),
                      lo=lo[:1], hi=hi[:1], root=np.int32(0))
        return from_interchange(arrays)
    inner, total = n - 1, 2 * n - 1
    child = np.full((total, 2), -1, np.int32)
    start = np.zeros(total, np.int32)
    count = np.zeros(total, np.int32)
    box_lo, box_hi = np.zeros((total, 3), lo.dtype), np.zeros((total, 3), lo.dtype)
    for i in range(n):
        leaf = inner + i
        start[leaf], count[leaf] = i, 1
        box_lo[leaf], box_hi[leaf] = lo[i], hi[i]
    for i in reversed(range(inner)):
        rest = i + 1 if i + 1 < inner else inner + n - 1
        child[i] = [inner + i, rest]
        box_lo[i] = np.minimum(lo[i], box_lo[rest])
        box_hi[i] = np.maximum(hi[i], box_hi[rest])
    arrays = dict(child=child, prim_start=start, prim_count=count, prim_index=np.arange(n, dtype=np.int32),
                  lo=box_lo, hi=box_hi, root=np.int32(0))
    return from_interchange(arrays, pad=False)


def brute_closest(triangles, point):
    """(d2 [T]) of ``point`` to every triangle, by the twin's triangle rule."""
    return np.array([ref.closest_on_triangle(point, *t)[0] for t in triangles])


def assert_twin_counts(got, i, counts):
    for name in COUNTERS:
        assert int(getattr(got, name)[i]) == counts[name], (name, i, int(getattr(got, name)[i]), counts)


# ----------------------------------------------------------------------------------
# Closest point
# ----------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), kind=st.sampled_from(["binned", "wide", "chain"]))
def test_closest_point_equals_brute_force_and_twin(seed, n, kind):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n)
    tree = make_tree(tri, kind)
    points = rng.uniform(-1.6, 1.6, (16, 3)).astype(np.float32)
    points[:4] = tri[rng.integers(0, n, 4), rng.integers(0, 3, 4)]  # on a corner: ties between triangles
    got = jax.tree_util.tree_map(np.asarray, queries.closest_point(tree, padded(tri), points, engine="jax"))
    assert not got.step_limit.any()
    for i, p in enumerate(points):
        d2 = brute_closest(tri, p)
        best = d2.min()
        assert got.prim[i] == np.flatnonzero(d2 == best)[0], (i, got.prim[i], d2[got.prim[i]], best)
        assert np.isclose(got.distance[i], np.sqrt(best), rtol=1e-6, atol=1e-7)
        prim, dist, counts, limit = ref.closest_point(tree, tri, p)
        assert prim == got.prim[i] and not limit
        assert_twin_counts(got, i, counts)
        # the reported point and barycentrics agree with the triangle
        a, b, c = tri[got.prim[i]].astype(np.float64)
        u, v = float(got.u[i]), float(got.v[i])
        assert u >= -1e-6 and v >= -1e-6 and u + v <= 1 + 1e-6
        assert np.allclose(a + u * (b - a) + v * (c - a), got.point[i], atol=1e-5)


def test_max_distance_limits_the_search():
    rng = np.random.default_rng(3)
    tri = random_triangles(rng, 30)
    tree = make_tree(tri, "binned")
    points = rng.uniform(-2, 2, (32, 3)).astype(np.float32)
    full = queries.closest_point(tree, padded(tri), points)
    radius = float(np.median(full.distance))
    cut = jax.tree_util.tree_map(np.asarray, queries.closest_point(tree, padded(tri), points, max_distance=radius))
    inside = np.asarray(full.distance) <= radius
    assert 0 < inside.sum() < len(points)
    assert np.array_equal(cut.prim[inside], np.asarray(full.prim)[inside])
    assert (cut.prim[~inside] == -1).all() and np.isinf(cut.distance[~inside]).all()
    assert (cut.feature[~inside] == -1).all() and np.isnan(cut.point[~inside]).all()
    for i in np.flatnonzero(~inside)[:4]:
        assert ref.closest_point(tree, tri, points[i], radius)[0] == -1
    assert (cut.prim_tests <= np.asarray(full.prim_tests)).all()


def test_closest_on_triangle_beats_every_sample():
    """The closest point lies on the triangle and no point of a dense sample of it is closer."""
    rng = np.random.default_rng(0)
    s = np.linspace(0, 1, 41)
    uu, vv = np.meshgrid(s, s)
    keep = uu + vv <= 1
    uu, vv = uu[keep], vv[keep]
    one = jax.jit(jax.vmap(queries.closest_on_triangle))
    p = rng.normal(0, 1, (200, 3))
    tri = rng.normal(0, 1, (200, 3, 3))
    tri[:10, 2] = tri[:10, 0] + 0.5 * (tri[:10, 1] - tri[:10, 0])  # degenerate: a segment
    tri[10:20, 1] = tri[10:20, 0]  # degenerate: two corners equal
    p[20:60] = np.einsum("pc,pcx->px", rng.dirichlet([1, 1, 1], 40), tri[20:60])  # on the triangle
    with jax.enable_x64(True):
        d2, q, u, v, feature = map(np.asarray, one(*map(jnp.asarray, (p, tri[:, 0], tri[:, 1], tri[:, 2]))))
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    assert np.allclose(a + u[:, None] * (b - a) + v[:, None] * (c - a), q, atol=1e-12)
    assert (u >= 0).all() and (v >= 0).all() and (u + v <= 1 + 1e-12).all()
    assert np.allclose(d2, np.sum((p - q) ** 2, axis=1), rtol=1e-12)
    samples = a[:, None] + uu[None, :, None] * (b - a)[:, None] + vv[None, :, None] * (c - a)[:, None]
    sampled = np.min(np.sum((p[:, None] - samples) ** 2, axis=2), axis=1)
    assert (d2 <= sampled + 1e-12).all()
    assert np.allclose(d2[20:60], 0, atol=1e-20)
    # the feature names where q lies: face interior, an edge's inside, or a corner
    corner = np.stack([a, b, c], axis=1)
    at_vertex = feature >= 4
    assert np.allclose(q[at_vertex], corner[at_vertex, feature[at_vertex] - 4])
    assert set(np.unique(feature)) <= set(range(7))


def winding_numbers(triangles, points):
    """Generalised winding number (Jacobson et al. 2013) of each point: 1 inside a closed
    outward-oriented mesh, 0 outside (the solid angles of every triangle, van Oosterom)."""
    out = []
    for p in points:
        a, b, c = (triangles[:, i] - p for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        out.append(np.sum(2 * np.arctan2(det, den)) / (4 * np.pi))
    return np.array(out)


def test_signed_distance_agrees_with_winding_number(bundled_mesh):
    """On the bundled mesh (closed), the pseudonormal sign is the winding number's inside."""
    tri = bundled_mesh.local_triangles().astype(np.float64)
    lo, hi = bundled_mesh.local_boxes()
    tree = jaxbvh.build(lo, hi, method="lbvh")
    rng = np.random.default_rng(1)
    centre, size = (lo.min(0) + hi.max(0)) / 2, hi.max(0) - lo.min(0)
    points = (centre + rng.uniform(-0.6, 0.6, (64, 3)) * size).astype(np.float32)
    # points close to the surface too: a corner or face centre moved a little along its normal
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pick = rng.integers(0, tri.shape[0], 32)
    near = tri[pick].mean(axis=1) + rng.choice([-1, 1], (32, 1)) * 1e-3 * np.linalg.norm(size) * normal[pick]
    points = np.concatenate([points, near.astype(np.float32)])
    signed = np.asarray(queries.closest_point(tree, tri.astype(np.float32), points,
                                              queries.pseudonormals(tri)).distance)
    winding = winding_numbers(tri, points.astype(np.float64))
    assert np.allclose(np.abs(winding - 0.5), 0.5, atol=1e-6), "the bundled mesh should be closed"
    assert np.array_equal(signed < 0, winding > 0.5)
    assert 10 < (signed < 0).sum() < len(points) - 10


# ----------------------------------------------------------------------------------
# Lists: overlap and within
# ----------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), kind=st.sampled_from(["binned", "wide", "chain"]),
       capacity=st.sampled_from([4, 64]), as_boxes=st.booleans())
def test_overlap_and_within_equal_brute_force_and_twin(seed, n, kind, capacity, as_boxes):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n)
    tree = make_tree(tri, kind)
    t_lo, t_hi = tri.min(axis=1), tri.max(axis=1)
    prims = (padded(t_lo[:, None])[:, 0], padded(t_hi[:, None])[:, 0]) if as_boxes else padded(tri)
    twin_prims = (t_lo, t_hi) if as_boxes else tri
    centre = rng.uniform(-1.3, 1.3, (8, 3)).astype(np.float32)
    half = rng.uniform(0, 0.6, (8, 3)).astype(np.float32)
    radius = rng.uniform(0, 0.8, 8).astype(np.float32)
    got_box = jax.tree_util.tree_map(np.asarray, queries.overlap(tree, prims, centre - half, centre + half,
                                                                 capacity=capacity, engine="jax"))
    got_ball = jax.tree_util.tree_map(np.asarray, queries.within(tree, prims, centre, radius, capacity=capacity,
                                                                  engine="jax"))
    for i in range(len(centre)):
        q_lo, q_hi = centre[i] - half[i], centre[i] + half[i]
        box_truth = np.flatnonzero(np.all((t_lo <= q_hi) & (q_lo <= t_hi), axis=1))
        if as_boxes:
            d2 = np.array([ref.box_distance2(centre[i], t_lo[j], t_hi[j]) for j in range(n)])
        else:
            d2 = brute_closest(tri, centre[i])
        ball_truth = np.flatnonzero(d2 <= radius[i] * radius[i])
        for got, truth, twin in ((got_box, box_truth, ref.overlap(tree, twin_prims, q_lo, q_hi, capacity)),
                                 (got_ball, ball_truth, ref.within(tree, twin_prims, centre[i], radius[i], capacity))):
            listed = got.prims[i][got.prims[i] >= 0]
            assert got.count[i] == truth.size and got.overflow[i] == (truth.size > capacity)
            assert len(set(listed.tolist())) == listed.size == min(truth.size, capacity)
            assert set(listed.tolist()) <= set(truth.tolist())
            assert got.prims[i].tolist() == twin[0] and got.count[i] == twin[1]
            assert_twin_counts(got, i, twin[2])
            assert not got.step_limit[i]


@pytest.mark.parametrize("engine", ["jax", "native"])
def test_queries_use_no_stack_a_deep_chain_is_exact(engine):
    """A 2,000-deep chain (a stack walk would need 2,000 entries per query): closest point
    and radius lists equal brute force; the walk's state is a few scalars."""
    rng = np.random.default_rng(7)
    n = 2000
    tri = random_triangles(rng, n, spread=3.0, size=0.05)
    tree = chain_tree(tri.min(axis=1), tri.max(axis=1))
    assert int(np.max(jaxbvh.tree.depth(tree))) == n - 1
    points = rng.uniform(-3, 3, (8, 3)).astype(np.float32)
    got = queries.closest_point(tree, tri, points, engine=engine)
    listed = queries.within(tree, tri, points, 0.3, capacity=32, engine=engine)
    for i, p in enumerate(points):
        d2 = brute_closest(tri, p)
        assert int(got.prim[i]) == np.flatnonzero(d2 == d2.min())[0]
        truth = np.flatnonzero(d2 <= np.float32(0.3) * np.float32(0.3))
        assert int(listed.count[i]) == truth.size
        assert set(np.asarray(listed.prims[i])[: truth.size].tolist()) == set(truth.tolist())


# ----------------------------------------------------------------------------------
# Inside a user's jit / vmap, and gradients
# ----------------------------------------------------------------------------------


def test_one_compile_serves_every_tree_of_a_bucket():
    """Trees and triangles are arguments: a second tree of the same shapes reuses the program,
    and the query runs inside a user's own jit and vmap."""
    rng = np.random.default_rng(5)
    trees = [(make_tree(t, "binned"), padded(t)) for t in (random_triangles(rng, 20), random_triangles(rng, 33))]

    @jax.jit
    def mean_distance(tree, tri, pts):
        return jnp.mean(jax.vmap(lambda p: queries.closest_point(tree, tri, p).distance)(pts))

    points = rng.uniform(-1, 1, (10, 3)).astype(np.float32)
    got = [float(mean_distance(t, tri, points)) for t, tri in trees]
    assert mean_distance._cache_size() == 1
    for (t, tri), g in zip(trees, got):
        assert np.isclose(g, np.mean(np.asarray(queries.closest_point(t, tri, points).distance)), rtol=1e-6)


def central_difference(f, x, h=1e-6):
    """d f / d x by central differences (f: float64 array -> float), same shape as ``x``."""
    x = np.array(x, np.float64)
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        step = np.zeros_like(x)
        step[idx] = h
        g[idx] = (f(x + step) - f(x - step)) / (2 * h)
    return g


def assert_gradient(analytic, numeric):
    analytic, numeric = np.asarray(analytic), np.asarray(numeric)
    scale = max(np.max(np.abs(numeric)), 1e-3)
    assert np.allclose(analytic, numeric, rtol=1e-6, atol=1e-6 * scale), (analytic, numeric)


def test_closest_point_distance_gradients_match_finite_differences():
    rng = np.random.default_rng(11)
    with jax.enable_x64(True):
        tri = random_triangles(rng, 24).astype(np.float64)
        tree = make_tree(tri.astype(np.float32), "binned")
        tree = tree.replace(lo=np.asarray(tree.lo, np.float64), hi=np.asarray(tree.hi, np.float64))
        tri_p = padded(tri)
        points = rng.uniform(-1.5, 1.5, (6, 3))
        pn = queries.pseudonormals(tri_p)
        for i, p in enumerate(points):
            def dist(pt, tr=tri_p):
                return queries.closest_point(tree, tr, pt, pn).distance

            hit = queries.closest_point(tree, tri_p, p)
            assert int(hit.prim) >= 0
            assert_gradient(jax.grad(dist)(p), central_difference(lambda x: float(dist(x)), p))
            # w.r.t. the chosen triangle's corners (the others have zero gradient)
            g_tri = np.asarray(jax.grad(lambda tr: dist(p, tr))(jnp.asarray(tri_p)))
            k = int(hit.prim)
            assert np.all(np.delete(g_tri, k, axis=0) == 0)

            assert_gradient(g_tri[k], central_difference(lambda c: float(dist(p, _with(tri_p, k, c))), tri_p[k]))
            for name in ("u", "v"):
                f = lambda pt, name=name: getattr(queries.closest_point(tree, tri_p, pt), name)  # noqa: E731
                assert_gradient(jax.grad(f)(p), central_difference(lambda x: float(f(x)), p))
            # forward mode gives the same directional derivative
            direction = rng.normal(size=3)
            _, tangent = jax.jvp(dist, (jnp.asarray(p),), (jnp.asarray(direction),))
            assert np.isclose(float(tangent), float(jax.grad(dist)(p) @ direction), rtol=1e-9)


def _with(tri, k, corners):
    out = np.array(tri, copy=True)
    out[k] = corners
    return out


def test_a_miss_has_zero_gradient():
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        tri = padded(random_triangles(rng, 10).astype(np.float64))
        tree = make_tree(tri[:10].astype(np.float32), "binned")
        far = jnp.array([9.0, 9.0, 9.0])
        g = jax.grad(lambda p: jnp.where(jnp.isinf(d := queries.closest_point(tree, tri, p, max_distance=0.5).distance),
                                         0.0, d))(far)
        assert np.all(np.asarray(g) == 0)
        t_grad = jax.grad(lambda o: queries.ray_hit(tri, -1, o, jnp.array([1.0, 0, 0]))[1])(far)
        assert np.all(np.asarray(t_grad) == 0)


def test_ray_hit_gradients_match_finite_differences():
    """t, u, v of closest hits (the search by jaxbvh.rays, the recompute differentiable)."""
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        tri = random_triangles(rng, 20).astype(np.float64)
        tree = make_tree(tri.astype(np.float32), "binned")
        target = np.einsum("rc,rcx->rx", rng.dirichlet([2, 2, 2], 6), tri[rng.integers(0, 20, 6)])
        origin = rng.uniform(-2, 2, (6, 3))
        direction = target - origin
        hits = queries.closest_hit(tree, tri.astype(np.float32), origin.astype(np.float32),
                                   direction.astype(np.float32))
        assert (hits.prim >= 0).all()
        t, _, _ = queries.ray_hit(tri, hits.prim, origin, direction)
        assert np.allclose(np.asarray(t), hits.t, rtol=1e-5)
        for r in range(6):
            k = int(hits.prim[r])
            for out in range(3):
                def f(o, d, c, out=out, k=k):
                    return queries.ray_hit(jnp.asarray(tri).at[k].set(c), k, o, d)[out]
                args = (origin[r], direction[r], tri[k])
                grads = jax.grad(f, argnums=(0, 1, 2))(*args)
                for which, g in enumerate(grads):
                    def moved(x, which=which):
                        a = list(args)
                        a[which] = x
                        return float(f(*a))
                    assert_gradient(g, central_difference(moved, args[which]))


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), kind=st.sampled_from(["binned", "wide", "chain"]),
       first=st.booleans())
def test_raycast_equals_brute_force_and_twin(seed, n, kind, first):
    rng = np.random.default_rng(seed)
    tri = random_triangles(rng, n)
    tree = make_tree(tri, kind)
    origin = rng.uniform(-1.5, 1.5, (16, 3)).astype(np.float32)
    target = np.einsum("rc,rcx->rx", rng.dirichlet([1, 1, 1], 16), tri[rng.integers(0, n, 16)])
    direction = np.where(rng.random((16, 1)) < 0.5, target - origin, rng.normal(size=(16, 3))).astype(np.float32)
    direction[0] = [0, 0, 1]  # zero components: the slab's huge inverse
    got = jax.tree_util.tree_map(np.asarray, queries.raycast(tree, padded(tri), origin, direction, first=first))
    assert isinstance(got, queries.Hits) and queries.RayHit is queries.Hits  # one result type
    assert not got.step_limit.any() and not got.stack_overflow.any()
    closest = queries.closest_hit(tree, padded(tri), origin, direction)  # jaxbvh.rays' own driver
    mode = "any" if first else "closest"
    twin = ray_twin.trace(tree, tri, origin, direction, mode=mode, capacity=STACK)
    for i in range(16):
        assert twin[i]["prim"] == got.prim[i] and not twin[i]["step_limit"]
        assert_twin_counts(got, i, twin[i])
        if first:
            assert (got.prim[i] >= 0) == (closest.prim[i] >= 0)
        else:
            assert got.prim[i] == closest.prim[i]
            assert np.isclose(got.t[i], closest.t[i], rtol=1e-5) or got.t[i] == closest.t[i]
    _, brute = ray_twin.brute_force_closest(tri, origin, direction)
    if not first:
        assert np.array_equal(got.prim, brute)
    # any leading shape: [2, 8] rays give the same records, reshaped
    square = queries.raycast(tree, padded(tri), origin.reshape(2, 8, 3), direction.reshape(2, 8, 3), first=first)
    assert np.array_equal(np.asarray(square.prim).reshape(-1), got.prim)


def test_raycast_gradients_match_finite_differences():
    """raycast inside jit, differentiated w.r.t. origin and direction (float64)."""
    rng = np.random.default_rng(9)
    with jax.enable_x64(True):
        tri = random_triangles(rng, 16).astype(np.float64)
        tree = make_tree(tri.astype(np.float32), "wide")
        tree = tree.replace(lo=np.asarray(tree.lo, np.float64), hi=np.asarray(tree.hi, np.float64))
        tri_p = padded(tri)
        target = np.einsum("rc,rcx->rx", rng.dirichlet([2, 2, 2], 4), tri[rng.integers(0, 16, 4)])
        origin = rng.uniform(-2, 2, (4, 3))
        for r in range(4):
            d = target[r] - origin[r]
            assert int(queries.raycast(tree, tri_p, origin[r], d).prim) >= 0
            for out in ("t", "u", "v"):
                def f(o, dd, out=out):
                    return getattr(queries.raycast(tree, tri_p, o, dd), out)
                g_o, g_d = jax.jit(jax.grad(f, argnums=(0, 1)))(origin[r], d)
                assert_gradient(g_o, central_difference(lambda x: float(f(x, d)), origin[r]))
                assert_gradient(g_d, central_difference(lambda x: float(f(origin[r], x)), d))


def test_lists_name_a_referenced_triangle_once():
    """Spatial splits (SBVH) put one triangle in several leaves: the lists still name it once,
    the counts equal brute force, the closest point is brute force's."""
    rng = np.random.default_rng(12)
    tri = []
    for i in range(6):  # long slivers crossing on a grid: spatial splits pay (tests/builders/test_sbvh.py)
        y = i / 6.0
        tri.append([[0, y, 0], [1, y + 0.01, 0.01], [1, y, 0.02]])
        tri.append([[y, 0, 0.01], [y + 0.01, 1, 0.0], [y, 1, 0.02]])
    tri = np.asarray(tri, np.float32)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    tree = jaxbvh.build(lo, hi, method="sbvh", triangles=tri, bins=8, capacity=PRIMS)
    tree = pad_to(tree, NODES, PRIMS)
    validate(tree, lo, hi, len(tri), references=True)
    assert int(np.asarray(tree.prim_count).sum()) > len(tri), "the example should have references"
    centre = rng.uniform(0, 1, (8, 3)).astype(np.float32)
    got = jax.tree_util.tree_map(np.asarray, queries.within(tree, padded(tri), centre, 0.3, capacity=64))
    near = jax.tree_util.tree_map(np.asarray, queries.closest_point(tree, padded(tri), centre))
    for i, p in enumerate(centre):
        d2 = brute_closest(tri, p)
        truth = np.flatnonzero(d2 <= np.float32(0.3) * np.float32(0.3))
        listed = got.prims[i][got.prims[i] >= 0]
        assert got.count[i] == truth.size and sorted(listed.tolist()) == truth.tolist()
        assert near.prim[i] == np.flatnonzero(d2 == d2.min())[0]


def test_two_level_trees_answer_through_their_flattened_tree():
    """A two-level (re-braided) tree answers the queries through ``twolevel.flatten`` (world
    triangle ids, the scene frame of ``Mesh.local_triangles``): equal to brute force."""
    from jaxbvh import scenes, twolevel

    trees = [scenes.tree_mesh(jax.random.key(k), levels=1, branches=2, sides=3, leaves=1) for k in (1, 2)]
    mesh = scenes.instanced_scene(jax.random.key(3), trees, 5, spread=0.5, upright=False)
    tl = twolevel.build(mesh, method="binned")
    flat = twolevel.flatten(tl)
    tri = mesh.local_triangles()
    lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
    points = np.random.default_rng(0).uniform(lo, hi, (12, 3)).astype(np.float32)
    got = jax.tree_util.tree_map(np.asarray, queries.closest_point(flat, tri, points))
    ball = jax.tree_util.tree_map(np.asarray, queries.within(flat, tri, points, 0.1 * float(np.max(hi - lo)),
                                                             capacity=256))
    r2 = np.float32(0.1 * float(np.max(hi - lo))) ** 2
    for i, p in enumerate(points):
        d2 = brute_closest(tri, p)
        # the instances' triangles share edges: a point closest to a shared edge is at the
        # same distance from both, up to the rounding of two formulas (XLA's and NumPy's)
        assert d2[got.prim[i]] <= d2.min() * (1 + 1e-6)
        truth = np.flatnonzero(d2 <= r2)
        assert ball.count[i] == truth.size and sorted(ball.prims[i][: truth.size].tolist()) == truth.tolist()
