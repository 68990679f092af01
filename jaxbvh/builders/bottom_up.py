"""From the linked tree a bottom-up builder makes to the BVH layout, collapsing small subtrees.

LBVH (:mod:`jaxbvh.builders.lbvh`) and PLOC (:mod:`jaxbvh.builders.ploc`) both end with a full binary tree
over the Morton-sorted primitives, one primitive per leaf, given as *linked form*
(:class:`Linked`); :func:`to_bvh` turns it into a :class:`~jaxbvh.tree.layout.BVH` (jitted,
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
The test is the one the top-down builders use (:mod:`jaxbvh.builders.topdown`), applied to the
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
and ``cap`` primitive slots, padding inert, as :func:`jaxbvh.builders.topdown` documents.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.numerics import exclusive_sum, half_area, take
from jaxbvh.tree.layout import BVH


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


def to_bvh(linked: Linked, max_leaf, ct, ci, scale, *, collapse: bool) -> BVH:
    """The :class:`~jaxbvh.tree.layout.BVH` of ``linked`` with small subtrees collapsed (traceable).

    ``max_leaf`` [] int32, ``ct``, ``ci``, ``scale`` [] in the boxes' dtype (``scale``:
    the power of two areas are measured with, :func:`jaxbvh.builders.topdown.scene_scale`).
    ``collapse`` (static; the builders pass ``max_leaf > 1``): without it every leaf
    holds one primitive and the layout is a pair of shifted copies; with it the
    leaf test runs and :func:`_collapse` renumbers. One compiled program per mode, the
    value of ``max_leaf`` is traced.
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
    parent = jnp.full(nodes, none, jnp.int32).at[left].set(slot, mode="drop").at[right].set(slot, mode="drop")
    if not collapse:
        return _in_place(linked, n, left, right, parent)

    # the SAH leaf test at every internal node, from its children
    count = jnp.concatenate([jnp.where(real, linked.count, 0), (slot < n).astype(jnp.int32)])
    area = jnp.concatenate([half_area(linked.lo, linked.hi, scale), half_area(linked.leaf_lo, linked.leaf_hi, scale)])
    split = (take(area, left, 0) * take(count, left, 0).astype(dtype)
             + take(area, right, 0) * take(count, right, 0).astype(dtype))
    own = area[:cap]
    n_own = count[:cap].astype(dtype)
    estimate = ct + jnp.where(own > 0, ci * split / jnp.where(own > 0, own, 1), ci * n_own)
    passes = real & (count[:cap] <= max_leaf) & (ci * n_own <= estimate)
    return _collapse(linked, (n, left, right, parent, count, passes), max_leaf)


def _in_place(linked: Linked, n, left, right, parent) -> BVH:
    """Layout without collapsing: internal slot k is node k, position p is node n - 1 + p."""
    cap = linked.leaf_lo.shape[0]
    nodes = 2 * cap
    node = jnp.arange(nodes, dtype=jnp.int32)
    is_internal = node < n - 1
    is_leaf = ~is_internal & (node < 2 * n - 1)

    def place(internal, leaf, fill):
        """Node array [nodes, ...]: ``internal`` [cap, ...] first, then ``leaf`` [cap, ...] from n - 1."""
        pad = jnp.full((cap,) + leaf.shape[1:], fill, leaf.dtype)
        shifted = jax.lax.dynamic_slice_in_dim(jnp.concatenate([pad, leaf, pad]), cap - (n - 1), nodes)
        expand = (slice(None),) + (None,) * (leaf.ndim - 1)
        return jnp.where(is_internal[expand], jnp.concatenate([internal, pad]),
                         jnp.where(is_leaf[expand], shifted, fill))

    def final(ids):  # linked id -> node id (none -> -1)
        return jnp.where(ids < cap, ids, jnp.where(ids < nodes, ids - cap + n - 1, -1))

    no_link = jnp.full(cap, -1, jnp.int32)
    slot = jnp.arange(cap, dtype=jnp.int32)
    return BVH(
        left=place(final(left), no_link, -1), right=place(final(right), no_link, -1),
        parent=place(final(parent[:cap]), final(parent[cap:]), -1),
        lo=place(linked.lo, linked.leaf_lo, jnp.inf), hi=place(linked.hi, linked.leaf_hi, -jnp.inf),
        prim_start=place(jnp.zeros(cap, jnp.int32), slot, 0),
        prim_count=place(jnp.zeros(cap, jnp.int32), jnp.ones(cap, jnp.int32), 0),
        axis=place(linked.axis, no_link, -1),
        prim_index=jnp.where(slot < n, linked.order, -1), root=jnp.int32(0),
    )


class _Kept(NamedTuple):
    """Which nodes of the linked tree the collapse keeps, by linked id [2 cap]."""

    inside: Any      # bool: the parent is covered (it or an ancestor passes), so the node is gone
    interior: Any    # bool: an internal slot that stays interior (nothing above or at it passes)
    final_leaf: Any  # bool: a leaf of the result (a passing node or a position, not inside)


class _Numbering(NamedTuple):
    """Node ids of the result: interior nodes in slot order, then leaves by lowest position."""

    final_id: Any       # int32 [2 cap]: the result's node id of each linked id (2 cap: gone)
    leaf_rank: Any      # int32 [2 cap]: a final leaf's rank among the leaves (cap: not a leaf)
    start_by_rank: Any  # int32 [cap]: first prim_index slot of the leaf of each rank


def _kept(parts, max_leaf, cap) -> _Kept:
    """The nodes kept: only the nearest ``max_leaf - 1`` ancestors of a node can pass, so
    "covered" spreads down from the passing nodes in at most ``max_leaf`` steps."""
    n, _, _, parent, _, passes = parts
    slot = jnp.arange(cap, dtype=jnp.int32)
    real = slot < n - 1
    up = parent[:cap]

    def spread(carry):
        covered, _, steps = carry
        new = passes | take(covered, up, False)
        return new, jnp.any(new != covered), steps + 1

    covered, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] <= jnp.minimum(max_leaf, cap)), spread,
                                       (passes, jnp.bool_(True), jnp.int32(0)))
    inside = take(covered, parent, False)  # [nodes]: the parent is covered, so the node is gone
    interior = real & ~covered
    final_leaf = jnp.concatenate([passes & ~inside[:cap], (slot < n) & ~inside[cap:]])
    return _Kept(inside=inside, interior=jnp.concatenate([interior, jnp.zeros(cap, bool)]), final_leaf=final_leaf)


def _number(linked: Linked, count, kept: _Kept) -> _Numbering:
    """Node ids and leaf ranks of the result, and where each leaf's primitives start."""
    cap = linked.leaf_lo.shape[0]
    none = 2 * cap
    slot = jnp.arange(cap, dtype=jnp.int32)
    first = jnp.concatenate([linked.first, slot])
    starts = jnp.zeros(cap, jnp.int32).at[jnp.where(kept.final_leaf, first, cap)].set(1, mode="drop")
    rank_at = exclusive_sum(starts)
    n_interior = jnp.sum(starts) - 1
    leaf_rank = jnp.where(kept.final_leaf, take(rank_at, first, 0), cap)
    final_id = jnp.where(kept.interior, jnp.concatenate([exclusive_sum(kept.interior[:cap]), slot]),
                         jnp.where(kept.final_leaf, n_interior + leaf_rank, none))
    size_by_rank = jnp.zeros(cap, jnp.int32).at[leaf_rank].set(count, mode="drop")
    return _Numbering(final_id=final_id, leaf_rank=leaf_rank, start_by_rank=exclusive_sum(size_by_rank))


def _prim_index(linked: Linked, parts, max_leaf, kept: _Kept, numbering: _Numbering):
    """``prim_index`` [cap] int32 of the result: every primitive walks up to its leaf,
    adding the primitives left of its path (at most ``max_leaf`` steps)."""
    n, left, right, parent, count, _ = parts
    cap = linked.leaf_lo.shape[0]
    nodes = 2 * cap
    none = nodes
    slot = jnp.arange(cap, dtype=jnp.int32)
    inside = kept.inside
    is_right = jnp.zeros(nodes, bool).at[right].set(True, mode="drop")
    left_all = jnp.concatenate([left, jnp.full(cap, none, jnp.int32)])

    def climb(carry):
        node, offset, _, steps = carry
        moving = take(inside, node, False)
        above = take(parent, node, none)
        add = jnp.where(moving & take(is_right, node, False), take(count, take(left_all, above, none), 0), 0)
        node = jnp.where(moving, above, node)
        return node, offset + add, jnp.any(take(inside, node, False)), steps + 1

    leaf_of, offset, _, _ = jax.lax.while_loop(
        lambda c: c[2] & (c[3] < jnp.minimum(max_leaf, cap)), climb,
        (cap + slot, jnp.zeros(cap, jnp.int32), jnp.any(inside[cap:] & (slot < n)), jnp.int32(0)))
    prim_slot = take(numbering.start_by_rank, take(numbering.leaf_rank, leaf_of, cap), 0) + offset
    return jnp.full(cap, -1, jnp.int32).at[jnp.where(slot < n, prim_slot, cap)].set(linked.order, mode="drop")


def _collapse(linked: Linked, parts, max_leaf) -> BVH:
    """Layout with the subtrees under passing nodes collapsed into leaves (module docstring)."""
    _, left, right, parent, count, _ = parts
    cap = linked.leaf_lo.shape[0]
    nodes = 2 * cap
    none = nodes
    kept = _kept(parts, max_leaf, cap)
    numbering = _number(linked, count, kept)
    prim_index = _prim_index(linked, parts, max_leaf, kept, numbering)
    final_id, leaf_rank = numbering.final_id, numbering.leaf_rank

    # every node id gathers its source (the inverse of final_id, one integer scatter)
    source = jnp.full(nodes, none, jnp.int32).at[final_id].set(jnp.arange(nodes, dtype=jnp.int32), mode="drop")
    is_leaf = take(kept.final_leaf, source, False)
    is_interior = take(kept.interior, source, False)

    def field(internal, leaf, fill):
        both = jnp.concatenate([internal, leaf])
        return take(both, source, fill)

    def link(ids):
        return jnp.where(is_interior, take(final_id, take(ids, source, none), -1), -1)

    left_all = jnp.concatenate([left, jnp.full(cap, none, jnp.int32)])
    right_all = jnp.concatenate([right, jnp.full(cap, none, jnp.int32)])
    parent_id = take(final_id, take(parent, source, none), -1)
    parent_id = jnp.where(parent_id < none, parent_id, -1)
    return BVH(
        left=link(left_all), right=link(right_all), parent=parent_id,
        lo=field(linked.lo, linked.leaf_lo, jnp.inf), hi=field(linked.hi, linked.leaf_hi, -jnp.inf),
        prim_start=jnp.where(is_leaf, take(numbering.start_by_rank, take(leaf_rank, source, cap), 0), 0),
        prim_count=jnp.where(is_leaf, take(count, source, 0), 0),
        axis=jnp.where(is_interior, take(linked.axis, source, -1), -1),
        prim_index=prim_index, root=jnp.int32(0),
    )
