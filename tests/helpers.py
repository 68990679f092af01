"""Small helpers for comparing trees in tests."""

from __future__ import annotations

import sys

import numpy as np

import jaxbvh

# canonical() recurses once per level; set at import, not inside a test, so hypothesis
# does not warn that the limit changed under it
sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))


def canonical(tree, with_axis: bool = True):
    """Tree as nested tuples from the root: node ids and prim order inside leaves ignored.

    Interior: ``(axis, left, right, lo, hi)``; leaf: ``("leaf", sorted prims, lo, hi)``.
    """
    t = jaxbvh.to_numpy(tree)

    def rec(n):
        box = (tuple(np.asarray(t.lo[n]).tolist()), tuple(np.asarray(t.hi[n]).tolist()))
        if t.prim_count[n] > 0:
            s, c = int(t.prim_start[n]), int(t.prim_count[n])
            return ("leaf", tuple(sorted(t.prim_index[s:s + c].tolist())), box)
        return (int(t.axis[n]) if with_axis else None, rec(int(t.left[n])), rec(int(t.right[n])), box)

    return rec(int(t.root))
