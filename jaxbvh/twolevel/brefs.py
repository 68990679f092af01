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
from typing import Any, NamedTuple

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


# ----------------------------------------------------------------------------------
# loop state and the steps of one level
# ----------------------------------------------------------------------------------


class _Refs(NamedTuple):
    """The BRef array, by slot ([C]; empty slots: node -1, the empty box)."""

    node: Any   # int32 [C]: forest node, -1 empty
    inst: Any   # int32 [C]: instance, -1 empty
    lo: Any     # float [C, 3]: scene-frame box (conservative world box)
    hi: Any     # float [C, 3]
    prims: Any  # int32 [C]: primitive count (exact or estimated)


class _Segments(NamedTuple):
    """The segments of the current level; per-segment arrays are keyed by the segment's start."""

    of: Any     # int32 [C]: start of the segment each slot belongs to, C: none
    end: Any    # int32 [C]: end of the segment's BRefs ([start, end))
    extra: Any  # int32 [C]: end of its spare room ([end, extra))
    node: Any   # int32 [C]: top-level node the segment becomes
    live: Any   # bool [C]: a segment starts here on this level


class _TopTree(NamedTuple):
    """The top-level tree as it grows, ``M = 2 C`` node slots, ids level by level."""

    left: Any        # int32 [M], -1: none
    right: Any       # int32 [M]
    parent: Any      # int32 [M]
    axis: Any        # int32 [M]: split axis, -1 for a leaf or a split without a plane
    prim_start: Any  # int32 [M]: a leaf's BRef slot (array order, before compaction)
    prim_count: Any  # int32 [M]: 1 for a leaf, else 0
    lo: Any          # float [M, 3]: node box (union of its BRefs' boxes)
    hi: Any          # float [M, 3]


class _Build(NamedTuple):
    """Loop state of the level-synchronous build."""

    refs: _Refs      # the BRef array
    segs: _Segments  # segments still to split
    top: _TopTree    # the top-level tree so far
    next_free: Any   # int32 []: first unused top-level node id
    level: Any       # int32 []: levels done (bounded by C)


class _View(NamedTuple):
    """One level's segments as seen from the slots (per slot) and as sets (per segment start)."""

    seg: Any      # int32 [C] per slot: its segment's start, C: none
    in_live: Any  # bool [C] per slot: it lies in a live segment
    end: Any      # int32 [C] per slot: its segment's end
    is_ref: Any   # bool [C] per slot: it holds a BRef of a live segment
    sid: Any      # int32 [C] per slot: ``seg`` where ``is_ref``, else C (segment-op key)
    count: Any    # int32 [C] per segment: BRefs
    lo: Any       # float [C, 3] per segment: union of its BRefs' boxes
    hi: Any       # float [C, 3]
    leaf: Any     # bool [C] per segment: live with one BRef (becomes a leaf)
    split: Any    # bool [C] per segment: live with two or more (splits)


class _Binned(NamedTuple):
    """The split segments' BRefs after opening, binned, and each segment's best plane."""

    is_ref: Any  # bool [C] per slot: holds a BRef of a split segment
    sid: Any     # int32 [C] per slot: its segment where ``is_ref``, else C
    count: Any   # int32 [C] per segment: BRefs after opening
    bin_p: Any   # int32 [C, 3] per slot: bin of the BRef's centre on each axis
    found: Any   # bool [C] per segment: a plane exists
    axis: Any    # int32 [C] per segment: the best plane's axis
    plane: Any   # int32 [C] per segment: the best plane (left: bins <= plane)


class _Halves(NamedTuple):
    """The partition of every split segment (step 5)."""

    goes_left: Any    # bool [C] per slot: the BRef goes to the left half
    rank_left: Any    # int32 [C] per slot: its rank among its segment's left BRefs
    rank_right: Any   # int32 [C] per slot: its rank among the right ones (where not left)
    n_left: Any       # int32 [C] per segment: BRefs going left
    n_right: Any      # int32 [C] per segment: BRefs going right
    right_start: Any  # int32 [C] per segment: first slot of the right half


@partial(jax.jit, static_argnames=("cap", "bins", "estimate"))
def _build(forest, instances, n_inst, slots, threshold, overlap, *, cap, bins, estimate):
    """The engine of :func:`build_top_level` (module docstring): ``cap`` slots, ``bins`` bins."""
    state = _initial(forest, instances, n_inst, slots, cap=cap)

    def level(s):
        return _level(forest, instances, s, threshold, overlap, cap=cap, bins=bins, estimate=estimate)

    s = jax.lax.while_loop(lambda s: jnp.any(s.segs.live) & (s.level <= cap), level, state)
    return _compact(s, cap=cap)


def _child_box(forest, instances, node, inst):
    """World boxes of forest nodes under instances (padding: the empty box)."""
    inf = jnp.asarray(jnp.inf, forest.lo.dtype)
    ok = (node >= 0) & (inst >= 0)
    n = jnp.where(ok, node, 0)
    k = jnp.where(ok, inst, 0)
    lo, hi = world_boxes(forest.lo[n], forest.hi[n], instances.to_scene[k], instances.margin[k])
    return jnp.where(ok[:, None], lo, inf), jnp.where(ok[:, None], hi, -inf)


def _interior(forest, node):
    """The forest nodes ``node`` (-1: none) have children."""
    nf = forest.left.shape[0]
    return take(forest.left, jnp.where(node >= 0, node, nf), -1) >= 0


def _initial(forest, instances, n_inst, slots, *, cap) -> _Build:
    """The instances' BRefs at ``[0, n_inst)``, one root segment ``[0, slots)``."""
    C, M = cap, 2 * cap
    dtype = forest.lo.dtype
    i32 = jnp.int32
    pos = jnp.arange(C, dtype=i32)
    inf = jnp.asarray(jnp.inf, dtype)
    first = pos < n_inst
    inst0 = jnp.where(first, pos, -1)
    root = forest.root[instances.object[jnp.minimum(pos, instances.object.shape[0] - 1)]]
    node0 = jnp.where(first, root, -1)
    lo0, hi0 = _child_box(forest, instances, node0, inst0)
    prims0 = jnp.where(first, take(forest.subtree_prims, jnp.where(first, root, forest.left.shape[0]), 0), 0)
    segs = _Segments(of=jnp.where(pos < slots, 0, C).astype(i32), end=jnp.zeros(C, i32).at[0].set(n_inst),
                     extra=jnp.zeros(C, i32).at[0].set(slots), node=jnp.zeros(C, i32),
                     live=jnp.zeros(C, bool).at[0].set(n_inst > 0))
    none = jnp.full(M, -1, i32)
    top = _TopTree(left=none, right=none, parent=none, axis=none, prim_start=jnp.zeros(M, i32),
                   prim_count=jnp.zeros(M, i32), lo=jnp.full((M, 3), inf, dtype), hi=jnp.full((M, 3), -inf, dtype))
    return _Build(refs=_Refs(node=node0, inst=inst0, lo=lo0, hi=hi0, prims=prims0), segs=segs, top=top,
                  next_free=i32(1), level=i32(0))


def _level(forest, instances, s: _Build, threshold, overlap, *, cap, bins, estimate) -> _Build:
    """One level: every live segment becomes a leaf or opens (steps 2-3), bins (4) and
    splits in two (5); its halves are the next level's segments."""
    view = _view(s.refs, s.segs, cap=cap)
    may_open = _may_open(s.refs, s.segs, view, overlap, cap=cap)
    refs, seg_end, extra = _open(forest, instances, s.refs, s.segs, view, may_open, threshold,
                                 cap=cap, estimate=estimate)
    binned = _bin(refs, view, seg_end, cap=cap, bins=bins)
    halves = _partition(forest, refs, view, binned, seg_end, extra, threshold, cap=cap)
    refs, seg_of = _move(refs, view, binned, halves, extra, cap=cap)
    segs, top, next_free = _grow(s, view, binned, halves, extra, cap=cap)
    return _Build(refs=refs, segs=segs._replace(of=seg_of), top=top, next_free=next_free, level=s.level + 1)


def _view(refs: _Refs, segs: _Segments, *, cap) -> _View:
    C = cap
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = segs.of
    in_live = take(segs.live, seg, False)
    end = take(segs.end, seg, 0)
    is_ref = in_live & (pos < end)
    sid = jnp.where(is_ref, seg, C)
    count = _segment(jax.ops.segment_sum, is_ref.astype(jnp.int32), sid, C)
    return _View(seg=seg, in_live=in_live, end=end, is_ref=is_ref, sid=sid, count=count,
                 lo=_segment(jax.ops.segment_min, refs.lo, sid, C), hi=_segment(jax.ops.segment_max, refs.hi, sid, C),
                 leaf=segs.live & (count == 1), split=segs.live & (count >= 2))


def _may_open(refs: _Refs, segs: _Segments, view: _View, overlap, *, cap):
    """Step 2, termination of opening: split segments with spare room that hold more than
    one instance and are not a few barely overlapping BRefs (bool [C] per segment)."""
    C = cap
    pos = jnp.arange(C, dtype=jnp.int32)
    seg, sid, is_ref, lo, hi = view.seg, view.sid, view.is_ref, refs.lo, refs.hi
    same = (_segment(jax.ops.segment_min, refs.inst, sid, C)
            == _segment(jax.ops.segment_max, refs.inst, sid, C))
    small_p = take(view.count, seg, 0) <= SMALL_SEGMENT
    overlaps = jnp.zeros(C, bool)
    for j in range(SMALL_SEGMENT):
        q = seg + j
        other = is_ref & small_p & (q < view.end) & (q != pos)
        qs = jnp.where(other, q, C)
        q_lo, q_hi = take(lo, qs, 0), take(hi, qs, 0)
        shorter = jnp.minimum(hi - lo, q_hi - q_lo)
        shared = jnp.minimum(hi, q_hi) - jnp.maximum(lo, q_lo)
        overlaps = overlaps | (other & jnp.all(shared >= overlap * shorter, axis=1))
    any_overlap = _segment(jax.ops.segment_max, overlaps.astype(jnp.int32), sid, C) > 0
    barely = (view.count <= SMALL_SEGMENT) & ~any_overlap
    return view.split & (segs.extra > segs.end) & ~same & ~barely


def _open(forest, instances, refs: _Refs, segs: _Segments, view: _View, may_open, threshold, *, cap,
          estimate):
    """Step 3, opening: all candidates of a segment or none. Returns the BRefs, each
    segment's new end and its room's end (dropped room: the new end)."""
    C = cap
    NF = forest.left.shape[0]
    seg = view.seg
    ext = view.hi - view.lo
    dim = jnp.argmax(ext, axis=1).astype(jnp.int32)
    ext_dim = jnp.take_along_axis(ext, dim[:, None], axis=1)[:, 0]
    dim_p = take(dim, seg, 0)
    width = (jnp.take_along_axis(refs.hi, dim_p[:, None], axis=1)
             - jnp.take_along_axis(refs.lo, dim_p[:, None], axis=1))[:, 0]
    candidate = view.is_ref & _interior(forest, refs.node) & (width > threshold * take(ext_dim, seg, 0))
    n_cand = _segment(jax.ops.segment_sum, candidate.astype(jnp.int32), view.sid, C)
    do_open = may_open & (n_cand > 0) & (n_cand <= segs.extra - segs.end)
    opens = candidate & take(do_open, seg, False)
    slot = jnp.where(opens, view.end + _exclusive_rank(opens, jnp.minimum(seg, C - 1)), C)
    safe = jnp.where(opens, refs.node, NF)
    kid_l = take(forest.left, safe, -1)
    kid_r = take(forest.right, safe, -1)
    l_lo, l_hi = _child_box(forest, instances, jnp.where(opens, kid_l, -1), refs.inst)
    r_lo, r_hi = _child_box(forest, instances, jnp.where(opens, kid_r, -1), refs.inst)
    if estimate:
        half = jnp.maximum(refs.prims // 2, 1)
        l_prims = r_prims = half
    else:
        l_prims = take(forest.subtree_prims, jnp.where(opens, kid_l, NF), 0)
        r_prims = take(forest.subtree_prims, jnp.where(opens, kid_r, NF), 0)
    opened = _Refs(node=jnp.where(opens, kid_l, refs.node).at[slot].set(kid_r, mode="drop"),
                   inst=refs.inst.at[slot].set(refs.inst, mode="drop"),
                   lo=jnp.where(opens[:, None], l_lo, refs.lo).at[slot].set(r_lo, mode="drop"),
                   hi=jnp.where(opens[:, None], l_hi, refs.hi).at[slot].set(r_hi, mode="drop"),
                   prims=jnp.where(opens, l_prims, refs.prims).at[slot].set(r_prims, mode="drop"))
    seg_end = segs.end + jnp.where(do_open, n_cand, 0)
    extra = jnp.where(may_open, segs.extra, seg_end)  # dropped room stays unused
    return opened, seg_end, extra


def _bin(refs: _Refs, view: _View, seg_end, *, cap, bins) -> _Binned:
    """Step 4, binning over the BRefs of the split segments, and each one's best plane."""
    C = cap
    dtype = refs.lo.dtype
    inf = jnp.asarray(jnp.inf, dtype)
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = view.seg
    end = take(seg_end, seg, 0)
    is_ref = view.in_live & (pos < end) & take(view.split, seg, False)
    sid = jnp.where(is_ref, seg, C)
    count = jnp.where(view.split, _segment(jax.ops.segment_sum, is_ref.astype(jnp.int32), sid, C), view.count)
    centre = 0.5 * refs.lo + 0.5 * refs.hi
    c_min = _segment(jax.ops.segment_min, jnp.where(is_ref[:, None], centre, inf), sid, C)
    c_max = _segment(jax.ops.segment_max, jnp.where(is_ref[:, None], centre, -inf), sid, C)
    span = c_max - c_min
    span_p = take(span, seg, 0)
    low_p = take(c_min, seg, 0)
    nb = jnp.asarray(bins, dtype)
    raw = jnp.floor((centre - low_p) * nb / jnp.where(span_p > 0, span_p, 1))
    bin_p = jnp.where(span_p > 0, jnp.clip(raw, 0, nb - 1), 0).astype(jnp.int32)  # [C, 3]
    best, best_key = _best_planes(sid, bin_p, refs.lo, refs.hi, refs.prims, bins=bins, cap=C)
    return _Binned(is_ref=is_ref, sid=sid, count=count, bin_p=bin_p, found=best < inf,
                   axis=best_key // bins, plane=best_key % bins)


def _partition(forest, refs: _Refs, view: _View, b: _Binned, seg_end, extra, threshold, *, cap) -> _Halves:
    """Step 5, the stable partition and the split of the spare room."""
    C = cap
    i32 = jnp.int32
    pos = jnp.arange(C, dtype=i32)
    seg, lo, hi = view.seg, refs.lo, refs.hi
    offset = pos - seg
    axis_p = take(b.axis, seg, 0)
    plane_p = take(b.plane, seg, 0)
    by_plane = jnp.take_along_axis(b.bin_p, axis_p[:, None], axis=1)[:, 0] <= plane_p
    goes_left = b.is_ref & jnp.where(take(b.found, seg, False), by_plane, offset < take(b.count, seg, 0) // 2)
    n_left = _segment(jax.ops.segment_sum, goes_left.astype(i32), b.sid, C)
    n_right = b.count - n_left
    rank_left = _exclusive_rank(goes_left, jnp.minimum(seg, C - 1))
    # the spare room goes in proportion to the BRefs that would open in each half
    key2 = jnp.where(b.is_ref, 2 * seg + jnp.where(goes_left, 0, 1), 2 * C)
    ch_lo = _segment(jax.ops.segment_min, lo, key2, 2 * C).reshape(C, 2, 3)
    ch_hi = _segment(jax.ops.segment_max, hi, key2, 2 * C).reshape(C, 2, 3)
    ch_ext = ch_hi - ch_lo
    ch_dim = jnp.argmax(ch_ext, axis=2).astype(i32)
    ch_ext_dim = jnp.take_along_axis(ch_ext, ch_dim[..., None], axis=2)[..., 0]
    k2 = jnp.minimum(key2, 2 * C - 1)
    d2 = ch_dim.reshape(-1)[k2]
    w2 = (jnp.take_along_axis(hi, d2[:, None], axis=1) - jnp.take_along_axis(lo, d2[:, None], axis=1))[:, 0]
    meets = b.is_ref & _interior(forest, refs.node) & (w2 > threshold * ch_ext_dim.reshape(-1)[k2])
    weight = _segment(jax.ops.segment_sum, meets.astype(i32), key2, 2 * C).reshape(C, 2)
    none = weight.sum(axis=1) == 0
    w_l = jnp.where(none, n_left, weight[:, 0])
    w_r = jnp.where(none, n_right, weight[:, 1])
    spare = jnp.maximum(extra - seg_end, 0)
    f32 = jnp.float32
    share = jnp.floor(w_l.astype(f32) / jnp.maximum(w_l + w_r, 1).astype(f32) * spare.astype(f32))
    spare_l = jnp.minimum(share.astype(i32), spare)
    return _Halves(goes_left=goes_left, rank_left=rank_left, rank_right=offset - rank_left, n_left=n_left,
                   n_right=n_right, right_start=pos + n_left + spare_l)


def _move(refs: _Refs, view: _View, b: _Binned, h: _Halves, extra, *, cap):
    """Move the BRefs of split segments into their halves; returns the BRefs and the
    next level's segment of every slot."""
    C = cap
    dtype = refs.lo.dtype
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = view.seg
    new_pos = jnp.where(h.goes_left, seg + h.rank_left, take(h.right_start, seg, 0) + h.rank_right)
    target = jnp.where(refs.node >= 0, jnp.where(b.is_ref, new_pos, pos), C)
    empty_i = jnp.full(C, -1, jnp.int32)
    moved = _Refs(node=empty_i.at[target].set(refs.node, mode="drop"),
                  inst=empty_i.at[target].set(refs.inst, mode="drop"),
                  lo=jnp.full((C, 3), jnp.inf, dtype).at[target].set(refs.lo, mode="drop"),
                  hi=jnp.full((C, 3), -jnp.inf, dtype).at[target].set(refs.hi, mode="drop"),
                  prims=jnp.zeros(C, jnp.int32).at[target].set(refs.prims, mode="drop"))
    rs_p = take(h.right_start, seg, C)
    split_p = take(view.split, seg, False)
    seg_of = jnp.where(split_p, jnp.where(pos < rs_p, seg, jnp.where(pos < take(extra, seg, 0), rs_p, C)), C)
    return moved, jnp.where(view.in_live, seg_of, C).astype(jnp.int32)


def _grow(s: _Build, view: _View, b: _Binned, h: _Halves, extra, *, cap):
    """This level's top-level nodes: leaves point at their BRef, split nodes get two
    children, the next level's segments. Returns ``(segments, tree, next_free)``
    (the segments' ``of`` is :func:`_move`'s)."""
    C, M = cap, 2 * cap
    i32 = jnp.int32
    pos = jnp.arange(C, dtype=i32)
    split_seg, leaf_seg = view.split, view.leaf
    nid = jnp.where(s.segs.live, s.segs.node, M)
    rank = jnp.cumsum(split_seg.astype(i32)) - split_seg.astype(i32)
    left_id = jnp.where(split_seg, s.next_free + 2 * rank, M)
    right_id = jnp.where(split_seg, left_id + 1, M)
    starts_l = jnp.where(split_seg, pos, C)
    starts_r = jnp.where(split_seg, h.right_start, C)

    def halves(left_value, right_value, fill, dtype):
        return jnp.full(C, fill, dtype).at[starts_l].set(left_value, mode="drop").at[starts_r].set(
            right_value, mode="drop")

    segs = _Segments(of=s.segs.of, end=halves(pos + h.n_left, h.right_start + h.n_right, 0, i32),
                     extra=halves(h.right_start, extra, 0, i32), node=halves(left_id, right_id, 0, i32),
                     live=halves(True, True, False, bool))
    t, node_ids = s.top, s.segs.node
    split_at = jnp.where(split_seg, nid, M)
    leaf_at = jnp.where(leaf_seg, nid, M)
    top = _TopTree(left=t.left.at[split_at].set(left_id, mode="drop"),
                   right=t.right.at[split_at].set(right_id, mode="drop"),
                   parent=t.parent.at[left_id].set(node_ids, mode="drop").at[right_id].set(node_ids, mode="drop"),
                   axis=t.axis.at[split_at].set(jnp.where(b.found, b.axis, -1), mode="drop"),
                   prim_start=t.prim_start.at[leaf_at].set(pos, mode="drop"),
                   prim_count=t.prim_count.at[leaf_at].set(1, mode="drop"),
                   lo=t.lo.at[nid].set(view.lo, mode="drop"), hi=t.hi.at[nid].set(view.hi, mode="drop"))
    return segs, top, s.next_free + 2 * jnp.sum(split_seg, dtype=i32)


def _compact(s: _Build, *, cap) -> TopLevel:
    """The BRefs compacted in array order; leaves point at their BRef's new id."""
    C = cap
    i32 = jnp.int32
    dtype = s.refs.lo.dtype
    pos = jnp.arange(C, dtype=i32)
    r, t = s.refs, s.top
    used = r.node >= 0
    new_id = jnp.cumsum(used.astype(i32)) - 1
    dest = jnp.where(used, new_id, C)
    n_refs = jnp.sum(used, dtype=i32)
    leaf = t.prim_count > 0
    top = BVH(left=t.left, right=t.right, parent=t.parent, lo=t.lo, hi=t.hi,
              prim_start=jnp.where(leaf, take(new_id, t.prim_start, 0), 0), prim_count=t.prim_count,
              axis=t.axis, prim_index=jnp.where(pos < n_refs, pos, -1), root=i32(0))
    return TopLevel(
        top=top,
        node=jnp.full(C, -1, i32).at[dest].set(r.node, mode="drop"),
        instance=jnp.full(C, -1, i32).at[dest].set(r.inst, mode="drop"),
        lo=jnp.full((C, 3), jnp.inf, dtype).at[dest].set(r.lo, mode="drop"),
        hi=jnp.full((C, 3), -jnp.inf, dtype).at[dest].set(r.hi, mode="drop"),
        prims=jnp.zeros(C, i32).at[dest].set(r.prims, mode="drop"),
        position=jnp.full(C, -1, i32).at[dest].set(pos, mode="drop"),
        count=n_refs, levels=s.level, complete=~jnp.any(s.segs.live))
