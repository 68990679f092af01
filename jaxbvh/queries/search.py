"""Closest point, box overlap and radius queries, for use inside your own ``jit`` / ``vmap`` / ``grad``.

Every query is a jitted function of the tree and the primitives passed as arguments
(never closed over): one compiled program serves every tree of a capacity bucket, and
inside your own ``jax.jit`` it is traced into your program. Queries come in batches of
any leading shape ``[...]``. A point or box query is one
:func:`jaxbvh.queries.parent_walk.walk` (stackless: its cost per step does not depend on
the tree's depth), ``vmap``-ed; :func:`raycast` runs the rays' own walk
(:mod:`jaxbvh.rays.stack_walk`: a wavefront of lanes, a short stack and parent links,
also depth-free) over the batch, so its hits and counters are those of
:func:`jaxbvh.rays.closest_hit` / :func:`jaxbvh.rays.any_hit`.

Primitives. ``triangles`` [T, 3, 3] (corners, in the tree's frame: the frame the tree's
boxes are in, e.g. ``Mesh.local_triangles()``), or, for :func:`overlap` and
:func:`within`, boxes as a pair ``(lo, hi)`` of [T, 3]. Ids are the tree's primitive ids
(``prim_index`` entries). To share one compile between meshes, pad ``triangles`` to a
common ``T`` (any rows: the tree never names them).

Results. :class:`PointHit` for :func:`closest_point`, :class:`Listed` for the list
queries; each with the walk's counters and ``step_limit`` (the walk was cut off: the
tree is broken, results incomplete).

Engines. :func:`closest_point`, :func:`overlap` and :func:`within` take ``engine``
(:data:`jaxbvh.native.ENGINES`, default :data:`jaxbvh.native.DEFAULT_ENGINE`; the one
rule is :func:`jaxbvh.native.choose`): ``"jax"``, the array program described here;
``"native"``, the same walk compiled by numba (:mod:`jaxbvh.queries.native_search`: one
CPU thread, query after query, many times faster on a CPU), the same results field for
field; ``"auto"`` takes native on a CPU with concrete arguments and jax whenever an
argument is being traced, i.e. inside your ``jit``, ``vmap``, ``grad`` or ``jvp`` (so
gradients always come from the jax engine, and ``engine="native"`` there is an error).
The native engine returns JAX arrays of the same shapes and dtypes.

Gradients. The search is a discrete choice and is not differentiated (it runs on
``stop_gradient`` copies of its inputs); the answer is then recomputed from the chosen
primitive's corners (:mod:`jaxbvh.queries.geometry`), so ``jax.grad`` / ``jax.jvp`` of
``distance``, ``u``, ``v`` and ``point`` reach the query points and the triangle corners,
exactly the derivative of the distance to the chosen triangle. A query that finds
nothing (beyond ``max_distance``) has zero gradient. Distance 0 (a point on the
surface) has gradient 0 (``|x|`` has none there). Where the chosen triangle changes
(equidistant from two) the distance is continuous but its gradient jumps; at such a
point you get the gradient of the triangle with the lower id.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import native
from jaxbvh.program_store import stored_jit
from jaxbvh.queries import geometry, native_search
from jaxbvh.queries.parent_walk import Hooks, walk
from jaxbvh.rays.stack_walk import Hits
from jaxbvh.rays.traversal import trace_batch

I32 = jnp.int32


class PointHit(NamedTuple):
    """Result of :func:`closest_point`, every array of the queries' shape ``[...]`` unless noted.

    ``distance`` float: to the closest point on the mesh, in the tree frame's units;
    negative inside when signed; ``inf`` when nothing lies within ``max_distance``.
    ``prim`` int32: the closest triangle (-1: none); equal distances go to the lower id
    (distances equal but for rounding, a point nearest to an edge two triangles share, may
    go to either).
    ``u``, ``v`` float: barycentrics of the closest point,
    ``point = a + u (b - a) + v (c - a)`` (0 when none). ``point`` float [..., 3]: the
    closest point (NaN when none). ``feature`` int32: the triangle's feature it lies on
    (:data:`jaxbvh.queries.geometry.FEATURES`; -1 when none). Counters int32
    ``box_tests``, ``prim_tests``, ``nodes_visited``, ``leaves_visited`` and
    ``step_limit`` bool (:mod:`jaxbvh.queries.parent_walk`).
    """

    distance: Any
    prim: Any
    u: Any
    v: Any
    point: Any
    feature: Any
    box_tests: Any
    prim_tests: Any
    nodes_visited: Any
    leaves_visited: Any
    step_limit: Any


RayHit = Hits
"""Result of :func:`raycast`: :class:`jaxbvh.rays.Hits` (the ray walk's one result type;
this name stays for old imports), every array of the rays' shape ``[...]``: ``t``
(``inf``: a miss), ``prim`` (-1), ``u``, ``v`` (0 for a miss), the walk's counters,
``stack_overflow`` (always False here) and ``step_limit``."""


class Listed(NamedTuple):
    """Result of :func:`overlap` and :func:`within` (queries' shape ``[...]``).

    ``prims`` int32 [..., capacity]: the first ``capacity`` primitives found, in the
    walk's order, -1 after; ``count`` int32: how many there are in all (listed or not);
    ``overflow`` bool: ``count > capacity`` (the list is then incomplete); counters and
    ``step_limit`` as :class:`PointHit`. A primitive that the tree references from several
    leaves (spatial splits) is listed once (exact while the list does not overflow).
    """

    prims: Any
    count: Any
    overflow: Any
    box_tests: Any
    prim_tests: Any
    nodes_visited: Any
    leaves_visited: Any
    step_limit: Any


def _batched(one, n_core: int, *queries):
    """``one`` over the leading ``[...]`` of ``queries`` (each with ``n_core`` trailing
    axes of its own, broadcast together): flattened, ``vmap``-ed, reshaped back."""
    shape = jnp.broadcast_shapes(*(q.shape[: q.ndim - k] for q, k in zip(queries, n_core)))
    flat = [jnp.broadcast_to(q, shape + q.shape[q.ndim - k:]).reshape((-1,) + q.shape[q.ndim - k:])
            for q, k in zip(queries, n_core)]
    out = jax.vmap(one)(*flat)
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), out)


def _frozen(x):
    """``x`` (a pytree) cut off from differentiation: the search is a discrete choice."""
    return jax.tree_util.tree_map(jax.lax.stop_gradient, x)


# ----------------------------------------------------------------------------------
# Closest point
# ----------------------------------------------------------------------------------


def _nearest_prim(tree, triangles, point, max_d2):
    """Search: ``(prim, counts, step_limit)`` of the closest triangle to ``point`` [3]."""

    def boxes(lo, hi, found):
        key = geometry.box_distance2(point, lo, hi)
        return key, key <= found[0]

    def primitive(found, prim, active):
        best, best_prim = found
        tri = triangles[jnp.maximum(prim, 0)]
        d2 = geometry.closest_on_triangle(point, tri[0], tri[1], tri[2])[0]
        take = active & ((d2 < best) | ((d2 == best) & ((best_prim < 0) | (prim < best_prim))))
        return jnp.where(take, d2, best), jnp.where(take, prim, best_prim)

    (_, prim), counts, limit = walk(tree, Hooks(boxes, primitive), (max_d2, I32(-1)))
    return prim, counts, limit


def _closest_one(tree, triangles, pseudonormals, max_distance, point):
    dtype = tree.lo.dtype
    point = point.astype(dtype)
    triangles = triangles.astype(dtype)
    max_distance = jnp.asarray(max_distance, dtype)
    max_d2 = jnp.where(jnp.isinf(max_distance), jnp.inf, max_distance * max_distance)
    prim, counts, limit = _nearest_prim(_frozen(tree), _frozen(triangles), _frozen(point), _frozen(max_d2))
    hit = prim >= 0
    tri = triangles[jnp.maximum(prim, 0)]
    d2, q, u, v, feature = geometry.closest_on_triangle(point, tri[0], tri[1], tri[2])
    distance = geometry.safe_sqrt(d2)
    if pseudonormals is not None:
        normal = _frozen(pseudonormals)[jnp.maximum(prim, 0), feature].astype(dtype)
        distance = jnp.where(geometry.dot(_frozen(point - q), normal) < 0, -distance, distance)
    zero = jnp.zeros((), dtype)
    return PointHit(distance=jnp.where(hit, distance, jnp.inf), prim=prim, u=jnp.where(hit, u, zero),
                    v=jnp.where(hit, v, zero), point=jnp.where(hit, q, jnp.nan),
                    feature=jnp.where(hit, feature, -1), box_tests=counts.box_tests,
                    prim_tests=counts.prim_tests, nodes_visited=counts.nodes_visited,
                    leaves_visited=counts.leaves_visited, step_limit=limit)


@stored_jit
def _closest_point_jax(tree, triangles, points, pseudonormals=None, max_distance=jnp.inf) -> PointHit:
    one = partial(_closest_one, tree, triangles, pseudonormals)
    return _batched(lambda p, r: one(r, p), (1, 0), jnp.asarray(points), jnp.asarray(max_distance))


def _flat_queries(dtype, *queries):
    """NumPy ``queries`` (each ``(array, n_core)``) in ``dtype``, broadcast over their
    leading shape and flattened: ``(shape, [flat arrays])`` (the native twin of :func:`_batched`)."""
    arrays = [np.asarray(q).astype(dtype, copy=False) for q, _ in queries]
    shape = np.broadcast_shapes(*(a.shape[: a.ndim - k] for a, (_, k) in zip(arrays, queries)))
    return shape, [np.broadcast_to(a, shape + a.shape[a.ndim - k:]).reshape((-1,) + a.shape[a.ndim - k:])
                   for a, (_, k) in zip(arrays, queries)]


def _shaped(result_type, shape, fields):
    """``result_type`` of JAX arrays from the native engine's flat NumPy ``fields``."""
    return result_type(**{name: jnp.asarray(a.reshape(shape + a.shape[1:])) for name, a in fields.items()})


def closest_point(tree, triangles, points, pseudonormals=None, max_distance=jnp.inf, *,
                  engine: str = native.DEFAULT_ENGINE) -> PointHit:
    """Closest point on a triangle mesh to each of ``points`` [..., 3]; jitted, differentiable.

    ``tree``: :class:`~jaxbvh.tree.layout.BVH` or :class:`~jaxbvh.tree.layout.WideBVH`
    over ``triangles`` [T, 3, 3] (tree frame); ``points`` in the same frame.
    ``pseudonormals`` [T, 7, 3] (optional, :func:`jaxbvh.queries.normals.pseudonormals`):
    sign the distance, negative inside a closed, consistently oriented mesh (the sign of
    ``(point - closest) . n`` with ``n`` the angle-weighted pseudonormal of the feature
    the closest point lies on, Bærentzen & Aanæs 2005; exact for closed manifold meshes).
    ``max_distance`` (scalar or [...]): search radius; a point farther from every
    triangle gets ``prim = -1`` and ``distance = inf`` (and the search is cheaper the
    smaller it is). ``engine``: ``"auto"``, ``"jax"`` or ``"native"`` (module docstring).
    Returns :class:`PointHit` (module docstring for gradients).
    """
    if native.choose(engine, tree, triangles, points, pseudonormals, max_distance,
                     supported=native_search.supports(tree)) == "jax":
        return _closest_point_jax(tree, triangles, points, pseudonormals, max_distance)

    dtype = np.asarray(tree.lo).dtype
    shape, (flat, radius) = _flat_queries(dtype, (points, 1), (max_distance, 0))
    max_d2 = np.where(np.isinf(radius), dtype.type(np.inf), radius * radius)
    return _shaped(PointHit, shape, native_search.closest_point(tree, triangles, flat, max_d2, pseudonormals))


# ----------------------------------------------------------------------------------
# Lists: box overlap and radius
# ----------------------------------------------------------------------------------


def _list(tree, test, boxes, capacity) -> Listed:
    """Walk with a list of ``capacity`` slots: ``test(prim) -> bool`` for a primitive,
    ``boxes(lo, hi) -> (key, keep)`` for children."""

    def primitive(found, prim, active):
        prims, count = found
        valid = active & test(prim) & ~jnp.any(prims == prim)
        slot = jnp.where(valid & (count < capacity), count, capacity)
        return prims.at[slot].set(prim, mode="drop"), count + valid.astype(I32)

    (prims, count), c, limit = walk(tree, Hooks(lambda lo, hi, _: boxes(lo, hi), primitive),
                                    (jnp.full(capacity, -1, I32), I32(0)))
    return Listed(prims=prims, count=count, overflow=count > capacity, box_tests=c.box_tests,
                  prim_tests=c.prim_tests, nodes_visited=c.nodes_visited,
                  leaves_visited=c.leaves_visited, step_limit=limit)


def _prim_boxes(prims, prim, dtype):
    """Box ``(lo, hi)`` [3] of primitive ``prim``: triangles [T, 3, 3] or a pair ``(lo, hi)``."""
    if isinstance(prims, (tuple, list)):
        lo, hi = prims
        return lo[prim].astype(dtype), hi[prim].astype(dtype)
    tri = prims[prim].astype(dtype)
    return jnp.min(tri, axis=0), jnp.max(tri, axis=0)


def _overlap_one(tree, prims, capacity, q_lo, q_hi):
    tree, prims = _frozen(tree), _frozen(prims)
    dtype = tree.lo.dtype
    q_lo, q_hi = _frozen(q_lo.astype(dtype)), _frozen(q_hi.astype(dtype))

    def test(prim):
        lo, hi = _prim_boxes(prims, jnp.maximum(prim, 0), dtype)
        return geometry.boxes_overlap(lo, hi, q_lo, q_hi)

    def boxes(lo, hi):
        return jnp.zeros(lo.shape[0], dtype), geometry.boxes_overlap(lo, hi, q_lo, q_hi)

    return _list(tree, test, boxes, capacity)


@partial(stored_jit, static_argnames=("capacity",))
def _overlap_jax(tree, prims, lo, hi, *, capacity: int) -> Listed:
    one = partial(_overlap_one, tree, prims, capacity)
    return _batched(one, (1, 1), jnp.asarray(lo), jnp.asarray(hi))


def overlap(tree, prims, lo, hi, *, capacity: int, engine: str = native.DEFAULT_ENGINE) -> Listed:
    """Primitives whose box overlaps the query box ``lo``, ``hi`` [..., 3] (closed boxes:
    touching counts); jitted.

    ``prims``: triangles [T, 3, 3] (their bounding boxes are tested) or boxes ``(lo, hi)``
    [T, 3], in the tree's frame. ``capacity`` (static): list length. ``engine``: module
    docstring. Returns :class:`Listed`; children in slot order.
    """
    if native.choose(engine, tree, prims, lo, hi, supported=native_search.supports(tree)) == "jax":
        return _overlap_jax(tree, prims, lo, hi, capacity=capacity)

    dtype = np.asarray(tree.lo).dtype
    shape, (q_lo, q_hi) = _flat_queries(dtype, (lo, 1), (hi, 1))
    fields = native_search.lists(tree, prims, native_search.OVERLAP, q_lo, q_hi, np.zeros(len(q_lo), dtype),
                                 int(capacity))
    return _shaped(Listed, shape, fields)


def _within_one(tree, prims, capacity, point, radius):
    tree, prims = _frozen(tree), _frozen(prims)
    dtype = tree.lo.dtype
    point, radius = _frozen(point.astype(dtype)), _frozen(radius.astype(dtype))
    r2 = radius * radius

    def test(prim):
        prim = jnp.maximum(prim, 0)
        if isinstance(prims, (tuple, list)):
            lo, hi = _prim_boxes(prims, prim, dtype)
            d2 = geometry.box_distance2(point, lo, hi)
        else:
            tri = prims[prim].astype(dtype)
            d2 = geometry.closest_on_triangle(point, tri[0], tri[1], tri[2])[0]
        return d2 <= r2

    def boxes(lo, hi):
        key = geometry.box_distance2(point, lo, hi)
        return key, key <= r2

    return _list(tree, test, boxes, capacity)


@partial(stored_jit, static_argnames=("capacity",))
def _within_jax(tree, prims, points, radius, *, capacity: int) -> Listed:
    one = partial(_within_one, tree, prims, capacity)
    return _batched(one, (1, 0), jnp.asarray(points), jnp.asarray(radius))


def within(tree, prims, points, radius, *, capacity: int, engine: str = native.DEFAULT_ENGINE) -> Listed:
    """Primitives within ``radius`` (scalar or [...], tree units; the ball is closed) of
    each of ``points`` [..., 3]; jitted.

    ``prims``: triangles [T, 3, 3] (exact point–triangle distance) or boxes ``(lo, hi)``
    [T, 3] (point–box distance). ``capacity`` (static): list length. Returns
    :class:`Listed`; children visited nearest box first, so on overflow the list holds
    primitives near the point. ``engine``: module docstring.
    """
    if native.choose(engine, tree, prims, points, radius, supported=native_search.supports(tree)) == "jax":
        return _within_jax(tree, prims, points, radius, capacity=capacity)

    dtype = np.asarray(tree.lo).dtype
    shape, (centre, r) = _flat_queries(dtype, (points, 1), (radius, 0))
    fields = native_search.lists(tree, prims, native_search.WITHIN_TRIANGLES, centre, centre, r * r, int(capacity))
    return _shaped(Listed, shape, fields)


# ----------------------------------------------------------------------------------
# Rays, inside jit
# ----------------------------------------------------------------------------------


@partial(stored_jit, static_argnames=("first",))
def raycast(tree, triangles, origin, direction, t_min=0.0, t_max=jnp.inf, *, first: bool = False) -> Hits:
    """Closest hit (or, with ``first=True``, any hit: shadow rays) of rays ``origin``,
    ``direction`` [..., 3] against ``triangles`` [T, 3, 3] through ``tree``, inside jit;
    differentiable.

    The in-program form of :func:`jaxbvh.rays.closest_hit` / :func:`jaxbvh.rays.any_hit`
    (host drivers that batch NumPy rays and raise on a broken tree): the same walk
    (:func:`jaxbvh.rays.traversal.trace_batch` over all the rays at once), tests (robust
    slab, two-sided Möller–Trumbore), hit rules (open interval ``(t_min, t_max)``,
    scalars or [...]; equal ``t`` to the lower id) and counters. The search is not
    differentiated; ``t``, ``u``, ``v`` are recomputed on the chosen triangle by
    :func:`jaxbvh.queries.geometry.ray_triangle`, so ``jax.grad`` / ``jax.jvp`` reach
    the origin, the direction and the corners; a miss has zero gradient. Returns
    :class:`~jaxbvh.rays.Hits` (``RayHit``) of the rays' shape; check ``step_limit``
    (a broken tree) yourself.
    """
    dtype = tree.lo.dtype
    origin, direction = jnp.asarray(origin, dtype), jnp.asarray(direction, dtype)
    t_min, t_max = jnp.asarray(t_min, dtype), jnp.asarray(t_max, dtype)
    shape = jnp.broadcast_shapes(origin.shape[:-1], direction.shape[:-1], t_min.shape, t_max.shape)
    origin = jnp.broadcast_to(origin, shape + (3,)).reshape(-1, 3)
    direction = jnp.broadcast_to(direction, shape + (3,)).reshape(-1, 3)
    triangles = jnp.asarray(triangles).astype(dtype)
    found = trace_batch(*_frozen((tree, triangles, origin, direction, jnp.broadcast_to(t_min, shape).reshape(-1),
                                  jnp.broadcast_to(t_max, shape).reshape(-1))),
                        mode="any" if first else "closest")
    hit = found.prim >= 0
    tri = triangles[jnp.maximum(found.prim, 0)]
    t, u, v = geometry.ray_triangle(origin, direction, tri[:, 0], tri[:, 1], tri[:, 2])
    zero = jnp.zeros((), dtype)
    found = dataclasses.replace(found, t=jnp.where(hit, t, jnp.inf), u=jnp.where(hit, u, zero),
                                v=jnp.where(hit, v, zero))
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), found)
