"""Segmented reductions over the BRef array and the best bin plane of every segment.

Part of :mod:`jaxbvh.twolevel.brefs` (Benthin et al. 2017), whose docstring explains the
BRef array, its segments and the binning (step 4: bins over the BRef centres, the plane
cost ``A_L N_L + A_R N_R``, the tie rule). Per-segment arrays are keyed by the
segment's start slot; :func:`segment` reduces over segments, :func:`exclusive_rank`
ranks flagged slots within theirs, :func:`widest_rank` ranks the opening's candidates
widest first, :func:`best_planes` finds each segment's cheapest plane with sorts and
segmented scans (no segments x bins table). Both sort plain int keys that encode the
slot: on a CPU a sort that carries the slots along as a second operand cost ~6x more
(3 x 2,048 keys: 1.05 against 0.18 ms).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.numerics import TIE_TOLERANCE, half_area, take
from jaxbvh.builders.topdown import segmented_box_scan


def segment(op, data, ids, n):
    """``op`` (segment_sum/min/max) over ``n`` segments; id ``n`` means "none" (dropped)."""
    return op(data, ids, num_segments=n + 1)[:n]


def exclusive_rank(flag, start):
    """Rank of each flagged position among the flagged positions of its segment
    (``flag`` [C] bool, ``start`` [C] int32 its segment's start): int32 [C]."""
    before = jnp.cumsum(flag.astype(jnp.int32)) - flag.astype(jnp.int32)
    return before - take(before, start, 0)


def widest_rank(width, candidate, block, start, size):
    """Rank of every candidate among its segment's candidates by (``width`` descending,
    slot) (int32 [C]; other slots: any value).

    ``width`` [C] float, ``candidate`` [C] bool; ``block`` [C] bool: the slot lies in its
    segment's BRefs ``[start, start + size)`` (``start``, ``size`` [C] int32 per slot; a
    segment's candidates lie in it). One :func:`_sort_in_blocks` by ``above``, the number
    of candidates wider than the slot's (C for a non-candidate); the sorted position minus
    ``start`` is the rank. Keys below 2^31 need ``C (C + 1) < 2^31``; larger arrays sort
    (segment, -width, slot) with a lexsort.
    """
    i32 = jnp.int32
    C = width.shape[0]
    pos = jnp.arange(C, dtype=i32)
    if C * (C + 1) >= 2 ** 31:
        key = jnp.where(candidate & block, start, C)
        order = jnp.lexsort((pos, -width, key)).astype(i32)
        first = segment(jax.ops.segment_min, pos, key[order], C)
        return jnp.zeros(C, i32).at[order].set(pos - take(first, key[order], 0))
    ordered = jnp.sort(jnp.where(candidate, width, -jnp.inf))
    above = jnp.where(candidate, C - jnp.searchsorted(ordered, width, side="right").astype(i32), C)
    slot, _ = _sort_in_blocks(above, block, start, size, C + 1)
    return jnp.zeros(C, i32).at[jnp.where(block, slot, C)].set(pos - start, mode="drop")


def _sort_in_blocks(major, block, start, size, stride: int):
    """Every segment's slots sorted by (``major``, slot) in place of the segment, by one
    sort of plain int keys along the last axis: ``(slot, major)`` int32 [..., C] at every
    sorted position (a position outside every segment keeps its own slot and major 0).

    ``major`` [..., C] int32 in ``[0, stride)``; ``block`` [C] bool: the slot lies in its
    segment's slots ``[start, start + size)`` (``start``, ``size`` [C] int32 per slot).
    The key ``start stride + major size + offset`` orders a segment's slots by (major,
    slot) inside the range ``[start stride, (start + size) stride)``, which no other
    slot's key enters (a slot outside every segment keeps ``pos stride``, and its place),
    so sorted position j lies in the block of slot j, and decoding the sorted key there
    gives its slot and major (the order of a stable sort by (segment, major)). Keys need
    ``C stride < 2^31``.
    """
    pos = jnp.arange(block.shape[0], dtype=jnp.int32)
    keys = jnp.where(block, start * stride + major * size + (pos - start), pos * stride)
    rel = jnp.sort(keys, axis=-1) - start * stride
    width = jnp.maximum(size, 1)
    return jnp.where(block, start + rel % width, pos).astype(jnp.int32), jnp.where(block, rel // width, 0)


def _scan(starts, lo, hi, prims):
    """Inclusive running (box, primitive count) along axis 1 of [S, P] rows, restarting
    where ``starts`` (``starts[:, 0]`` True): the builders' segmented box scan
    (:func:`jaxbvh.builders.topdown.segmented_box_scan`: a small program, where
    ``lax.associative_scan`` unrolls ``2 log2 P`` levels) and a sum since each run's start
    (integers: exact)."""
    pos = jnp.arange(starts.shape[1], dtype=jnp.int32)
    run_start = jax.lax.cummax(jnp.where(starts, pos, 0), axis=1)
    offset = pos - run_start
    run_lo, run_hi = segmented_box_scan(lo, hi, offset, jnp.max(offset) + 1)
    total = jnp.cumsum(prims, axis=1)
    return run_lo, run_hi, total - jnp.take_along_axis(total - prims, run_start, axis=1)


def best_planes(sid, bin_p, lo, hi, prims, *, bins, cap):
    """Cheapest bin plane of every segment: ``(cost, axis * bins + plane)`` [C].

    ``sid`` [C] int32: the segment (start slot) of each slot that takes part, ``cap``
    for the others; ``bin_p`` [C, 3] int32: the bin of each slot's centre per axis;
    ``lo``, ``hi`` [C, 3], ``prims`` [C] int32: the BRefs' boxes and primitive counts.
    Per axis the BRefs are sorted by (segment, bin); forward and backward segmented scans
    give the box and primitive count of both sides of every plane where the bin changes
    (empty bins between two occupied ones give the same partition; the lowest such plane
    is named). Costs and the tie rule are those of :mod:`jaxbvh.twolevel.brefs` (step 4);
    segments without a plane get ``(inf, max int)``.
    """
    i32 = jnp.int32
    dtype = lo.dtype
    axes = jnp.arange(3, dtype=i32)
    pos = jnp.arange(cap, dtype=i32)
    takes = sid < cap
    start = jnp.where(takes, sid, pos)
    size = take(segment(jax.ops.segment_sum, takes.astype(i32), sid, cap), sid, 1)  # its segment's BRefs
    # per axis, each segment's BRefs (slots [start, start + size)) sorted by (bin, slot)
    order, b = _sort_in_blocks(bin_p.T, takes, start, size, bins)  # [3, C]
    seg = jnp.broadcast_to(sid, (3, cap))
    s_lo, s_hi, s_p = lo[order], hi[order], prims[order]  # [3, C, 3], [3, C]
    step = jnp.concatenate([seg[:, 1:] != seg[:, :-1], jnp.ones((3, 1), bool)], axis=1)  # last of a run
    first = jnp.concatenate([jnp.ones((3, 1), bool), step[:, :-1]], axis=1)
    # the forward scans (left sides) and the backward ones (right sides) as one scan of 6 rows
    both = lambda a, b: jnp.concatenate([a, b[:, ::-1]], axis=0)  # noqa: E731
    out = _scan(both(first, step), both(s_lo, s_lo), both(s_hi, s_hi), both(s_p, s_p))
    (l_lo, l_hi, l_p), (r_lo, r_hi, r_p) = [a[:3] for a in out], [a[3:, ::-1] for a in out]
    shift = lambda a, fill: jnp.concatenate([a[:, 1:], jnp.full_like(a[:, :1], fill)], axis=1)  # noqa: E731
    r_lo, r_hi, r_p = shift(r_lo, jnp.inf), shift(r_hi, -jnp.inf), shift(r_p, 0)
    # a plane after every sorted BRef whose successor in the segment has a higher bin (so
    # both sides hold BRefs; bins differ only on an axis of positive span)
    plane = (seg < cap) & ~step & (b != shift(b, -1))
    cost = (half_area(l_lo, l_hi) * l_p.astype(dtype) + half_area(r_lo, r_hi) * r_p.astype(dtype))
    cost = jnp.where(plane, cost, jnp.inf)
    ids = jnp.where(plane, seg, cap).ravel()
    best = segment(jax.ops.segment_min, cost.ravel(), ids, cap)
    near = (best * (1 + TIE_TOLERANCE)).at[ids].get(mode="fill", fill_value=-jnp.inf)
    key = jnp.where(plane & (cost.ravel() <= near).reshape(3, cap), axes[:, None] * bins + b,
                    jnp.iinfo(i32).max)
    best_key = segment(jax.ops.segment_min, key.ravel(), ids, cap)
    return best, best_key
