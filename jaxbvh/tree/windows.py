"""Windows over a schedule of nodes: the loop every level-by-level pass shares.

A pass that processes a tree level by level (Kensler's rotations and treelet
restructuring by height, :mod:`jaxbvh.optimize.rotate_passes` and
:mod:`jaxbvh.optimize.treelet`; collapsing's sweeps by depth, :mod:`jaxbvh.wide.levels`)
lists its nodes in an array ``order`` with the nodes of one level at consecutive
*positions*, and hands them to a ``step`` a window of positions at a time, never two
levels in one window (a level's nodes do not depend on each other; the next level's do).

Windows. A level ``[begin, end)`` of positions goes through windows of the largest size
in ``widths`` while that many positions remain, then the next size down, the smallest
taking the rest (its last window masks the positions outside the level). So the work is
about the number of nodes plus (levels x smallest width), not nodes x levels, and each
width is one compiled copy of ``step``. ``step(carry, start, valid) -> carry`` gets the
window's first position ``start`` (int32) and ``valid`` [W] bool, true for the positions
inside the level; it reads ``order`` itself (``jax.lax.dynamic_slice``), so ``order``
needs ``widths[0]`` spare positions past its end (and before its start for
:func:`backward`) for the slice never to be clipped.

* :func:`forward`, :func:`backward`: one level, front to back or back to front.
* :func:`by_runs`: every level of an ``order`` sorted by a key (height), each run of
  equal keys a level, lowest key first.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def forward(step: Callable, carry, begin, end, widths: tuple):
    """``step`` on windows over positions ``[begin, end)`` front to back (module
    docstring); the last window masks what lies past ``end``. ``widths``: static ints,
    largest first."""

    def run(state, width, last):
        def cond(s):
            _, start = s
            return (end - start >= width) | (last & (start < end))

        def body(s):
            carry, start = s
            valid = start + jnp.arange(width) < end
            return step(carry, start, valid), start + jnp.minimum(width, end - start)

        return jax.lax.while_loop(cond, body, state)

    state = (carry, begin)
    for i, width in enumerate(widths):
        state = run(state, width, i == len(widths) - 1)
    return state[0]


def backward(step: Callable, carry, begin, end, widths: tuple):
    """``step`` on windows over positions ``[begin, end)`` back to front; the last window
    masks what lies before ``begin``."""

    def run(state, width, last):
        def cond(s):
            _, stop = s
            return (stop - begin >= width) | (last & (stop > begin))

        def body(s):
            carry, stop = s
            start = stop - width
            valid = start + jnp.arange(width) >= begin
            return step(carry, start, valid), jnp.maximum(start, begin)

        return jax.lax.while_loop(cond, body, state)

    state = (carry, end)
    for i, width in enumerate(widths):
        state = run(state, width, i == len(widths) - 1)
    return state[0]


def by_runs(step: Callable, carry, keys, count, widths: tuple):
    """``step`` on windows over each run of equal ``keys`` among positions ``[0, count)``,
    in order (:func:`forward` per run): a level-by-level pass over an ``order`` sorted by
    ``keys`` [P] int32 (ascending; ``count`` int32 the scheduled length)."""

    def cond(c):
        return c[1] < count

    def body(c):
        carry, start = c
        end = jnp.searchsorted(keys, keys[start], side="right").astype(jnp.int32)
        return forward(step, carry, start, end, widths), end

    carry, _ = jax.lax.while_loop(cond, body, (carry, jnp.int32(0)))
    return carry
