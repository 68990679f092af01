"""Ray sets for measuring trees: random rays, pinhole camera rays, diffuse bounce rays.

Every generator returns ``(origin, direction)``, both [R, 3] in the frame it was given
(the tree's frame when fed the tree's root box or the tree-frame triangles), with unit
directions so that hit distances ``t`` are lengths in that frame. Generators that draw
random numbers take a ``jax.random`` key first; the same key gives the same rays.

* :func:`random_rays` — Ng & Trifonov's test distribution: origins uniform in a box
  (usually the root box), directions uniform on the sphere.
* :func:`camera_rays` — one ray per pixel centre of a pinhole camera that looks at the
  centre of a box from a given direction and frames its bounding sphere; row-major,
  top row first, so ``reshape(height, width)`` gives an image.
* :func:`bounce_rays` — secondary rays: points uniform on the surface (triangles chosen
  by area, uniform barycentrics), cosine-weighted directions about the geometric normal
  (the winding's side; both sides with ``two_sided=True``), origins lifted off the
  surface by ``offset`` times the scene diagonal so they do not re-hit their triangle.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.program_store import stored_jit


def _normalize(v):
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


@partial(stored_jit, static_argnames=("n", "dtype"))
def random_rays(key, lo, hi, n: int, dtype=jnp.float32):
    """``n`` rays: origins uniform in the box ``lo``, ``hi`` [3], directions uniform on S^2."""
    k_origin, k_direction = jax.random.split(key)
    lo = jnp.asarray(lo, dtype)
    hi = jnp.asarray(hi, dtype)
    origin = lo + jax.random.uniform(k_origin, (n, 3), dtype) * (hi - lo)
    direction = _normalize(jax.random.normal(k_direction, (n, 3), dtype))
    return jnp.clip(origin, lo, hi), direction


def camera_rays(lo, hi, width: int, height: int, *, view=(1.0, 0.6, 1.8), up=(0.0, 1.0, 0.0),
                fov_degrees: float = 40.0, dtype=np.float32):
    """Pinhole camera rays [height * width, 3] framing the box ``lo``, ``hi`` [3].

    The eye sits in direction ``view`` from the box centre, far enough that the
    bounding sphere of the box fits the vertical field of view ``fov_degrees``;
    ``up`` sets the roll. Pixel ``(row, col)`` is ray ``row * width + col``, row 0 at
    the top. Deterministic (host NumPy, float64 then cast to ``dtype``).
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), np.finfo(np.float32).tiny)
    half = np.radians(fov_degrees) / 2
    back = np.asarray(view, np.float64)
    back = back / np.linalg.norm(back)
    eye = centre + back * radius / np.sin(half)
    forward = -back
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking along up
        right = np.cross(forward, [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    tan = np.tan(half)
    aspect = width / height
    cols = ((np.arange(width) + 0.5) / width * 2 - 1) * tan * aspect
    rows = (1 - (np.arange(height) + 0.5) / height * 2) * tan
    x, y = np.meshgrid(cols, rows)  # [height, width]
    direction = forward + x[..., None] * right + y[..., None] * true_up
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    direction = direction.reshape(-1, 3)
    origin = np.broadcast_to(eye, direction.shape)
    return origin.astype(dtype), direction.astype(dtype)


def _basis(normal):
    """Orthonormal tangents of unit ``normal`` [..., 3] (Duff et al. 2017, branchless)."""
    nx, ny, nz = normal[..., 0], normal[..., 1], normal[..., 2]
    sign = jnp.where(nz >= 0, 1.0, -1.0).astype(normal.dtype)
    a = -1 / (sign + nz)
    b = nx * ny * a
    t1 = jnp.stack([1 + sign * nx * nx * a, sign * b, -sign * nx], axis=-1)
    t2 = jnp.stack([b, sign + ny * ny * a, -ny], axis=-1)
    return t1, t2


@partial(stored_jit, static_argnames=("n", "two_sided"))
def bounce_rays(key, triangles, n: int, *, offset=1e-4, two_sided: bool = False):
    """``n`` diffuse bounce rays from the surface of ``triangles`` [T, 3, 3].

    Returns ``(origin, direction)`` [n, 3] in the triangles' frame and dtype.
    """
    dtype = triangles.dtype
    k_tri, k_bary, k_dir, k_side = jax.random.split(key, 4)
    v0, v1, v2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    cross = jnp.cross(v1 - v0, v2 - v0)
    area = jnp.linalg.norm(cross, axis=-1)
    tri = jax.random.choice(k_tri, triangles.shape[0], (n,), p=area / jnp.sum(area))
    r = jax.random.uniform(k_bary, (n, 2), dtype)
    root = jnp.sqrt(r[:, 0])
    b1 = root * (1 - r[:, 1])
    b2 = root * r[:, 1]
    point = v0[tri] + b1[:, None] * (v1 - v0)[tri] + b2[:, None] * (v2 - v0)[tri]
    normal = cross[tri] / area[tri, None]
    if two_sided:
        flip = jax.random.bernoulli(k_side, 0.5, (n,))
        normal = jnp.where(flip[:, None], -normal, normal)
    d = jax.random.uniform(k_dir, (n, 2), dtype)
    radius = jnp.sqrt(d[:, 0])
    phi = 2 * jnp.pi * d[:, 1]
    t1, t2 = _basis(normal)
    z = jnp.sqrt(jnp.maximum(1 - d[:, 0], 0))
    direction = (radius * jnp.cos(phi))[:, None] * t1 + (radius * jnp.sin(phi))[:, None] * t2 \
        + z[:, None] * normal
    direction = _normalize(direction)
    flat = triangles.reshape(-1, 3)
    diagonal = jnp.linalg.norm(jnp.max(flat, axis=0) - jnp.min(flat, axis=0))
    origin = point + (offset * diagonal) * normal
    return origin.astype(dtype), direction.astype(dtype)
