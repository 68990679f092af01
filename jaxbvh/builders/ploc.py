"""PLOC: Parallel Locally-Ordered Clustering (Meister & Bittner 2017, IEEE TVCG 2018) (jitted).

Algorithm
=========
Agglomerative clustering, bottom-up, in parallel. The primitives, sorted along the
Morton curve (:mod:`jaxbvh.builders.morton`), start as one cluster each, kept in an array in
that order. Each iteration:

1. **Nearest neighbour.** Every cluster looks at the ``r`` clusters before it and the
   ``r`` after it in the array and picks the one whose merged box has the smallest
   surface area (the paper's distance). The area of each pair is computed once, as an
   ``[r, C]`` array of shifted unions: cluster ``i`` reads its right neighbours from
   column ``i`` and its left ones from the columns ``i - d``.
2. **Merge** every mutual pair (``i`` picks ``j`` and ``j`` picks ``i``): the merged
   cluster takes the place of the lower one, the upper place is emptied.
3. **Compact** the array in order (an exclusive prefix sum).

until one cluster is left. ``r`` (``radius``) is the effort knob: the paper uses 8 to
25; a larger ``r`` looks further for neighbours at proportionally more work per
iteration (the SAH reached is not monotone in ``r``: ``bench/results/build_trade.md``).

Neighbour rule (the NumPy twin :mod:`jaxbvh.builders.ploc_reference` keeps the same one).
Areas within a relative ``TIE_TOLERANCE`` of the least count as equal (XLA may fuse a
multiply-add, so one area can differ by an ulp here and in NumPy; the rule of
:mod:`jaxbvh.builders.topdown`). Among equal ones the nearest in the array wins, and between the
two at distance ``d`` the one that pairs ``(m, m + d)`` with ``m // d`` even: every
cluster's choice is then its least pair in one order on pairs, so equal boxes pair off
``(0, 1), (2, 3), ...`` and a scene of identical boxes gives a balanced tree. With a
tolerance, choices can form a cycle of three or more clusters and no pair be mutual;
an iteration that finds no mutual pair is redone with exact comparisons, where the
least pair of all is always mutual, so every iteration merges at least one pair and
``n - 1`` iterations always suffice.

Work. The cluster count falls quickly, so the array is processed in *stages* of
halving static sizes (``cap, cap / 2, ...`` down to :data:`SMALLEST_STAGE`): each stage
is its own ``while_loop`` over a prefix of the array and hands over when the clusters
fit the next size. Work per iteration follows the clusters left, not the input.

Output: interior nodes in the reverse of their creation (root 0), then the leaves in
Morton order; ``axis`` is -1 (a clustering has no split planes; run
:func:`jaxbvh.optimize.rotate.assign_split_axes` for traversal order). Leaves collapse by the
SAH test of the top-down builders (:mod:`jaxbvh.builders.bottom_up`). Boxes are unions (exact), so
the tree is identical to the twin's.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from jaxbvh.builders import morton
from jaxbvh.builders.bottom_up import Linked, to_bvh
from jaxbvh.builders.configs import PLOCConfig
from jaxbvh.numerics import TIE_TOLERANCE, exclusive_sum, half_area
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH

SMALLEST_STAGE = 2048


def stage_sizes(cap: int) -> tuple[int, ...]:
    """Static array sizes of the stages: ``cap``, then halving down to :data:`SMALLEST_STAGE`."""
    sizes = [int(cap)]
    while sizes[-1] > SMALLEST_STAGE:
        sizes.append((sizes[-1] + 1) // 2)
    return tuple(sizes)


def _parity(pos, d):
    """``(pos // d) % 2`` for int32 ``pos`` >= 0 and a traced ``d`` >= 1, without an integer divide.

    A float quotient is within 1 of the true one; one correction each way makes it exact.
    """
    q = jnp.floor(pos.astype(jnp.float32) * (1.0 / d.astype(jnp.float32))).astype(jnp.int32)
    q = jnp.where(q * d > pos, q - 1, q)
    q = jnp.where((q + 1) * d <= pos, q + 1, q)
    return q & 1


def _pair_areas(lo, hi, c, scale, reach: int):
    """Merged-box areas of every cluster with the ``reach`` clusters after it, [reach, C].

    Row ``d - 1`` pairs cluster ``i`` with ``i + d``; ``inf`` where there is no such
    cluster. A loop over ``d`` (the program does not grow with the radius); each row is
    one fused pass over static-size shifted slices.
    """
    size = lo.shape[0]
    pos = jnp.arange(size, dtype=jnp.int32)
    pad = jnp.full((reach, 3), jnp.inf, lo.dtype)
    lo_next, hi_next = jnp.concatenate([lo, pad]), jnp.concatenate([hi, -pad])

    def row(k, rows):
        d = k + 1
        other_lo = jax.lax.dynamic_slice(lo_next, (d, 0), (size, 3))
        other_hi = jax.lax.dynamic_slice(hi_next, (d, 0), (size, 3))
        area = half_area(jnp.minimum(lo, other_lo), jnp.maximum(hi, other_hi), scale)
        return rows.at[k].set(jnp.where(pos + d < c, area, jnp.inf))

    return jax.lax.fori_loop(0, reach, row, jnp.zeros((reach, size), lo.dtype))


def _shifted(row, d, reach: int):
    """``row[i - d]`` (``inf`` for ``i < d``): the left-neighbour view of a right-neighbour row."""
    padded = jnp.concatenate([jnp.full(reach, jnp.inf, row.dtype), row])
    return jax.lax.dynamic_slice(padded, (reach - d,), (row.shape[0],))


def _least_area(areas):
    """Least area of every cluster's candidates [C] (a fold: XLA's float min-reduce is slow on CPU)."""
    reach = areas.shape[0]

    def fold(k, best):
        return jnp.minimum(best, jnp.minimum(areas[k], _shifted(areas[k], k + 1, reach)))

    return jax.lax.fori_loop(0, reach, fold, jnp.full(areas.shape[1], jnp.inf, areas.dtype))


def _choose(areas, limit):
    """Offset (+-d) of every cluster's choice among its candidates with area ``<= limit`` [C].

    Rule: module docstring. The tie key of pair ``(m, m + d)`` is ``2 d + (m // d) % 2``;
    keys are scaled by ``radix`` and the candidate's row added, so the least key also
    names the row.
    """
    reach, size = areas.shape
    pos = jnp.arange(size, dtype=jnp.int32)
    radix = 1 << (2 * reach).bit_length()
    never = jnp.iinfo(jnp.int32).max

    def fold(k, key):
        d = k + 1
        parity = _parity(pos, d)
        right = jnp.where(areas[k] <= limit, (2 * d + parity) * radix + k, never)
        left = jnp.where(_shifted(areas[k], d, reach) <= limit, (2 * d + 1 - parity) * radix + reach + k, never)
        return jnp.minimum(key, jnp.minimum(right, left))

    row = jax.lax.fori_loop(0, reach, fold, jnp.full(size, never, jnp.int32)) % radix
    return jnp.where(row < reach, row + 1, reach - 1 - row)


def _iteration(n, scale, radius: int, carry):
    """One iteration over a stage's arrays: neighbours, merges, compaction."""
    (node, lo, hi, count, first, c), internal, made, steps = carry
    size = lo.shape[0]
    cap = internal[0].shape[0]
    pos = jnp.arange(size, dtype=jnp.int32)
    valid = pos < c

    def mutual_of(offset):
        partner = pos + offset
        back = jnp.take(offset, jnp.clip(partner, 0, size - 1), mode="clip")
        return valid & (partner >= 0) & (partner < c) & (back == -offset)

    areas = _pair_areas(lo, hi, c, scale, min(radius, size - 1))
    best = _least_area(areas)
    offset = _choose(areas, best * (1 + TIE_TOLERANCE))
    # the exact rule only when no pair is mutual (rare)
    offset = jax.lax.cond(jnp.any(mutual_of(offset)), lambda: offset, lambda: _choose(areas, best))
    mutual = mutual_of(offset)

    partner = jnp.clip(pos + offset, 0, size - 1)
    lower = mutual & (offset > 0)
    upper = mutual & (offset < 0)
    rank = exclusive_sum(lower)
    slot = jnp.where(lower, (n - 2) - (made + rank), cap)  # the root (last merge) lands in slot 0
    m_lo = jnp.minimum(lo, jnp.take(lo, partner, axis=0, mode="clip"))
    m_hi = jnp.maximum(hi, jnp.take(hi, partner, axis=0, mode="clip"))
    m_count = count + jnp.take(count, partner, axis=0, mode="clip")
    m_first = jnp.minimum(first, jnp.take(first, partner, axis=0, mode="clip"))
    i_left, i_right, i_lo, i_hi, i_count, i_first = internal
    m_right = jnp.take(node, partner, mode="clip")
    internal = (i_left.at[slot].set(node, mode="drop"), i_right.at[slot].set(m_right, mode="drop"),
                i_lo.at[slot].set(m_lo, mode="drop"), i_hi.at[slot].set(m_hi, mode="drop"),
                i_count.at[slot].set(m_count, mode="drop"), i_first.at[slot].set(m_first, mode="drop"))
    node = jnp.where(lower, slot, node)
    lo = jnp.where(lower[:, None], m_lo, lo)
    hi = jnp.where(lower[:, None], m_hi, hi)
    count = jnp.where(lower, m_count, count)
    first = jnp.where(lower, m_first, first)

    keep = valid & ~upper
    target = jnp.where(keep, exclusive_sum(keep), size)

    def compact(values, fill):
        return jnp.full_like(values, fill).at[target].set(values, mode="drop")

    clusters = (compact(node, 2 * cap), compact(lo, jnp.inf), compact(hi, -jnp.inf), compact(count, 0),
                compact(first, 0), jnp.sum(keep, dtype=jnp.int32))
    return clusters, internal, made + jnp.sum(lower, dtype=jnp.int32), steps + 1


@partial(stored_jit, static_argnames=("radius", "stages", "collapse"))
def cluster(lo, hi, n, order, max_leaf, ct, ci, scale, *, radius, stages, collapse):
    """The clustering and the layout (module docstring), jitted: what :func:`build` runs after the sort.

    ``lo``, ``hi`` [cap, 3]: padded boxes (first ``n`` real); ``order`` int32 [cap]: the
    ids in Morton order (:func:`jaxbvh.builders.morton.morton_order`); ``max_leaf``,
    ``ct``, ``ci``, ``scale``: traced scalars. Static: ``radius``, ``stages``
    (:func:`stage_sizes`), ``collapse`` (``max_leaf > 1``); one compiled program per
    capacity and static values. ``TIE_TOLERANCE`` is read at trace time (a test that
    changes it clears this function's cache). Returns a :class:`~jaxbvh.tree.layout.BVH`.
    """
    cap = lo.shape[0]
    # padding positions read padding slots
    leaf_lo, leaf_hi = jnp.take(lo, order, axis=0, mode="clip"), jnp.take(hi, order, axis=0, mode="clip")
    pos = jnp.arange(cap, dtype=jnp.int32)
    clusters = (cap + pos, leaf_lo, leaf_hi, (pos < n).astype(jnp.int32), pos, jnp.asarray(n, jnp.int32))
    internal = (jnp.full(cap, 2 * cap, jnp.int32), jnp.full(cap, 2 * cap, jnp.int32),
                jnp.full((cap, 3), jnp.inf, lo.dtype), jnp.full((cap, 3), -jnp.inf, lo.dtype),
                jnp.zeros(cap, jnp.int32), jnp.zeros(cap, jnp.int32))
    carry = (clusters, internal, jnp.int32(0), jnp.int32(0))
    for k, size in enumerate(stages):
        goal = stages[k + 1] if k + 1 < len(stages) else 1
        carry = ((*(a[:size] for a in carry[0][:5]), carry[0][5]),) + carry[1:]
        # every iteration merges a pair, so n iterations in all always suffice
        carry = jax.lax.while_loop(lambda c, goal=goal: (c[0][5] > goal) & (c[3] < n),
                                   partial(_iteration, n, scale, radius), carry)
    _, (i_left, i_right, i_lo, i_hi, i_count, i_first), _, _ = carry
    linked = Linked(n=n, left=i_left, right=i_right, lo=i_lo, hi=i_hi, count=i_count, first=i_first,
                    axis=jnp.full(cap, -1, jnp.int32), leaf_lo=leaf_lo, leaf_hi=leaf_hi, order=order)
    return to_bvh(linked, max_leaf, ct, ci, scale, collapse=collapse)


def build(lo, hi, n, scale, config: PLOCConfig) -> BVH:
    """PLOC over padded boxes ``lo``, ``hi`` [cap, 3] (NumPy or JAX, first ``n`` real).

    ``scale``: the scene's area scale; ``config``: the knobs (``radius``: neighbours
    looked at on each side, static: one compile per value; ``max_leaf``, ``ct``, ``ci``,
    ``morton_bits``). Returns a :class:`~jaxbvh.tree.layout.BVH` of JAX arrays.
    """
    bits = config.morton_bits
    dtype = lo.dtype
    lo_j, hi_j = jnp.asarray(lo), jnp.asarray(hi)
    n = int(n)
    origin, grid = morton.quantization(lo_j, hi_j, n, bits)
    order = morton.morton_order(lo_j, hi_j, n, jnp.asarray(origin), jnp.asarray(grid), bits=bits)
    return cluster(lo_j, hi_j, jnp.int32(n), order, jnp.int32(config.max_leaf), jnp.asarray(config.ct, dtype),
                    jnp.asarray(config.ci, dtype), jnp.asarray(scale, dtype), radius=config.radius,
                    stages=stage_sizes(lo.shape[0]), collapse=config.max_leaf > 1)
