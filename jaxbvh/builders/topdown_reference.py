"""Sequential NumPy twin of :mod:`jaxbvh.builders.topdown`: one node at a time, as the papers say.

Recursive top-down construction (an explicit stack stands in for recursion so deep
trees do not hit Python's limit). The split rules, tie rule and leaf test are those of
:mod:`jaxbvh.builders.topdown`, and every quantity is computed in the boxes' own dtype with the
same expressions, so on inputs without ties both produce the same tree (up to node
numbering and the order of primitives inside a leaf). Nodes come out in depth-first
order, root 0, unpadded.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.builders import lbvh_reference as lbvh
from jaxbvh.builders import ploc_reference as ploc
from jaxbvh.builders.binning_rules import binned_split
from jaxbvh.builders.node_list_rules import NodeList
from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale
from jaxbvh.tree.layout import BVH


def sweep_candidates(ids, lo, hi, centre, scale):
    """Every split of the full sweep over all axes: ``(cost, tie code, axis, left ids,
    right ids)``, cost ``A_L N_L + A_R N_R``, code ``(|2 N_L - N| * 2 + (2 N_L > N)) * 3 +
    axis`` (nearest the middle, the smaller left side first, then the lowest axis)."""
    dtype = lo.dtype
    n = len(ids)
    candidates = []
    for axis in range(3):
        order = ids[np.lexsort((ids, centre[ids, axis]))]
        # forward sweep: box of the first k primitives
        left_area = np.empty(n, dtype)
        box_lo, box_hi = lo[order[0]].copy(), hi[order[0]].copy()
        for i in range(n):
            box_lo = np.minimum(box_lo, lo[order[i]])
            box_hi = np.maximum(box_hi, hi[order[i]])
            left_area[i] = half_area(box_lo, box_hi, scale)
        # backward sweep: box of the primitives from i on
        right_area = np.empty(n, dtype)
        box_lo, box_hi = lo[order[-1]].copy(), hi[order[-1]].copy()
        for i in range(n - 1, -1, -1):
            box_lo = np.minimum(box_lo, lo[order[i]])
            box_hi = np.maximum(box_hi, hi[order[i]])
            right_area[i] = half_area(box_lo, box_hi, scale)
        for k in range(1, n):
            cost = left_area[k - 1] * dtype.type(k) + right_area[k] * dtype.type(n - k)
            tie = (abs(2 * k - n) * 2 + (2 * k > n)) * 3 + axis
            candidates.append((cost, tie, axis, order[:k], order[k:]))
    return candidates


def tie_winner(candidates):
    """The tie rule: least cost, then the least code among costs within ``TIE_TOLERANCE``."""
    best = min(c[0] for c in candidates)
    near = best * type(best)(1 + TIE_TOLERANCE)
    return min((c for c in candidates if c[0] <= near), key=lambda c: c[1])


def _sweep_split(ids, lo, hi, centre, scale):
    """Full sweep over all axes; returns (cost, axis, left ids, right ids)."""
    candidates = sweep_candidates(ids, lo, hi, centre, scale)
    _, _, axis, left, right = tie_winner(candidates)
    return min(c[0] for c in candidates), axis, left, right


def _binned_split(ids, lo, hi, centre, scale, bins):
    """Wald's binned SAH (:func:`~jaxbvh.builders.binning_rules.binned_split`, one
    primitive per row); returns (cost, axis, left, right) or None without a plane."""
    split = binned_split(centre[ids], lo[ids], hi[ids], np.ones(len(ids), np.int64), bins, scale)
    if split is None:
        return None
    cost, axis, _, left = split
    return cost, axis, ids[left], ids[~left]


def _node_split(config, ids, lo, hi, centre, scale, box_lo, box_hi):
    """The split the method picks for a node over ``ids`` (its box ``box_lo``,
    ``box_hi``): ``(cost or None, axis, left ids, right ids)``, or None without one.

    The cost is ``A_L N_L + A_R N_R`` for the SAH methods; None for the median and for
    the binned builder's fallback (no plane: the first half by id goes left).
    """
    method = config.method
    count = len(ids)
    if count <= 1:
        return None
    if method == "sweep":
        return _sweep_split(ids, lo, hi, centre, scale)
    if method == "binned":
        split = _binned_split(ids, lo, hi, centre, scale, config.bins)
        if split is None and count > config.max_leaf:
            ordered = np.sort(ids)
            split = (None, 0, ordered[: count // 2], ordered[count // 2:])
        return split
    if method == "median":
        axis = int(np.argmax(box_hi - box_lo))
        ordered = ids[np.lexsort((ids, centre[ids, axis]))]
        return (None, axis, ordered[: count // 2], ordered[count // 2:])
    raise ValueError(f"unknown builder {method!r}")


def _is_leaf(config, split, count, area, ct, ci, dtype) -> bool:
    """The leaf test: no split, or ``count <= max_leaf`` and the split does not pay
    (the median, and a split without a cost, never pay; an SAH split pays when
    ``Ci N > (Ct + Ci cost / A) (1 + TIE_TOLERANCE)``, ``Ct + Ci N`` for ``A = 0``)."""
    if split is None:
        return True
    if count > config.max_leaf:
        return False
    if config.method == "median" or split[0] is None:
        return True
    estimate = ct + (ci * split[0] / area if area > 0 else ci * dtype.type(count))
    return bool(ci * dtype.type(count) <= estimate * dtype.type(1 + TIE_TOLERANCE))


def build(prim_lo, prim_hi, config) -> BVH:
    """Reference build of ``config`` (a builder Config of :mod:`jaxbvh.builders.configs`, read
    for its ``method`` and knobs only), boxes used in their dtype.

    Returns an unpadded NumPy :class:`~jaxbvh.tree.layout.BVH` in depth-first order. The
    bottom-up builders have twins of their own (:mod:`jaxbvh.builders.lbvh_reference`,
    :mod:`jaxbvh.builders.ploc_reference`), which this dispatches to.
    """
    if config.method == "lbvh":
        return lbvh.build(prim_lo, prim_hi, config)
    if config.method == "ploc":
        return ploc.build(prim_lo, prim_hi, config)
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    dtype = lo.dtype
    ct, ci = dtype.type(config.ct), dtype.type(config.ci)
    scale = dtype.type(scene_scale(lo, hi))
    centre = dtype.type(0.5) * lo + dtype.type(0.5) * hi

    nodes = NodeList()
    stack = [(nodes.new(-1), np.arange(lo.shape[0]))]
    while stack:
        node, ids = stack.pop()
        box_lo, box_hi = lo[ids].min(0), hi[ids].max(0)
        nodes.lo[node], nodes.hi[node] = box_lo, box_hi
        split = _node_split(config, ids, lo, hi, centre, scale, box_lo, box_hi)
        if _is_leaf(config, split, len(ids), half_area(box_lo, box_hi, scale), ct, ci, dtype):
            nodes.make_leaf(node, ids)
            continue
        _, axis, left_ids, right_ids = split
        nodes.axis[node] = axis
        l_id, r_id = nodes.new(node), nodes.new(node)
        nodes.left[node], nodes.right[node] = l_id, r_id
        stack.append((r_id, right_ids))
        stack.append((l_id, left_ids))
    return nodes.to_bvh(dtype)
