"""Interchange form: trees as ``.npz`` files other BVH libraries read and write.

:func:`save` / :func:`load` use ``.npz`` files with exactly the arrays
``child`` (int32 [nodes, k]), ``prim_start``, ``prim_count`` (int32 [nodes]),
``prim_index`` (int32), ``lo``, ``hi`` (float [nodes, 3]) and ``root`` (int32 scalar),
as other BVH libraries export them; when the boxes are scene-relative two more arrays,
``origin`` (float64 [3]) and ``scale`` (float64 scalar), record the frame.

Padding is removed on the way out and added on the way in (capacity buckets,
:mod:`jaxbvh.tree.layout`); node ids may be in any order and the root anywhere.

Reading checks every array before using it, and a refusal is one ``ValueError`` naming
the file and the array: ids and counts of an integer type with values inside int32;
``root`` and ``scale`` scalars (shape ()), not arrays of one element; ``origin`` [3];
the frame finite with ``scale > 0`` (a NaN or zero scale would put every box nowhere).
Boxes are used as float32 or float64. Other float widths are converted so that every
box still contains what it contained, with a warning naming the array: float16 widens
to float32 exactly, long double narrows to float64 rounded outward. Boxes that hold
subnormal coordinates are scaled out of that range by a power of two (exact) and the
frame scaled back (:func:`_out_of_subnormals`): the device would flush them to zero.
``prim_index`` may name a primitive in several leaves (a tree with references: our
SBVH, tinybvh's ``BuildHQ``); nothing here assumes each id once, and
``jaxbvh.validate(tree, ..., references=True)`` checks such a tree.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
import zipfile

import numpy as np

from jaxbvh.files import atomic_write
from jaxbvh.numerics import root_exponent
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.layout import BVH, WideBVH, capacity_bucket, concat_ranges, pad_rows, real_nodes, to_numpy

INTERCHANGE_KEYS = ("child", "prim_start", "prim_count", "prim_index", "lo", "hi", "root")
#: the frame's arrays: both or neither (module docstring)
FRAME_KEYS = ("origin", "scale")
#: the float types boxes are used in as stored; other widths are converted (:func:`_box_array`)
BOX_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
_INT32 = np.iinfo(np.int32)


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


def from_interchange(arrays, *, pad: bool = True, dtype=None):
    """Tree from interchange arrays (any node order, any root, leaves of any size).

    Returns a :class:`BVH` when ``child`` has two columns, else a :class:`WideBVH`;
    arrays are NumPy, padded to a capacity bucket unless ``pad=False``. Structural
    problems (wrong keys, shapes, out-of-range ids) raise ``ValueError`` naming them;
    use :func:`jaxbvh.tree.validate` for the full invariant check.
    """
    missing = [k for k in INTERCHANGE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"tree is missing array(s) {', '.join(missing)}; "
                         f"expected {', '.join(INTERCHANGE_KEYS)}")
    child = _integer_array(arrays, "child")
    if child.ndim != 2 or child.shape[1] < 2 or child.shape[0] < 1:
        raise ValueError(f"tree 'child' must be int [nodes, k>=2], got shape {child.shape}")
    nodes = child.shape[0]
    fields = {}
    for key in ("prim_start", "prim_count"):
        a = _integer_array(arrays, key)
        if a.shape != (nodes,):
            raise ValueError(f"tree '{key}' must be int [{nodes}] (a row per row of 'child'), "
                             f"got {a.dtype} {a.shape}")
        fields[key] = a
    for key in ("lo", "hi"):
        a = np.asarray(arrays[key])
        if a.shape != (nodes, 3):
            raise ValueError(f"tree '{key}' must be float [{nodes}, 3] (a row per row of 'child'), "
                             f"got {a.dtype} {a.shape}")
        fields[key] = _box_array(key, a, dtype)
    prim_index = _integer_array(arrays, "prim_index")
    if prim_index.ndim != 1:
        raise ValueError(f"tree 'prim_index' must be int [prims], got {prim_index.dtype} {prim_index.shape}")
    root = _integer_array(arrays, "root")
    if root.shape != ():
        raise ValueError(f"tree 'root' must be an integer scalar (shape ()), got {root.dtype} {root.shape}")
    root = int(root)
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
    count, start = count.astype(np.int32), start.astype(np.int32)
    parent = np.full(nodes, -1, np.int32)
    rows, cols = np.nonzero(child >= 0)
    parent[child[rows, cols]] = rows.astype(np.int32)
    prim_index = prim_index.astype(np.int32)
    fields["prim_start"] = np.where(count > 0, start, 0).astype(np.int32)

    node_cap = capacity_bucket(nodes) if pad else nodes
    prim_cap = capacity_bucket(prim_index.shape[0]) if pad else prim_index.shape[0]
    fdt = fields["lo"].dtype
    common = dict(
        parent=pad_rows(parent, node_cap, -1),
        lo=pad_rows(fields["lo"], node_cap, np.inf).astype(fdt),
        hi=pad_rows(fields["hi"], node_cap, -np.inf).astype(fdt),
        prim_start=pad_rows(fields["prim_start"], node_cap, 0),
        prim_count=pad_rows(count, node_cap, 0),
        prim_index=pad_rows(prim_index, prim_cap, -1),
        root=np.int32(root),
    )
    child = pad_rows(child, node_cap, -1)
    if child.shape[1] == 2:
        return BVH(left=child[:, 0].copy(), right=child[:, 1].copy(),
                   axis=np.full(node_cap, -1, np.int32), **common)
    return WideBVH(child=child, **common)



def _integer_array(arrays, key: str) -> np.ndarray:
    """``arrays[key]`` as int64, refused (``ValueError`` naming it) unless it is of an
    integer type with every value in int32's range (the type trees use)."""
    a = np.asarray(arrays[key])
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"tree '{key}' must be integer, got {a.dtype} {a.shape}")
    if a.size and (a.min() < _INT32.min or a.max() > _INT32.max):
        raise ValueError(f"tree '{key}' holds values outside int32 (up to {a.max()}); ids and "
                         "counts are int32")
    return a.astype(np.int64)


def _box_array(key: str, a: np.ndarray, dtype=None) -> np.ndarray:
    """Box corners ``a`` [nodes, 3] in a float type the tree can be used in.

    float32 and float64 stay as stored (or become ``dtype`` if given). A narrower float
    (float16) widens to float32, which holds each of its values exactly; a wider one
    (long double) narrows to float64 rounded outward (``lo`` down, ``hi`` up), so that
    every box still contains what it contained. Either conversion is announced with a
    ``UserWarning`` naming the array. Other types (integers, complex, bool) are refused.
    """
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"tree '{key}' must be float32 or float64 [nodes, 3], got {a.dtype} {a.shape}")
    if dtype is not None:
        return a.astype(dtype)
    if a.dtype in BOX_DTYPES:
        return a
    if a.dtype.itemsize < 4:
        warnings.warn(f"tree '{key}' is stored as {a.dtype}: widened to float32 (exact)", stacklevel=4)
        return a.astype(np.float32)
    wide = a.astype(np.float64)
    # outward: lo must not grow, hi must not shrink (np.nextafter moves one float64 ulp)
    if key == "lo":
        wide = np.where(wide > a, np.nextafter(wide, -np.inf), wide)
    else:
        wide = np.where(wide < a, np.nextafter(wide, np.inf), wide)
    warnings.warn(f"tree '{key}' is stored as {a.dtype}: narrowed to float64, rounded outward", stacklevel=4)
    return wide


def read_frame(arrays) -> Frame:
    """The frame stored with interchange ``arrays`` (identity when there is none).

    ``origin`` must be a real [3] array and ``scale`` a real scalar (shape ()), both
    finite, ``scale > 0``; otherwise ``ValueError`` naming the array.
    """
    present = [k for k in FRAME_KEYS if k in arrays]
    if not present:
        return Frame.identity()
    if len(present) == 1:
        other = "scale" if present[0] == "origin" else "origin"
        raise ValueError(f"tree has '{present[0]}' but no '{other}': a frame needs both")
    origin, scale = np.asarray(arrays["origin"]), np.asarray(arrays["scale"])
    for key, a, shape in (("origin", origin, (3,)), ("scale", scale, ())):
        real = np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
        if not real or a.shape != shape:
            what = "a real scalar (shape ())" if shape == () else "real [3]"
            raise ValueError(f"tree '{key}' must be {what}, got {a.dtype} {a.shape}")
    origin, scale = origin.astype(np.float64), float(scale)
    if not np.isfinite(origin).all():
        raise ValueError(f"tree 'origin' must be finite, got {origin.tolist()}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"tree 'scale' must be finite and > 0, got {scale!r}")
    return Frame(origin, scale)


def _out_of_subnormals(tree, frame: Frame):
    """``tree`` with boxes scaled by a power of two out of the subnormal range, and
    ``frame`` scaled back, when real boxes hold subnormal coordinates.

    XLA on CPU flushes subnormals to zero, so such boxes would collapse on the device
    (costs of zero-area boxes, optimizers breaking containment). Scaling by ``2^k`` is
    exact, and the frame's scale divided by ``2^k`` maps the boxes to the same world
    space, so the tree is the same; a ``UserWarning`` says so.
    """
    lo, hi = np.asarray(tree.lo), np.asarray(tree.hi)
    root = int(tree.root)
    finite = np.isfinite(lo) & np.isfinite(hi)
    tiny = np.finfo(lo.dtype).tiny
    sub = lambda x: (x != 0) & (np.abs(x) < tiny)  # noqa: E731
    if not (finite.all(1).any() and ((sub(lo) | sub(hi)) & finite).any()):
        return tree, frame
    if not (np.isfinite(lo[root]).all() and np.isfinite(hi[root]).all()):
        return tree, frame  # validation names the broken root box
    exponent = root_exponent(lo[root], hi[root])
    if exponent <= 0:
        return tree, frame  # the extent is not small: the subnormals are below the tree's precision
    with np.errstate(over="ignore"):
        new_lo, new_hi = np.ldexp(lo, exponent).astype(lo.dtype), np.ldexp(hi, exponent).astype(hi.dtype)
    if (np.isfinite(new_lo) != np.isfinite(lo)).any() or (np.isfinite(new_hi) != np.isfinite(hi)).any():
        return tree, frame  # would overflow elsewhere: leave it as stored
    warnings.warn(f"boxes hold subnormal coordinates (which the device flushes to zero): scaled by "
                  f"2^{exponent} (exact), and the frame's scale by 2^-{exponent}", stacklevel=4)
    return dataclasses.replace(tree, lo=new_lo, hi=new_hi), Frame(frame.origin, float(np.ldexp(frame.scale, -exponent)))

def save(path: str | os.PathLike, tree, frame: Frame | None = None) -> None:
    """Write ``tree`` to ``path`` as an interchange ``.npz`` (padding removed).

    ``frame``, if given and not the identity, is stored as ``origin`` and ``scale``.
    The file is replaced only once it is complete (:func:`jaxbvh.files.atomic_write`):
    a write that fails leaves the old file as it was, and raises ``OSError`` naming
    ``path``.
    """
    arrays = to_interchange(tree)
    if frame is not None and not frame.is_identity:
        arrays["origin"] = np.asarray(frame.origin, np.float64)
        arrays["scale"] = np.float64(frame.scale)
    with atomic_write(path) as f:
        np.savez(f, **arrays)


def load(path: str | os.PathLike, *, pad: bool = True):
    """Read an interchange ``.npz``; returns ``(tree, frame)`` (NumPy arrays).

    ``frame`` is the identity when the file stores none (boxes in world space).
    """
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
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            frame = read_frame(arrays)
            tree = from_interchange(arrays, pad=pad)
            tree, frame = _out_of_subnormals(tree, frame)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    for w in caught:  # again, naming the file
        warnings.warn(f"{path}: {w.message}", w.category, stacklevel=2)
    return tree, frame
