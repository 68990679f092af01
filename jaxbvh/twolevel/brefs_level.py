"""One level of the re-braiding top-level build: its loop state and its steps.

Part of :mod:`jaxbvh.twolevel.brefs` (Benthin et al. 2017), whose docstring explains the
BRef array, its segments and the five steps one segment takes. :class:`Build` is the
loop state of the level-synchronous build; :func:`initial` starts it (one BRef per
instance, one root segment) and :func:`level` runs every live segment of one level
through the steps at once: :func:`_view` (the segments seen from the slots),
:func:`_may_open` (step 2), :func:`_open` (3), :func:`_bin` (4), :func:`_partition`
(5), then :func:`_move` (the BRefs into their halves) and :func:`_grow` (the top-level
nodes and the next level's segments).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.numerics import take
from jaxbvh.twolevel.brefs_segments import best_planes, exclusive_rank, segment, widest_rank
from jaxbvh.twolevel.objects import bref_boxes

SMALL_SEGMENT = 4        # paper §4.4: the overlap test applies to <= 4 BRefs


# ----------------------------------------------------------------------------------
# loop state and the steps of one level
# ----------------------------------------------------------------------------------


class Refs(NamedTuple):
    """The BRef array, by slot ([C]; empty slots: node -1, the empty box)."""

    node: Any   # int32 [C]: forest node, -1 empty
    inst: Any   # int32 [C]: instance, -1 empty
    lo: Any     # float [C, 3]: scene-frame box (conservative world box)
    hi: Any     # float [C, 3]
    prims: Any  # int32 [C]: primitive count (exact or estimated)


class Segments(NamedTuple):
    """The segments of the current level; per-segment arrays are keyed by the segment's start."""

    of: Any     # int32 [C]: start of the segment each slot belongs to, C: none
    end: Any    # int32 [C]: end of the segment's BRefs ([start, end))
    extra: Any  # int32 [C]: end of its spare room ([end, extra))
    node: Any   # int32 [C]: top-level node the segment becomes
    live: Any   # bool [C]: a segment starts here on this level


class TopTree(NamedTuple):
    """The top-level tree as it grows, ``M = 2 C`` node slots, ids level by level."""

    left: Any        # int32 [M], -1: none
    right: Any       # int32 [M]
    parent: Any      # int32 [M]
    axis: Any        # int32 [M]: split axis, -1 for a leaf or a split without a plane
    prim_start: Any  # int32 [M]: a leaf's BRef slot (array order, before compaction)
    prim_count: Any  # int32 [M]: 1 for a leaf, else 0
    lo: Any          # float [M, 3]: node box (union of its BRefs' boxes)
    hi: Any          # float [M, 3]


class Build(NamedTuple):
    """Loop state of the level-synchronous build."""

    refs: Refs      # the BRef array
    segs: Segments  # segments still to split
    top: TopTree    # the top-level tree so far
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



def _child_box(forest, instances, node, inst):
    """BRef boxes of forest nodes under instances (padding: the empty box): the world box
    of the node's triangles as the instance places them (:mod:`jaxbvh.twolevel.brefs`,
    "BRef boxes"; :func:`jaxbvh.twolevel.objects.bref_boxes`)."""
    ok = (node >= 0) & (inst >= 0)
    return bref_boxes(instances, jnp.where(ok, node, -1), jnp.where(ok, inst, 0))


def _interior(forest, node):
    """The forest nodes ``node`` (-1: none) have children."""
    nf = forest.left.shape[0]
    return take(forest.left, jnp.where(node >= 0, node, nf), -1) >= 0


def initial(forest, instances, n_inst, slots, *, cap) -> Build:
    """The instances' BRefs at ``[0, n_inst)``, one root segment ``[0, slots)``.

    ``forest``, ``instances``: :func:`jaxbvh.twolevel.objects.pack` output (JAX arrays);
    ``n_inst``, ``slots`` [] int32; ``cap`` (static): the size of the BRef array.
    """
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
    segs = Segments(of=jnp.where(pos < slots, 0, C).astype(i32), end=jnp.zeros(C, i32).at[0].set(n_inst),
                     extra=jnp.zeros(C, i32).at[0].set(slots), node=jnp.zeros(C, i32),
                     live=jnp.zeros(C, bool).at[0].set(n_inst > 0))
    none = jnp.full(M, -1, i32)
    top = TopTree(left=none, right=none, parent=none, axis=none, prim_start=jnp.zeros(M, i32),
                   prim_count=jnp.zeros(M, i32), lo=jnp.full((M, 3), inf, dtype), hi=jnp.full((M, 3), -inf, dtype))
    return Build(refs=Refs(node=node0, inst=inst0, lo=lo0, hi=hi0, prims=prims0), segs=segs, top=top,
                  next_free=i32(1), level=i32(0))


def level(forest, instances, s: Build, threshold, overlap, rounds, *, cap, bins, estimate) -> Build:
    """One level: every live segment becomes a leaf or opens (steps 2-3 of
    :mod:`jaxbvh.twolevel.brefs`), bins (4) and splits in two (5); its halves are the
    next level's segments. ``threshold``, ``overlap`` []: the opening and overlap
    tolerances; ``rounds`` [] int32: most rounds of opening per segment; ``cap``,
    ``bins``, ``estimate``: static, as for :func:`initial` and
    :func:`jaxbvh.twolevel.brefs.build_top_level`."""
    view = _view(s.refs, s.segs, cap=cap)

    def opening():
        may_open = _may_open(s.refs, s.segs, view, overlap, cap=cap)
        return _open(forest, instances, s.refs, s.segs, view, may_open, threshold, rounds, cap=cap,
                     estimate=estimate)

    # below the first few levels no segment has room left (dropped or used): skip steps 2-3
    has_room = jnp.any(view.split & (s.segs.extra > s.segs.end))
    refs, seg_end, extra = jax.lax.cond(has_room, opening, lambda: (s.refs, s.segs.end, s.segs.end))
    binned = _bin(refs, view, seg_end, cap=cap, bins=bins)
    halves = _partition(forest, refs, view, binned, seg_end, extra, threshold, cap=cap)
    refs, seg_of = _move(refs, view, binned, halves, extra, cap=cap)
    segs, top, next_free = _grow(s, view, binned, halves, extra, cap=cap)
    return Build(refs=refs, segs=segs._replace(of=seg_of), top=top, next_free=next_free, level=s.level + 1)


def _view(refs: Refs, segs: Segments, *, cap) -> _View:
    C = cap
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = segs.of
    in_live = take(segs.live, seg, False)
    end = take(segs.end, seg, 0)
    is_ref = in_live & (pos < end)
    sid = jnp.where(is_ref, seg, C)
    count = segment(jax.ops.segment_sum, is_ref.astype(jnp.int32), sid, C)
    return _View(seg=seg, in_live=in_live, end=end, is_ref=is_ref, sid=sid, count=count,
                 lo=segment(jax.ops.segment_min, refs.lo, sid, C), hi=segment(jax.ops.segment_max, refs.hi, sid, C),
                 leaf=segs.live & (count == 1), split=segs.live & (count >= 2))


def _may_open(refs: Refs, segs: Segments, view: _View, overlap, *, cap):
    """Step 2, termination of opening: split segments with spare room that hold more than
    one instance and are not a few barely overlapping BRefs (bool [C] per segment)."""
    C = cap
    pos = jnp.arange(C, dtype=jnp.int32)
    seg, sid, is_ref, lo, hi = view.seg, view.sid, view.is_ref, refs.lo, refs.hi
    same = (segment(jax.ops.segment_min, refs.inst, sid, C)
            == segment(jax.ops.segment_max, refs.inst, sid, C))
    small_p = take(view.count, seg, 0) <= SMALL_SEGMENT

    def against(j, overlaps):  # each BRef against the segment's j-th
        q = seg + j
        other = is_ref & small_p & (q < view.end) & (q != pos)
        qs = jnp.where(other, q, C)
        q_lo, q_hi = take(lo, qs, 0), take(hi, qs, 0)
        shorter = jnp.minimum(hi - lo, q_hi - q_lo)
        shared = jnp.minimum(hi, q_hi) - jnp.maximum(lo, q_lo)
        return overlaps | (other & jnp.all(shared >= overlap * shorter, axis=1))

    # a loop, not SMALL_SEGMENT unrolled copies: ~150 StableHLO ops fewer (issue 38)
    overlaps = jax.lax.fori_loop(0, SMALL_SEGMENT, against, jnp.zeros(C, bool))
    any_overlap = segment(jax.ops.segment_max, overlaps.astype(jnp.int32), sid, C) > 0
    barely = (view.count <= SMALL_SEGMENT) & ~any_overlap
    return view.split & (segs.extra > segs.end) & ~same & ~barely


def _open(forest, instances, refs: Refs, segs: Segments, view: _View, may_open, threshold, rounds, *, cap,
          estimate):
    """Step 3, opening, round after round (a ``while_loop`` bounded by ``rounds`` and by
    ``C``: each round opens one BRef at least) until no segment has a candidate left or
    room for one.
    Returns the BRefs, each segment's new end and its room's end (dropped room: the new
    end)."""
    C = cap
    ext = view.hi - view.lo  # the segment's box before opening: the yardstick of every round
    dim = jnp.argmax(ext, axis=1).astype(jnp.int32)
    ext_dim = jnp.take_along_axis(ext, dim[:, None], axis=1)[:, 0]
    limit = threshold * take(ext_dim, view.seg, 0)
    dim_p = take(dim, view.seg, 0)

    def more(carry):
        _, _, opened, done = carry
        return opened & (done < jnp.minimum(rounds, C))

    def one_round(carry):
        refs, seg_end, _, done = carry
        refs, n_open = _open_once(forest, instances, refs, view, may_open, seg_end, segs.extra, dim_p, limit,
                                  cap=cap, estimate=estimate)
        return refs, seg_end + n_open, jnp.any(n_open > 0), done + 1

    refs, seg_end, _, _ = jax.lax.while_loop(more, one_round, (refs, segs.end, jnp.any(may_open), jnp.int32(0)))
    extra = jnp.where(may_open, segs.extra, seg_end)  # dropped room stays unused
    return refs, seg_end, extra


def _open_once(forest, instances, refs: Refs, view: _View, may_open, seg_end, extra, dim_p, limit, *, cap,
               estimate):
    """One round of opening in every segment that may open: its widest candidates that
    fit into the room (all if they fit; ties to the lower slot). Returns the BRefs and
    the BRefs each segment gained (int32 [C] per segment)."""
    C = cap
    NF = forest.left.shape[0]
    i32 = jnp.int32
    pos = jnp.arange(C, dtype=i32)
    seg = view.seg
    end_p = take(seg_end, seg, 0)
    width = (jnp.take_along_axis(refs.hi, dim_p[:, None], axis=1)
             - jnp.take_along_axis(refs.lo, dim_p[:, None], axis=1))[:, 0]
    candidate = (view.in_live & (pos < end_p) & take(may_open, seg, False) & _interior(forest, refs.node)
                 & (width > limit))
    key = jnp.where(candidate, seg, C)
    room_s = jnp.maximum(extra - seg_end, 0)

    # the sort only where some segment has more candidates than room (else all open)
    short = jnp.any(segment(jax.ops.segment_sum, candidate.astype(i32), key, C) > room_s)
    rank = jax.lax.cond(short, lambda: widest_rank(width, candidate, view.in_live & (pos < end_p), seg, end_p - seg),
                        lambda: jnp.zeros(C, i32))
    opens = candidate & (rank < take(room_s, seg, 0))
    slot = jnp.where(opens, end_p + exclusive_rank(opens, jnp.minimum(seg, C - 1)), C)
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
    opened = Refs(node=jnp.where(opens, kid_l, refs.node).at[slot].set(kid_r, mode="drop"),
                   inst=refs.inst.at[slot].set(refs.inst, mode="drop"),
                   lo=jnp.where(opens[:, None], l_lo, refs.lo).at[slot].set(r_lo, mode="drop"),
                   hi=jnp.where(opens[:, None], l_hi, refs.hi).at[slot].set(r_hi, mode="drop"),
                   prims=jnp.where(opens, l_prims, refs.prims).at[slot].set(r_prims, mode="drop"))
    n_open = segment(jax.ops.segment_sum, opens.astype(i32), jnp.where(opens, seg, C), C)
    return opened, n_open


def _bin(refs: Refs, view: _View, seg_end, *, cap, bins) -> _Binned:
    """Step 4, binning over the BRefs of the split segments, and each one's best plane."""
    C = cap
    dtype = refs.lo.dtype
    inf = jnp.asarray(jnp.inf, dtype)
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = view.seg
    end = take(seg_end, seg, 0)
    is_ref = view.in_live & (pos < end) & take(view.split, seg, False)
    sid = jnp.where(is_ref, seg, C)
    count = jnp.where(view.split, segment(jax.ops.segment_sum, is_ref.astype(jnp.int32), sid, C), view.count)
    centre = 0.5 * refs.lo + 0.5 * refs.hi
    c_min = segment(jax.ops.segment_min, jnp.where(is_ref[:, None], centre, inf), sid, C)
    c_max = segment(jax.ops.segment_max, jnp.where(is_ref[:, None], centre, -inf), sid, C)
    span = c_max - c_min
    span_p = take(span, seg, 0)
    low_p = take(c_min, seg, 0)
    nb = jnp.asarray(bins, dtype)
    raw = jnp.floor((centre - low_p) * nb / jnp.where(span_p > 0, span_p, 1))
    bin_p = jnp.where(span_p > 0, jnp.clip(raw, 0, nb - 1), 0).astype(jnp.int32)  # [C, 3]
    best, best_key = best_planes(sid, bin_p, refs.lo, refs.hi, refs.prims, bins=bins, cap=C)
    return _Binned(is_ref=is_ref, sid=sid, count=count, bin_p=bin_p, found=best < inf,
                   axis=best_key // bins, plane=best_key % bins)


def _partition(forest, refs: Refs, view: _View, b: _Binned, seg_end, extra, threshold, *, cap) -> _Halves:
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
    n_left = segment(jax.ops.segment_sum, goes_left.astype(i32), b.sid, C)
    n_right = b.count - n_left
    rank_left = exclusive_rank(goes_left, jnp.minimum(seg, C - 1))
    spare = jnp.maximum(extra - seg_end, 0)

    def share_of_spare():  # the spare room goes in proportion to the BRefs that would open in each half
        key2 = jnp.where(b.is_ref, 2 * seg + jnp.where(goes_left, 0, 1), 2 * C)
        ch_lo = segment(jax.ops.segment_min, lo, key2, 2 * C).reshape(C, 2, 3)
        ch_hi = segment(jax.ops.segment_max, hi, key2, 2 * C).reshape(C, 2, 3)
        ch_ext = ch_hi - ch_lo
        ch_dim = jnp.argmax(ch_ext, axis=2).astype(i32)
        ch_ext_dim = jnp.take_along_axis(ch_ext, ch_dim[..., None], axis=2)[..., 0]
        k2 = jnp.minimum(key2, 2 * C - 1)
        d2 = ch_dim.reshape(-1)[k2]
        w2 = (jnp.take_along_axis(hi, d2[:, None], axis=1) - jnp.take_along_axis(lo, d2[:, None], axis=1))[:, 0]
        meets = b.is_ref & _interior(forest, refs.node) & (w2 > threshold * ch_ext_dim.reshape(-1)[k2])
        weight = segment(jax.ops.segment_sum, meets.astype(i32), key2, 2 * C).reshape(C, 2)
        none = weight.sum(axis=1) == 0
        w_l = jnp.where(none, n_left, weight[:, 0])
        w_r = jnp.where(none, n_right, weight[:, 1])
        f32 = jnp.float32
        share = jnp.floor(w_l.astype(f32) / jnp.maximum(w_l + w_r, 1).astype(f32) * spare.astype(f32))
        return jnp.minimum(share.astype(i32), spare)

    # no room anywhere (every level below the opening ones): the share is 0, skip computing it
    spare_l = jax.lax.cond(jnp.any(view.split & (spare > 0)), share_of_spare, lambda: jnp.zeros(C, i32))
    return _Halves(goes_left=goes_left, rank_left=rank_left, rank_right=offset - rank_left, n_left=n_left,
                   n_right=n_right, right_start=pos + n_left + spare_l)


def _move(refs: Refs, view: _View, b: _Binned, h: _Halves, extra, *, cap):
    """Move the BRefs of split segments into their halves; returns the BRefs and the
    next level's segment of every slot."""
    C = cap
    dtype = refs.lo.dtype
    pos = jnp.arange(C, dtype=jnp.int32)
    seg = view.seg
    new_pos = jnp.where(h.goes_left, seg + h.rank_left, take(h.right_start, seg, 0) + h.rank_right)
    target = jnp.where(refs.node >= 0, jnp.where(b.is_ref, new_pos, pos), C)
    empty_i = jnp.full(C, -1, jnp.int32)
    moved = Refs(node=empty_i.at[target].set(refs.node, mode="drop"),
                  inst=empty_i.at[target].set(refs.inst, mode="drop"),
                  lo=jnp.full((C, 3), jnp.inf, dtype).at[target].set(refs.lo, mode="drop"),
                  hi=jnp.full((C, 3), -jnp.inf, dtype).at[target].set(refs.hi, mode="drop"),
                  prims=jnp.zeros(C, jnp.int32).at[target].set(refs.prims, mode="drop"))
    rs_p = take(h.right_start, seg, C)
    split_p = take(view.split, seg, False)
    seg_of = jnp.where(split_p, jnp.where(pos < rs_p, seg, jnp.where(pos < take(extra, seg, 0), rs_p, C)), C)
    return moved, jnp.where(view.in_live, seg_of, C).astype(jnp.int32)


def _grow(s: Build, view: _View, b: _Binned, h: _Halves, extra, *, cap):
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

    segs = Segments(of=s.segs.of, end=halves(pos + h.n_left, h.right_start + h.n_right, 0, i32),
                     extra=halves(h.right_start, extra, 0, i32), node=halves(left_id, right_id, 0, i32),
                     live=halves(True, True, False, bool))
    t, node_ids = s.top, s.segs.node
    split_at = jnp.where(split_seg, nid, M)
    leaf_at = jnp.where(leaf_seg, nid, M)
    top = TopTree(left=t.left.at[split_at].set(left_id, mode="drop"),
                   right=t.right.at[split_at].set(right_id, mode="drop"),
                   parent=t.parent.at[left_id].set(node_ids, mode="drop").at[right_id].set(node_ids, mode="drop"),
                   axis=t.axis.at[split_at].set(jnp.where(b.found, b.axis, -1), mode="drop"),
                   prim_start=t.prim_start.at[leaf_at].set(pos, mode="drop"),
                   prim_count=t.prim_count.at[leaf_at].set(1, mode="drop"),
                   lo=t.lo.at[nid].set(view.lo, mode="drop"), hi=t.hi.at[nid].set(view.hi, mode="drop"))
    return segs, top, s.next_free + 2 * jnp.sum(split_seg, dtype=i32)
