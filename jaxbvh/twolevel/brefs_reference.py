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

import numpy as np

from jaxbvh.numerics import TIE_TOLERANCE, half_area
from jaxbvh.tree.layout import BVH

SMALL_SEGMENT = 4


def world_box(lo, hi, to_scene, margin):
    """Scene-frame box of one object-frame box: Arvo's per-axis min/max, widened (see jaxbvh.forest)."""
    dtype = lo.dtype
    out_lo = np.empty(3, dtype)
    out_hi = np.empty(3, dtype)
    for i in range(3):
        a = to_scene[i, :3] * lo
        b = to_scene[i, :3] * hi
        low, high = np.minimum(a, b), np.maximum(a, b)
        size = np.maximum(np.abs(a), np.abs(b))
        t = to_scene[i, 3]
        out_lo[i] = ((t + low[0]) + low[1]) + low[2]
        out_hi[i] = ((t + high[0]) + high[1]) + high[2]
        if margin > 0:
            scale = ((np.abs(t) + size[0]) + size[1]) + size[2]
            widen = margin * scale + np.finfo(dtype).tiny
            out_lo[i] -= widen
            out_hi[i] += widen
    return out_lo, out_hi



def build_top_level(forest, instances, n_instances, *, threshold=0.1, slots=None, bins=16,
                    overlap=0.1, estimate=False):
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
    node = np.full(slots, -1, np.int64)
    inst = np.full(slots, -1, np.int64)
    lo = np.full((slots, 3), np.inf, dtype)
    hi = np.full((slots, 3), -np.inf, dtype)
    prims = np.zeros(slots, np.int64)

    def bref(n, i):
        box_lo, box_hi = world_box(f.lo[n], f.hi[n], instances.to_scene[i], instances.margin[i])
        return box_lo, box_hi

    for i in range(n_instances):
        n = int(f.root[instances.object[i]])
        node[i], inst[i] = n, i
        lo[i], hi[i] = bref(n, i)
        prims[i] = f.subtree_prims[n]

    def is_interior(n):
        return f.left[n] >= 0

    def wide(p, box_lo, box_hi):
        ext = box_hi - box_lo
        dim = int(np.argmax(ext))
        # threshold = inf never opens (and inf * a zero extent would be NaN)
        return bool(np.isfinite(threshold)) and bool((hi[p, dim] - lo[p, dim]) > threshold * ext[dim])

    left, right, parent, axis, top_lo, top_hi, leaf_slot = [], [], [], [], [], [], []

    def new_node(par):
        for arr, v in ((left, -1), (right, -1), (parent, par), (axis, -1), (leaf_slot, -1)):
            arr.append(v)
        top_lo.append(None)
        top_hi.append(None)
        return len(left) - 1

    stack = [(new_node(-1), 0, n_instances, slots)]
    while stack:
        t, start, end, extra = stack.pop()
        ids = np.arange(start, end)
        box_lo, box_hi = lo[ids].min(0), hi[ids].max(0)
        top_lo[t], top_hi[t] = box_lo, box_hi
        if end - start == 1:
            leaf_slot[t] = start
            continue

        # termination of opening
        if extra > end:
            if len(set(inst[ids].tolist())) == 1:
                extra = end
            elif end - start <= SMALL_SEGMENT:
                overlapping = False
                for a in ids:
                    for b in ids:
                        if a == b:
                            continue
                        shorter = np.minimum(hi[a] - lo[a], hi[b] - lo[b])
                        shared = np.minimum(hi[a], hi[b]) - np.maximum(lo[a], lo[b])
                        if np.all(shared >= overlap * shorter):
                            overlapping = True
                if not overlapping:
                    extra = end

        # opening: all candidates or none
        if extra > end:
            candidates = [p for p in ids if is_interior(node[p]) and wide(p, box_lo, box_hi)]
            if 0 < len(candidates) <= extra - end:
                for k, p in enumerate(candidates):
                    n, i, slot = node[p], inst[p], end + k
                    kid_l, kid_r = int(f.left[n]), int(f.right[n])
                    if estimate:
                        count_l = count_r = max(prims[p] // 2, 1)
                    else:
                        count_l, count_r = f.subtree_prims[kid_l], f.subtree_prims[kid_r]
                    node[slot], inst[slot], prims[slot] = kid_r, i, count_r
                    lo[slot], hi[slot] = bref(kid_r, i)
                    node[p], prims[p] = kid_l, count_l
                    lo[p], hi[p] = bref(kid_l, i)
                end += len(candidates)
                ids = np.arange(start, end)

        # binning: bins count primitives
        centre = dtype.type(0.5) * lo[ids] + dtype.type(0.5) * hi[ids]
        c_min, c_max = centre.min(0), centre.max(0)
        best = None  # (cost, axis, plane, bin of each BRef on that axis)
        candidates = []
        for a in range(3):
            span = c_max[a] - c_min[a]
            if not span > 0:
                continue
            raw = np.floor((centre[:, a] - c_min[a]) * dtype.type(bins) / span)
            b = np.clip(raw, 0, bins - 1).astype(np.int64)
            for plane in range(bins - 1):
                on_left = b <= plane
                if on_left.all() or not on_left.any():
                    continue
                l_ids, r_ids = ids[on_left], ids[~on_left]
                cost = (half_area(lo[l_ids].min(0), hi[l_ids].max(0)) * dtype.type(prims[l_ids].sum())
                        + half_area(lo[r_ids].min(0), hi[r_ids].max(0)) * dtype.type(prims[r_ids].sum()))
                candidates.append((cost, a, plane, b))
        if candidates:
            least = min(c[0] for c in candidates)
            near = least * dtype.type(1 + TIE_TOLERANCE)
            best = next(c for c in candidates if c[0] <= near)
            goes_left = best[3] <= best[2]
            axis[t] = best[1]
        else:
            goes_left = np.arange(len(ids)) < len(ids) // 2

        # stable partition and spare split
        l_ids, r_ids = ids[goes_left], ids[~goes_left]
        weights = []
        for side in (l_ids, r_ids):
            side_lo, side_hi = lo[side].min(0), hi[side].max(0)
            weights.append(sum(1 for p in side if is_interior(node[p]) and wide(p, side_lo, side_hi)))
        if sum(weights) == 0:
            weights = [len(l_ids), len(r_ids)]
        spare = extra - end
        share = np.floor(np.float32(weights[0]) / np.float32(sum(weights)) * np.float32(spare))
        spare_l = min(int(share), spare)
        fields = [node, inst, lo, hi, prims]
        saved = [a[np.concatenate([l_ids, r_ids])].copy() for a in fields]
        for a, fill in zip(fields, (-1, -1, np.inf, -np.inf, 0)):
            a[start:extra] = fill
        n_l = len(l_ids)
        right_start = start + n_l + spare_l
        for a, v in zip(fields, saved):
            a[start:start + n_l] = v[:n_l]
            a[right_start:right_start + len(r_ids)] = v[n_l:]
        kid_l, kid_r = new_node(t), new_node(t)
        left[t], right[t] = kid_l, kid_r
        stack.append((kid_r, right_start, right_start + len(r_ids), extra))
        stack.append((kid_l, start, start + n_l, right_start))

    leaf = np.asarray(leaf_slot) >= 0
    n_leaves = int(leaf.sum())
    order = np.flatnonzero(leaf)
    prim_start = np.zeros(len(left), np.int32)
    prim_start[order] = np.arange(n_leaves)
    i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
    top = BVH(left=i32(left), right=i32(right), parent=i32(parent), lo=np.stack(top_lo).astype(dtype),
              hi=np.stack(top_hi).astype(dtype), prim_start=prim_start, prim_count=i32(leaf),
              axis=i32(axis), prim_index=i32(np.asarray(leaf_slot)[order]), root=np.int32(0))
    brefs = dict(node=node.astype(np.int32), instance=inst.astype(np.int32), lo=lo, hi=hi,
                 prims=prims.astype(np.int32))
    return top, brefs
