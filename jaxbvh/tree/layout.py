"""The BVH as fixed-shape index arrays: the one place its layout is defined.

Layout
======
A **binary BVH** (:class:`BVH`) over ``n`` primitives grouped into ``L`` leaves has
``2L - 1`` real nodes. Every array is indexed by node id; ids are arbitrary (our
builders number nodes level by level, root 0, but a loaded tree may use any order and
any root).

======================  =================  ==============================================
field                   shape, dtype       meaning
======================  =================  ==============================================
``left``, ``right``     [N] int32          children; -1 for a leaf and for padding
``parent``              [N] int32          parent; -1 for the root and for padding
``lo``, ``hi``          [N, 3] float       box corners; padding holds the empty box
                                           (``+inf``, ``-inf``)
``prim_start``          [N] int32          first slot of the leaf's run in ``prim_index``
``prim_count``          [N] int32          primitives in the leaf; 0 for interior nodes
                                           and padding (a leaf holds at least one)
``axis``                [N] int32          split axis (0, 1, 2) the children are ordered
                                           along (left = lower), -1 if unknown or leaf
``prim_index``          [P] int32          primitive ids, each leaf's run contiguous;
                                           -1 in padding slots
``root``                [] int32           id of the root node
======================  =================  ==============================================

A **wide BVH** (:class:`WideBVH`) is the same with ``child`` [N, k] int32 in place of
``left``/``right``/``axis``: the children of node ``i`` are the entries of ``child[i]``
that are not -1.

Capacity. ``N`` and ``P`` may exceed what the tree needs: arrays are padded to a
*capacity bucket* (:func:`capacity_bucket`) so that jitted functions compile for a few
sizes rather than one per mesh. Padded entries are inert: no links, count 0, empty box,
and no real node points at them. Our builders make ``N = 2 * P``; a loaded tree gets
the bucket of its own node count (leaves of several primitives need far fewer nodes).

Units. Boxes are in whatever frame the primitive boxes were given in; :mod:`jaxbvh.io.meshes`
hands out scene-relative boxes together with the :class:`~jaxbvh.tree.frame.Frame` that maps
them back to world space. All costs are ratios of areas, so they do not depend on the
frame.

Interchange: :mod:`jaxbvh.tree.interchange`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import compile_cache
from jaxbvh.tree.walks import depths

# the package's JAX code passes here before it compiles anything: the persistent
# compilation cache is on from then (idempotent; jaxbvh.compile_cache says when not)
compile_cache.enable_default()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BVH:
    """Binary BVH as fixed-shape arrays (layout: module docstring)."""

    left: Any
    right: Any
    parent: Any
    lo: Any
    hi: Any
    prim_start: Any
    prim_count: Any
    axis: Any
    prim_index: Any
    root: Any

    @property
    def child(self):
        """Children as one [N, 2] array, the form shared with :class:`WideBVH`."""
        xp = np if isinstance(self.left, np.ndarray) else jnp
        return xp.stack([self.left, self.right], axis=1)

    @property
    def capacity(self) -> int:
        return int(self.left.shape[0])

    def replace(self, **changes) -> "BVH":
        """A copy with the given fields (arrays of the shapes above) replaced."""
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WideBVH:
    """k-ary BVH as fixed-shape arrays (layout: module docstring)."""

    child: Any
    parent: Any
    lo: Any
    hi: Any
    prim_start: Any
    prim_count: Any
    prim_index: Any
    root: Any

    @property
    def capacity(self) -> int:
        return int(self.child.shape[0])

    @property
    def arity(self) -> int:
        return int(self.child.shape[1])

    def replace(self, **changes) -> "WideBVH":
        """A copy with the given fields (arrays of the shapes above) replaced."""
        return dataclasses.replace(self, **changes)


def capacity_bucket(n: int, minimum: int = 4) -> int:
    """Smallest size of the form 2^k or 3 * 2^(k-1) that holds ``n``.

    Consecutive buckets differ by at most 1.5x, so padding wastes at most a third of
    the arrays while a run over many meshes compiles for only a few shapes.
    """
    if n < 0:
        raise ValueError(f"capacity_bucket: n must be non-negative, got {n}")
    if minimum < 2:  # 1 would never grow: its half is 0
        raise ValueError(f"capacity_bucket: minimum must be >= 2, got {minimum}")
    size = minimum
    while size < n:
        half = size // 2
        # sizes go 4, 6, 8, 12, 16, 24, ...
        size = size + half if size & (size - 1) == 0 else (size // 3) * 4
    return size


def to_numpy(tree):
    """The same tree with every array as a NumPy array (host copy)."""
    return jax.tree_util.tree_map(np.asarray, tree)


def to_jax(tree):
    """The same tree with every array as a JAX array (NumPy arrays put on the device as
    they are: ``jnp.asarray`` of a NumPy array compiles a small program per new shape in
    every process, ~10 ms each, :func:`jaxbvh.numerics.on_device`)."""
    return jax.tree_util.tree_map(_to_jax_array, tree)


def _to_jax_array(x):
    return jax.device_put(x) if isinstance(x, (np.ndarray, np.generic)) else jnp.asarray(x)


def real_nodes(tree) -> np.ndarray:
    """Boolean mask [N] of nodes that are not padding (interior or leaf)."""
    t = to_numpy(tree)
    child = np.asarray(t.child)
    return (child >= 0).any(axis=1) | (np.asarray(t.prim_count) > 0)


def node_count(tree) -> int:
    """Number of real (non-padding) nodes."""
    return int(real_nodes(tree).sum())


def prim_total(tree) -> int:
    """Number of primitives the leaves reference (padding excluded)."""
    return int(np.asarray(to_numpy(tree).prim_count).sum())


def depth(tree) -> np.ndarray:
    """Depth of every node [N] int32 (root 0); -1 for nodes not reachable from the root."""
    t = to_numpy(tree)
    return depths(t.child, [int(t.root)], np.int32)


def concat_ranges(starts, counts) -> np.ndarray:
    """``concatenate([arange(s, s + c) for s, c in zip(starts, counts)])``, vectorised (int64)."""
    starts = np.asarray(starts, np.int64)
    counts = np.asarray(counts, np.int64)
    offsets = np.cumsum(counts) - counts
    return np.arange(int(counts.sum()), dtype=np.int64) + np.repeat(starts - offsets, counts)


def pad_rows(a: np.ndarray, rows: int, fill) -> np.ndarray:
    """``a`` [M, ...] extended to [rows, ...] (rows >= M) with ``fill``, in ``a``'s dtype."""
    out = np.full((rows,) + a.shape[1:], fill, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


def pad_to(tree, nodes: int, prims: int):
    """``tree`` (as NumPy) padded with inert entries to capacity ``nodes`` / ``prims``.

    Works for :class:`BVH` and :class:`WideBVH`; raises ``ValueError`` if the tree is
    already larger. Used to give trees of a batch one shape.
    """
    t = to_numpy(tree)
    n, p = t.parent.shape[0], t.prim_index.shape[0]
    if nodes < n or prims < p:
        raise ValueError(f"pad_to: capacity ({nodes}, {prims}) is below the tree's ({n}, {p})")
    common = dict(parent=pad_rows(t.parent, nodes, -1), lo=pad_rows(t.lo, nodes, np.inf),
                  hi=pad_rows(t.hi, nodes, -np.inf), prim_start=pad_rows(t.prim_start, nodes, 0),
                  prim_count=pad_rows(t.prim_count, nodes, 0), prim_index=pad_rows(t.prim_index, prims, -1),
                  root=np.asarray(t.root, np.int32))
    if isinstance(t, WideBVH):
        return WideBVH(child=pad_rows(t.child, nodes, -1), **common)
    return BVH(left=pad_rows(t.left, nodes, -1), right=pad_rows(t.right, nodes, -1),
               axis=pad_rows(t.axis, nodes, -1), **common)
