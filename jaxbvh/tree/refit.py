"""Refitting: every interior box set to the union of its children's boxes.

Optimizers that change a tree's topology (:mod:`jaxbvh.optimize.reinsert`, :mod:`jaxbvh.optimize.treelet`)
start from tight interior boxes, so that a node's box is exactly the union of the boxes
below it (a loaded tree may have looser ones). Leaves keep their boxes. Min and max are
exact, so a refit gives the same bits in JAX and in NumPy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def refit_boxes(child, lo, hi):
    """``(lo, hi)`` [N, 3] with every interior box the union of its children's.

    ``child`` [N, 2] int32 (-1: none). Bottom-up sweeps over all nodes: each sets every
    interior box from its children's, and they stop when nothing changes (height + 1
    sweeps; at most ``N + 1``). Traceable (use inside ``jit``).
    """
    cap = child.shape[0]
    interior = (child[:, 0] >= 0)[:, None]
    left = jnp.clip(child[:, 0], 0, cap - 1)
    right = jnp.clip(child[:, 1], 0, cap - 1)

    def cond(c):
        return c[2] & (c[3] <= cap)

    def body(c):
        lo, hi, _, i = c
        new_lo = jnp.where(interior, jnp.minimum(lo[left], lo[right]), lo)
        new_hi = jnp.where(interior, jnp.maximum(hi[left], hi[right]), hi)
        changed = jnp.any(new_lo != lo) | jnp.any(new_hi != hi)
        return new_lo, new_hi, changed, i + 1

    lo, hi, _, _ = jax.lax.while_loop(cond, body, (lo, hi, jnp.bool_(True), jnp.int32(0)))
    return lo, hi
