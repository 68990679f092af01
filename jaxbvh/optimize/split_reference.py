"""Sequential NumPy twin of :mod:`jaxbvh.optimize.split`: every leaf split down to one primitive.

Follows the definition literally, in the JAX version's rounds: while a leaf holds several
primitives, every such leaf (in ascending node id) sorts its run by centroid along its
axis, takes the sweep's cheapest cut, and hands its two halves to the two lowest free node
ids. Costs in the tree's dtype with the JAX version's expressions, so the two agree exactly.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import half_area, scale_for_extent
from jaxbvh.tree.layout import to_numpy


def _cut(boxes_lo, boxes_hi, count: int, scale):
    """``j``: the left half is the first ``j`` of the sorted run (1 <= j < count), the
    sweep's cheapest cut (area times primitives, each side), the first of equal costs."""
    dtype = boxes_lo.dtype.type
    best, best_j = None, None
    for j in range(1, count):
        cost = (half_area(boxes_lo[:j].min(0), boxes_hi[:j].max(0), scale) * dtype(j)
                + half_area(boxes_lo[j:].min(0), boxes_hi[j:].max(0), scale) * dtype(count - j))
        if best is None or cost < best:
            best, best_j = cost, j
    return best_j


def split_leaves(tree, prim_lo, prim_hi):
    """``(tree, overflow)``: ``tree`` (binary BVH; NumPy arrays) with every leaf of several
    primitives made a binary subtree of one-primitive leaves (see
    :mod:`jaxbvh.optimize.split`); ``overflow``: the capacity ran out (the leaves left
    whole where no free ids were left)."""
    t = to_numpy(tree)
    out = {k: np.array(v) for k, v in vars(t).items() if k != "root"}
    plo, phi = np.asarray(prim_lo), np.asarray(prim_hi)
    dtype = out["lo"].dtype
    cap = out["left"].shape[0]
    root = int(t.root)
    extent = np.max(t.hi[root] - t.lo[root])
    scale = dtype.type(scale_for_extent(extent)) if extent > 0 else dtype.type(1)
    overflow = False
    while True:
        real = (out["left"] >= 0) | (out["prim_count"] > 0)
        real[root] = True
        big = [n for n in range(cap) if out["left"][n] < 0 and out["prim_count"][n] > 1]
        if not big:
            break
        free = [n for n in range(cap) if not real[n]]
        if len(free) < 2 * len(big):  # the lowest ids split while free ids last
            overflow = True
            big = big[:len(free) // 2]
            if not big:
                break
        for rank, node in enumerate(big):
            start, count = int(out["prim_start"][node]), int(out["prim_count"][node])
            run = out["prim_index"][start:start + count].copy()
            # the primitives' boxes inside the leaf's box (a spatial split's reference is a
            # clipped triangle: its part in this leaf)
            blo = np.maximum(plo[run].astype(dtype), out["lo"][node])
            bhi = np.minimum(phi[run].astype(dtype), out["hi"][node])
            centre = blo + bhi
            axis = int(np.argmax(centre.max(0) - centre.min(0)))
            order = np.argsort(centre[:, axis], kind="stable")
            run, blo, bhi = run[order], blo[order], bhi[order]
            j = _cut(blo, bhi, count, scale)
            out["prim_index"][start:start + count] = run
            kids = free[2 * rank], free[2 * rank + 1]
            halves = ((start, j, blo[:j], bhi[:j]), (start + j, count - j, blo[j:], bhi[j:]))
            for kid, (s, k, lo, hi) in zip(kids, halves):
                out["parent"][kid] = node
                out["lo"][kid], out["hi"][kid] = lo.min(0), hi.max(0)
                out["prim_start"][kid], out["prim_count"][kid] = s, k
                out["left"][kid] = out["right"][kid] = out["axis"][kid] = -1
            out["left"][node], out["right"][node] = kids
            out["axis"][node] = axis
            out["prim_start"][node] = out["prim_count"][node] = 0
    return type(t)(**out, root=t.root), overflow
