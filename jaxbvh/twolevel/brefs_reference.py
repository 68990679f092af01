"""Sequential NumPy twin of :mod:`jaxbvh.twolevel.brefs`: the re-braiding top-level build, recursively.

One segment at a time, as the paper describes it (an explicit stack stands in for the
recursion): the BRef array is one NumPy array per field, segments are ``(start, end,
extra)`` triples, opening appends right children after ``end``, the partition writes the
two halves back in place with the spare room between them. Every rule (termination,
opening, binning, tie-breaking, stable partition, spare split) is the one
:mod:`jaxbvh.twolevel.brefs` documents, computed in the boxes' dtype with the same expressions,
so both put every BRef in the same slot. Top-level nodes come out in depth-first order,
root 0, unpadded.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxbvh.builders.binning_rules import binned_split
from jaxbvh.tree.layout import BVH

SMALL_SEGMENT = 4


@dataclasses.dataclass
class _BRefArray:
    """The BRef array, one NumPy array per field, by slot (changed in place)."""

    node: np.ndarray   # int64 [slots]: forest node, -1 empty
    inst: np.ndarray   # int64 [slots]: instance, -1 empty
    lo: np.ndarray     # float [slots, 3]: scene-frame box (empty: inf)
    hi: np.ndarray     # float [slots, 3] (empty: -inf)
    prims: np.ndarray  # int64 [slots]: primitive count

    FILL = (-1, -1, np.inf, -np.inf, 0)  # empty slot, field by field

    def fields(self):
        return [self.node, self.inst, self.lo, self.hi, self.prims]


@dataclasses.dataclass
class _TopNodes:
    """The top-level tree as it grows, one Python list per field, depth-first ids."""

    left: list = dataclasses.field(default_factory=list)
    right: list = dataclasses.field(default_factory=list)
    parent: list = dataclasses.field(default_factory=list)
    axis: list = dataclasses.field(default_factory=list)       # split axis, -1 none
    lo: list = dataclasses.field(default_factory=list)         # node box
    hi: list = dataclasses.field(default_factory=list)
    leaf_slot: list = dataclasses.field(default_factory=list)  # a leaf's BRef slot, -1 interior

    def new_node(self, parent):
        for field, value in ((self.left, -1), (self.right, -1), (self.parent, parent), (self.axis, -1),
                             (self.leaf_slot, -1), (self.lo, None), (self.hi, None)):
            field.append(value)
        return len(self.left) - 1


def build_top_level(forest, instances, n_instances, *, threshold=0.1, slots=None, bins=16,
                    overlap=0.1, estimate=False, rounds=64):
    """Reference top-level build over the first ``n_instances`` instances.

    ``forest``, ``instances``: :func:`jaxbvh.twolevel.objects.pack` output (NumPy); ``slots``: size
    of the BRef array (:func:`jaxbvh.twolevel.brefs.brefs_capacity`). Returns ``(top, brefs)``:
    ``top`` an unpadded :class:`~jaxbvh.tree.layout.BVH` whose leaves hold one entry each, the
    *slot* of their BRef; ``brefs`` a dict of the BRef array by slot (``node``,
    ``instance``, ``lo``, ``hi``, ``prims``; empty slots: -1, the empty box, 0).
    """
    f = forest
    dtype = np.asarray(f.lo).dtype
    threshold = dtype.type(threshold)
    overlap = dtype.type(overlap)
    slots = n_instances if slots is None else slots
    refs = _instances_brefs(f, instances, n_instances, slots, dtype)
    top = _TopNodes()
    stack = [(top.new_node(-1), 0, n_instances, slots)]
    while stack:
        t, start, end, extra = stack.pop()
        ids = np.arange(start, end)
        box_lo, box_hi = refs.lo[ids].min(0), refs.hi[ids].max(0)
        top.lo[t], top.hi[t] = box_lo, box_hi
        if end - start == 1:
            top.leaf_slot[t] = start
            continue
        if extra > end and _stops_opening(refs, ids, overlap):
            extra = end
        if extra > end:
            end = _open(refs, f, instances, start, end, extra, box_lo, box_hi, threshold, estimate, rounds)
            ids = np.arange(start, end)
        axis, goes_left = _best_split(refs, ids, bins, dtype)
        if axis is not None:
            top.axis[t] = axis
        l_ids, r_ids = ids[goes_left], ids[~goes_left]
        spare_l = _spare_left(refs, f, l_ids, r_ids, extra - end, threshold)
        right_start = start + len(l_ids) + spare_l
        _write_halves(refs, start, extra, l_ids, r_ids, right_start)
        kid_l, kid_r = top.new_node(t), top.new_node(t)
        top.left[t], top.right[t] = kid_l, kid_r
        stack.append((kid_r, right_start, right_start + len(r_ids), extra))
        stack.append((kid_l, start, start + len(l_ids), right_start))
    brefs = dict(node=refs.node.astype(np.int32), instance=refs.inst.astype(np.int32), lo=refs.lo, hi=refs.hi,
                 prims=refs.prims.astype(np.int32))
    return _to_bvh(top, dtype), brefs


def _bref_box(instances, n, i):
    """BRef box of forest node ``n`` under instance ``i``: its row of the placed nodes'
    world boxes (:func:`jaxbvh.twolevel.objects.pack` computes them once for both builds)."""
    row = n + int(instances.box_shift[i])
    return instances.world_lo[row].copy(), instances.world_hi[row].copy()


def _instances_brefs(f, instances, n_instances, slots, dtype) -> _BRefArray:
    """The BRef array with one BRef per instance (its object's root) at ``[0, n_instances)``."""
    refs = _BRefArray(node=np.full(slots, -1, np.int64), inst=np.full(slots, -1, np.int64),
                   lo=np.full((slots, 3), np.inf, dtype), hi=np.full((slots, 3), -np.inf, dtype),
                   prims=np.zeros(slots, np.int64))
    for i in range(n_instances):
        n = int(f.root[instances.object[i]])
        refs.node[i], refs.inst[i] = n, i
        refs.lo[i], refs.hi[i] = _bref_box(instances, n, i)
        refs.prims[i] = f.subtree_prims[n]
    return refs


def _is_interior(f, n):
    return f.left[n] >= 0


def _wide(refs, p, box_lo, box_hi, threshold):
    """BRef ``p`` is wider than ``threshold`` x the largest extent of the box, along that axis."""
    ext = box_hi - box_lo
    dim = int(np.argmax(ext))
    # threshold = inf never opens (and inf * a zero extent would be NaN)
    return bool(np.isfinite(threshold)) and bool((refs.hi[p, dim] - refs.lo[p, dim]) > threshold * ext[dim])


def _stops_opening(refs, ids, overlap) -> bool:
    """Termination of opening: one instance only, or <= 4 BRefs of which no two overlap."""
    if len(set(refs.inst[ids].tolist())) == 1:
        return True
    if len(ids) > SMALL_SEGMENT:
        return False
    for p in ids:
        for q in ids:
            if p == q:
                continue
            shorter = np.minimum(refs.hi[p] - refs.lo[p], refs.hi[q] - refs.lo[q])
            shared = np.minimum(refs.hi[p], refs.hi[q]) - np.maximum(refs.lo[p], refs.lo[q])
            if np.all(shared >= overlap * shorter):
                return False
    return True


def _open(refs, f, instances, start, end, extra, box_lo, box_hi, threshold, estimate, rounds) -> int:
    """Opening, round after round until no candidate is left, the room is full or
    ``rounds`` rounds are done. Returns the segment's new end."""
    for _ in range(min(rounds, extra - start)):
        new_end = _open_once(refs, f, instances, np.arange(start, end), end, extra, box_lo, box_hi, threshold,
                             estimate)
        if new_end == end:
            return end
        end = new_end
    return end


def _open_once(refs, f, instances, ids, end, extra, box_lo, box_hi, threshold, estimate) -> int:
    """One round of opening: the widest candidates that fit into the room (all of them if
    they fit; widths along the segment box's largest axis, ties to the lower slot); a
    candidate's slot takes its left child, its right child goes to ``end, end + 1, ...``
    in slot order. Returns the segment's new end."""
    candidates = [p for p in ids if _is_interior(f, refs.node[p]) and _wide(refs, p, box_lo, box_hi, threshold)]
    room = extra - end
    if room < len(candidates):
        dim = int(np.argmax(box_hi - box_lo))
        width = {p: refs.hi[p, dim] - refs.lo[p, dim] for p in candidates}
        candidates = sorted(sorted(candidates, key=lambda p: (-width[p], p))[:room])
    for k, p in enumerate(candidates):
        n, i, slot = refs.node[p], refs.inst[p], end + k
        kid_l, kid_r = int(f.left[n]), int(f.right[n])
        if estimate:
            count_l = count_r = max(refs.prims[p] // 2, 1)
        else:
            count_l, count_r = f.subtree_prims[kid_l], f.subtree_prims[kid_r]
        refs.node[slot], refs.inst[slot], refs.prims[slot] = kid_r, i, count_r
        refs.lo[slot], refs.hi[slot] = _bref_box(instances, kid_r, i)
        refs.node[p], refs.prims[p] = kid_l, count_l
        refs.lo[p], refs.hi[p] = _bref_box(instances, kid_l, i)
    return end + len(candidates)


def _best_split(refs, ids, bins, dtype):
    """Binning, bins counting primitives
    (:func:`~jaxbvh.builders.binning_rules.binned_split`, each BRef weighing its
    primitives): ``(axis, goes_left)`` of the cheapest plane (first within the tie
    tolerance), or ``(None, first half)`` without any plane."""
    lo, hi = refs.lo[ids], refs.hi[ids]
    centre = dtype.type(0.5) * lo + dtype.type(0.5) * hi
    split = binned_split(centre, lo, hi, refs.prims[ids], bins)
    if split is None:
        return None, np.arange(len(ids)) < len(ids) // 2
    _, axis, _, goes_left = split
    return axis, goes_left


def _spare_left(refs, f, l_ids, r_ids, spare, threshold) -> int:
    """The left half's share of the spare room: in proportion to the BRefs that would
    open in each half (measured against the half's own box), else to their numbers."""
    weights = []
    for side in (l_ids, r_ids):
        side_lo, side_hi = refs.lo[side].min(0), refs.hi[side].max(0)
        weights.append(sum(1 for p in side if _is_interior(f, refs.node[p]) and _wide(refs, p, side_lo, side_hi, threshold)))
    if sum(weights) == 0:
        weights = [len(l_ids), len(r_ids)]
    share = np.floor(np.float32(weights[0]) / np.float32(sum(weights)) * np.float32(spare))
    return min(int(share), spare)


def _write_halves(refs, start, extra, l_ids, r_ids, right_start) -> None:
    """Stable partition in place: the left half at ``start``, the right at ``right_start``,
    the rest of ``[start, extra)`` empty."""
    saved = [field[np.concatenate([l_ids, r_ids])].copy() for field in refs.fields()]
    for field, fill in zip(refs.fields(), _BRefArray.FILL):
        field[start:extra] = fill
    n_l = len(l_ids)
    for field, v in zip(refs.fields(), saved):
        field[start:start + n_l] = v[:n_l]
        field[right_start:right_start + len(r_ids)] = v[n_l:]


def _to_bvh(top: _TopNodes, dtype) -> BVH:
    """The unpadded top-level BVH; leaf ``j`` (in node order) holds its BRef's slot."""
    leaf = np.asarray(top.leaf_slot) >= 0
    n_leaves = int(leaf.sum())
    order = np.flatnonzero(leaf)
    prim_start = np.zeros(len(top.left), np.int32)
    prim_start[order] = np.arange(n_leaves)
    i32 = lambda v: np.asarray(v, np.int32)  # noqa: E731
    return BVH(left=i32(top.left), right=i32(top.right), parent=i32(top.parent),
               lo=np.stack(top.lo).astype(dtype), hi=np.stack(top.hi).astype(dtype), prim_start=prim_start,
               prim_count=i32(leaf), axis=i32(top.axis), prim_index=i32(np.asarray(top.leaf_slot)[order]),
               root=np.int32(0))
