"""Primitive boxes as every builder takes them: checked on the host, cast to the working
dtype, padded to a capacity with empty boxes (inert: ``+inf`` lo, ``-inf`` hi)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import scene_scale, working_dtype
from jaxbvh.tree.layout import capacity_bucket
from jaxbvh.tree.validate import few_ids


def check_prim_boxes(prim_lo, prim_hi, what: str = "primitive boxes"):
    """Host-side check of ``prim_lo``, ``prim_hi`` [n, 3]; returns them as NumPy arrays.

    Raises ``ValueError`` naming the problem: wrong shape, no primitives, NaN/inf
    (with how many and which), or ``lo > hi``.
    """
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    if lo.ndim != 2 or lo.shape[-1] != 3 or lo.shape != hi.shape:
        raise ValueError(f"{what}: lo and hi must both have shape [n, 3], got {lo.shape} and {hi.shape}")
    if lo.shape[0] == 0:
        raise ValueError(f"{what}: no primitives (n = 0); a BVH needs at least one")
    if not (np.issubdtype(lo.dtype, np.floating) and np.issubdtype(hi.dtype, np.floating)):
        lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    bad = ~(np.isfinite(lo).all(1) & np.isfinite(hi).all(1))
    if bad.any():
        ids = np.flatnonzero(bad)
        raise ValueError(f"{what}: {ids.size} of {lo.shape[0]} have NaN or infinite coordinates "
                         f"(first: {few_ids(ids)})")
    inverted = (lo > hi).any(1)
    if inverted.any():
        ids = np.flatnonzero(inverted)
        raise ValueError(f"{what}: {ids.size} have lo > hi (first: {few_ids(ids)})")
    return lo, hi


def prepare(prim_lo, prim_hi, *, pad: bool = True, capacity: int | None = None, dtype=None):
    """Checked, cast and padded builder inputs ``(lo, hi, n, scale)``.

    ``lo``, ``hi``: [capacity, 3] JAX arrays (padding: the empty box); ``n``: int32
    primitive count; ``scale``: the scene's power-of-two area scale. The capacity is
    ``capacity`` if given (>= n; one compile for inputs of many sizes), else the capacity
    bucket of ``n`` (``pad=True``) or ``n``. ``dtype``: float32 (None) or float64 (needs
    x64). Errors: :func:`check_prim_boxes`, and a capacity below ``n``.
    """
    lo, hi = check_prim_boxes(prim_lo, prim_hi)
    dt = working_dtype(dtype, lo.dtype)
    lo, hi = lo.astype(dt), hi.astype(dt)
    n = lo.shape[0]
    cap = int(capacity) if capacity is not None else (capacity_bucket(n) if pad else n)
    if cap < n:
        raise ValueError(f"capacity {cap} is below the {n} primitives")
    lo_p = np.full((cap, 3), np.inf, dt)
    hi_p = np.full((cap, 3), -np.inf, dt)
    lo_p[:n], hi_p[:n] = lo, hi
    return jnp.asarray(lo_p), jnp.asarray(hi_p), jnp.int32(n), jnp.asarray(scene_scale(lo, hi), dt)
