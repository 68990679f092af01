"""Trees for C++ tracers: tinybvh's flat node file (``TBVHNOD1``), written and read back.

:func:`export_tinybvh` writes a binary tree and its triangles in the form tinybvh's
``BVH`` holds them in memory, so that a C++ renderer loads the file with two ``memcpy``
and traces it with tinybvh's own kernels (``BVH``, and ``BVH_SoA``, ``BVH4_CPU``,
``BVH8_CPU`` made from it by their ``ConvertFrom``); :func:`read_tinybvh` reads such a
file back into a :class:`~jaxbvh.tree.layout.BVH`. The shared tracer
(``../shared/peer/tinybvh_trace``) reads the same file (``--tree NAME=FILE``).

File layout (little-endian)::

    8 bytes   magic b"TBVHNOD1"
    uint32    used_nodes, idx_count, tri_count, flags (bit 0: FLAG_REFERENCES)
    used_nodes x 32 bytes    tinybvh::BVH::BVHNode (NODE_DTYPE): float32 aabbMin[3],
                             uint32 leftFirst, float32 aabbMax[3], uint32 triCount;
                             triCount > 0: a leaf, its primitives primIdx[leftFirst ..
                             leftFirst + triCount); else an interior node whose children
                             are nodes leftFirst and leftFirst + 1
    uint32    primIdx[idx_count]         (idx_count > tri_count when triangles are
                                         referenced in several leaves)
    float32   triangles[tri_count, 3, 3] world space, v0 xyz, v1 xyz, v2 xyz

What the writer guarantees (tinybvh's own layout, what its ``CombineLeafs`` and wide
conversions rely on): node 0 is the root and node 1 unused (zeros); nodes are numbered
as ``BVH::Compact`` numbers them (sibling pairs allocated depth first, left child
first); each subtree's primitives are one contiguous run of ``primIdx`` (leaves in
depth-first order). Boxes are in world space, float32, and contain what they must in
float32: the tree's boxes (in its :class:`~jaxbvh.tree.frame.Frame`) are mapped to world
space in float64 and rounded outward, a leaf is widened to the float32 boxes of its
triangles (for a triangle it holds whole), and an interior node to its children's
boxes, so that every leaf contains its float32 world triangles and every child lies in
its parent (the tracer checks both). In a tree with spatial splits (SBVH: a triangle in
several leaves, ``FLAG_REFERENCES``) a leaf may bound only the clipped piece of a
triangle it owns; such a box is widened by the rounding that separates the tree's
frame from float32 world space (:func:`_tolerance`), then kept inside the float32
boxes of its triangles, so the pieces still cover each triangle.

Triangles are written as given, cast to float32: from a :class:`~jaxbvh.io.Mesh`
(``mesh.triangles``, float64 world space), they are bit-identical to the triangle file
of ``../shared/peer/dump_tris.py`` (uint32 n, then the same float32 array).

Wide trees are refused: tinybvh makes its 4- and 8-wide layouts from the binary tree,
so export the binary tree they were collapsed from.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from jaxbvh.files import atomic_write
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.interchange import from_interchange
from jaxbvh.tree.layout import BVH, concat_ranges, to_numpy
from jaxbvh.tree.validate import check, few_ids

__all__ = ["TINYBVH_MAGIC", "FLAG_REFERENCES", "NODE_DTYPE", "TinyBVHFile", "export_tinybvh",
           "read_tinybvh", "tinybvh_arrays"]

TINYBVH_MAGIC = b"TBVHNOD1"
#: flags bit 0: the tree names a triangle in several leaves (spatial splits)
FLAG_REFERENCES = 1
#: tinybvh::BVH::BVHNode, 32 bytes
NODE_DTYPE = np.dtype([("lo", "<f4", (3,)), ("left_first", "<u4"), ("hi", "<f4", (3,)), ("tri_count", "<u4")])
#: the header after the magic: used_nodes, idx_count, tri_count, flags
_HEADER = 8 + 4 * 4
_F32 = np.finfo(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class TinyBVHFile:
    """A node file read back (:func:`read_tinybvh`).

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy, unpadded) with float32 world-space
    boxes, nodes in the order they are first reached from the file's node 0 (breadth first; root 0;
    nodes no link reaches, the unused node 1 among them, left out), ``prim_index`` packed to the leaves' runs;
    ``triangles``: float32 [n, 3, 3] world space; ``references``: flags bit 0 (a triangle
    may sit in several leaves); ``path``: the file.
    """

    tree: BVH
    triangles: np.ndarray
    references: bool
    path: str

    @property
    def frame(self) -> Frame:
        """The identity: boxes and triangles are in world space."""
        return Frame.identity()


# ----------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------


def _outward32(x: np.ndarray, down: bool) -> np.ndarray:
    """float64 ``x`` as float32 rounded down (``down``) or up: never inside ``x``."""
    with np.errstate(over="ignore"):
        y = x.astype(np.float32)
    if down:
        return np.where(y.astype(np.float64) > x, np.nextafter(y, np.float32(-np.inf)), y)
    return np.where(y.astype(np.float64) < x, np.nextafter(y, np.float32(np.inf)), y)


def _depth_first(left: np.ndarray, right: np.ndarray, root: int):
    """Nodes in ``BVH::Compact``'s order: ``(order, slot, level, visits)``: ``order`` lists
    our node ids by file slot (slot 1, the unused node: -1), ``slot[i]`` is node i's slot,
    ``level`` [slots] each slot's depth (root 0; -1 for slot 1), ``visits`` our node ids
    in depth-first visiting order, left first (the order of the leaves' runs in primIdx:
    a sibling pair gets its slots when its parent is visited, so slot order is not it)."""
    capacity = left.shape[0]
    order, level, visits = [root, -1], [0, -1], []
    slot = np.full(capacity, -1, np.int64)
    slot[root] = 0
    stack = [(root, 0)]
    while stack:  # each pop places a node's two children: at most one pass per node
        n, d = stack.pop()
        visits.append(n)
        if left[n] < 0:
            continue
        slot[left[n]], slot[right[n]] = len(order), len(order) + 1
        order += [int(left[n]), int(right[n])]
        level += [d + 1, d + 1]
        stack += [(int(right[n]), d + 1), (int(left[n]), d + 1)]  # left first
    return np.asarray(order, np.int64), slot, np.asarray(level, np.int64), np.asarray(visits, np.int64)


def _tolerance(frame: Frame, local: np.ndarray, world: np.ndarray) -> np.ndarray:
    """How far [.., 3] world coordinates of the same point may differ between a float
    rounding in the tree's frame and one in world space: a few float32 ulps of each
    (the builders round each triangle to the tree's dtype in its frame)."""
    local_ulp = np.spacing(np.abs(local).astype(np.float32)).astype(np.float64) * frame.scale
    world_ulp = np.spacing(np.abs(world).astype(np.float32)).astype(np.float64)
    return 4.0 * (local_ulp + world_ulp)


def tinybvh_arrays(tree, triangles, frame: Frame | None = None, *, references: bool | None = None):
    """The node file's arrays for ``tree`` over ``triangles`` (module docstring).

    ``tree``: a binary :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX, padded or not) whose
    boxes are in ``frame`` (``None``: world space); ``triangles``: [n, 3, 3] world space,
    float64 (a :class:`~jaxbvh.io.Mesh`'s ``triangles``) or float32, primitive ``i`` =
    triangle ``i``; ``references``: the tree may name a triangle in several leaves
    (``None``: when it does). Returns ``(nodes, prim_idx, triangles, flags)``: a
    :data:`NODE_DTYPE` array [used_nodes], uint32 [idx_count], float32 [n, 3, 3], int.

    Raises ``ValueError`` for a wide tree, a broken tree, triangles that are not [n, 3, 3]
    finite (also in float32), primitive ids outside the triangles, triangles no leaf
    holds, and leaf boxes that do not hold their triangles (the tree of another mesh).
    """
    t = to_numpy(tree)
    if not isinstance(t, BVH):
        raise ValueError(f"tinybvh's node file holds binary trees; this tree is {np.asarray(t.child).shape[1]}-wide "
                         "(export the binary tree it was collapsed from: tinybvh makes its 4- and 8-wide "
                         "layouts from the binary tree itself)")
    frame = Frame.identity() if frame is None else frame
    tri64 = np.asarray(triangles)
    if tri64.ndim != 3 or tri64.shape[1:] != (3, 3) or tri64.shape[0] < 1:
        raise ValueError(f"triangles must be float [n >= 1, 3, 3], got {tri64.dtype} {tri64.shape}")
    if not np.issubdtype(tri64.dtype, np.floating):
        raise ValueError(f"triangles must be float [n, 3, 3], got {tri64.dtype}")
    tri64 = tri64.astype(np.float64)
    with np.errstate(over="ignore"):
        tri32 = tri64.astype(np.float32)
    if not np.isfinite(tri32).all():
        bad = np.flatnonzero(~np.isfinite(tri32).all(axis=(1, 2)))
        raise ValueError(f"triangle(s) {few_ids(bad)} are not finite in float32 (tinybvh's vertices "
                         f"are float32; |coordinates| up to {_F32.max:.3g})")
    n = tri64.shape[0]

    problems = check(t, references=bool(references))
    if problems and references is None:  # a tree that names a triangle twice: check it as such
        problems = check(t, references=True)
    if problems:
        raise ValueError(f"invalid tree: {problems[0]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))

    left, right = np.asarray(t.left, np.int64), np.asarray(t.right, np.int64)
    count, start = np.asarray(t.prim_count, np.int64), np.asarray(t.prim_start, np.int64)
    prim_index = np.asarray(t.prim_index, np.int64)
    root = int(t.root)
    order, slot, level, visits = _depth_first(left, right, root)
    placed = order[order >= 0]  # our node ids in file order (slot 1 left out)
    level = level[order >= 0]

    # primIdx: leaves in depth-first order, so every subtree's run is contiguous
    leaves = visits[count[visits] > 0]
    runs = concat_ranges(start[leaves], count[leaves])
    prims = prim_index[runs]
    if prims.size and (prims.min() < 0 or prims.max() >= n):
        bad = prims[(prims < 0) | (prims >= n)]
        raise ValueError(f"the tree names primitive(s) {few_ids(np.unique(bad))}, but there are {n} triangles "
                         "(is this the tree of another mesh?)")
    uses = np.bincount(prims, minlength=n)
    if (uses == 0).any():
        missing = np.flatnonzero(uses == 0)
        raise ValueError(f"{missing.size} of the {n} triangles are in no leaf (triangle(s) {few_ids(missing)}; "
                         f"the tree's leaves hold {prims.size} primitives): is this the tree of another mesh?")
    if references is None:
        references = bool((uses > 1).any())
    new_start = np.zeros(count.shape[0], np.int64)
    new_start[leaves] = np.cumsum(count[leaves]) - count[leaves]

    # boxes: the tree's, in world space (float64), before rounding
    lo_local, hi_local = np.asarray(t.lo, np.float64)[placed], np.asarray(t.hi, np.float64)[placed]
    lo_w, hi_w = frame.to_world(lo_local), frame.to_world(hi_local)
    if not (np.isfinite(lo_w).all() and np.isfinite(hi_w).all()):
        raise ValueError("the tree's boxes are not finite in world space")
    tri_lo, tri_hi = tri32.min(axis=1).astype(np.float64), tri32.max(axis=1).astype(np.float64)

    # each leaf must hold its triangles (or, with references, meet them), up to the
    # rounding between the tree's frame and float32 world space
    row_of = np.full(count.shape[0], -1, np.int64)  # our node id -> its row in `placed`
    row_of[placed] = np.arange(placed.size)
    ref_leaf = np.repeat(row_of[leaves], count[leaves])  # the row of each entry of `prims`
    tol_lo = _tolerance(frame, lo_local, lo_w)[ref_leaf]
    tol_hi = _tolerance(frame, hi_local, hi_w)[ref_leaf]
    if references:
        apart = (tri_lo[prims] > hi_w[ref_leaf] + tol_hi) | (tri_hi[prims] < lo_w[ref_leaf] - tol_lo)
        how = "does not meet"
    else:
        apart = (tri_lo[prims] < lo_w[ref_leaf] - tol_lo) | (tri_hi[prims] > hi_w[ref_leaf] + tol_hi)
        how = "does not contain"
    if apart.any():
        k = int(np.flatnonzero(apart.any(axis=1))[0])
        raise ValueError(f"the box of leaf {int(placed[ref_leaf[k]])} {how} its triangle {int(prims[k])} "
                         f"({int(apart.any(axis=1).sum())} such primitive(s) in all): is this the tree of "
                         "another mesh, or of these triangles in another frame?")

    # a leaf holding a clipped piece (a triangle also in another leaf): widened by the
    # rounding margin, then kept within its triangles' float32 boxes
    whole = uses[prims] == 1 if references else np.ones(prims.size, bool)
    piece_leaf = np.zeros(placed.size, bool)
    piece_leaf[ref_leaf[~whole]] = True
    lo_w = lo_w.copy()
    hi_w = hi_w.copy()
    if piece_leaf.any():
        margin_lo, margin_hi = _tolerance(frame, lo_local, lo_w), _tolerance(frame, hi_local, hi_w)
        span_lo = np.full((placed.size, 3), np.inf)
        span_hi = np.full((placed.size, 3), -np.inf)
        np.minimum.at(span_lo, ref_leaf, tri_lo[prims])
        np.maximum.at(span_hi, ref_leaf, tri_hi[prims])
        lo_w[piece_leaf] = np.maximum(lo_w - margin_lo, span_lo)[piece_leaf]
        hi_w[piece_leaf] = np.minimum(hi_w + margin_hi, span_hi)[piece_leaf]
    lo32, hi32 = _outward32(lo_w, down=True), _outward32(hi_w, down=False)
    # whole triangles inside their leaves; a piece's leaf at least meets its triangle
    w = ~whole
    np.minimum.at(lo32, ref_leaf[whole], tri32.min(axis=1)[prims[whole]])
    np.maximum.at(hi32, ref_leaf[whole], tri32.max(axis=1)[prims[whole]])
    np.minimum.at(lo32, ref_leaf[w], tri32.max(axis=1)[prims[w]])
    np.maximum.at(hi32, ref_leaf[w], tri32.min(axis=1)[prims[w]])
    if not (np.isfinite(lo32).all() and np.isfinite(hi32).all()):
        raise ValueError(f"the tree's boxes do not fit float32 in world space (|coordinates| up to {_F32.max:.3g})")

    # interior nodes hold their children: level by level, from the deepest
    interior = count[placed] == 0
    for d in range(int(level.max()) - 1, -1, -1):
        rows = np.flatnonzero(interior & (level == d))
        a, b = row_of[left[placed[rows]]], row_of[right[placed[rows]]]
        lo32[rows] = np.minimum(lo32[rows], np.minimum(lo32[a], lo32[b]))
        hi32[rows] = np.maximum(hi32[rows], np.maximum(hi32[a], hi32[b]))

    nodes = np.zeros(order.size, NODE_DTYPE)
    rows = np.flatnonzero(order >= 0)
    nodes["lo"][rows], nodes["hi"][rows] = lo32, hi32
    nodes["left_first"][rows] = np.where(interior, slot[np.maximum(left[placed], 0)], new_start[placed])
    nodes["tri_count"][rows] = count[placed]
    flags = FLAG_REFERENCES if references else 0
    return nodes, prims.astype(np.uint32), tri32, flags


def export_tinybvh(path: str | os.PathLike, tree, triangles, frame: Frame | None = None, *,
                   references: bool | None = None) -> dict:
    """Write ``tree`` over ``triangles`` as a tinybvh node file (module docstring).

    Arguments as :func:`tinybvh_arrays` (``frame``: the frame the tree's boxes are in, a
    :class:`~jaxbvh.io.Mesh`'s ``frame`` for a tree built from its ``local_boxes``). The
    file is replaced only once it is complete (:func:`jaxbvh.files.atomic_write`). Returns
    ``{"nodes", "primitive_ids", "triangles", "flags", "bytes"}`` of what was written
    (``primitive_ids``: entries of ``primIdx``, more than ``triangles`` with references).
    """
    nodes, prims, tri32, flags = tinybvh_arrays(tree, triangles, frame, references=references)
    header = np.array([nodes.size, prims.size, tri32.shape[0], flags], "<u4")
    with atomic_write(path) as f:
        f.write(TINYBVH_MAGIC)
        f.write(header.tobytes())
        f.write(nodes.tobytes())
        f.write(prims.astype("<u4").tobytes())
        f.write(tri32.astype("<f4").tobytes())
    return {"nodes": int(nodes.size), "primitive_ids": int(prims.size), "triangles": int(tri32.shape[0]),
            "flags": int(flags), "bytes": _HEADER + nodes.nbytes + 4 * prims.size + tri32.nbytes}


# ----------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------


def read_tinybvh(path: str | os.PathLike) -> TinyBVHFile:
    """Read a tinybvh node file (module docstring) into a :class:`TinyBVHFile`.

    Any node numbering is read (the nodes reachable from node 0; others, node 1 among
    them, are ignored), as long as the links form a tree. A file that is not one (another
    magic, a size that disagrees with its header, links outside the nodes, a node
    reached twice, primitive runs outside ``primIdx``, ids outside the triangles) raises
    ``ValueError`` naming the file; a missing one ``FileNotFoundError``.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"node file not found: {path}")
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a directory, expected a tinybvh node file")
    with open(path, "rb") as f:
        data = f.read()
    try:
        return TinyBVHFile(*_parse(data), path=path)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _parse(data: bytes):
    if len(data) < _HEADER or data[:8] != TINYBVH_MAGIC:
        raise ValueError(f"not a tinybvh node file (expected the magic {TINYBVH_MAGIC.decode()} and a "
                         f"{_HEADER}-byte header)")
    used, idx, tris, flags = (int(x) for x in np.frombuffer(data, "<u4", 4, 8))
    expected = _HEADER + NODE_DTYPE.itemsize * used + 4 * idx + 36 * tris
    if len(data) != expected:
        what = "cut short" if len(data) < expected else "longer than its header says"
        raise ValueError(f"{what}: its header announces {used:,} nodes, {idx:,} primitive ids and "
                         f"{tris:,} triangles ({expected:,} bytes), the file has {len(data):,} bytes")
    if used < 1 or tris < 1:
        raise ValueError(f"no tree: {used} nodes, {tris} triangles")
    off = _HEADER
    nodes = np.frombuffer(data, NODE_DTYPE, used, off)
    off += nodes.nbytes
    prim_idx = np.frombuffer(data, "<u4", idx, off).astype(np.int64)
    off += 4 * idx
    triangles = np.frombuffer(data, "<f4", 9 * tris, off).reshape(tris, 3, 3).astype(np.float32)
    if not np.isfinite(triangles).all():
        raise ValueError("triangles with NaN/inf coordinates")
    first = nodes["left_first"].astype(np.int64)
    count = nodes["tri_count"].astype(np.int64)

    # walk from node 0; the file's nodes in the order first reached
    order, seen = [0], np.zeros(used, bool)
    seen[0] = True
    parent = {0: -1}
    i = 0
    while i < len(order):  # each node enters the list once (seen), so at most `used` steps
        n = order[i]
        i += 1
        if count[n] > 0:
            if first[n] + count[n] > idx:
                raise ValueError(f"leaf node {n} covers primIdx[{first[n]}:{first[n] + count[n]}], "
                                 f"outside its {idx} entries")
            continue
        for c in (first[n], first[n] + 1):
            if not 0 <= c < used or first[n] == 0:
                raise ValueError(f"interior node {n} links to nodes {first[n]} and {first[n] + 1}, "
                                 f"outside nodes 1..{used - 1}")
            if seen[c]:
                raise ValueError(f"node {c} is reached twice (from node {parent[int(c)]} and node {n}): "
                                 "the links do not form a tree")
            seen[c] = True
            parent[int(c)] = n
            order.append(int(c))
    order = np.asarray(order, np.int64)
    new_id = np.full(used, -1, np.int64)
    new_id[order] = np.arange(order.size)
    leaf = count[order] > 0
    child = np.full((order.size, 2), -1, np.int64)
    child[~leaf, 0] = new_id[first[order][~leaf]]
    child[~leaf, 1] = new_id[first[order][~leaf] + 1]
    runs = concat_ranges(first[order][leaf], count[order][leaf])
    if runs.size and prim_idx[runs].max() >= tris:
        bad = prim_idx[runs][prim_idx[runs] >= tris]
        raise ValueError(f"primIdx names triangle(s) {few_ids(np.unique(bad))}, but the file has {tris}")
    # primIdx packed to the leaves' runs, in the order the leaves were reached
    prim_start = np.zeros(order.size, np.int64)
    prim_start[leaf] = np.cumsum(count[order][leaf]) - count[order][leaf]
    arrays = {
        "child": child,
        "prim_start": prim_start,
        "prim_count": count[order],
        "prim_index": prim_idx[runs],
        "lo": nodes["lo"][order].astype(np.float32),
        "hi": nodes["hi"][order].astype(np.float32),
        "root": np.int64(0),
    }
    tree = from_interchange(arrays, pad=False)
    return tree, triangles, bool(flags & FLAG_REFERENCES)
