"""From the nodes a collapse keeps to the wide tree: areas, schedule, slots, emission, prices.

Part of :mod:`jaxbvh.wide.collapse` (Susano Pinto 2010), whose docstring explains the
cost model and the outputs; the three methods decide which nodes to keep and share
everything here. :func:`schedule` lists the interior nodes level by level
(:mod:`jaxbvh.wide.levels`), :func:`layout` gives every kept node its anchor and child
slot, :func:`emit` writes the :class:`~jaxbvh.tree.layout.WideBVH` on the input's ids and
prices it, :func:`prices` is Pinto's ``R`` (and the leaf cost) of any tree.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from jaxbvh.numerics import extent_scale, half_area, take
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import WideBVH
from jaxbvh.wide import levels as lv


def relative_areas(lo, hi, root):
    """``a(n) = S(n) / S(root)`` [N] (all 1 when the root has zero area); padding 0 or 1."""
    scale = extent_scale(lo[root], hi[root])
    area = half_area(lo, hi, scale)
    root_area = area[root]
    return jnp.where(root_area > 0, area / jnp.where(root_area > 0, root_area, 1), jnp.ones_like(area))


def window_width(n: int) -> int:
    """Window of the level sweeps for ``n`` nodes (speed only; one size, one compiled step).

    About ``n / 64``, a power of two in [64, 4096]: wide enough for the big levels, narrow
    enough that the nearly empty levels near the root and the deepest leaves, each one
    window, cost little.
    """
    return int(min(4096, max(64, 1 << max(0, (n // 64 - 1)).bit_length())))


def links(tree):
    """``(left, right, interior, real)`` [N] of a binary tree: children with ``N`` for
    none (int32), and whether each node is interior / a real node (bool)."""
    n = tree.left.shape[0]
    left = jnp.where(tree.left >= 0, tree.left, n).astype(jnp.int32)
    right = jnp.where(tree.right >= 0, tree.right, n).astype(jnp.int32)
    interior = tree.left >= 0
    real = interior | (tree.prim_count > 0)
    return left, right, interior, real


@stored_jit
def schedule(tree):
    """The interior nodes level by level (:mod:`jaxbvh.wide.levels`); one compile per capacity,
    shared by the three methods."""
    left, right, interior, _ = links(tree)
    return lv.level_order(left, right, tree.root, interior, (window_width(tree.left.shape[0]),))


@stored_jit
def layout(tree, levels, kept):
    """Anchor (nearest kept proper ancestor) and child slot of every node, from ``kept``
    [N] bool; and the most children of a node: ``(anchor [N] int32, slot [N] int32,
    width [] int32)``.

    Bottom-up: ``e(n)`` entry points ``n`` gives its anchor (1 if kept, else the sum of
    its children's). Top-down: a kept node's children start at slot 0, a removed node's
    at its own slot; the right child follows the left child's ``e``.
    """
    n = tree.left.shape[0]
    left, right, _, _ = links(tree)

    def count_up(e, start, valid):
        x = levels.window(start, valid)
        total = take(e, left[jnp.minimum(x, n - 1)], 0) + take(e, right[jnp.minimum(x, n - 1)], 0)
        return e.at[x].set(jnp.where(take(kept, x, True), 1, total), mode="drop")

    e = lv.sweep_up(levels, count_up, jnp.ones(n, jnp.int32))

    def place_down(state, start, valid):
        anchor, slot = state
        x = levels.window(start, valid)
        xs = jnp.minimum(x, n - 1)
        keep_x = kept[xs]
        base = jnp.where(keep_x, 0, slot[xs])
        owner = jnp.where(keep_x, xs, anchor[xs])
        l, r = jnp.where(x < n, left[xs], n), jnp.where(x < n, right[xs], n)
        kids = jnp.concatenate([l, r])
        anchor = anchor.at[kids].set(jnp.concatenate([owner, owner]), mode="drop")
        slot = slot.at[kids].set(jnp.concatenate([base, base + take(e, l, 0)]), mode="drop")
        return anchor, slot

    anchor, slot = lv.sweep_down(levels, place_down, (jnp.full(n, -1, jnp.int32), jnp.zeros(n, jnp.int32)))
    width = jnp.max(jnp.where(kept & (jnp.arange(n) != tree.root), slot, 0)) + 1
    return anchor, slot, width


def prices(a, child, prim_count, table, ci):
    """``(R, leaf cost)`` of a tree with relative areas ``a`` [N] (:func:`relative_areas`),
    ``child`` [N, K] and ``prim_count`` [N]: ``table`` [K + 1] is ``T(k)``
    (:func:`jaxbvh.wide.box_tests.cost_table`), ``ci`` the cost of a primitive test
    (see :func:`jaxbvh.wide.collapse.rcost`)."""
    k = jnp.sum(child >= 0, axis=1)
    per_node = a * jnp.take(table.astype(a.dtype), k, mode="clip")
    rc = jnp.sum(jnp.where(k > 0, per_node, 0))
    leaves = jnp.sum(jnp.where(prim_count > 0, a * prim_count.astype(a.dtype), 0)) * ci
    return rc, leaves


@partial(stored_jit, static_argnames=("arity",))
def emit(tree, kept, anchor, slot, leaf_count, leaf_start, prim_index, table, ci, *, arity):
    """The WideBVH on the input's ids (kept nodes linked to their anchors at their
    slots, ``arity`` children per node), and ``(R, leaf cost)`` of it and of the input.

    ``leaf_count``, ``leaf_start`` [N] int32, ``prim_index`` [P] int32: the leaves of the
    result (the input's, or the merged ones of :func:`jaxbvh.wide.collapse_dp.regroup_prims`).
    """
    n = tree.left.shape[0]
    ids = jnp.arange(n, dtype=jnp.int32)
    linked = kept & (ids != tree.root)
    rows = jnp.where(linked, anchor, n)
    child = jnp.full((n, arity), -1, jnp.int32).at[rows, jnp.where(linked, slot, 0)].set(ids, mode="drop")
    is_leaf = kept & (leaf_count > 0)
    wide = WideBVH(child=child, parent=jnp.where(linked, anchor, -1).astype(jnp.int32),
                   lo=jnp.where(kept[:, None], tree.lo, jnp.inf).astype(tree.lo.dtype),
                   hi=jnp.where(kept[:, None], tree.hi, -jnp.inf).astype(tree.hi.dtype),
                   prim_start=jnp.where(is_leaf, leaf_start, 0).astype(jnp.int32),
                   prim_count=jnp.where(is_leaf, leaf_count, 0).astype(jnp.int32),
                   prim_index=prim_index, root=tree.root)
    a = relative_areas(tree.lo, tree.hi, tree.root)  # kept boxes are the input's: one area pass
    ci = jnp.asarray(ci, a.dtype)
    return wide, prices(a, child, wide.prim_count, table, ci), prices(a, tree.child, tree.prim_count, table[:3], ci)

