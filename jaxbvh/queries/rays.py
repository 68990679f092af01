"""Differentiable ray hits: the hit distance and barycentrics of a ray on the triangle a search chose.

The ray searches (:func:`jaxbvh.rays.closest_hit`, :func:`jaxbvh.rays.any_hit`) choose a
triangle per ray; that choice is discrete and is not differentiated. :func:`ray_hit`
recomputes ``(t, u, v)`` from the chosen triangle's corners with the Möller–Trumbore
formula (:func:`jaxbvh.queries.geometry.ray_triangle`), so ``jax.grad`` / ``jax.jvp``
of ``t``, ``u``, ``v`` reach the ray origin, its direction and the vertex positions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.program_store import stored_jit
from jaxbvh.queries.geometry import ray_triangle


@stored_jit
def ray_hit(triangles, prim, origin, direction):
    """Hit distance and barycentrics of rays ``origin``, ``direction`` [..., 3] on
    triangles ``prim`` [...] int (``Hits.prim``; -1: a miss) of ``triangles`` [T, 3, 3];
    jitted, differentiable.

    Returns ``(t, u, v)`` [...]: ``origin + t * direction`` is the hit point (``t`` in
    units of ``|direction|``), ``u``, ``v`` its barycentrics on the triangle (the
    convention of :func:`jaxbvh.rays.moller_trumbore`). A miss has ``t = inf``,
    ``u = v = 0`` and zero gradient. The line of the ray is intersected with the
    triangle's plane without an inside test (the search decided that), so a small step of
    the ray or the vertices moves the hit point smoothly across the plane.
    """
    prim = jnp.asarray(prim)
    tri = jnp.asarray(triangles)[jnp.maximum(prim, 0)]  # [..., 3, 3]
    origin = jnp.asarray(origin, tri.dtype)
    direction = jnp.asarray(direction, tri.dtype)
    t, u, v = ray_triangle(origin, direction, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    hit = prim >= 0
    zero = jnp.zeros_like(u)
    return jnp.where(hit, t, jnp.inf), jnp.where(hit, u, zero), jnp.where(hit, v, zero)
