"""Wald's binned SAH split, written once for the sequential NumPy twins that bin centres.

The top-down twin (binned builder), the SBVH twin (its object split) and the re-braiding
twin (its top level over BRefs) each choose a node's split this way; they differ only in
what a row weighs (one primitive, or a BRef's primitive count) and in the area scale.
Named ``*_rules`` because a twin may import only neutral modules and other twins
(``tests/test_architecture.py``); no JAX module imports it, so the engines are still
checked against an independent statement of the rule.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import TIE_TOLERANCE, half_area


def binned_split(centre, lo, hi, weight, bins: int, scale=1.0):
    """The cheapest binned plane over rows with centres ``centre`` [m, 3], boxes ``lo``,
    ``hi`` [m, 3] (their dtype is the working dtype) and weights ``weight`` [m] (the
    primitives each row counts for):

    on each axis whose centres span more than 0, ``bins`` equal bins over the centres'
    range, and every plane between two bins that leaves rows on both sides costs
    ``area(left box) * left weight + area(right box) * right weight`` (half areas, extents
    times ``scale``). Returns ``(cost, axis, plane, goes_left)``: the least cost, and the
    first plane (lowest axis, then lowest plane) within :data:`TIE_TOLERANCE` of it, with
    ``goes_left`` [m] bool its rows in bins ``<= plane``; or None when no plane exists.
    """
    dt = lo.dtype
    cmin, cmax = centre.min(0), centre.max(0)
    candidates = []  # (cost, axis, plane, goes_left): lowest axis, then lowest plane first
    for axis in range(3):
        span = cmax[axis] - cmin[axis]
        if not span > 0:
            continue
        raw = np.floor((centre[:, axis] - cmin[axis]) * dt.type(bins) / span)
        b = np.clip(raw, 0, bins - 1).astype(np.int64)
        for plane in range(bins - 1):
            left = b <= plane
            if left.all() or not left.any():
                continue
            cost = (half_area(lo[left].min(0), hi[left].max(0), scale) * dt.type(weight[left].sum())
                    + half_area(lo[~left].min(0), hi[~left].max(0), scale) * dt.type(weight[~left].sum()))
            candidates.append((cost, axis, plane, left))
    if not candidates:
        return None
    best = min(c[0] for c in candidates)
    near = best * dt.type(1 + TIE_TOLERANCE)
    _, axis, plane, left = next(c for c in candidates if c[0] <= near)
    return best, axis, plane, left
