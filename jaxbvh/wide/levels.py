"""Level-by-level sweeps over a binary tree: nodes in breadth-first order, processed in windows.

Many tree algorithms are one recurrence over parents and children: a node's value from
its children's (bottom-up), or from its parent's (top-down). Nodes of equal depth never
depend on each other, so a sweep can process a whole depth (a *level*) at once. This
module provides that schedule for any binary tree of the layout in :mod:`jaxbvh.tree.layout`
(any node order, any root), for the nodes of interest: the interior nodes.

Schedule (:func:`level_order`). The interior nodes in breadth-first order: the root's
level first, each level's nodes followed by their interior children, left child before
right, in the order of their parents. ``order`` holds them at *positions*
``[pad, pad + count)`` (``pad`` = the largest window; ``N`` = no node elsewhere) and
``starts[d]`` is the first position of level ``d`` (``starts[levels]`` the end). It is
built by a top-down sweep of its own: a window of a level's nodes places their interior
children after the children already placed, with a prefix count. No sort: the work is
a few gathers and scatters per node, whatever the node ids are.

Sweeps (:func:`sweep_down`, :func:`sweep_up`) call ``step(carry, start, valid)`` on
windows ``[start, start + W)`` of positions of one level (``valid`` [W] bool masks the
positions outside it), root level first or deepest level first. A level with many
nodes goes through windows of the largest size in ``widths`` while that many remain,
then the next size down (:mod:`jaxbvh.tree.windows`, the loop the optimizers' passes by
height share); so the work is about the number of nodes plus (levels x smallest width),
not nodes x levels.

Arrays that a step writes by position (``jax.lax.dynamic_update_slice`` at ``start``)
have ``levels.order.shape[0]`` rows. In a bottom-up sweep a level's last window is
placed to end at the level's first unprocessed position, so what it writes outside the
level (masked entries) lands on shallower levels, which are processed, and overwritten,
later; it never touches a level already done.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp

from jaxbvh.tree import windows as level_windows


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Levels:
    """A level schedule (:func:`level_order`); positions are indices into ``order``.

    ``order`` [pad + N + pad] int32: node id at each position, ``N`` for none;
    ``starts`` [N + 2] int32: ``starts[d]`` first position of level ``d``, for
    ``d <= levels`` (``starts[levels]`` is the end); ``levels`` int32: number of levels;
    ``position`` [N] int32: position of each scheduled node (``pad + N + pad`` for the
    others); ``widths``: window sizes (static ints, largest first; ``pad`` = the largest).
    """

    order: Any
    starts: Any
    levels: Any
    position: Any
    widths: tuple = dataclasses.field(metadata=dict(static=True))

    @property
    def pad(self) -> int:
        return self.widths[0]

    def window(self, start, valid):
        """Node ids [W] at positions ``[start, start + W)``, ``N`` where not ``valid``."""
        n = self.position.shape[0]
        nodes = jax.lax.dynamic_slice(self.order, (start,), (valid.shape[0],))
        return jnp.where(valid, nodes, n)


def _prefix(x):
    """Exclusive prefix sum of ``x`` [W] (associative_scan: faster than cumsum on CPU)."""
    return jax.lax.associative_scan(jnp.add, x) - x


def level_order(left, right, root, interior, widths=(4096, 128)) -> Levels:
    """Breadth-first schedule of the ``interior`` [N] bool nodes (module docstring).

    ``left``, ``right`` [N] int32 children (``-1`` or ``N`` for none), ``root`` int32.
    ``widths`` (static) are clipped to ``N``. Bounded: each level adds at least one node.
    """
    n = left.shape[0]
    widths = tuple(sorted({max(1, min(int(w), n)) for w in widths}, reverse=True))
    pad = widths[0]
    rows = pad + n + pad
    left = jnp.where(left >= 0, left, n)
    right = jnp.where(right >= 0, right, n)
    has_root = interior[root]
    order = jnp.full(rows, n, jnp.int32).at[pad].set(jnp.where(has_root, root, n))
    starts = jnp.full(n + 2, pad + n, jnp.int32).at[0].set(pad).at[1].set(pad + has_root.astype(jnp.int32))

    def inner(c):
        return jnp.take(interior, c, mode="fill", fill_value=False)

    def place(state, start, valid):
        order, end = state
        x = jnp.where(valid, jax.lax.dynamic_slice(order, (start,), (valid.shape[0],)), n)
        l, r = jnp.take(left, x, mode="fill", fill_value=n), jnp.take(right, x, mode="fill", fill_value=n)
        il, ir = inner(l), inner(r)
        count = il.astype(jnp.int32) + ir.astype(jnp.int32)
        at = end + _prefix(count)
        order = order.at[jnp.where(il, at, rows)].set(l, mode="drop")
        order = order.at[jnp.where(ir, at + il, rows)].set(r, mode="drop")
        return order, end + jnp.sum(count, dtype=jnp.int32)

    def cond(c):
        _, starts, d = c
        return (starts[d + 1] > starts[d]) & (d < n)

    def body(c):
        order, starts, d = c
        begin, end = starts[d], starts[d + 1]
        order, next_end = level_windows.forward(place, (order, end), begin, end, widths)
        return order, starts.at[d + 2].set(next_end), d + 1

    order, starts, levels = jax.lax.while_loop(cond, body, (order, starts, jnp.int32(0)))
    position = jnp.full(n, rows, jnp.int32).at[order].set(jnp.arange(rows, dtype=jnp.int32), mode="drop")
    return Levels(order, starts, levels, position, widths)


def sweep_down(levels: Levels, step: Callable, carry):
    """``step(carry, start, valid) -> carry`` on every level, the root's first."""

    def body(d, carry):
        return level_windows.forward(step, carry, levels.starts[d], levels.starts[d + 1], levels.widths)

    return jax.lax.fori_loop(0, levels.levels, body, carry)


def sweep_up(levels: Levels, step: Callable, carry):
    """``step(carry, start, valid) -> carry`` on every level, the deepest first."""

    def body(i, carry):
        d = levels.levels - 1 - i
        return level_windows.backward(step, carry, levels.starts[d], levels.starts[d + 1], levels.widths)

    return jax.lax.fori_loop(0, levels.levels, body, carry)


def depth_of(levels: Levels):
    """Depth [N] int32 of every scheduled node (its level); -1 for the others."""
    n = levels.position.shape[0]
    pos = levels.position
    scheduled = pos < levels.order.shape[0]
    d = jnp.searchsorted(levels.starts, pos, side="right").astype(jnp.int32) - 1
    return jnp.where(scheduled, jnp.clip(d, 0, n), -1)
