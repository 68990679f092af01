"""The growing node list of the sequential NumPy twins (top-down, SBVH).

A twin builds its tree node by node into plain lists and turns them into a
:class:`~jaxbvh.tree.layout.BVH` at the end. Shared by the twins, so it lives apart from
any of them; named ``*_rules`` because a twin may import only neutral modules and other
twins (``tests/test_architecture.py``), never a JAX module.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxbvh.tree.layout import BVH


@dataclasses.dataclass
class NodeList:
    """The tree as it is built: one list per BVH field, a node per entry, in the order made."""

    left: list = dataclasses.field(default_factory=list)        # child id, -1 for a leaf
    right: list = dataclasses.field(default_factory=list)
    parent: list = dataclasses.field(default_factory=list)      # -1 for the root
    axis: list = dataclasses.field(default_factory=list)        # split axis, -1 for a leaf
    lo: list = dataclasses.field(default_factory=list)          # [3] box (None until built)
    hi: list = dataclasses.field(default_factory=list)
    prim_start: list = dataclasses.field(default_factory=list)  # a leaf's first prim_index slot
    prim_count: list = dataclasses.field(default_factory=list)  # a leaf's primitives, 0 interior
    prim_index: list = dataclasses.field(default_factory=list)  # primitive ids, leaf by leaf

    def new(self, parent: int) -> int:
        """A fresh node under ``parent``: a leaf of no primitives until built. Its id."""
        for column, value in ((self.left, -1), (self.right, -1), (self.parent, parent), (self.axis, -1),
                              (self.prim_start, 0), (self.prim_count, 0), (self.lo, None), (self.hi, None)):
            column.append(value)
        return len(self.left) - 1

    def make_leaf(self, node: int, ids) -> None:
        """Make ``node`` a leaf of primitives ``ids``, appended to ``prim_index``."""
        self.prim_start[node] = len(self.prim_index)
        self.prim_count[node] = len(ids)
        self.prim_index.extend(int(i) for i in ids)

    def to_bvh(self, dtype) -> BVH:
        """The finished tree: an unpadded NumPy :class:`~jaxbvh.tree.layout.BVH`, boxes in ``dtype``."""
        i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
        return BVH(left=i32(self.left), right=i32(self.right), parent=i32(self.parent),
                   lo=np.stack(self.lo).astype(dtype), hi=np.stack(self.hi).astype(dtype),
                   prim_start=i32(self.prim_start), prim_count=i32(self.prim_count), axis=i32(self.axis),
                   prim_index=i32(self.prim_index), root=np.int32(0))
