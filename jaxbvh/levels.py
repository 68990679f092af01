"""Level-by-level sweeps over a tree: nodes grouped by depth, processed in windows (jitted).

Many tree algorithms are one recurrence over parents and children: a node's value from
its children's (bottom-up), or a node's value from its parent's (top-down). Nodes of
equal depth never depend on each other, so a sweep can process a whole depth at once.
This module provides that schedule for any tree of the layout in :mod:`jaxbvh.tree`:

1. :func:`depths` — the depth of every node by pointer jumping over ``parent``
   (``ceil(log2(height)) + 1`` rounds of one gather each, never more than
   ``bit_length(N) + 1``, whatever the node order).
2. :func:`level_order` — the chosen nodes (usually the interior ones) sorted deepest
   first: ``order`` [N + width] int32 (node ids, ``N`` past the end) and ``keys``
   [N + width] (``max_depth - depth``, ascending; huge past the end). A node's
   children always sit at earlier positions than the node.
3. :func:`sweep_up` / :func:`sweep_down` — call ``step(carry, start, valid)`` on windows
   ``[start, start + W)`` of positions, deepest level first (up) or shallowest first
   (down). A window never mixes two levels: ``valid`` [W] bool masks positions outside
   the current level. Levels with many nodes go through windows of the largest size in
   ``widths`` while that many remain, then the next size down, so the work is about the
   number of nodes plus (levels x smallest width), not nodes x levels.

Arrays a step writes by *position* (``jax.lax.dynamic_update_slice`` at ``start``) need
``N + max(widths)`` rows (``levels.order.shape[0]``): a window at the end of a level may reach past it (masked), and
in a bottom-up sweep the positions it overwrites belong to levels not processed yet.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

BIG_KEY = 2 ** 31 - 1


class Levels(NamedTuple):
    """A level schedule (:func:`level_order`).

    ``order`` [N + pad] int32: node ids deepest first, ``N`` past ``count``;
    ``keys`` [N + pad] int32: ``max_depth - depth`` of each entry (ascending), huge past
    ``count``; ``count`` int32: number of scheduled nodes; ``position`` [N] int32: the
    position of each scheduled node in ``order`` (``N + pad`` for the others);
    ``widths``: the window sizes (static ints, largest first; ``pad`` is the largest).
    """

    order: Any
    keys: Any
    count: Any
    position: Any
    widths: tuple


def depths(parent, real):
    """Depth of every node [N] int32 (root 0); -1 for padding.

    ``parent`` [N] int32 (-1 for the root and padding), ``real`` [N] bool. Pointer
    jumping: ``up[i]`` is an ancestor of ``i`` at distance ``dist[i]``; each round adds
    the distance of ``up[i]`` and jumps to ``up[up[i]]``, doubling the span. The loop is
    bounded (``bit_length(N) + 1`` rounds), so a broken tree cannot hang it.
    """
    n = parent.shape[0]
    has_up = real & (parent >= 0)
    up = jnp.where(has_up, parent, n).astype(jnp.int32)
    dist = has_up.astype(jnp.int32)
    rounds = int(n).bit_length() + 1

    def cond(state):
        up, _, i = state
        return jnp.any(up < n) & (i < rounds)

    def body(state):
        up, dist, i = state
        live = up < n
        dist = dist + jnp.where(live, jnp.take(dist, up, mode="fill", fill_value=0), 0)
        up = jnp.where(live, jnp.take(up, up, mode="fill", fill_value=n), n)
        return up, dist, i + 1

    _, dist, _ = jax.lax.while_loop(cond, body, (up, dist, jnp.int32(0)))
    return jnp.where(real, dist, -1)


def level_order(depth, chosen, widths=(4096, 128)) -> Levels:
    """The ``chosen`` [N] bool nodes sorted deepest first, for windows of ``widths``.

    ``depth`` [N] int32 from :func:`depths`; ``widths``: window sizes of the sweeps
    (static; clipped to ``N``). Within a level nodes are in id order.
    One sort of a packed ``key << bits | id`` when the keys fit 32 bits (depth below
    ``2^(32 - bits)``, ``bits = bit_length(N)``), else a stable two-key sort.
    """
    n = depth.shape[0]
    widths = tuple(sorted({max(1, min(int(w), n)) for w in widths}, reverse=True))
    pad = widths[0]
    max_depth = jnp.max(jnp.where(chosen, depth, 0))
    key = jnp.where(chosen, max_depth - depth, BIG_KEY).astype(jnp.int32)
    ids = jnp.arange(n, dtype=jnp.int32)
    bits = max(1, int(n).bit_length())

    def two_keys(_):
        k, i = jax.lax.sort((key, ids), num_keys=1, is_stable=True)
        return k, i

    if bits >= 31:
        keys, order = two_keys(None)
    else:
        top = (1 << (32 - bits)) - 1

        def packed(_):
            k = jnp.where(chosen, key, top).astype(jnp.uint32)
            s = jnp.sort((k << bits) | ids.astype(jnp.uint32))
            order = (s & ((1 << bits) - 1)).astype(jnp.int32)
            return jnp.take(key, order), order

        keys, order = jax.lax.cond(max_depth < top, packed, two_keys, None)
    count = jnp.sum(chosen, dtype=jnp.int32)
    valid = jnp.arange(n) < count
    order = jnp.where(valid, order, n)
    keys = jnp.where(valid, keys, BIG_KEY)
    order = jnp.concatenate([order, jnp.full(pad, n, jnp.int32)])
    keys = jnp.concatenate([keys, jnp.full(pad, BIG_KEY, jnp.int32)])
    position = jnp.full(n, n + pad, jnp.int32).at[order].set(
        jnp.arange(n + pad, dtype=jnp.int32), mode="drop")
    return Levels(order, keys, count, position, widths)


def sweep_up(levels: Levels, step: Callable, carry):
    """``step(carry, start, valid) -> carry`` over all levels, deepest first.

    Each call covers positions ``[start, start + W)`` of one level (``valid`` [W] bool
    says which of them are in it). Bounded: every call advances at least one position.
    """
    sizes = levels.widths

    def windows(carry, width, last):
        def cond(c):
            _, start, end = c
            return (end - start >= width) | (last & (start < end))

        def body(c):
            inner, start, end = c
            valid = start + jnp.arange(width) < end
            inner = step(inner, start, valid)
            return inner, start + jnp.minimum(width, end - start), end

        return jax.lax.while_loop(cond, body, carry)

    def cond(c):
        return c[1] < levels.count

    def body(c):
        inner, start = c
        end = jnp.searchsorted(levels.keys, levels.keys[start], side="right").astype(jnp.int32)
        state = (inner, start, end)
        for i, width in enumerate(sizes):
            state = windows(state, width, i == len(sizes) - 1)
        return state[0], state[1]

    carry, _ = jax.lax.while_loop(cond, body, (carry, jnp.int32(0)))
    return carry


def sweep_down(levels: Levels, step: Callable, carry):
    """``step(carry, start, valid) -> carry`` over all levels, shallowest (root) first.

    The same windows as :func:`sweep_up` in reverse: within a level, the last positions
    first; a level's last, partial window starts at the level's first position and
    masks what lies beyond the part not yet done.
    """
    sizes = levels.widths

    def windows(carry, width, last):
        def cond(c):
            _, begin, end = c
            return (end - begin >= width) | (last & (end > begin))

        def body(c):
            inner, begin, end = c
            start = jnp.maximum(begin, end - width)
            pos = start + jnp.arange(width)
            inner = step(inner, start, pos < end)
            return inner, begin, start

        return jax.lax.while_loop(cond, body, carry)

    def cond(c):
        return c[1] > 0

    def body(c):
        inner, end = c
        begin = jnp.searchsorted(levels.keys, levels.keys[end - 1], side="left").astype(jnp.int32)
        state = (inner, begin, end)
        for i, width in enumerate(sizes):
            state = windows(state, width, i == len(sizes) - 1)
        return state[0], begin

    carry, _ = jax.lax.while_loop(cond, body, (carry, levels.count))
    return carry
