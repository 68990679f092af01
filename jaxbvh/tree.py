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

Units. Boxes are in whatever frame the primitive boxes were given in; :mod:`jaxbvh.io`
hands out scene-relative boxes together with the :class:`~jaxbvh.frame.Frame` that maps
them back to world space. All costs are ratios of areas, so they do not depend on the
frame.

Interchange. :func:`save` / :func:`load` use ``.npz`` files with exactly the arrays
``child`` (int32 [nodes, k]), ``prim_start``, ``prim_count`` (int32 [nodes]),
``prim_index`` (int32), ``lo``, ``hi`` (float [nodes, 3]) and ``root`` (int32 scalar),
as other BVH libraries export them; when the boxes are scene-relative two more arrays,
``origin`` (float64 [3]) and ``scale`` (float64 scalar), record the frame.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.frame import Frame

INTERCHANGE_KEYS = ("child", "prim_start", "prim_count", "prim_index", "lo", "hi", "root")


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
        return dataclasses.replace(self, **changes)


def capacity_bucket(n: int, minimum: int = 4) -> int:
    """Smallest size of the form 2^k or 3 * 2^(k-1) that holds ``n``.

    Consecutive buckets differ by at most 1.5x, so padding wastes at most a third of
    the arrays while a run over many meshes compiles for only a few shapes.
    """
    if n < 0:
        raise ValueError(f"capacity_bucket: n must be non-negative, got {n}")
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
    """The same tree with every array as a JAX array."""
    return jax.tree_util.tree_map(jnp.asarray, tree)


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
    child = np.asarray(t.child)
    out = np.full(child.shape[0], -1, np.int32)
    frontier = np.array([int(t.root)])
    d = 0
    while frontier.size and d <= child.shape[0]:
        out[frontier] = d
        nxt = child[frontier].ravel()
        frontier = nxt[nxt >= 0]
        d += 1
    return out


# ----------------------------------------------------------------------------------
# Interchange form
# ----------------------------------------------------------------------------------


def to_interchange(tree) -> dict[str, np.ndarray]:
    """Compact interchange arrays (module docstring) with padding removed.

    Real nodes keep their relative order; ids are renumbered densely.
    """
    t = to_numpy(tree)
    child = np.asarray(t.child)
    keep = real_nodes(t)
    new_id = np.full(child.shape[0] + 1, -1, np.int32)  # slot -1 -> -1
    new_id[:-1][keep] = np.arange(int(keep.sum()), dtype=np.int32)
    child_c = new_id[child[keep]]
    count = np.asarray(t.prim_count)[keep].astype(np.int32)
    start = np.where(count > 0, np.asarray(t.prim_start)[keep], 0).astype(np.int32)
    used = int(count.sum())
    prim_index = np.asarray(t.prim_index)
    # keep the prim_index slots the leaves use, in order, and re-point the leaves
    leaf_ids = np.flatnonzero(count > 0)
    leaf_ids = leaf_ids[np.argsort(start[leaf_ids], kind="stable")]
    leaf_counts = count[leaf_ids].astype(np.int64)
    new_start = np.zeros_like(start)
    new_start[leaf_ids] = np.cumsum(leaf_counts) - leaf_counts
    prim_c = prim_index[concat_ranges(start[leaf_ids], leaf_counts)].astype(np.int32)
    assert prim_c.shape[0] == used
    return {
        "child": child_c.astype(np.int32),
        "prim_start": new_start,
        "prim_count": count,
        "prim_index": prim_c,
        "lo": np.asarray(t.lo)[keep],
        "hi": np.asarray(t.hi)[keep],
        "root": np.int32(new_id[int(t.root)]),
    }


def concat_ranges(starts, counts) -> np.ndarray:
    """``concatenate([arange(s, s + c) for s, c in zip(starts, counts)])``, vectorised (int64)."""
    starts = np.asarray(starts, np.int64)
    counts = np.asarray(counts, np.int64)
    offsets = np.cumsum(counts) - counts
    return np.arange(int(counts.sum()), dtype=np.int64) + np.repeat(starts - offsets, counts)


def compact(tree):
    """``tree`` (as NumPy) trimmed to the capacity bucket of its real node count.

    A loaded tree gets that capacity, so a tree and its saved copy then have the same
    shape (and compile the same programs). Node ids are kept when the real nodes are a
    prefix of the ids (our builders number them so); otherwise the tree goes through the
    interchange form (ids renumbered densely, split axes dropped).
    """
    t = to_numpy(tree)
    real = real_nodes(t)
    n = int(real.sum())
    nodes = max(capacity_bucket(n), 1)
    if real[:n].all():
        keep = slice(0, min(nodes, real.shape[0]))
        fields = {f.name: getattr(t, f.name) for f in dataclasses.fields(t)}
        trimmed = {k: (v if k in ("prim_index", "root") else v[keep]) for k, v in fields.items()}
        return type(t)(**trimmed)
    return from_interchange(to_interchange(t))


def _pad_rows(a: np.ndarray, rows: int, fill) -> np.ndarray:
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
    common = dict(parent=_pad_rows(t.parent, nodes, -1), lo=_pad_rows(t.lo, nodes, np.inf),
                  hi=_pad_rows(t.hi, nodes, -np.inf), prim_start=_pad_rows(t.prim_start, nodes, 0),
                  prim_count=_pad_rows(t.prim_count, nodes, 0), prim_index=_pad_rows(t.prim_index, prims, -1),
                  root=np.asarray(t.root, np.int32))
    if isinstance(t, WideBVH):
        return WideBVH(child=_pad_rows(t.child, nodes, -1), **common)
    return BVH(left=_pad_rows(t.left, nodes, -1), right=_pad_rows(t.right, nodes, -1),
               axis=_pad_rows(t.axis, nodes, -1), **common)


def from_interchange(arrays, *, pad: bool = True, dtype=None):
    """Tree from interchange arrays (any node order, any root, leaves of any size).

    Returns a :class:`BVH` when ``child`` has two columns, else a :class:`WideBVH`;
    arrays are NumPy, padded to a capacity bucket unless ``pad=False``. Structural
    problems (wrong keys, shapes, out-of-range ids) raise ``ValueError`` naming them;
    use :func:`jaxbvh.validate` for the full invariant check.
    """
    missing = [k for k in INTERCHANGE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"tree is missing array(s) {', '.join(missing)}; "
                         f"expected {', '.join(INTERCHANGE_KEYS)}")
    child = np.asarray(arrays["child"])
    if child.ndim != 2 or child.shape[1] < 2 or child.shape[0] < 1:
        raise ValueError(f"tree 'child' must be int [nodes, k>=2], got shape {child.shape}")
    if not np.issubdtype(child.dtype, np.integer):
        raise ValueError(f"tree 'child' must be integer, got {child.dtype}")
    nodes = child.shape[0]
    fields = {}
    for key in ("prim_start", "prim_count"):
        a = np.asarray(arrays[key])
        if a.shape != (nodes,) or not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"tree '{key}' must be int [{nodes}], got {a.dtype} {a.shape}")
        fields[key] = a.astype(np.int32)
    for key in ("lo", "hi"):
        a = np.asarray(arrays[key])
        if a.shape != (nodes, 3) or not np.issubdtype(a.dtype, np.floating):
            raise ValueError(f"tree '{key}' must be float [{nodes}, 3], got {a.dtype} {a.shape}")
        fields[key] = a.astype(dtype or a.dtype)
    prim_index = np.asarray(arrays["prim_index"])
    if prim_index.ndim != 1 or not np.issubdtype(prim_index.dtype, np.integer):
        raise ValueError(f"tree 'prim_index' must be int [prims], got {prim_index.dtype} {prim_index.shape}")
    root = np.asarray(arrays["root"])
    if root.size != 1 or not np.issubdtype(root.dtype, np.integer):
        raise ValueError(f"tree 'root' must be one integer, got {root.dtype} {root.shape}")
    root = int(root.reshape(()))
    if not 0 <= root < nodes:
        raise ValueError(f"tree 'root' {root} is outside the {nodes} nodes")
    bad = (child < -1) | (child >= nodes)
    if bad.any():
        i = int(np.argwhere(bad)[0][0])
        raise ValueError(f"tree 'child' of node {i} is {child[i].tolist()}: ids must be -1 or in [0, {nodes})")
    count, start = fields["prim_count"], fields["prim_start"]
    if (count < 0).any():
        raise ValueError(f"tree 'prim_count' is negative at node {int(np.argmax(count < 0))}")
    over = (count > 0) & ((start < 0) | (start + count > prim_index.shape[0]))
    if over.any():
        i = int(np.argmax(over))
        raise ValueError(f"leaf {i} covers prim_index[{start[i]}:{start[i] + count[i]}], "
                         f"outside its {prim_index.shape[0]} entries")
    child = child.astype(np.int32)
    parent = np.full(nodes, -1, np.int32)
    rows, cols = np.nonzero(child >= 0)
    parent[child[rows, cols]] = rows.astype(np.int32)
    prim_index = prim_index.astype(np.int32)
    fields["prim_start"] = np.where(count > 0, start, 0).astype(np.int32)

    node_cap = capacity_bucket(nodes) if pad else nodes
    prim_cap = capacity_bucket(prim_index.shape[0]) if pad else prim_index.shape[0]
    fdt = fields["lo"].dtype
    common = dict(
        parent=_pad_rows(parent, node_cap, -1),
        lo=_pad_rows(fields["lo"], node_cap, np.inf).astype(fdt),
        hi=_pad_rows(fields["hi"], node_cap, -np.inf).astype(fdt),
        prim_start=_pad_rows(fields["prim_start"], node_cap, 0),
        prim_count=_pad_rows(count, node_cap, 0),
        prim_index=_pad_rows(prim_index, prim_cap, -1),
        root=np.int32(root),
    )
    child = _pad_rows(child, node_cap, -1)
    if child.shape[1] == 2:
        return BVH(left=child[:, 0].copy(), right=child[:, 1].copy(),
                   axis=np.full(node_cap, -1, np.int32), **common)
    return WideBVH(child=child, **common)


def save(path: str | os.PathLike, tree, frame: Frame | None = None) -> None:
    """Write ``tree`` to ``path`` as an interchange ``.npz`` (padding removed).

    ``frame``, if given and not the identity, is stored as ``origin`` and ``scale``.
    """
    arrays = to_interchange(tree)
    if frame is not None and not frame.is_identity:
        arrays["origin"] = np.asarray(frame.origin, np.float64)
        arrays["scale"] = np.float64(frame.scale)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def load(path: str | os.PathLike, *, pad: bool = True):
    """Read an interchange ``.npz``; returns ``(tree, frame)`` (NumPy arrays).

    ``frame`` is the identity when the file stores none (boxes in world space).
    """
    import zipfile

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"tree file not found: {path}")
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a directory, expected a tree file (.npz)")
    if not zipfile.is_zipfile(path):
        # np.load would read it as a pickle or a lone .npy array and say so, confusingly
        raise ValueError(f"{path}: not a tree file: an .npz tree is a zip archive of arrays "
                         f"({', '.join(INTERCHANGE_KEYS)}), and this file is not one")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:  # a damaged archive, or an array of objects inside
        raise ValueError(f"{path}: not a readable .npz tree file ({exc})") from None
    try:
        tree = from_interchange(arrays, pad=pad)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    frame = Frame.identity()
    if "origin" in arrays or "scale" in arrays:
        frame = Frame(np.asarray(arrays["origin"], np.float64).reshape(3),
                      float(np.asarray(arrays["scale"])))
    return tree, frame
