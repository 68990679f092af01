"""Point, box and ray tests of one primitive, differentiable (JAX).

These are the primitive tests of :mod:`jaxbvh.queries.search` and, at the same time, the
differentiable part of every query: a search picks a primitive (a discrete choice, not
differentiated), then the answer is recomputed from that primitive's corners by the
functions here, so ``jax.grad`` / ``jax.jvp`` reach the query point, the ray and the
vertices. Every division and square root is guarded by a "double ``where``", so no branch
that is not taken can put a NaN into a gradient.

Closest point on a triangle ``a, b, c`` [3] to a point ``p`` [3] (branch-free): the
projection of ``p`` on the triangle's plane when it falls inside the triangle, else the
nearest of the closest points on the three edges (each edge a clamped segment; ties go to
the first edge in the order ``ab, bc, ca``). It is reported as

* ``q`` [3], the closest point, and ``d2``, ``|p - q|^2`` summed x, y, z in that order
  (the order the box distance of :func:`box_distance2` uses, so that a box's distance to
  ``p`` never exceeds the distance of a corner of a triangle inside it: pruning by box
  distance keeps every tie);
* barycentrics ``(u, v)``: ``q = a + u (b - a) + v (c - a)``, the convention of the ray
  test (:func:`jaxbvh.rays.moller_trumbore`);
* ``feature`` (int32): the triangle feature ``q`` lies on, which selects the
  pseudonormal of a signed distance: 0 face interior, 1 edge ab, 2 edge bc, 3 edge ca,
  4 vertex a, 5 vertex b, 6 vertex c (:data:`FEATURES`).

A degenerate triangle (zero area) has no face candidate; its closest point is on an edge.
"""

from __future__ import annotations

import jax.numpy as jnp

#: the order of the 7 features (and of the pseudonormals of :func:`jaxbvh.queries.normals.pseudonormals`)
FEATURES = ("face", "edge ab", "edge bc", "edge ca", "vertex a", "vertex b", "vertex c")


def dot(a, b):
    """``a . b`` over the last axis, summed x, y, z in that order."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a, b):
    """``a x b`` over the last axis [..., 3]."""
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def safe_divide(num, den):
    """``num / den`` where ``den != 0``, else 0; the gradient is finite either way."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1), 0)


def safe_sqrt(x):
    """``sqrt(x)`` for ``x >= 0`` with gradient 0 (not inf) at ``x == 0``."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1)), 0)


def _segment(p, s, e):
    """Closest point on segment ``s``-``e`` to ``p``: ``(q, t)``, ``q = s + t (e - s)``,
    ``t`` in [0, 1]; the end points themselves (not ``s + 1 * (e - s)``) at the ends."""
    d = e - s
    t = jnp.clip(safe_divide(dot(p - s, d), dot(d, d)), 0, 1)
    q = jnp.where(t <= 0, s, jnp.where(t >= 1, e, s + t * d))
    return q, t


def closest_on_triangle(p, a, b, c):
    """Closest point on triangle ``a, b, c`` to ``p`` (all [3]; module docstring).

    Returns ``(d2, q, u, v, feature)``: squared distance, closest point [3],
    barycentrics, feature id (:data:`FEATURES`).
    """
    ab, ac, ap = b - a, c - a, p - a
    n = cross(ab, ac)
    nn = dot(n, n)
    u_face = safe_divide(dot(cross(ap, ac), n), nn)
    v_face = safe_divide(dot(cross(ab, ap), n), nn)
    inside = (nn > 0) & (u_face >= 0) & (v_face >= 0) & (u_face + v_face <= 1)
    q_face = a + u_face * ab + v_face * ac

    q_ab, t_ab = _segment(p, a, b)
    q_bc, t_bc = _segment(p, b, c)
    q_ca, t_ca = _segment(p, c, a)
    d_ab, d_bc, d_ca = dot(p - q_ab, p - q_ab), dot(p - q_bc, p - q_bc), dot(p - q_ca, p - q_ca)
    # nearest edge, ties to the first (ab, bc, ca)
    pick_ab = (d_ab <= d_bc) & (d_ab <= d_ca)
    pick_bc = ~pick_ab & (d_bc <= d_ca)
    q_edge = jnp.where(pick_ab, q_ab, jnp.where(pick_bc, q_bc, q_ca))
    t = jnp.where(pick_ab, t_ab, jnp.where(pick_bc, t_bc, t_ca))
    zero = jnp.zeros_like(t)
    u_edge = jnp.where(pick_ab, t, jnp.where(pick_bc, 1 - t, zero))
    v_edge = jnp.where(pick_ab, zero, jnp.where(pick_bc, t, 1 - t))
    # the edge's end points: t == 0 is its start, t == 1 its end
    start = jnp.where(pick_ab, 4, jnp.where(pick_bc, 5, 6))
    end = jnp.where(pick_ab, 5, jnp.where(pick_bc, 6, 4))
    edge = jnp.where(pick_ab, 1, jnp.where(pick_bc, 2, 3))
    f_edge = jnp.where(t <= 0, start, jnp.where(t >= 1, end, edge))

    q = jnp.where(inside, q_face, q_edge)
    u = jnp.where(inside, u_face, u_edge)
    v = jnp.where(inside, v_face, v_edge)
    feature = jnp.where(inside, 0, f_edge).astype(jnp.int32)
    return dot(p - q, p - q), q, u, v, feature


def box_distance2(p, lo, hi):
    """Squared distance from ``p`` [3] to boxes ``lo``, ``hi`` [..., 3] (0 inside; an empty
    box, ``lo = +inf``, is infinitely far)."""
    gap = jnp.maximum(jnp.maximum(lo - p, p - hi), 0)
    return dot(gap, gap)


def boxes_overlap(lo, hi, q_lo, q_hi):
    """Closed boxes ``lo``, ``hi`` [..., 3] meet the box ``q_lo``, ``q_hi`` [3] (touching counts)."""
    return jnp.all((lo <= q_hi) & (q_lo <= hi), axis=-1)


def ray_triangle(origin, direction, a, b, c):
    """Differentiable Möller–Trumbore (the formula of :func:`jaxbvh.rays.moller_trumbore`,
    guarded for gradients): ``(t, u, v)`` of the ray's line against the triangle's plane,
    with no inside test (the search made that choice); ``t`` in units of ``|direction|``."""
    e1, e2 = b - a, c - a
    pv = cross(direction, e2)
    det = dot(e1, pv)
    s = origin - a
    qv = cross(s, e1)
    return safe_divide(dot(e2, qv), det), safe_divide(dot(s, pv), det), safe_divide(dot(direction, qv), det)
