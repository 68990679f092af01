"""The native CPU engine of the ray queries: the same walk as a compiled scalar loop (numba).

:func:`jaxbvh.rays.trace` (and ``closest_hit``, ``any_hit``, ``all_hits``, ``measure``)
runs on one of two engines, chosen by ``engine=``:

* ``"jax"``: the array program of :mod:`jaxbvh.rays.stack_walk` (lanes of rays, one
  ``while_loop``), always available; the engine for a GPU and the one whose functions
  live inside JAX programs (:func:`jaxbvh.queries.raycast` for ``jit`` / ``vmap`` /
  ``grad``);
* ``"native"``: :mod:`jaxbvh.rays.native_kernels`, the same walk one ray at a time in a
  loop compiled by numba (no per-step kernels over lanes: ``bench/results/ray_anatomy.md``
  measured that the array program's step costs ~270 ns per lane under XLA's CPU compiler,
  ``bench/results/bench_rays_native.md`` what the loop costs). Needs numba and concrete
  (not traced) arrays; rays run on :data:`THREADS` threads (the kernel releases the GIL);
* ``"auto"`` (default): :func:`jaxbvh.native.choose` decides (the one rule of every query).

Both engines make the same walk with the same rules (visiting order, the
``entry <= t_best`` cull, the robust slab test, Möller–Trumbore in the tree's dtype, ties
to the lower id, any-hit stop, all-hits lists, the short ring stack of ``capacity``
entries with its parent-link climb, the step bound ``3 N + P + 1``), so every counter and
every hit is the same ray by ray (``tests/rays/test_native.py``), with one exception:
XLA on the CPU contracts multiply-adds in Möller–Trumbore and numba does not, so a hit
distance may differ in its last bit, and a box entered exactly there is culled by one
engine and not the other (1-130 of 20,000 rays on the bench meshes, counters only; on
those the native engine equals the NumPy twin :mod:`jaxbvh.rays.traversal_reference`,
which it matches bit for bit everywhere).
triangles are read in the tree's dtype (the JAX walk promotes a float32 tree's rays to
float64 triangles under x64); ``lanes`` and ``batch`` change nothing here but the
progress callback's steps.

Packing. The kernel reads the tree in its own layout (each node's children's boxes in the
node's row, the triangles as edge rows in leaf order), packed from the tree's arrays: a
few ms per 100k triangles, as much as tracing 20,000 camera rays. A tree and triangles
given as JAX arrays (immutable) are packed once and reused while they live
(:data:`PACKED_TREES`); NumPy arrays may change in place between calls, so they are
packed in every call (into the previous call's memory).

First-call cost. numba compiles :func:`~jaxbvh.rays.native_kernels.trace_rays` once per
float dtype and kind of tree (a few CPU seconds; a binary tree without skip flags, the
common case, gets the kernel without its wide and general branches: :func:`_branches`). numba is imported on the first native trace, never by
``import jaxbvh``, and keeps its compiled kernels where :mod:`jaxbvh.native` says (beside
jaxbvh's compilation cache).
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import jax
import numpy as np

from jaxbvh import native
from jaxbvh.numerics import INV_BIG, robust_factor
from jaxbvh.rays.stack_walk import LEAF_WIDTH, MODES, Hits
from jaxbvh.tree.layout import BVH

THREADS = 1
"""Threads a native call splits its rays over (the kernel releases the GIL). One: on the
2-core shared machine two threads gave ~25% more rays per wall second but ~20% fewer per
CPU second (bench/results/bench_rays_native.md, "Threads"); raise it for wall time on
an idle machine with more cores."""
MIN_RAYS_PER_THREAD = 256
"""Fewer rays than this per thread run on one thread (a thread's start costs ~50 us)."""

PACKED_TREES = 4
"""Packed trees kept for reuse (least recently used first out), for trees and triangles
given as JAX arrays only: those are immutable, so a packed copy stays right while they
live (a NumPy array can change in place between calls, so it is packed again each call).
Packing costs ~5 ms per 100k triangles, as much as tracing 20,000 camera rays
(bench/results/bench_rays_native.md)."""

_kernels = {}
_packed = OrderedDict()  # key (leaf ids, dtype) -> (weak references to the leaves, PackedTree)
_packed_lock = threading.Lock()  # callers on several threads share the cache
_spare = {}  # (rows, width, dtype) -> the rows of the last uncached call, reused (no page faults)


def kernels():
    """:mod:`jaxbvh.rays.native_kernels`, imported (with numba, :func:`jaxbvh.native.numba`,
    its disk cache set up first) on first use."""
    if "module" not in _kernels:
        native.numba()
        # the one library import inside a function (tests/test_architecture.py,
        # DEFERS_IMPORTS): it imports numba, which `import jaxbvh` must not
        from jaxbvh.rays import native_kernels

        _kernels["module"] = native_kernels
    return _kernels["module"]


def _c(x, dtype):
    """``x`` as a C-contiguous, writable array of ``dtype``: numba types read-only arrays
    (NumPy views of JAX arrays) apart, and each type would be one more compile."""
    a = np.ascontiguousarray(x, dtype)
    return a if a.flags.writeable else a.copy()


def _aligned_rows(n: int, width: int, dtype):
    """An uninitialised [n, width] array of ``dtype`` starting on a 64-byte boundary (a
    binary float32 node row is 64 bytes: one cache line) and its integer view; the last
    uncached call's rows of that shape when there are (:meth:`PackedTree.release`): fresh memory
    costs a page fault per 4 kB, more than packing into it."""
    spare = _spare.pop((n, width, np.dtype(dtype).str), None)
    if spare is not None:
        return spare
    itemsize = np.dtype(dtype).itemsize
    raw = np.empty(n * width * itemsize + 64, np.uint8)
    offset = -raw.ctypes.data % 64
    rows = raw[offset:offset + n * width * itemsize].view(dtype).reshape(n, width)
    return rows, rows.view(np.int32 if itemsize == 4 else np.int64)


def row_width(k: int, dtype) -> int:
    """Entries of a packed node row of a ``k``-wide tree (:func:`~jaxbvh.rays.native_kernels.trace_rays`):
    ``7 k + 2``, padded to whole 64-byte cache lines where the padding is under 7 entries
    (so ``(width - 2) // 7`` still gives ``k``): a 4-wide float32 row is 128 bytes, two
    lines, rather than 120 bytes over two or three."""
    width = 7 * k + 2
    per_line = 64 // np.dtype(dtype).itemsize
    padded = -(-width // per_line) * per_line
    return padded if (padded - 2) // 7 == k else width


class PackedTree:
    """A tree and its triangles packed as the kernel reads them
    (:func:`~jaxbvh.rays.native_kernels.trace_rays`; :func:`~jaxbvh.rays.native_kernels.pack_rows`
    fills them: O(N k + P), a few ms per 100k triangles)."""

    def __init__(self, kernels, tree, triangles, skip, dtype):
        i32 = np.int32
        if isinstance(tree, BVH):
            child = np.stack([np.asarray(tree.left, i32), np.asarray(tree.right, i32)], axis=1)
            axis = _c(tree.axis, i32)
        else:
            child = _c(tree.child, i32)
            axis = np.full(child.shape[0], -1, i32)  # wide nodes: distance order
        n, k = child.shape
        self.k = k
        self.has_skip = skip is not None and bool(np.any(skip))
        skip = np.zeros(n, i32) if skip is None else _c(skip, i32)
        prim_index = _c(tree.prim_index, i32)
        self.root = int(np.asarray(tree.root))
        self.parent = _c(tree.parent, i32)
        self.rows, self.irows = _aligned_rows(n, row_width(k, dtype), dtype)
        self.flags = np.empty(n, i32)
        self.slot_rows, self.slot_irows = _aligned_rows(prim_index.shape[0], 10, dtype)
        lo, hi = _c(tree.lo, dtype), _c(tree.hi, dtype)
        n_rows = kernels.pack_rows(child, lo, hi, _c(tree.prim_start, i32), _c(tree.prim_count, i32), axis, skip,
                                   prim_index, _c(triangles, dtype), self.rows, self.irows, self.flags,
                                   self.slot_rows, self.slot_irows)
        # the kernel reads the filled rows only (a capacity's padding shares the last one)
        self.full_rows = (self.rows, self.irows)
        self.rows, self.irows, self.flags = self.rows[:n_rows], self.irows[:n_rows], self.flags[:n_rows]
        self.root_box = np.concatenate([lo[self.root], hi[self.root]])
        self.consts = np.array([1, robust_factor(dtype), INV_BIG], dtype)

    def release(self):
        """Leave the rows for the next uncached call (this object is not used again)."""
        for rows, irows in (self.full_rows, (self.slot_rows, self.slot_irows)):
            _spare[(rows.shape[0], rows.shape[1], rows.dtype.str)] = (rows, irows)


def _immutable(x) -> bool:
    return isinstance(x, (jax.Array, np.generic, int, float))


def packed(kernels, tree, triangles, skip, dtype) -> tuple[PackedTree, bool]:
    """The packed arrays of ``tree`` and ``triangles`` (:class:`PackedTree`) and whether they
    are cached: a tree and triangles of JAX arrays (immutable) packed before and still
    alive are not packed again (:data:`PACKED_TREES`); the key holds the leaves' ids and
    weak references check that they are the same objects (an id is reused after death)."""
    leaves = jax.tree_util.tree_leaves((tree, triangles))
    if skip is not None or not all(_immutable(x) for x in leaves):
        return PackedTree(kernels, tree, triangles, skip, dtype), False
    key = (tuple(id(x) for x in leaves), type(tree).__name__, np.dtype(dtype).str)
    with _packed_lock:
        hit = _packed.get(key)
        if hit is not None and all(ref is leaf or (callable(ref) and ref() is leaf)
                                   for ref, leaf in zip(hit[0], leaves)):
            _packed.move_to_end(key)
            return hit[1], True
    arrays = PackedTree(kernels, tree, triangles, None, dtype)
    # scalars cannot be weakly referenced: they are kept (and compared) as they are; the
    # entry goes when a leaf dies (a dict's pop is atomic: no lock in a callback of the
    # collector, which may run while this thread holds it)
    forget = lambda _, key=key: _packed.pop(key, None)  # noqa: E731
    refs = tuple(weakref.ref(x, forget) if isinstance(x, jax.Array) else x for x in leaves)
    with _packed_lock:
        _packed[key] = (refs, arrays)
        _packed.move_to_end(key)
        while len(_packed) > PACKED_TREES:
            _packed.popitem(last=False)
    return arrays, True


def _branches(packed_tree: PackedTree) -> tuple[int | None, int | None]:
    """The kernel's ``four_wide`` and ``other_nodes`` arguments for this tree: ``None``
    where the tree has no node for that branch of :func:`~jaxbvh.rays.native_kernels.trace_rays`
    (the written-out 4-wide node; the general k-ary loops). numba drops a branch under
    ``x is not None`` with ``x`` None from the compiled code, so a binary tree without
    skip flags (the common case) compiles the binary branch alone: its cold first call
    6.0-6.4 CPU s against 8.8 with every branch (spot, 1,000 rays, load 0.1-0.4)."""
    binary_only = packed_tree.k == 2 and not packed_tree.has_skip
    return (1 if packed_tree.k == 4 else None), (None if binary_only else 1)


def trace(tree, triangles, origin, direction, t_min, t_max, *, dtype, mode: str, capacity: int, max_hits: int,
          step_limit: int, skip=None, leaf_width: int = LEAF_WIDTH, batch: int | None = None,
          on_batch: Callable[[int], None] | None = None) -> Hits:
    """The native engine of :func:`jaxbvh.rays.traversal.trace` (checked arguments):
    :class:`Hits` of NumPy arrays [R], the dtypes of the JAX engine's.

    ``tree`` (NumPy or JAX arrays), ``triangles`` [T, 3, 3], ``origin``, ``direction``
    [R, 3]; ``t_min``, ``t_max`` scalars or [R]; ``dtype``: the tree's float dtype as the
    JAX engine sees it (float32 unless x64); ``skip``: [N] bool or None. ``batch``: rays
    between ``on_batch(n)`` calls (None: one call for all).
    """
    k = kernels()
    a, cached = packed(k, tree, triangles, skip, dtype)
    r = origin.shape[0]
    o = _c(origin, dtype)
    d = _c(direction, dtype)
    lo_t = _c(np.broadcast_to(np.asarray(t_min, dtype), (r,)), dtype)
    hi_t = _c(np.broadcast_to(np.asarray(t_max, dtype), (r,)), dtype)
    all_hits = mode == "all"
    h = max_hits if all_hits else 0
    out = dict(t=np.empty(r, dtype), u=np.empty(r, dtype), v=np.empty(r, dtype), prim=np.empty(r, np.int32),
               counts=np.empty((r, 4), np.int32), limit=np.empty(r, np.bool_), hit_count=np.zeros(r, np.int32),
               hit_prims=np.full((r, h), -1, np.int32), hit_t=np.full((r, h), np.inf, dtype))
    code = MODES.index(mode)

    def run(first, stop):
        k.trace_rays(a.rows, a.irows, a.flags, a.has_skip, a.parent, a.root_box, a.slot_rows, a.slot_irows, a.root, o, d, lo_t, hi_t, a.consts, code, int(capacity), int(h),
                     int(step_limit), int(max(1, leaf_width)), *_branches(a), first, stop, out["t"], out["u"], out["v"],
                     out["prim"], out["counts"], out["limit"], out["hit_count"], out["hit_prims"], out["hit_t"])

    step = max(1, r if batch is None else int(batch))
    for start in range(0, r, step):
        stop = min(start + step, r)
        threads = max(1, min(THREADS, (stop - start) // MIN_RAYS_PER_THREAD))
        if threads == 1:
            run(start, stop)
        else:
            # interleaved chunks would balance better, but contiguous ones keep each thread's
            # rays (and so its writes) apart; rays of a set are shuffled enough in practice
            edges = np.linspace(start, stop, threads + 1).astype(int)
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(run, edges[:-1], edges[1:]))
        if on_batch is not None:
            on_batch(stop - start)
    if not cached:
        a.release()
    extra = {}
    if all_hits:
        extra = dict(hit_count=out["hit_count"], hit_prims=out["hit_prims"], hit_t=out["hit_t"],
                     hits_overflow=out["hit_count"] > max_hits)
    c = out["counts"]
    return Hits(t=out["t"], prim=out["prim"], u=out["u"], v=out["v"], box_tests=c[:, 0].copy(),
                prim_tests=c[:, 1].copy(), nodes_visited=c[:, 2].copy(), leaves_visited=c[:, 3].copy(),
                stack_overflow=np.zeros(r, np.bool_), step_limit=out["limit"], **extra)
