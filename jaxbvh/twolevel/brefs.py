"""Build references (BRefs) and the re-braiding top-level build (Benthin et al. 2017, §4-5).

A **BRef** is one subtree of one placed object: ``(forest node, instance, world box,
primitive count)`` (:mod:`jaxbvh.twolevel.objects` for the forest, the instances and the
conservative world boxes). The top-level builder starts with one BRef per instance (its
object's root) and splits them top-down, as a binned SAH builder over boxes does, while
*opening* BRefs that are too large: a BRef is replaced by the BRefs of its children, so
the top level can reach into the object BVHs where objects overlap.

The BRef array
==============
All BRefs live in one array of fixed capacity ``C`` (``budget`` x #instances; the paper
uses 4; ``capacity`` sets it directly, e.g. to the paper's #primitives / 1000 for
scenes built in world space, a rule meant for scenes of millions of triangles: it would
give the 32,720-triangle drone 32 slots for its 39 objects). A *segment* is a contiguous piece ``[start, extra)`` of it owned by one node of
the top-level tree: its BRefs are ``[start, end)``, the rest ``[end, extra)`` is spare
room that opening may fill. The root segment is ``[0, C)`` with the instances' BRefs at
``[0, #instances)``. One step on a segment of ``count = end - start`` BRefs:

1. ``count == 1``: a top-level leaf that points at this BRef. Done.
2. Termination of opening (tested first, §4.4): if all BRefs belong to one instance, or
   if ``count <= 4`` and no two of their boxes overlap by more than ``overlap`` (default
   0.1) of the shorter extent on every axis, the segment drops its spare room: neither it
   nor anything below it opens again.
3. Opening (§4.2, §5.3): with ``dim`` the axis of the largest extent ``ext`` of the
   segment's box (the union of its BRef boxes; lowest axis on ties), the *candidates* are
   the BRefs whose forest node is not a leaf and whose box is wider than ``threshold *
   ext`` along ``dim``. If they all fit into the spare room, all open: a candidate's slot
   takes its left child, its right child goes to ``end, end + 1, ...`` in the order of
   the candidates' positions. Otherwise none opens at this step (as Embree does: the
   halves get the room and retry with fewer, smaller candidates).
4. Binning (§4.3): ``bins`` equal bins per axis over the segment's BRef centres
   (``0.5 lo + 0.5 hi``); each bin counts the *primitives* of its BRefs, and the plane
   between bins ``k`` and ``k + 1`` costs ``A_L N_L + A_R N_R`` (half-areas of the two
   sides' boxes, their primitive counts). The cheapest plane wins; costs within a
   relative ``TIE_TOLERANCE`` (2^-20, as :mod:`jaxbvh.builders.topdown`) tie, and ties go to the
   lowest axis, then the lowest plane. Without any plane (all centres in one point) the
   first ``count // 2`` positions go left.
5. Partition (§5.2): stable (both sides keep their order). The spare room ``extra -
   end`` is split between the halves in proportion to the number of their BRefs that
   meet the opening criterion of step 3 measured against the half's own box (to the
   numbers of BRefs when neither has any): ``spare_L = min(floor(f32(w_L) / f32(w_L +
   w_R) * f32(spare)), spare)``. The left half becomes ``[start, start + n_L)`` with its
   room after it, the right half starts at ``start + n_L + spare_L``. So how much a
   subtree may open does not depend on the order segments are processed in.

Primitive counts are exact by default (``Forest.subtree_prims``); ``estimate=True``
uses the paper's estimate instead: the root has its object's count, a child gets
``max(parent // 2, 1)`` (binary object trees). ``threshold = inf`` never opens: the
plain two-level BVH over the instances (its array then has room for the instances only).

Level-synchronous. The JAX builder runs all segments of one level of the top-level
tree at once (segment reductions keyed by the segment's start position; the binning
sorts each axis by (segment, bin) and scans, so no segments x bins table is needed), in
a ``while_loop`` bounded by ``C + 1`` levels (reaching the bound raises). It equals the recursive NumPy twin
:func:`jaxbvh.twolevel.brefs_reference.build_top_level` BRef by BRef: every BRef ends in the
same slot of the array with the same node, instance, box and count, and the top-level
trees are the same up to node numbering. Exactness: world boxes, centres, bins, opening
tests, overlap tests and the spare split are computed with operations that rounding
cannot make differ between XLA and NumPy (no product feeds an addition, see
:mod:`jaxbvh.twolevel.objects`); only the SAH costs can differ by an ulp, which the tie tolerance
absorbs.

Output (:class:`TopLevel`): a :class:`~jaxbvh.tree.layout.BVH` over the BRefs (node ids level by
level, root 0; every leaf holds exactly one BRef; ``axis`` is the split axis, -1 for a
split without a plane) and the BRefs compacted in array order, with the slot each one
had (``position``).
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import TIE_TOLERANCE, half_area, take
from jaxbvh.tree.layout import BVH, capacity_bucket
from jaxbvh.twolevel.objects import world_boxes

DEFAULT_THRESHOLD = 0.1  # paper §4.2 / Figure 4
DEFAULT_BUDGET = 4.0     # paper §5.2: 4 x #instances
DEFAULT_OVERLAP = 0.1    # ours: "barely overlapping" (the paper gives no number)
DEFAULT_BINS = 16
SMALL_SEGMENT = 4        # paper §4.4: the overlap test applies to <= 4 BRefs


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TopLevel:
    """Result of the top-level build.

    ``top``: :class:`~jaxbvh.tree.layout.BVH` with ``2 C`` node slots whose leaves hold one BRef
    each (``prim_index`` entries are BRef ids). BRefs [C], compacted, padding after
    ``count``: ``node`` int32 forest node (-1 padding), ``instance`` int32, ``lo``, ``hi``
    [C, 3] scene-frame boxes (padding: the empty box), ``prims`` int32 primitive counts
    (exact or estimated), ``position`` int32 slot in the build array. ``count``: number
    of BRefs (int32 scalar); ``levels``: levels the build took; ``complete``: the loop
    ended because no segment was left, not at its bound (the driver raises otherwise).
    """

    top: Any
    node: Any
    instance: Any
    lo: Any
    hi: Any
    prims: Any
    position: Any
    count: Any
    levels: Any
    complete: Any


def check_options(threshold, budget, bins, overlap) -> None:
    """Raise ``ValueError`` naming a bad option (shared by the twin and the CLI)."""
    if not threshold > 0:  # also catches NaN
        raise ValueError(f"threshold must be > 0 (inf: never open), got {threshold}")
    if not budget >= 1 or math.isinf(budget):
        raise ValueError(f"budget must be >= 1 (BRef capacity per instance), got {budget}")
    if int(bins) < 2:
        raise ValueError(f"bins must be >= 2, got {bins}")
    if not overlap >= 0:
        raise ValueError(f"overlap must be >= 0, got {overlap}")


def brefs_capacity(n_instances: int, threshold: float, budget: float,
                   capacity: int | None = None) -> int:
    """Slots of the BRef array: ``capacity``, else ``ceil(budget * n)``; ``n`` when never opening."""
    if math.isinf(threshold):
        return n_instances
    if capacity is not None:
        if capacity < n_instances:
            raise ValueError(f"capacity {capacity} is below the {n_instances} instances")
        return int(capacity)
    return max(n_instances, int(math.ceil(budget * n_instances)))


def build_top_level(forest, instances, n_instances: int, *, threshold: float = DEFAULT_THRESHOLD,
                    budget: float = DEFAULT_BUDGET, capacity: int | None = None,
                    bins: int = DEFAULT_BINS, overlap: float = DEFAULT_OVERLAP,
                    estimate: bool = False, array_size: int | None = None) -> TopLevel:
    """Re-braiding top-level build over the first ``n_instances`` instances (module docstring).

    ``forest``, ``instances``: :func:`jaxbvh.twolevel.objects.pack` output (NumPy or JAX arrays);
    ``threshold``: opening threshold, a fraction of the segment's largest extent (inf:
    plain two-level); ``budget``: BRef slots per instance (or ``capacity`` slots in all);
    ``bins``: SAH bins per axis; ``overlap``: "barely overlapping" tolerance of the
    <= 4-BRef termination test; ``estimate``: the paper's estimated primitive counts;
    ``array_size``: size of the arrays (default: the capacity bucket of the slots; a
    larger one changes nothing but the shapes, e.g. to compile once for many scenes).
    Returns a :class:`TopLevel` of JAX arrays.
    """
    check_options(threshold, budget, bins, overlap)
    if n_instances < 1:
        raise ValueError("a top level needs at least one instance")
    slots = brefs_capacity(n_instances, threshold, budget, capacity)
    cap = max(capacity_bucket(slots), array_size or 0)
    dtype = np.asarray(forest.lo).dtype
    result = _build(jax.tree_util.tree_map(jnp.asarray, forest),
                    jax.tree_util.tree_map(jnp.asarray, instances), jnp.int32(n_instances),
                    jnp.int32(slots), jnp.asarray(threshold, dtype), jnp.asarray(overlap, dtype),
                    cap=cap, bins=int(bins), estimate=bool(estimate))
    if not bool(result.complete):  # cannot happen: every level splits every segment of >= 2 BRefs
        raise RuntimeError(f"top-level build stopped at its bound of {cap + 1} levels with segments left")
    return result


# ----------------------------------------------------------------------------------
# the level-synchronous engine
# ----------------------------------------------------------------------------------


def _segment(op, data, ids, n):
    """``op`` (segment_sum/min/max) over ``n`` segments; id ``n`` means "none" (dropped)."""
    return op(data, ids, num_segments=n + 1)[:n]



def _exclusive_rank(flag, start):
    """Rank of each flagged position among the flagged positions of its segment."""
    before = jnp.cumsum(flag.astype(jnp.int32)) - flag.astype(jnp.int32)
    return before - take(before, start, 0)


def _scan(starts, lo, hi, prims):
    """Inclusive running (box, primitive count) along axis 1, restarting where ``starts``."""

    def combine(a, b):
        fa, la, ha, pa = a
        fb, lb, hb, pb = b
        keep = fb[..., None]
        return (fa | fb, jnp.where(keep, lb, jnp.minimum(la, lb)), jnp.where(keep, hb, jnp.maximum(ha, hb)),
                jnp.where(fb, pb, pa + pb))

    return jax.lax.associative_scan(combine, (starts, lo, hi, prims), axis=1)[1:]


def _best_planes(sid, bin_p, lo, hi, prims, *, bins, cap):
    """Cheapest bin plane of every segment: ``(cost, axis * bins + plane)`` [C].

    Per axis the BRefs are sorted by (segment, bin); forward and backward segmented scans
    give the box and primitive count of both sides of every plane where the bin changes
    (empty bins between two occupied ones give the same partition; the lowest such plane
    is named). Costs and the tie rule are those of the module docstring; segments without
    a plane get ``(inf, max int)``.
    """
    i32 = jnp.int32
    dtype = lo.dtype
    axes = jnp.arange(3, dtype=i32)
    none = cap * bins  # sorts after every real key
    keys = jnp.where(sid[None, :] < cap, sid[None, :] * bins + bin_p.T, none)  # [3, C]
    order = jnp.argsort(keys, axis=1, stable=True).astype(i32)
    seg = jnp.take_along_axis(jnp.broadcast_to(sid, (3, cap)), order, axis=1)
    b = jnp.take_along_axis(bin_p.T, order, axis=1)
    s_lo, s_hi, s_p = lo[order], hi[order], prims[order]  # [3, C, 3], [3, C]
    step = jnp.concatenate([seg[:, 1:] != seg[:, :-1], jnp.ones((3, 1), bool)], axis=1)  # last of a run
    first = jnp.concatenate([jnp.ones((3, 1), bool), step[:, :-1]], axis=1)
    l_lo, l_hi, l_p = _scan(first, s_lo, s_hi, s_p)
    r_lo, r_hi, r_p = (a[:, ::-1] for a in _scan(step[:, ::-1], s_lo[:, ::-1], s_hi[:, ::-1], s_p[:, ::-1]))
    shift = lambda a, fill: jnp.concatenate([a[:, 1:], jnp.full_like(a[:, :1], fill)], axis=1)  # noqa: E731
    r_lo, r_hi, r_p = shift(r_lo, jnp.inf), shift(r_hi, -jnp.inf), shift(r_p, 0)
    # a plane after every sorted BRef whose successor in the segment has a higher bin (so
    # both sides hold BRefs; bins differ only on an axis of positive span)
    plane = (seg < cap) & ~step & (b != shift(b, -1))
    cost = (half_area(l_lo, l_hi) * l_p.astype(dtype) + half_area(r_lo, r_hi) * r_p.astype(dtype))
    cost = jnp.where(plane, cost, jnp.inf)
    ids = jnp.where(plane, seg, cap).ravel()
    best = _segment(jax.ops.segment_min, cost.ravel(), ids, cap)
    near = (best * (1 + TIE_TOLERANCE)).at[ids].get(mode="fill", fill_value=-jnp.inf)
    key = jnp.where(plane & (cost.ravel() <= near).reshape(3, cap), axes[:, None] * bins + b,
                    jnp.iinfo(i32).max)
    best_key = _segment(jax.ops.segment_min, key.ravel(), ids, cap)
    return best, best_key


@partial(jax.jit, static_argnames=("cap", "bins", "estimate"))
def _build(forest, instances, n_inst, slots, threshold, overlap, *, cap, bins, estimate):
    C = cap
    M = 2 * C
    NF = forest.left.shape[0]
    n_inst_cap = instances.object.shape[0]
    dtype = forest.lo.dtype
    i32 = jnp.int32
    pos = jnp.arange(C, dtype=i32)
    inf = jnp.asarray(jnp.inf, dtype)

    def child_box(node, inst):
        """World boxes of forest nodes under instances (padding: the empty box)."""
        ok = (node >= 0) & (inst >= 0)
        n = jnp.where(ok, node, 0)
        k = jnp.where(ok, inst, 0)
        lo, hi = world_boxes(forest.lo[n], forest.hi[n], instances.to_scene[k], instances.margin[k])
        return jnp.where(ok[:, None], lo, inf), jnp.where(ok[:, None], hi, -inf)

    # the instances' BRefs at [0, n_inst)
    first = pos < n_inst
    inst0 = jnp.where(first, pos, -1)
    root = forest.root[instances.object[jnp.minimum(pos, n_inst_cap - 1)]]
    node0 = jnp.where(first, root, -1)
    lo0, hi0 = child_box(node0, inst0)
    state = dict(
        node=node0, inst=inst0, lo=lo0, hi=hi0,
        prims=jnp.where(first, take(forest.subtree_prims, jnp.where(first, root, NF), 0), 0),
        seg_of=jnp.where(pos < slots, 0, C).astype(i32),
        seg_end=jnp.zeros(C, i32).at[0].set(n_inst),
        seg_extra=jnp.zeros(C, i32).at[0].set(slots),
        seg_node=jnp.zeros(C, i32),
        seg_live=jnp.zeros(C, bool).at[0].set(n_inst > 0),
        left=jnp.full(M, -1, i32), right=jnp.full(M, -1, i32), parent=jnp.full(M, -1, i32),
        axis=jnp.full(M, -1, i32), prim_start=jnp.zeros(M, i32), prim_count=jnp.zeros(M, i32),
        top_lo=jnp.full((M, 3), inf, dtype), top_hi=jnp.full((M, 3), -inf, dtype),
        next_free=i32(1), level=i32(0),
    )

    def interior(node):
        return take(forest.left, jnp.where(node >= 0, node, NF), -1) >= 0

    def level(s):
        seg = s["seg_of"]
        live = s["seg_live"]
        in_live = take(live, seg, False)
        end = take(s["seg_end"], seg, 0)
        is_ref = in_live & (pos < end)
        sid = jnp.where(is_ref, seg, C)
        count = _segment(jax.ops.segment_sum, is_ref.astype(i32), sid, C)
        lo, hi, node, inst = s["lo"], s["hi"], s["node"], s["inst"]
        seg_lo = _segment(jax.ops.segment_min, lo, sid, C)
        seg_hi = _segment(jax.ops.segment_max, hi, sid, C)
        leaf_seg = live & (count == 1)
        split_seg = live & (count >= 2)

        # 2. termination of opening
        same = (_segment(jax.ops.segment_min, inst, sid, C)
                == _segment(jax.ops.segment_max, inst, sid, C))
        small_p = take(count, seg, 0) <= SMALL_SEGMENT
        overlaps = jnp.zeros(C, bool)
        for j in range(SMALL_SEGMENT):
            q = seg + j
            other = is_ref & small_p & (q < end) & (q != pos)
            qs = jnp.where(other, q, C)
            q_lo, q_hi = take(lo, qs, 0), take(hi, qs, 0)
            shorter = jnp.minimum(hi - lo, q_hi - q_lo)
            shared = jnp.minimum(hi, q_hi) - jnp.maximum(lo, q_lo)
            overlaps = overlaps | (other & jnp.all(shared >= overlap * shorter, axis=1))
        any_overlap = _segment(jax.ops.segment_max, overlaps.astype(i32), sid, C) > 0
        barely = (count <= SMALL_SEGMENT) & ~any_overlap
        may_open = split_seg & (s["seg_extra"] > s["seg_end"]) & ~same & ~barely

        # 3. opening
        ext = seg_hi - seg_lo
        dim = jnp.argmax(ext, axis=1).astype(i32)
        ext_dim = jnp.take_along_axis(ext, dim[:, None], axis=1)[:, 0]
        dim_p = take(dim, seg, 0)
        width = (jnp.take_along_axis(hi, dim_p[:, None], axis=1)
                 - jnp.take_along_axis(lo, dim_p[:, None], axis=1))[:, 0]
        candidate = is_ref & interior(node) & (width > threshold * take(ext_dim, seg, 0))
        n_cand = _segment(jax.ops.segment_sum, candidate.astype(i32), sid, C)
        do_open = may_open & (n_cand > 0) & (n_cand <= s["seg_extra"] - s["seg_end"])
        opens = candidate & take(do_open, seg, False)
        slot = jnp.where(opens, end + _exclusive_rank(opens, jnp.minimum(seg, C - 1)), C)
        safe = jnp.where(opens, node, NF)
        kid_l = take(forest.left, safe, -1)
        kid_r = take(forest.right, safe, -1)
        l_lo, l_hi = child_box(jnp.where(opens, kid_l, -1), inst)
        r_lo, r_hi = child_box(jnp.where(opens, kid_r, -1), inst)
        if estimate:
            half = jnp.maximum(s["prims"] // 2, 1)
            l_prims = r_prims = half
        else:
            l_prims = take(forest.subtree_prims, jnp.where(opens, kid_l, NF), 0)
            r_prims = take(forest.subtree_prims, jnp.where(opens, kid_r, NF), 0)
        node = jnp.where(opens, kid_l, node).at[slot].set(kid_r, mode="drop")
        inst = inst.at[slot].set(inst, mode="drop")
        lo = jnp.where(opens[:, None], l_lo, lo).at[slot].set(r_lo, mode="drop")
        hi = jnp.where(opens[:, None], l_hi, hi).at[slot].set(r_hi, mode="drop")
        prims = jnp.where(opens, l_prims, s["prims"]).at[slot].set(r_prims, mode="drop")
        seg_end = s["seg_end"] + jnp.where(do_open, n_cand, 0)
        extra = jnp.where(may_open, s["seg_extra"], seg_end)  # dropped room stays unused

        # 4. binning over the BRefs of the split segments
        end = take(seg_end, seg, 0)
        is_ref = in_live & (pos < end) & take(split_seg, seg, False)
        sid = jnp.where(is_ref, seg, C)
        count = jnp.where(split_seg, _segment(jax.ops.segment_sum, is_ref.astype(i32), sid, C), count)
        centre = 0.5 * lo + 0.5 * hi
        c_min = _segment(jax.ops.segment_min, jnp.where(is_ref[:, None], centre, inf), sid, C)
        c_max = _segment(jax.ops.segment_max, jnp.where(is_ref[:, None], centre, -inf), sid, C)
        span = c_max - c_min
        span_p = take(span, seg, 0)
        low_p = take(c_min, seg, 0)
        nb = jnp.asarray(bins, dtype)
        raw = jnp.floor((centre - low_p) * nb / jnp.where(span_p > 0, span_p, 1))
        bin_p = jnp.where(span_p > 0, jnp.clip(raw, 0, nb - 1), 0).astype(i32)  # [C, 3]
        best, best_key = _best_planes(sid, bin_p, lo, hi, prims, bins=bins, cap=C)
        found = best < inf
        best_axis = best_key // bins
        best_plane = best_key % bins

        # 5. partition and spare split
        offset = pos - seg
        axis_p = take(best_axis, seg, 0)
        plane_p = take(best_plane, seg, 0)
        by_plane = jnp.take_along_axis(bin_p, axis_p[:, None], axis=1)[:, 0] <= plane_p
        goes_left = is_ref & jnp.where(take(found, seg, False), by_plane,
                                       offset < take(count, seg, 0) // 2)
        n_left = _segment(jax.ops.segment_sum, goes_left.astype(i32), sid, C)
        n_right = count - n_left
        rank_left = _exclusive_rank(goes_left, jnp.minimum(seg, C - 1))
        rank_right = offset - rank_left
        key2 = jnp.where(is_ref, 2 * seg + jnp.where(goes_left, 0, 1), 2 * C)
        ch_lo = _segment(jax.ops.segment_min, lo, key2, 2 * C).reshape(C, 2, 3)
        ch_hi = _segment(jax.ops.segment_max, hi, key2, 2 * C).reshape(C, 2, 3)
        ch_ext = ch_hi - ch_lo
        ch_dim = jnp.argmax(ch_ext, axis=2).astype(i32)
        ch_ext_dim = jnp.take_along_axis(ch_ext, ch_dim[..., None], axis=2)[..., 0]
        k2 = jnp.minimum(key2, 2 * C - 1)
        d2 = ch_dim.reshape(-1)[k2]
        w2 = (jnp.take_along_axis(hi, d2[:, None], axis=1) - jnp.take_along_axis(lo, d2[:, None], axis=1))[:, 0]
        meets = is_ref & interior(node) & (w2 > threshold * ch_ext_dim.reshape(-1)[k2])
        weight = _segment(jax.ops.segment_sum, meets.astype(i32), key2, 2 * C).reshape(C, 2)
        none = weight.sum(axis=1) == 0
        w_l = jnp.where(none, n_left, weight[:, 0])
        w_r = jnp.where(none, n_right, weight[:, 1])
        spare = jnp.maximum(extra - seg_end, 0)
        f32 = jnp.float32
        share = jnp.floor(w_l.astype(f32) / jnp.maximum(w_l + w_r, 1).astype(f32) * spare.astype(f32))
        spare_l = jnp.minimum(share.astype(i32), spare)
        right_start = pos + n_left + spare_l  # per segment start

        # move the BRefs of split segments into their halves
        split_p = take(split_seg, seg, False)
        valid_ref = node >= 0
        new_pos = jnp.where(goes_left, seg + rank_left, take(right_start, seg, 0) + rank_right)
        target = jnp.where(valid_ref, jnp.where(is_ref, new_pos, pos), C)
        empty_i = jnp.full(C, -1, i32)
        node_n = empty_i.at[target].set(node, mode="drop")
        inst_n = empty_i.at[target].set(inst, mode="drop")
        prims_n = jnp.zeros(C, i32).at[target].set(prims, mode="drop")
        lo_n = jnp.full((C, 3), inf, dtype).at[target].set(lo, mode="drop")
        hi_n = jnp.full((C, 3), -inf, dtype).at[target].set(hi, mode="drop")
        rs_p = take(right_start, seg, C)
        seg_of = jnp.where(split_p, jnp.where(pos < rs_p, seg, jnp.where(pos < take(extra, seg, 0), rs_p, C)), C)
        seg_of = jnp.where(in_live, seg_of, C)

        # the top-level nodes of this level
        nid = jnp.where(live, s["seg_node"], M)
        rank = jnp.cumsum(split_seg.astype(i32)) - split_seg.astype(i32)
        left_id = jnp.where(split_seg, s["next_free"] + 2 * rank, M)
        right_id = jnp.where(split_seg, left_id + 1, M)
        starts_l = jnp.where(split_seg, pos, C)
        starts_r = jnp.where(split_seg, right_start, C)
        new_end = jnp.zeros(C, i32).at[starts_l].set(pos + n_left, mode="drop").at[starts_r].set(
            right_start + n_right, mode="drop")
        new_extra = jnp.zeros(C, i32).at[starts_l].set(right_start, mode="drop").at[starts_r].set(
            extra, mode="drop")
        new_node = jnp.zeros(C, i32).at[starts_l].set(left_id, mode="drop").at[starts_r].set(
            right_id, mode="drop")
        new_live = jnp.zeros(C, bool).at[starts_l].set(True, mode="drop").at[starts_r].set(True, mode="drop")
        node_ids = s["seg_node"]
        return dict(
            node=node_n, inst=inst_n, lo=lo_n, hi=hi_n, prims=prims_n, seg_of=seg_of.astype(i32),
            seg_end=new_end, seg_extra=new_extra, seg_node=new_node, seg_live=new_live,
            left=s["left"].at[jnp.where(split_seg, nid, M)].set(left_id, mode="drop"),
            right=s["right"].at[jnp.where(split_seg, nid, M)].set(right_id, mode="drop"),
            parent=s["parent"].at[left_id].set(node_ids, mode="drop").at[right_id].set(node_ids, mode="drop"),
            axis=s["axis"].at[jnp.where(split_seg, nid, M)].set(jnp.where(found, best_axis, -1), mode="drop"),
            prim_start=s["prim_start"].at[jnp.where(leaf_seg, nid, M)].set(pos, mode="drop"),
            prim_count=s["prim_count"].at[jnp.where(leaf_seg, nid, M)].set(1, mode="drop"),
            top_lo=s["top_lo"].at[nid].set(seg_lo, mode="drop"),
            top_hi=s["top_hi"].at[nid].set(seg_hi, mode="drop"),
            next_free=s["next_free"] + 2 * jnp.sum(split_seg, dtype=i32),
            level=s["level"] + 1,
        )

    s = jax.lax.while_loop(lambda s: jnp.any(s["seg_live"]) & (s["level"] <= C), level, state)

    # compact the BRefs in array order; leaves point at their BRef's new id
    used = s["node"] >= 0
    new_id = jnp.cumsum(used.astype(i32)) - 1
    dest = jnp.where(used, new_id, C)
    n_refs = jnp.sum(used, dtype=i32)
    leaf = s["prim_count"] > 0
    top = BVH(left=s["left"], right=s["right"], parent=s["parent"], lo=s["top_lo"], hi=s["top_hi"],
              prim_start=jnp.where(leaf, take(new_id, s["prim_start"], 0), 0), prim_count=s["prim_count"],
              axis=s["axis"], prim_index=jnp.where(pos < n_refs, pos, -1), root=i32(0))
    return TopLevel(
        top=top,
        node=jnp.full(C, -1, i32).at[dest].set(s["node"], mode="drop"),
        instance=jnp.full(C, -1, i32).at[dest].set(s["inst"], mode="drop"),
        lo=jnp.full((C, 3), inf, dtype).at[dest].set(s["lo"], mode="drop"),
        hi=jnp.full((C, 3), -inf, dtype).at[dest].set(s["hi"], mode="drop"),
        prims=jnp.zeros(C, i32).at[dest].set(s["prims"], mode="drop"),
        position=jnp.full(C, -1, i32).at[dest].set(pos, mode="drop"),
        count=n_refs, levels=s["level"], complete=~jnp.any(s["seg_live"]))
