"""Kensler's final pass: every interior node's split axis, children ordered along it.

After optimizing, each interior node gets the axis along which its two children are
separated most (overlap least, :func:`split_axis_rule`), and the child lower along it
goes left, so that a traversal can visit the nearer child first (Kensler 2008, end of
section 4). The SAH does not change. Used by every optimizer and by the builders whose
node order does not follow a split axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.numerics import none_to_oob, take
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH, to_jax


def split_axis_rule(lo_a, hi_a, lo_b, hi_b, xp=jnp):
    """Axis of greatest separation of two boxes (least overlap), and whether to swap.

    Separation along an axis is ``max(lo_b - hi_a, lo_a - hi_b)`` (negative: overlap);
    the first axis with the greatest wins. The children are swapped when the first one's
    centre is above the second's along that axis. Works on NumPy or JAX arrays [..., 3].
    """
    gap = xp.maximum(lo_b - hi_a, lo_a - hi_b)
    axis = xp.argmax(gap, axis=-1)
    centre_a = xp.take_along_axis(lo_a + hi_a, axis[..., None], axis=-1)[..., 0]
    centre_b = xp.take_along_axis(lo_b + hi_b, axis[..., None], axis=-1)[..., 0]
    return axis.astype(xp.int32), centre_a > centre_b


@stored_jit
def apply_split_axes(tree):
    """The pass itself on a :class:`BVH` of JAX arrays (traceable; no checks)."""
    cap = tree.left.shape[0]
    interior = tree.left >= 0
    left, right = none_to_oob(tree.left, cap), none_to_oob(tree.right, cap)
    lo_a = take(tree.lo, left, 0)
    hi_a = take(tree.hi, left, 0)
    lo_b = take(tree.lo, right, 0)
    hi_b = take(tree.hi, right, 0)
    axis, swap = split_axis_rule(lo_a, hi_a, lo_b, hi_b)
    swap = swap & interior
    return tree.replace(left=jnp.where(swap, tree.right, tree.left),
                        right=jnp.where(swap, tree.left, tree.right),
                        axis=jnp.where(interior, axis, -1).astype(jnp.int32))


def assign_split_axes(tree):
    """Kensler's final pass: set ``axis`` of every interior node and order its children.

    The axis is the one of greatest separation between the two children's boxes (least
    overlap if none separates, :func:`split_axis_rule`); the child lower along it goes
    left. Leaves get ``-1``. The SAH does not change.
    """
    if not isinstance(tree, BVH):
        raise ValueError(f"tree must be a binary jaxbvh.BVH, got {type(tree).__name__}")
    return apply_split_axes(to_jax(tree))
