"""A batch of trees: meshes of many sizes in a few groups, each group's trees stacked on a leading axis.

Layout
======
A :class:`TreeBatch` holds the trees of ``M`` meshes (in the order they were given) as a
tuple of :class:`Group` s. A group is one compiled program's worth of trees: every tree
in it is padded to the group's capacity and the trees are stacked along a new leading
axis of length ``B`` (the :class:`~jaxbvh.tree.layout.BVH` layout, each array with one
more axis in front):

==================  =================  ================================================
field               shape, dtype       meaning
==================  =================  ================================================
``trees``           BVH of [B, ...]    the stacked trees (``2 C`` node slots, ``C``
                                       primitive slots: the group's capacity)
``index``           [B] int64          position in the input list of each tree
``prims``           [B] int64          real primitives of each tree (``n``)
==================  =================  ================================================

A group holds no filler rows: runs that padded the batch axis (to a device multiple or a
batch-size bucket) dropped them before making the group. Groups are ordered by capacity.

Own capacity. A tree alone (``jaxbvh.build`` of its mesh) has the capacity bucket of
its own ``n``; the builders number real nodes from 0 and put nothing but padding
past ``2 * capacity_bucket(n)`` nodes and ``capacity_bucket(n)`` primitive slots, so
:meth:`TreeBatch.unstack` cuts each tree back to that capacity and gives exactly the
tree the single call gives (``own=False`` keeps the group's capacity).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxbvh.tree.layout import BVH, capacity_bucket, real_nodes, to_numpy


@dataclasses.dataclass(frozen=True)
class Group:
    """Trees of one capacity, stacked (layout: module docstring)."""

    trees: Any       # BVH with a leading batch axis B (NumPy or JAX arrays)
    index: np.ndarray  # int64 [B]: position of each tree in the input list
    prims: np.ndarray  # int64 [B]: real primitives of each tree

    @property
    def capacity(self) -> int:
        """Primitive slots of every tree in the group."""
        return int(self.trees.prim_index.shape[1])

    def __len__(self) -> int:
        return int(self.index.shape[0])

    def tree(self, row: int, own: bool = True):
        """Row ``row``'s tree as NumPy arrays, cut to its own capacity (``own``) or not."""
        t = jax.tree_util.tree_map(lambda a: np.asarray(a[row]), to_numpy(self.trees))
        return own_capacity(t, int(self.prims[row])) if own else t


@dataclasses.dataclass(frozen=True)
class TreeBatch:
    """The trees of ``size`` meshes in capacity groups (layout: module docstring)."""

    groups: tuple   # of Group, by capacity
    size: int       # meshes in the batch (every position 0 .. size - 1 in exactly one group)

    def __len__(self) -> int:
        return self.size

    @property
    def capacities(self) -> tuple[int, ...]:
        return tuple(g.capacity for g in self.groups)

    def where(self) -> list[tuple[int, int]]:
        """``(group, row)`` of every mesh, in input order (None: a mesh left out)."""
        out = [None] * self.size
        for gi, g in enumerate(self.groups):
            for row, i in enumerate(g.index):
                out[int(i)] = (gi, row)
        return out

    def unstack(self, own: bool = True) -> list:
        """Per-mesh :class:`~jaxbvh.tree.layout.BVH` s (NumPy), in input order.

        ``own``: cut each to the capacity of its own primitive count (module docstring),
        so each equals, array for array, what the single-tree call gives.
        """
        groups = [to_numpy(g.trees) for g in self.groups]
        out = []
        for at in self.where():
            if at is None:  # a mesh left out (its error is in the build's result)
                out.append(None)
                continue
            gi, row = at
            t = jax.tree_util.tree_map(lambda a, row=row: np.asarray(a[row]), groups[gi])
            out.append(own_capacity(t, int(self.groups[gi].prims[row])) if own else t)
        return out


def own_capacity(tree, n: int):
    """``tree`` (NumPy, one tree) cut to the capacity :func:`jaxbvh.build` gives ``n``
    primitives (``2 capacity_bucket(n)`` node slots); ``ValueError`` if a real node or
    primitive slot lies past it (a tree that does not fit is never cut silently)."""
    prims = capacity_bucket(n)
    nodes = 2 * prims
    if tree.left.shape[0] <= nodes and tree.prim_index.shape[0] <= prims:
        return tree
    real = real_nodes(tree)
    if real[nodes:].any() or (np.asarray(tree.prim_index)[prims:] >= 0).any():
        raise ValueError(f"own_capacity: the tree has real entries past the capacity of {n} primitives")
    return BVH(left=tree.left[:nodes], right=tree.right[:nodes], parent=tree.parent[:nodes],
               lo=tree.lo[:nodes], hi=tree.hi[:nodes], prim_start=tree.prim_start[:nodes],
               prim_count=tree.prim_count[:nodes], axis=tree.axis[:nodes],
               prim_index=tree.prim_index[:prims], root=tree.root)
