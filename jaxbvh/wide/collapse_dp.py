"""The optimal collapse (Susano Pinto 2010, Algorithm 3) as a dynamic program, level by level.

Part of :mod:`jaxbvh.wide.collapse`, whose docstring defines the tables ``g(n, t)`` and
``h(n, t)``, the tie rule and the merged leaves (``max_leaf > 1``). :func:`decide`
solves the tables bottom-up, one depth at a time (a vectorised min-plus product of the
two children's tables per node), and back-tracks the choices top-down;
:func:`regroup_prims` puts the primitives of every merged leaf in one run.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.numerics import min_gain, take
from jaxbvh.program_store import stored_jit
from jaxbvh.wide import levels as lv
from jaxbvh.wide.collapse_layout import links, relative_areas


def _first_near_min(candidates):
    """Tie rule over a list of candidate arrays: ``(index, value)`` of the first within
    :func:`jaxbvh.numerics.min_gain` of the least (elementwise; unrolled, so XLA fuses it into one loop)."""
    best = candidates[0]
    for c in candidates[1:]:
        best = jnp.minimum(best, c)
    near = best * (1 + min_gain(best.dtype))
    index = jnp.zeros(best.shape, jnp.int32)
    value = candidates[-1]
    for i in range(len(candidates) - 1, -1, -1):  # the last assignment is the first candidate
        within = candidates[i] <= near
        index = jnp.where(within, i, index)
        value = jnp.where(within, candidates[i], value)
    return index, value


def _min_plus(gl, gr):
    """``h[t] = g_L[i] + g_R[t - i]`` at the first near-least ``i``: ``(h, i)`` [K+1, W].

    Tables are [K+1, W] (one row per ``t``). Unrolled over the ``K (K - 1) / 2`` pairs
    ``(t, i < t)`` on whole rows, which XLA fuses into one loop (3x faster on CPU than
    shifting whole tables; compile time grows as K^2, hence :data:`MAX_CHILDREN_LIMIT`).
    """
    k1, w = gl.shape
    h = [jnp.full((w,), jnp.inf, gl.dtype)] * 2
    split = [jnp.zeros((w,), jnp.int32)] * 2
    for t in range(2, k1):
        i, value = _first_near_min([gl[i] + gr[t - i] for i in range(1, t)])
        h.append(value)
        split.append(i + 1)
    return jnp.stack(h), jnp.stack(split).astype(jnp.int8)


class _Tables(NamedTuple):
    """The DP's tables: one column per interior node, in level order (``R`` columns:
    the rows of :class:`jaxbvh.wide.levels.Levels`)."""

    g: Any       # [K+1, R] float: g(n, t) for t >= 2, the value of the choice made at t = 1
    choice: Any  # [R] int8: the t of n kept (2..K), 0: n becomes a leaf (merging only)
    split: Any   # [K+1, R] int8: for each t, the left child's share i of the entry points
    prims: Any   # [R] int32: primitives under n


class _Placement(NamedTuple):
    """What the back-tracking gives every node [N]."""

    tau: Any     # int32: entry points the node gives its anchor (1: kept, 0: inside a new leaf)
    anchor: Any  # int32: nearest kept proper ancestor (-1: none)
    slot: Any    # int32: its child slot at the anchor (a removed node: its first child's)
    owner: Any   # int32: the new leaf that absorbs it (N: none)


def _solve(tree, levels, a, table, ci, leaf_value, max_leaf, *, k, merge) -> _Tables:
    """The tables of every interior node, bottom-up one depth at a time.

    ``a`` [N]: relative areas; ``table`` [K+1]: ``T(t)``; ``ci`` []: the cost of a
    primitive test; ``leaf_value`` [N]: a leaf's ``g(n, 1)``, all in ``a``'s dtype.
    """
    n = tree.left.shape[0]
    left, right, _, _ = links(tree)
    dtype = a.dtype
    rows_total = levels.order.shape[0]
    is_leaf = tree.prim_count > 0
    t_index = jnp.arange(k + 1)[:, None]

    def child_table(g, prims, c):
        """Tables [K+1, W] of the children ``c`` [W]: a leaf's from its cost, others from ``g``."""
        pos = take(levels.position, c, rows_total)
        leaf = take(is_leaf, c, False)
        stored = jnp.take(g, pos, axis=1, mode="fill", fill_value=jnp.inf)
        leaf_table = jnp.where(t_index == 1, take(leaf_value, c, 0)[None, :], jnp.inf)
        count = jnp.where(leaf, take(tree.prim_count, c, 0), take(prims, pos, 0))
        return jnp.where(leaf[None, :], leaf_table, stored), count

    def solve(state: _Tables, start, valid) -> _Tables:
        g, choice, split, prims = state
        x = levels.window(start, valid)
        xs = jnp.minimum(x, n - 1)
        w = x.shape[0]
        both, counts = child_table(g, prims, jnp.concatenate([left[xs], right[xs]]))  # one gather
        gl, gr, pl, pr = both[:, :w], both[:, w:], counts[:w], counts[w:]
        h, i_best = _min_plus(gl, gr)
        t_best, value = _first_near_min([a[xs] * table[t] + h[t] for t in range(2, k + 1)])
        t_best = t_best + 2
        count = pl + pr
        if merge:
            as_leaf = jnp.where(count <= max_leaf, a[xs] * ci * count.astype(dtype), jnp.inf)
            make_leaf = value > as_leaf * (1 + min_gain(dtype))
            t_best = jnp.where(make_leaf, 0, t_best)
            value = jnp.where(make_leaf, as_leaf, value)
        g = jax.lax.dynamic_update_slice(g, h.at[1].set(value), (jnp.int32(0), start))
        choice = jax.lax.dynamic_update_slice(choice, t_best.astype(jnp.int8), (start,))
        split = jax.lax.dynamic_update_slice(split, i_best, (jnp.int32(0), start))
        prims = jax.lax.dynamic_update_slice(prims, count, (start,))
        return _Tables(g, choice, split, prims)

    state = _Tables(g=jnp.full((k + 1, rows_total), jnp.inf, dtype), choice=jnp.zeros(rows_total, jnp.int8),
                    split=jnp.zeros((k + 1, rows_total), jnp.int8), prims=jnp.zeros(rows_total, jnp.int32))
    return lv.sweep_up(levels, solve, state)


def _back_track(tree, levels, tables: _Tables, *, k) -> _Placement:
    """The choices top-down, one depth at a time: every node's entry points, anchor,
    slot and absorbing leaf."""
    n = tree.left.shape[0]
    left, right, _, _ = links(tree)
    choice, split = tables.choice, tables.split

    def back(state: _Placement, start, valid) -> _Placement:
        tau, anchor, slot, owner = state
        x = levels.window(start, valid)
        xs = jnp.minimum(x, n - 1)
        live = x < n
        tau_x = tau[xs]
        keep_x = tau_x == 1
        ch = jax.lax.dynamic_slice(choice, (start,), (x.shape[0],)).astype(jnp.int32)
        sp = jax.lax.dynamic_slice(split, (jnp.int32(0), start), (k + 1, x.shape[0])).astype(jnp.int32)
        becomes_leaf = keep_x & (ch == 0)
        inside = tau_x == 0
        entries = jnp.where(keep_x, ch, tau_x)
        i = jnp.take_along_axis(sp, jnp.clip(entries, 0, k)[None, :], axis=0)[0]
        gone = inside | becomes_leaf
        kids = jnp.concatenate([jnp.where(live, left[xs], n), jnp.where(live, right[xs], n)])
        base = jnp.where(keep_x, 0, slot[xs])
        up = jnp.where(keep_x, xs, anchor[xs])
        new_owner = jnp.where(becomes_leaf, xs, jnp.where(inside, owner[xs], n))

        def both(l_value, r_value):
            return jnp.concatenate([l_value, r_value])

        tau = tau.at[kids].set(both(jnp.where(gone, 0, i), jnp.where(gone, 0, entries - i)), mode="drop")
        anchor = anchor.at[kids].set(both(up, up), mode="drop")
        slot = slot.at[kids].set(both(base, base + i), mode="drop")
        owner = owner.at[kids].set(both(new_owner, new_owner), mode="drop")
        return _Placement(tau, anchor, slot, owner)

    start = _Placement(tau=jnp.zeros(n, jnp.int32).at[tree.root].set(1), anchor=jnp.full(n, -1, jnp.int32),
                       slot=jnp.zeros(n, jnp.int32), owner=jnp.full(n, n, jnp.int32))
    return lv.sweep_down(levels, back, start)


@partial(stored_jit, static_argnames=("max_children", "merge"))
def decide(tree, levels, table, ci, max_leaf, *, max_children, merge):
    """The optimal collapse of ``tree`` (a JAX binary BVH) with ``K = max_children``.

    ``levels``: :func:`jaxbvh.wide.collapse_layout.schedule` of the tree; ``table``
    [K+1]: ``T(t)``; ``ci`` []: the cost of a primitive test; ``max_leaf`` [] int32 and
    ``merge`` (static: ``max_leaf > 1``): subtrees of up to ``max_leaf`` primitives may
    become leaves. Values are traced, so one program serves every ``T`` and ``max_leaf``.

    Returns ``(kept [N] bool, anchor [N] int32, slot [N] int32, objective [],
    made_leaf [N] bool, owner [N] int32, count [N] int32)``: the nodes kept, where they
    sit (:func:`jaxbvh.wide.collapse_layout.layout`'s form), the DP's ``g(root, 1)``, the
    interior nodes that became leaves, the new leaf absorbing each node (``N``: none) and
    the primitives of every leaf.
    """
    n = tree.left.shape[0]
    _, _, interior, real = links(tree)
    a = relative_areas(tree.lo, tree.hi, tree.root)
    dtype = a.dtype
    ci = jnp.asarray(ci, dtype)
    leaf_value = (a * ci * tree.prim_count.astype(dtype)) if merge else jnp.zeros(n, dtype)
    tables = _solve(tree, levels, a, table.astype(dtype), ci, leaf_value, max_leaf, k=max_children, merge=merge)
    root_pos = levels.position[tree.root]
    objective = jnp.where(interior[tree.root], take(tables.g[1], root_pos, jnp.inf), leaf_value[tree.root])
    placed = _back_track(tree, levels, tables, k=max_children)
    kept = real & (placed.tau == 1)
    made_leaf = kept & interior
    if merge:
        made_leaf = made_leaf & (take(tables.choice, levels.position, 1) == 0)
    else:
        made_leaf = jnp.zeros(n, bool)
    count = jnp.where(made_leaf, take(tables.prims, levels.position, 0), tree.prim_count)
    return kept, placed.anchor, placed.slot, objective, made_leaf, placed.owner, count


@stored_jit
def regroup_prims(tree, owner, count):
    """``prim_index`` with every new leaf's primitives in one run: ``(start, prim_index)``.

    ``owner[leaf]`` is the new leaf that absorbs a binary leaf (``N``: it stays a leaf).
    Slots are sorted by the leaf that ends up holding them (stable), so runs stay runs.
    """
    n = tree.left.shape[0]
    p = tree.prim_index.shape[0]
    leaf = tree.prim_count > 0
    ids = jnp.arange(n, dtype=jnp.int32)
    slots = jnp.arange(p, dtype=jnp.int32)
    first = jnp.full(p, -1, jnp.int32).at[jnp.where(leaf, tree.prim_start, p)].set(ids, mode="drop")
    last_start = jax.lax.cummax(jnp.where(first >= 0, slots, -1))
    holder = take(first, jnp.where(last_start >= 0, last_start, p), -1)
    hs = jnp.maximum(holder, 0)
    used = (holder >= 0) & (slots < tree.prim_start[hs] + tree.prim_count[hs])
    final = jnp.where(owner[hs] < n, owner[hs], hs)
    key = jnp.where(used, final, n)
    key_sorted, order = jax.lax.sort((key, slots), num_keys=1, is_stable=True)
    prim_index = jnp.where(key_sorted < n, tree.prim_index[order], -1)
    start = jnp.full(n, p, jnp.int32).at[key_sorted].min(slots, mode="drop")
    return jnp.where(count > 0, start, 0), prim_index
