"""Sequential NumPy twin of :mod:`jaxbvh.optimize.leaves`: the exact leaf merge by recursion.

Follows the definition literally: ``C*`` by a post-order walk (the leaf where it is
strictly cheaper and holds at most ``max_leaf`` primitives), then a depth-first walk from
the root that turns every merged node into one leaf of its subtree's primitives (its
leaves' runs, left before right) and lays ``prim_index`` out in that order. Costs in the
tree's dtype with the JAX version's expressions (half-areas scaled by the root's power of
two), so the two agree exactly.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import half_area, scale_for_extent
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.walks import post_order


def merge_leaves(tree, max_leaf: int, ct=1.0, ci=1.0):
    """``tree`` (binary BVH) with every subtree merged into one leaf where that lowers its
    cost (see :mod:`jaxbvh.optimize.leaves`); NumPy arrays, the same capacity."""
    t = to_numpy(tree)
    root = int(t.root)
    dtype = t.lo.dtype.type
    extent = np.max(t.hi[root] - t.lo[root])
    scale = dtype(scale_for_extent(extent)) if extent > 0 else dtype(1)
    area = half_area(t.lo, t.hi, scale).astype(t.lo.dtype)
    ct, ci = dtype(ct), dtype(ci)
    count, best, merge = {}, {}, {}
    for node in post_order(np.stack([t.left, t.right], axis=1), root):
        if t.left[node] < 0:
            count[node] = int(t.prim_count[node])
            best[node] = ci * dtype(count[node])
            merge[node] = False
            continue
        left, right = int(t.left[node]), int(t.right[node])
        count[node] = count[left] + count[right]
        if area[node] > 0:
            keep = ct + (area[left] * best[left] + area[right] * best[right]) / area[node]
        else:
            keep = ct + (best[left] + best[right])
        as_leaf = ci * dtype(count[node])
        merge[node] = count[node] <= max_leaf and as_leaf < keep
        best[node] = as_leaf if merge[node] else keep
    if not any(merge.values()):
        return t

    def prims(node):  # the primitives under ``node``, leaves left before right
        if t.left[node] < 0:
            s = int(t.prim_start[node])
            return list(t.prim_index[s:s + int(t.prim_count[node])])
        return prims(int(t.left[node])) + prims(int(t.right[node]))

    cap = t.left.shape[0]
    out = {k: np.array(v) for k, v in vars(t).items() if k != "root"}
    out["left"][:] = -1
    out["right"][:] = -1
    out["parent"][:] = -1
    out["lo"][:] = np.inf
    out["hi"][:] = -np.inf
    out["prim_start"][:] = 0
    out["prim_count"][:] = 0
    out["axis"][:] = -1
    out["prim_index"][:] = -1
    slot = 0
    stack = [root]
    while stack:
        node = stack.pop()
        out["parent"][node] = t.parent[node]
        out["lo"][node], out["hi"][node] = t.lo[node], t.hi[node]
        if t.left[node] >= 0 and not merge[node]:
            out["left"][node], out["right"][node] = t.left[node], t.right[node]
            out["axis"][node] = t.axis[node]
            stack += [int(t.right[node]), int(t.left[node])]
            continue
        run = list(dict.fromkeys(prims(node)))  # a triangle several leaves referenced: once
        out["prim_start"][node], out["prim_count"][node] = slot, len(run)
        out["prim_index"][slot:slot + len(run)] = run
        slot += len(run)
    assert cap == out["left"].shape[0]
    return type(t)(**out, root=t.root)
