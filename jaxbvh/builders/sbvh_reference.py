"""Sequential NumPy twin of :mod:`jaxbvh.builders.sbvh`: one node at a time, as the paper says.

Stich, Friedrich & Dietrich 2009, node by node: the best binned object split; where its
children overlap, the best binned spatial split with reference unsplitting; the SAH leaf
test. The rules (bins, planes, tie rule, unsplitting, leaf test, reference capacity) are
those written at the top of :mod:`jaxbvh.builders.sbvh`, with the same expressions, so on
the same input both give the same tree up to node numbering and the order inside a leaf.

A first-in first-out queue stands in for recursion: nodes are then taken level by level
in the order the JAX engine numbers them, which is the order in which it grants
reference slots when the capacity runs short (a stack would grant them depth first).
Nodes come out in that order, root 0, unpadded.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

from jaxbvh.builders import sbvh_rules as rules
from jaxbvh.builders.binning_rules import binned_split
from jaxbvh.builders.node_list_rules import NodeList
from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale
from jaxbvh.tree.layout import BVH


class ReferenceBuild(NamedTuple):
    """The twin's result: the tree (unpadded, NumPy), references used, spatial splits
    taken, and whether a spatial split was refused for want of reference slots."""

    tree: BVH
    references: int
    spatial_splits: int
    out_of_capacity: bool


class _Refs(NamedTuple):
    """A node's references: triangle ids [m] and boxes [m, 3], sorted by id."""

    prim: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def take(self, mask):
        return _Refs(self.prim[mask], self.lo[mask], self.hi[mask])


def _union(lo, hi):
    return lo.min(0), hi.max(0)


def _overlap_area(a_lo, a_hi, b_lo, b_hi, scale):
    """Half-area of the intersection of two boxes, 0 when they do not meet."""
    lo, hi = np.maximum(a_lo, b_lo), np.minimum(a_hi, b_hi)
    return half_area(lo, hi, scale) if (lo <= hi).all() else lo.dtype.type(0)


def _object_split(refs: _Refs, scale, bins):
    """Binned object split over the reference boxes' centres (the binned builder's rule,
    :func:`~jaxbvh.builders.binning_rules.binned_split`, one primitive per reference):
    ``(cost, axis, plane, goes_left [m])`` or None without a plane."""
    dt = refs.lo.dtype
    centre = dt.type(0.5) * refs.lo + dt.type(0.5) * refs.hi
    return binned_split(centre, refs.lo, refs.hi, np.ones(len(refs.lo), np.int64), bins, scale)


class _Spatial(NamedTuple):
    cost: float
    axis: int
    plane: int              # k: the plane between bins k and k + 1
    left_lo: np.ndarray     # [3] the estimated boxes of both sides (bin boxes)
    left_hi: np.ndarray
    right_lo: np.ndarray
    right_hi: np.ndarray
    n_left: int             # references entering a bin <= k, leaving a bin > k
    n_right: int
    entry: np.ndarray       # [m] entry and exit bins of the references on the axis
    exit: np.ndarray


def _bin_boxes(tri, refs: _Refs, axis, node_lo, ext, bins):
    """Estimated box [B, 3] (lo, hi) of the triangles' pieces in each spatial bin: the
    reference's corners (clamped to its box) in their bins, and the crossings of the
    inner planes its box spans (clamped), in the bins on both sides."""
    dt = refs.lo.dtype
    inf = dt.type(np.inf)
    box_lo = np.full((bins, 3), inf, dt)
    box_hi = np.full((bins, 3), -inf, dt)
    mask = np.arange(3) == axis
    for r in range(len(refs.prim)):
        t = tri[refs.prim[r]]
        b0 = int(rules.bin_of(refs.lo[r, axis], node_lo[axis], ext, bins))
        b1 = int(rules.bin_of(refs.hi[r, axis], node_lo[axis], ext, bins))
        for v in range(3):
            point = np.clip(t[v], refs.lo[r], refs.hi[r])
            b = int(rules.bin_of(point[axis], node_lo[axis], ext, bins))
            box_lo[b] = np.minimum(box_lo[b], point)
            box_hi[b] = np.maximum(box_hi[b], point)
        for j in range(b0 + 1, b1 + 1):  # inner planes between the reference's bins
            plane = rules.plane_at(node_lo[axis], ext, j, bins)
            x_lo, x_hi, crosses = rules.crossings(t, mask, np.asarray(plane, dt))
            if not crosses.any():
                continue
            c_lo = np.clip(x_lo[crosses].min(0), refs.lo[r], refs.hi[r])
            c_hi = np.clip(x_hi[crosses].max(0), refs.lo[r], refs.hi[r])
            for b in (j - 1, j):
                box_lo[b] = np.minimum(box_lo[b], c_lo)
                box_hi[b] = np.maximum(box_hi[b], c_hi)
    return box_lo, box_hi


def _spatial_split(tri, refs: _Refs, node_lo, node_hi, scale, bins):
    """Best binned spatial split (same tie rule as the object split): a :class:`_Spatial` or None."""
    dt = refs.lo.dtype
    candidates = []
    for axis in range(3):
        ext = node_hi[axis] - node_lo[axis]
        if not ext > 0:
            continue
        entry = np.array([rules.bin_of(x, node_lo[axis], ext, bins) for x in refs.lo[:, axis]], np.int64)
        exit_ = np.array([rules.bin_of(x, node_lo[axis], ext, bins) for x in refs.hi[:, axis]], np.int64)
        box_lo, box_hi = _bin_boxes(tri, refs, axis, node_lo, ext, bins)
        for k in range(bins - 1):
            n_left, n_right = int((entry <= k).sum()), int((exit_ > k).sum())
            if n_left == 0 or n_right == 0 or not rules.separates(n_left, n_right, len(refs.prim)):
                continue
            l_lo, l_hi = _union(box_lo[: k + 1], box_hi[: k + 1])
            r_lo, r_hi = _union(box_lo[k + 1:], box_hi[k + 1:])
            cost = half_area(l_lo, l_hi, scale) * dt.type(n_left) + half_area(r_lo, r_hi, scale) * dt.type(n_right)
            candidates.append(_Spatial(cost, axis, k, l_lo, l_hi, r_lo, r_hi, n_left, n_right, entry, exit_))
    if not candidates:
        return None
    best = min(c.cost for c in candidates)
    near = best * dt.type(1 + TIE_TOLERANCE)
    return next(c for c in candidates if c.cost <= near)._replace(cost=best)


def _spatial_sides(tri, refs: _Refs, s: _Spatial, node_lo, node_hi, scale, bins):
    """Where each reference goes under spatial split ``s``: ``(extra, left_refs, right_refs)``
    or None when a side would be empty (then the node takes its object split).

    Straddlers are clipped to both half-spaces. One whose piece on a side is empty (the
    plane in its box's widening) goes whole to the other side; the others are unsplit
    where that is cheaper (the paper's rule, each reference priced on its own against
    the split's totals), unless unsplitting would empty a side. ``extra``: references
    kept on both sides (the new slots the split takes).
    """
    dt = refs.lo.dtype
    axis = s.axis
    straddle = (s.entry <= s.plane) & (s.exit > s.plane)
    to_left = s.exit <= s.plane
    to_right = s.entry > s.plane
    mask = np.arange(3) == axis
    plane = np.asarray(rules.plane_at(node_lo[axis], node_hi[axis] - node_lo[axis], s.plane + 1, bins), dt)
    a_l, a_r = half_area(s.left_lo, s.left_hi, scale), half_area(s.right_lo, s.right_hi, scale)
    n_l, n_r = dt.type(s.n_left), dt.type(s.n_right)
    c_split = a_l * n_l + a_r * n_r
    one = dt.type(1)
    m = len(refs.prim)
    forced_left, forced_right = np.zeros(m, bool), np.zeros(m, bool)
    cheap_left, cheap_right = np.zeros(m, bool), np.zeros(m, bool)
    clip = {}
    for r in np.flatnonzero(straddle):
        t = tri[refs.prim[r]]
        lo_l, hi_l = rules.halfspace_box(t, mask, plane, np.bool_(True), refs.lo[r], refs.hi[r])
        lo_r, hi_r = rules.halfspace_box(t, mask, plane, np.bool_(False), refs.lo[r], refs.hi[r])
        clip[r] = (lo_l, hi_l, lo_r, hi_r)
        forced_right[r] = bool((lo_l > hi_l).any())
        forced_left[r] = bool((lo_r > hi_r).any()) and not forced_right[r]
        c_left = half_area(np.minimum(s.left_lo, refs.lo[r]), np.maximum(s.left_hi, refs.hi[r]), scale) * n_l \
            + a_r * (n_r - one)
        c_right = a_l * (n_l - one) \
            + half_area(np.minimum(s.right_lo, refs.lo[r]), np.maximum(s.right_hi, refs.hi[r]), scale) * n_r
        left_wins = bool(c_left * dt.type(1 + TIE_TOLERANCE) < c_split)
        right_wins = bool(c_right * dt.type(1 + TIE_TOLERANCE) < c_split)
        cheap_left[r] = left_wins and bool(c_left <= c_right)
        cheap_right[r] = right_wins and not cheap_left[r]
    forced = forced_left | forced_right
    cheap_left &= ~forced
    cheap_right &= ~forced

    def sides(only_left, only_right):
        return to_left | (straddle & ~only_right), to_right | (straddle & ~only_left)

    go_left, go_right = sides(forced_left | cheap_left, forced_right | cheap_right)
    if not go_left.any() or not go_right.any():
        go_left, go_right = sides(forced_left, forced_right)
        if not go_left.any() or not go_right.any():
            return None
        cheap_left[:], cheap_right[:] = False, False
    keep_split = go_left & go_right
    left_ids, right_ids = np.flatnonzero(go_left), np.flatnonzero(go_right)
    left_lo, left_hi = refs.lo[left_ids].copy(), refs.hi[left_ids].copy()
    right_lo, right_hi = refs.lo[right_ids].copy(), refs.hi[right_ids].copy()
    for i, r in enumerate(left_ids):
        if keep_split[r]:
            left_lo[i], left_hi[i] = clip[r][0], clip[r][1]
    for i, r in enumerate(right_ids):
        if keep_split[r]:
            right_lo[i], right_hi[i] = clip[r][2], clip[r][3]
    return (int(keep_split.sum()), _Refs(refs.prim[left_ids], left_lo, left_hi),
            _Refs(refs.prim[right_ids], right_lo, right_hi))


def _is_leaf(count, best, area, max_leaf, ct, ci, dt) -> bool:
    """The top-down builders' SAH leaf test (``best`` None: no split found)."""
    if count <= 1:
        return True
    if count > max_leaf:
        return False
    if best is None:
        return True
    estimate = ct + (ci * best / area if area > 0 else ci * dt.type(count))
    return bool(ci * dt.type(count) <= estimate * dt.type(1 + TIE_TOLERANCE))


def build(triangles, config, capacity: int | None = None) -> ReferenceBuild:
    """Reference SBVH of ``triangles`` [n, 3, 3] (computed in their dtype) under ``config``
    (an :class:`~jaxbvh.builders.configs.SBVHConfig`, read for its knobs only).

    ``capacity``: reference slots (default ``ceil(reference_capacity * n)``).
    """
    tri = np.asarray(triangles)
    dt = tri.dtype
    n = tri.shape[0]
    cap = int(capacity) if capacity is not None else int(np.ceil(config.reference_capacity * n))
    bins = config.bins
    ct, ci = dt.type(config.ct), dt.type(config.ci)
    lo, hi = tri.min(1), tri.max(1)
    scale = dt.type(scene_scale(lo, hi))
    threshold = dt.type(config.alpha) * half_area(lo.min(0), hi.max(0), scale)

    nodes = NodeList()
    queue = deque([(nodes.new(-1), 0, _Refs(np.arange(n), lo, hi))])
    total, spatial_count, out_of_capacity = n, 0, False
    level, room, asked = -1, 0, 0  # reference slots free at the level's start, asked for on it
    while queue:
        node, depth, refs = queue.popleft()
        if depth != level:
            level, room, asked = depth, cap - total, 0
        box_lo, box_hi = _union(refs.lo, refs.hi)
        nodes.lo[node], nodes.hi[node] = box_lo, box_hi
        count = len(refs.prim)
        obj = _object_split(refs, scale, bins) if count > 1 else None
        spatial = None
        spatial_bins = int(rules.spatial_bins(count, config.spatial_bins))  # fewer for a node of few references
        if obj is not None:
            left = obj[3]
            overlap = _overlap_area(*_union(refs.lo[left], refs.hi[left]),
                                    *_union(refs.lo[~left], refs.hi[~left]), scale)
            if overlap > threshold:
                spatial = _spatial_split(tri, refs, box_lo, box_hi, scale, spatial_bins)
        if spatial is not None and not spatial.cost * dt.type(1 + TIE_TOLERANCE) < obj[0]:
            spatial = None
        best = spatial.cost if spatial is not None else (obj[0] if obj is not None else None)
        if _is_leaf(count, best, half_area(box_lo, box_hi, scale), config.max_leaf, ct, ci, dt):
            nodes.make_leaf(node, refs.prim)
            continue
        children = None
        sides = (_spatial_sides(tri, refs, spatial, box_lo, box_hi, scale, spatial_bins) if spatial is not None
                 else None)
        if sides is not None:
            extra, left_refs, right_refs = sides
            asked += extra
            if asked <= room:
                children, axis = (left_refs, right_refs), spatial.axis
                total += extra
                spatial_count += 1
            else:
                out_of_capacity = True
        if children is None and obj is not None:
            children, axis = (refs.take(obj[3]), refs.take(~obj[3])), obj[1]
        elif children is None:  # every centre in one point: halves by triangle id (refs are sorted)
            half = np.arange(count) < count // 2
            children, axis = (refs.take(half), refs.take(~half)), 0
        nodes.axis[node] = axis
        l_id, r_id = nodes.new(node), nodes.new(node)
        nodes.left[node], nodes.right[node] = l_id, r_id
        queue.append((l_id, depth + 1, children[0]))
        queue.append((r_id, depth + 1, children[1]))
    return ReferenceBuild(nodes.to_bvh(dt), total, spatial_count, out_of_capacity)
