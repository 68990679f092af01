"""Sequential NumPy twin of :mod:`jaxbvh.builders.ploc`: agglomerative clustering, one cluster at a time.

Clusters in a Python list in Morton order (:mod:`jaxbvh.builders.morton_reference`). Each
iteration computes the merged-box area of every pair at most ``radius`` apart, lets
each cluster pick its neighbour by the rule of :mod:`jaxbvh.builders.ploc` (least area, ties
within the tolerance to the nearest, then by the parity of ``min(i, j) // d``), merges
mutual pairs into the lower place and drops the upper; an iteration without a mutual
pair is redone with exact comparisons. Leaves collapse by
:mod:`jaxbvh.builders.bottom_up_reference`.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.builders import morton_reference as morton
from jaxbvh.builders.bottom_up_reference import Node, to_bvh
from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale
from jaxbvh.tree.layout import BVH


def nearest(clusters: list[Node], radius: int, scale, exact: bool) -> list[int]:
    """The index of every cluster's chosen neighbour."""
    c = len(clusters)
    dtype = clusters[0].lo.dtype
    area = {}
    for i in range(c):
        for d in range(1, radius + 1):
            if i + d < c:
                a, b = clusters[i], clusters[i + d]
                area[i, i + d] = half_area(np.minimum(a.lo, b.lo), np.maximum(a.hi, b.hi), scale)
    chosen = []
    for i in range(c):
        candidates = []  # (area, tie key, neighbour)
        for d in range(1, radius + 1):
            for j in (i - d, i + d):
                if 0 <= j < c:
                    pair = (min(i, j), max(i, j))
                    candidates.append((area[pair], 2 * d + (pair[0] // d) % 2, j))
        best = min(x[0] for x in candidates)
        limit = best if exact else best * dtype.type(1 + TIE_TOLERANCE)
        chosen.append(min((x for x in candidates if x[0] <= limit), key=lambda x: x[1])[2])
    return chosen


def cluster(clusters: list[Node], radius: int, scale) -> Node:
    """Merge mutual nearest neighbours until one cluster is left; returns it."""
    while len(clusters) > 1:
        choice = nearest(clusters, radius, scale, exact=False)
        if not any(choice[choice[i]] == i for i in range(len(clusters))):
            choice = nearest(clusters, radius, scale, exact=True)
        merged = []
        for i, j in enumerate(choice):
            if choice[j] != i:
                merged.append(clusters[i])
            elif i < j:
                merged.append(Node.merge(clusters[i], clusters[j]))
        clusters = merged
    return clusters[0]


def build(prim_lo, prim_hi, config) -> BVH:
    """Reference PLOC of ``config`` (read for ``radius``, ``max_leaf``, ``ct``, ``ci``,
    ``morton_bits``); boxes used in their dtype. Unpadded NumPy BVH, depth-first."""
    lo, hi = np.asarray(prim_lo), np.asarray(prim_hi)
    _, ids = morton.sorted_keys(lo, hi, config.morton_bits)
    scale = lo.dtype.type(scene_scale(lo, hi))
    root = cluster([Node.leaf(p, lo, hi) for p in ids], int(config.radius), scale)
    return to_bvh(root, lo, hi, max_leaf=config.max_leaf, ct=config.ct, ci=config.ci)
