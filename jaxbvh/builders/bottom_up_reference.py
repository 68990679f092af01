"""Sequential NumPy twin of :mod:`jaxbvh.builders.bottom_up`: a linked tree of objects to a BVH, top-down.

The bottom-up twins (:mod:`jaxbvh.builders.lbvh_reference`, :mod:`jaxbvh.builders.ploc_reference`) build
a tree of :class:`Node` objects; :func:`to_bvh` walks it from the root the way the
top-down reference builder does, stopping at the first node that passes the SAH leaf
test (rule in :mod:`jaxbvh.builders.bottom_up`), and writes nodes in depth-first order, root 0,
unpadded.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxbvh.numerics import half_area, scene_scale
from jaxbvh.tree.layout import BVH


@dataclasses.dataclass
class Node:
    """A primitive (``prims`` of one id, no children) or a merge of two nodes."""

    lo: np.ndarray
    hi: np.ndarray
    prims: list  # primitive ids below, left to right
    left: "Node | None" = None
    right: "Node | None" = None
    axis: int = -1

    @staticmethod
    def leaf(prim: int, lo: np.ndarray, hi: np.ndarray) -> "Node":
        return Node(lo[prim].copy(), hi[prim].copy(), [prim])

    @staticmethod
    def merge(left: "Node", right: "Node", axis: int = -1) -> "Node":
        return Node(np.minimum(left.lo, right.lo), np.maximum(left.hi, right.hi),
                    left.prims + right.prims, left, right, axis)




def passes_leaf_test(node: Node, scale, max_leaf: int, ct, ci) -> bool:
    """The top-down builders' SAH leaf test, with the node's own children as the split."""
    count = len(node.prims)
    if node.left is None:
        return True
    if count > max_leaf:
        return False
    dtype = node.lo.dtype
    area = half_area(node.lo, node.hi, scale)
    split = (half_area(node.left.lo, node.left.hi, scale) * dtype.type(len(node.left.prims))
             + half_area(node.right.lo, node.right.hi, scale) * dtype.type(len(node.right.prims)))
    estimate = ct + (ci * split / area if area > 0 else ci * dtype.type(count))
    return bool(ci * dtype.type(count) <= estimate)


def to_bvh(root: Node, prim_lo, prim_hi, *, max_leaf, ct, ci) -> BVH:
    """The BVH of the tree under ``root``, small subtrees collapsed; depth-first, unpadded."""
    dtype = np.asarray(prim_lo).dtype
    ct, ci = dtype.type(ct), dtype.type(ci)
    scale = dtype.type(scene_scale(np.asarray(prim_lo), np.asarray(prim_hi)))
    left, right, parent, axis = [], [], [], []
    node_lo, node_hi, prim_start, prim_count = [], [], [], []
    prim_index: list[int] = []
    stack = [(root, -1)]
    while stack:
        node, par = stack.pop()
        me = len(left)
        for arr, v in ((left, -1), (right, -1), (parent, par), (axis, -1), (prim_start, 0), (prim_count, 0)):
            arr.append(v)
        node_lo.append(node.lo)
        node_hi.append(node.hi)
        if par >= 0:  # children are pushed right first, so a left child is written first
            if left[par] == -1:
                left[par] = me
            else:
                right[par] = me
        if passes_leaf_test(node, scale, max_leaf, ct, ci):
            prim_start[me] = len(prim_index)
            prim_count[me] = len(node.prims)
            prim_index.extend(int(p) for p in node.prims)
            continue
        axis[me] = node.axis
        stack.append((node.right, me))
        stack.append((node.left, me))
    i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
    return BVH(left=i32(left), right=i32(right), parent=i32(parent),
               lo=np.stack(node_lo).astype(dtype), hi=np.stack(node_hi).astype(dtype),
               prim_start=i32(prim_start), prim_count=i32(prim_count), axis=i32(axis),
               prim_index=i32(prim_index), root=np.int32(0))
