"""From the linked tree a bottom-up builder makes to the BVH layout, collapsing small subtrees.

LBVH (:mod:`jaxbvh.lbvh`) and PLOC (:mod:`jaxbvh.ploc`) both end with a full binary tree
over the Morton-sorted primitives, one primitive per leaf, given as *linked form*
(:class:`Linked`); :func:`to_bvh` turns it into a :class:`~jaxbvh.tree.BVH` (jitted,
inside the builders' programs).

Linked form
===========
With ``cap`` the padded primitive count and ``n`` the real one: the tree has
``n - 1`` internal nodes in slots ``0 .. n-2`` of ``[cap]`` arrays (slot 0 is the root
when ``n >= 2``) and ``n`` leaves, the sorted *positions* ``0 .. n-1``. A child is named
by a *linked id*: internal slot ``k`` is ``k``, the leaf at position ``p`` is ``cap + p``.
Each internal slot has ``left``, ``right`` (linked ids), its box ``lo``, ``hi``, the
number of primitives below it (``count``), the lowest position below it (``first``)
and its split ``axis`` (or -1); each position has its primitive box and the primitive
id ``order[p]``. Slots and positions past the real ones are ignored.

Leaves (``max_leaf``)
=====================
The test is the one the top-down builders use (:mod:`jaxbvh.build`), applied to the
children the bottom-up tree already has: an internal node of ``N <= max_leaf``
primitives *passes* when ``Ci N <= Ct + Ci (A_L N_L + A_R N_R) / A`` (for a zero-area
node the right side is ``Ct + Ci N``, so it passes). A top-down builder stops at the
first node that passes, so a node becomes a leaf holding its whole subtree when it
passes and no ancestor does; everything below it disappears. Counts grow towards the
root, so only the ``max_leaf - 1`` nearest ancestors can pass: "no ancestor passes"
takes at most ``max_leaf`` gathers over the tree, and each primitive finds its leaf
(and its place in the leaf, left to right) by walking up at most as far.

Output layout
=============
Kept interior nodes first, in slot order (so the root is node 0), then the leaves,
ordered by their lowest position; each leaf's primitives are contiguous in
``prim_index``, in the tree's left-to-right order. Arrays have ``2 * cap`` node slots
and ``cap`` primitive slots, padding inert, as :func:`jaxbvh.build` documents.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.cost import half_area
from jaxbvh.tree import BVH


class Linked(NamedTuple):
    """A full binary tree over sorted positions (module docstring: the linked form)."""

    n: Any          # [] int32, real primitives
    left: Any       # [cap] int32 linked ids
    right: Any      # [cap] int32
    lo: Any         # [cap, 3] internal boxes
    hi: Any         # [cap, 3]
    count: Any      # [cap] int32 primitives below
    first: Any      # [cap] int32 lowest position below
    axis: Any       # [cap] int32 split axis or -1
    leaf_lo: Any    # [cap, 3] box of the primitive at each position (padding: empty box)
    leaf_hi: Any    # [cap, 3]
    order: Any      # [cap] int32 primitive id at each position


def _take(arr, idx, fill):
    """``arr[idx]`` with ``fill`` where ``idx`` is out of range (no wrap-around of -1)."""
    return arr.at[idx].get(mode="fill", fill_value=fill)


def to_bvh(linked: Linked, max_leaf, ct, ci, scale) -> BVH:
    """The :class:`~jaxbvh.tree.BVH` of ``linked`` with small subtrees collapsed (traceable).

    ``max_leaf`` [] int32, ``ct``, ``ci``, ``scale`` [] in the boxes' dtype (``scale``:
    the power of two areas are measured with, :func:`jaxbvh.build.scene_scale`).
    """
    n = linked.n
    cap = linked.leaf_lo.shape[0]
    nodes = 2 * cap
    none = nodes  # out-of-range linked id: "no node"
    dtype = linked.leaf_lo.dtype
    slot = jnp.arange(cap, dtype=jnp.int32)
    real = slot < n - 1
    left = jnp.where(real, linked.left, none)
    right = jnp.where(real, linked.right, none)
    box_lo = jnp.concatenate([jnp.where(real[:, None], linked.lo, jnp.inf), linked.leaf_lo])
    box_hi = jnp.concatenate([jnp.where(real[:, None], linked.hi, -jnp.inf), linked.leaf_hi])
    count = jnp.concatenate([jnp.where(real, linked.count, 0), (slot < n).astype(jnp.int32)])
    first = jnp.concatenate([linked.first, slot])
    parent = jnp.full(nodes, none, jnp.int32).at[left].set(slot, mode="drop").at[right].set(slot, mode="drop")
    is_right = jnp.zeros(nodes, bool).at[right].set(True, mode="drop")

    # the SAH leaf test at every internal node, from its children
    area = half_area(box_lo, box_hi, scale)
    n_left, n_right = _take(count, left, 0), _take(count, right, 0)
    split = (_take(area, left, 0) * n_left.astype(dtype) + _take(area, right, 0) * n_right.astype(dtype))
    own = area[:cap]
    n_own = count[:cap].astype(dtype)
    estimate = ct + jnp.where(own > 0, ci * split / jnp.where(own > 0, own, 1), ci * n_own)
    passes = real & (count[:cap] <= max_leaf) & (ci * n_own <= estimate)

    # covered: the node or one of its ancestors passes (only the nearest max_leaf - 1 can)
    up = parent[:cap]

    def spread(carry):
        covered, _, steps = carry
        new = passes | _take(covered, up, False)
        return new, jnp.any(new != covered), steps + 1

    covered, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] <= jnp.minimum(max_leaf, cap)), spread,
                                       (passes, jnp.bool_(True), jnp.int32(0)))
    inside = _take(covered, parent, False)  # [nodes]: the parent is covered, so the node is gone
    interior = real & ~covered
    final_leaf = jnp.concatenate([passes & ~inside[:cap], (slot < n) & ~inside[cap:]])

    # numbering: interior nodes in slot order, then leaves by lowest position
    starts = jnp.zeros(cap, jnp.int32).at[jnp.where(final_leaf, first, cap)].set(1, mode="drop")
    rank_at = jnp.cumsum(starts) - starts
    n_leaves = jnp.sum(starts)
    n_interior = n_leaves - 1
    interior_id = jnp.cumsum(interior.astype(jnp.int32)) - interior
    leaf_rank = jnp.where(final_leaf, _take(rank_at, first, 0), cap)
    final_id = jnp.where(jnp.concatenate([interior, jnp.zeros(cap, bool)]),
                         jnp.concatenate([interior_id, interior_id]),
                         jnp.where(final_leaf, n_interior + leaf_rank, none))
    size_by_rank = jnp.zeros(cap, jnp.int32).at[leaf_rank].set(count, mode="drop")
    start_by_rank = jnp.cumsum(size_by_rank) - size_by_rank

    # every primitive walks up to its leaf, adding the primitives left of its path
    left_all = jnp.concatenate([left, jnp.full(cap, none, jnp.int32)])
    leaf_of = cap + slot
    offset = jnp.zeros(cap, jnp.int32)

    def climb(carry):
        node, offset, _, steps = carry
        moving = _take(inside, node, False)
        above = _take(parent, node, none)
        sibling = _take(left_all, above, none)
        add = jnp.where(moving & _take(is_right, node, False), _take(count, sibling, 0), 0)
        node = jnp.where(moving, above, node)
        return node, offset + add, jnp.any(_take(inside, node, False)), steps + 1

    leaf_of, offset, _, _ = jax.lax.while_loop(
        lambda c: c[2] & (c[3] < jnp.minimum(max_leaf, cap)), climb,
        (leaf_of, offset, jnp.any(inside[cap:] & (slot < n)), jnp.int32(0)))
    prim_slot = _take(start_by_rank, _take(leaf_rank, leaf_of, cap), 0) + offset
    prim_index = jnp.full(cap, -1, jnp.int32).at[jnp.where(slot < n, prim_slot, cap)].set(linked.order, mode="drop")

    # scatter every kept node to its final id
    target = jnp.where(final_id < none, final_id, none)
    interior_all = jnp.concatenate([interior, jnp.zeros(cap, bool)])
    child_id = lambda ids: jnp.where(interior_all, _take(final_id, ids, none), -1)  # noqa: E731
    right_all = jnp.concatenate([right, jnp.full(cap, none, jnp.int32)])
    axis_all = jnp.concatenate([linked.axis, jnp.full(cap, -1, jnp.int32)])
    parent_id = jnp.where(parent < none, _take(final_id, parent, none), -1)

    def put(fill, values, dtype_):
        return jnp.full((nodes,) + values.shape[1:], fill, dtype_).at[target].set(values, mode="drop")

    return BVH(
        left=put(-1, child_id(left_all), jnp.int32),
        right=put(-1, child_id(right_all), jnp.int32),
        parent=put(-1, parent_id, jnp.int32),
        lo=put(jnp.inf, box_lo, dtype), hi=put(-jnp.inf, box_hi, dtype),
        prim_start=put(0, jnp.where(final_leaf, _take(start_by_rank, leaf_rank, 0), 0), jnp.int32),
        prim_count=put(0, jnp.where(final_leaf, count, 0), jnp.int32),
        axis=put(-1, jnp.where(interior_all, axis_all, -1), jnp.int32),
        prim_index=prim_index, root=jnp.int32(0),
    )
