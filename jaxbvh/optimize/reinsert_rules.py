"""The rules of parallel reinsertion that the optimizer and its NumPy twin share.

Which nodes are searched when (candidates by octaves of parent area below the root's,
coarse to fine) and how many of the moves found an iteration considers: both
:mod:`jaxbvh.optimize.reinsert` and :mod:`jaxbvh.optimize.reinsert_reference` follow
these, so they choose the same moves.

The first octaves
=================
An iteration searches the nodes whose parent's area is at least ``2^-k`` of the root's
(``k`` octaves). A run starts at the fewest octaves ``k`` in ``0 .. 63`` that hold
:func:`candidates_needed` nodes (about ``first_fraction`` of them), or with every node
(:data:`ALL_OCTAVES`) when none does, when ``first_fraction >= 1``, when the root has
no area or the tree has no node but the root. :func:`octaves_holding` applies the rule
to NumPy or JAX arrays (``xp``): the NumPy twin calls it on the host, the optimizer
inside its traced step (the pipeline starts a reinsertion stage there). The count
itself is taken on the host (:func:`candidates_needed`, in float64 as the rule reads):
a tree's node count never changes while it is optimized.

The octaves widen after an iteration that lowers the SAH by at most ``escalate``
(relative); by default that is :data:`ESCALATE_NODES` over the node count
(:func:`escalate_for`, host float64, as the count).
"""

from __future__ import annotations

import math

import numpy as np

#: ``octaves`` at and above this: every node is a candidate (the threshold is 0)
ALL_OCTAVES = 4096

#: octaves tried for the first candidates (beyond: every node)
FIRST_OCTAVES_TRIED = 64

#: about the share of nodes the first iteration searches (those of largest parent area).
#: Measured on the tinybvh trees of legocar and drone (bench/bench_quality.py, CPU
#: seconds of the pipeline to tinybvh's optimizer SAH, first fractions 1/32 .. 1): 1/8
#: reaches it soonest, 2.4x sooner than 1/32 on legocar and 1.6x on drone, and 1/32's
#: first iterations find a few moves that lock each other (4 of 21 taken on legocar).
DEFAULT_FIRST_FRACTION = 1 / 8

#: the relative SAH drop of an iteration at or below which the next one searches one
#: more octave is this over the node count (:func:`escalate_for`; a Config's
#: ``escalate`` replaces it). A move gains about the same area wherever the tree is
#: large or small, so an iteration's *relative* drop shrinks with the node count: a fixed
#: threshold widened drone (30,019 nodes) too soon and legocar (10,594) too late.
#: Measured (pipeline from tinybvh's binned trees, steps to tinybvh's ``Optimize(200)``
#: SAH and the CPU seconds of those steps, each timed alone, same process per mesh):
#: legocar 1e-4: 43 steps, 1.22 s; 3e-4: 36, 0.93 s; 7.6e-4 (8 / nodes): 27, 0.81 s;
#: 1e-3: 27, 0.75 - 0.77 s; drone 1e-4: 31, 1.72 - 1.90 s; 2.7e-4 (8 / nodes): 28,
#: 1.74 s; 5e-4: 27, 2.33 s; 1e-3: 26, 2.9 - 3.0 s (its wider octaves cost 4 - 5 times
#: as much per iteration). Bunny (75,207 nodes) gets 1.1e-4, the former fixed default.
ESCALATE_NODES = 8.0

#: ``escalate`` of the Configs: None, by the node count (:func:`escalate_for`)
DEFAULT_ESCALATE = None


def move_width(capacity: int) -> int:
    """Moves considered per iteration: a static size from the capacity."""
    return int(min(capacity, max(4096, capacity // 32)))


def escalate_for(nodes: int, escalate: float | None = None) -> float:
    """The relative SAH drop at or below which an iteration widens the candidates by an
    octave: ``escalate`` when given, else :data:`ESCALATE_NODES` over ``nodes`` (real
    nodes but the root; at least 1). Host float64."""
    if escalate is not None:
        return float(escalate)
    return ESCALATE_NODES / max(int(nodes), 1)


def widening_stop(widen_until: float | None, nodes: int) -> int:
    """The candidate count from which a widening ends the run instead: ``ceil(widen_until
    * nodes)``, or ``nodes + 1`` (never: no iteration searches more than every node) for
    None. Host integers, float64 arithmetic, as :func:`candidates_needed`."""
    if widen_until is None:
        return int(nodes) + 1
    return _share(widen_until, nodes)


def candidates_needed(first_fraction: float, nodes: int) -> int:
    """How many of ``nodes`` (real nodes but the root) the first iteration searches at
    least: ``ceil(first_fraction * nodes)``; ``nodes + 1`` (no octave holds that many:
    every node) for ``first_fraction >= 1``. Host integers, float64 arithmetic."""
    if first_fraction >= 1:
        return int(nodes) + 1
    return _share(first_fraction, nodes)


def _share(fraction: float, nodes: int) -> int:
    """``ceil(fraction * nodes)``: host integers, float64 arithmetic (both rules' count)."""
    return int(math.ceil(float(fraction) * int(nodes)))


def octaves_holding(area, parent, root, need, xp=np):
    """The fewest octaves ``k`` in ``0 .. 63`` whose candidates number at least ``need``
    (module docstring), else :data:`ALL_OCTAVES`; an int32 scalar of ``xp``.

    ``area`` [N]: scaled half-areas; ``parent`` [N] int (-1: root or padding); ``root``:
    the root's id; ``need``: :func:`candidates_needed`. ``xp``: ``numpy`` or
    ``jax.numpy`` (traceable then). The counts compare areas with exact powers of two
    of the root's area, as the iterations' candidate test does.
    """
    area, parent = xp.asarray(area), xp.asarray(parent)
    valid = parent >= 0
    area_p = xp.where(valid, area[xp.maximum(parent, 0)], -xp.inf)
    root_area = area[root]
    thresholds = xp.ldexp(xp.full(FIRST_OCTAVES_TRIED, root_area, area.dtype),
                          -xp.arange(FIRST_OCTAVES_TRIED, dtype=np.int32))
    ascending = xp.sort(area_p)
    # candidates of k octaves: parent areas >= the threshold of k (never a padding -inf)
    counts = area_p.shape[0] - xp.searchsorted(ascending, thresholds, side="left")
    enough = counts >= need
    first = xp.argmax(enough).astype(np.int32)
    usable = xp.any(enough) & (root_area > 0) & xp.any(valid)
    return xp.where(usable, first, np.int32(ALL_OCTAVES)).astype(np.int32)


def first_octaves(area, parent, root, first_fraction: float) -> int:
    """:func:`octaves_holding` for ``first_fraction`` of the tree's nodes (host)."""
    nodes = int(np.sum(np.asarray(parent) >= 0))
    return int(octaves_holding(np.asarray(area), np.asarray(parent), int(root),
                               candidates_needed(first_fraction, nodes)))
