"""What :mod:`jaxbvh.optimize.split` and its twin share: the clip of a triangle to its leaf."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxbvh.builders.sbvh_rules import halfspace_box


def clip_to_leaf(tri, lo, hi, leaf_lo, leaf_hi):
    """Box [..., 3] x 2 of the part of triangles ``tri`` [..., 3, 3] inside the leaf boxes
    ``leaf_lo``, ``leaf_hi`` [..., 3], starting from the primitive boxes ``lo``, ``hi``
    clipped to them: each of the six faces' half-space cut in turn (the SBVH builder's own
    rule, :func:`jaxbvh.builders.sbvh_rules.halfspace_box`, conservative by its margin),
    x low, x high, y low, ...; where a cut leaves nothing (a triangle that only touches the
    leaf), the starting box. NumPy or JAX arrays (the twin calls it too)."""
    xp = np if isinstance(tri, np.ndarray) else jnp
    start_lo, start_hi = lo, hi
    for face in range(6):
        axis_mask = xp.broadcast_to(xp.arange(3) == face // 2, lo.shape)
        below = face % 2 == 1
        plane = (leaf_hi if below else leaf_lo)[..., face // 2]
        lo, hi = halfspace_box(tri, axis_mask, plane, xp.full(plane.shape, below), lo, hi)
    empty = xp.any(lo > hi, axis=-1, keepdims=True)
    return xp.where(empty, start_lo, lo), xp.where(empty, start_hi, hi)
