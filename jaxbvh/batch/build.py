"""Build the trees of many meshes in a few compiled calls: :func:`build`.

Every builder's compiled core runs over a chunk of meshes padded to one capacity
(:mod:`jaxbvh.batch.plan`), the rows one after another or vmapped
(:mod:`jaxbvh.batch.rows`): the top-down engine (sweep, binned, median) in one call; LBVH
and PLOC in two, the Morton sort in JAX's x64 scope and the tree after it, as
:func:`jaxbvh.build` runs them. The inputs of each mesh are made by the same
:func:`jaxbvh.builders.inputs.prepare` the single build uses (checks, working dtype,
scene scale), padded to the chunk's capacity instead of the mesh's own bucket; a
padded primitive is inert, so every tree equals, node for node, :func:`jaxbvh.build` of
its mesh alone (:meth:`jaxbvh.batch.TreeBatch.unstack`; tested for every builder).

SBVH (``"sbvh"``, which needs the triangles) has no batched core: each mesh is built by
the single-mesh builder and the trees are grouped by reference slots (:func:`sbvh_groups`).

Bad input. A mesh whose boxes fail the builder's checks (no primitives, NaN or
infinite coordinates, ``lo > hi``) is refused before any compiling with a
``ValueError`` naming its position (``errors="raise"``), or left out with its own
one-line message in :attr:`BuildResult.errors` while the others are built
(``errors="keep"``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxbvh.batch import devices as batch_devices
from jaxbvh.batch import rows as batch_rows
from jaxbvh.batch.layout import Group, TreeBatch
from jaxbvh.batch.plan import BYTES_PER_SLOT, BatchConfig, chunks
from jaxbvh.batch.rows import each_row
from jaxbvh.builders import lbvh, morton, ploc, topdown
from jaxbvh.builders import dispatch
from jaxbvh.builders.configs import ALL_BUILDERS, DEFAULT_BUILDER, TRIANGLE_BUILDERS, BuilderConfig, make_config
from jaxbvh.builders.inputs import check_prim_boxes, prepare


@dataclasses.dataclass(frozen=True)
class Inputs:
    """The meshes that can be built (their boxes, checked) and the messages of those that cannot."""

    boxes: dict       # position -> (lo [n, 3], hi [n, 3]) NumPy
    errors: dict      # position -> one-line message of a mesh that cannot be built


def mesh_boxes(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` [n, 3] of a mesh: a pair of arrays, or anything with ``local_boxes()``
    (:class:`jaxbvh.io.Mesh`: scene-relative boxes, as the command line builds them)."""
    if hasattr(mesh, "local_boxes"):
        return mesh.local_boxes()
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return mesh[0], mesh[1]
    raise ValueError(f"a mesh must be a pair (lo, hi) of [n, 3] arrays or a jaxbvh.io.Mesh, "
                     f"got {type(mesh).__name__}")


def check_inputs(meshes, errors: str = "raise") -> Inputs:
    """Every mesh's boxes checked by the builders' rule (:func:`check_prim_boxes`).

    ``errors``: ``"raise"`` (``ValueError`` naming the first bad mesh's position) or
    ``"keep"`` (its message kept, the others go on).
    """
    if errors not in ("raise", "keep"):
        raise ValueError(f"errors must be 'raise' or 'keep', got {errors!r}")
    meshes = list(meshes)
    if not meshes:
        raise ValueError("batch: no meshes")
    good, bad = {}, {}
    for i, mesh in enumerate(meshes):
        try:
            good[i] = check_prim_boxes(*mesh_boxes(mesh), what=f"mesh {i}")
        except ValueError as err:
            if errors == "raise":
                raise
            bad[i] = str(err)
    return Inputs(good, bad)


def builder_config(config: BuilderConfig | str | None = None, method: str | None = None, **options):
    """The builder Config of :func:`jaxbvh.build`'s arguments (its rules: one or the other)."""
    if isinstance(config, str):
        if method is not None:
            raise TypeError(f"method given twice: {config!r} and method={method!r}")
        config, method = None, config
    if config is None:
        return make_config(DEFAULT_BUILDER if method is None else method, **options)
    if method is not None or options:
        raise TypeError("give a builder Config or method and keyword options, not both")
    if not isinstance(config, BuilderConfig) or config.method not in ALL_BUILDERS:
        raise TypeError(f"config must be a builder Config, got {type(config).__name__}")
    return config


@dataclasses.dataclass(frozen=True)
class Stacked:
    """Prepared inputs of one chunk, stacked: ``lo``, ``hi`` [R, C, 3], ``n`` int32 [R],
    ``scale`` [R] (each mesh's area scale, in the working dtype), ``real`` bool [R]
    (False: a filler row, :mod:`jaxbvh.batch.rows`)."""

    lo: Any
    hi: Any
    n: Any
    scale: Any
    real: Any


def stack_inputs(boxes: dict, rows, capacity: int, dtype, real: int | None = None) -> Stacked:
    """The prepared inputs of the meshes ``rows`` [R] (positions in ``boxes``) at ``capacity``;
    ``dtype``: the Config's (None: what :func:`jaxbvh.build` picks for the boxes); the
    first ``real`` rows are real meshes, the rest filler (None: all real)."""
    made = {}
    for i in dict.fromkeys(int(r) for r in rows):
        lo, hi, n, scale = prepare(*boxes[i], capacity=capacity, dtype=dtype)
        made[i] = (np.asarray(lo), np.asarray(hi), np.int32(n), np.asarray(scale))
    parts = [made[int(r)] for r in rows]
    real = len(parts) if real is None else real
    return Stacked(*(np.stack([p[k] for p in parts]) for k in range(4)), np.arange(len(parts)) < real)


# ----------------------------------------------------------------------------------
# The builders' compiled cores, vmapped over rows (each a function of batched arrays)
# ----------------------------------------------------------------------------------


def _topdown_rows(real, lo, hi, n, scale, max_leaf, ct, ci, *, mode, method, bins):
    return each_row(lambda a, b, c, d, e, f, g: topdown.engine(a, b, c, e, f, g, d, method=method, bins=bins),
                    mode)(real, lo, hi, n, scale, max_leaf, ct, ci)


def _centre_bounds_rows(real, lo, hi, n, *, mode):
    return each_row(morton.centre_bounds, mode)(real, lo, hi, n)


def _lbvh_topology_rows(real, lo, hi, n, origin, grid, *, mode, bits):
    return each_row(lambda *a: lbvh.topology(*a, bits=bits), mode)(real, lo, hi, n, origin, grid)


def _lbvh_assemble_rows(real, lo, hi, n, order, left, right, first, count, axis, max_leaf, ct, ci, scale, *,
                        mode, window, collapse):
    return each_row(lambda *a: lbvh.assemble(*a, window=window, collapse=collapse), mode)(
        real, lo, hi, n, order, left, right, first, count, axis, max_leaf, ct, ci, scale)


def _morton_order_rows(real, lo, hi, n, origin, grid, *, mode, bits):
    return each_row(lambda *a: morton.morton_order(*a, bits=bits), mode)(real, lo, hi, n, origin, grid)


def _ploc_rows(real, lo, hi, n, order, max_leaf, ct, ci, scale, *, mode, radius, stages, collapse):
    return each_row(lambda *a: ploc.cluster(*a, radius=radius, stages=stages, collapse=collapse), mode)(
        real, lo, hi, n, order, max_leaf, ct, ci, scale)


def quantization_rows(s: Stacked, bits: int, devices, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`jaxbvh.builders.morton.quantization` of every row of ``s``: ``origin`` [R, 3]
    and ``grid`` [R], the same host arithmetic per row (filler rows: any values)."""
    dtype = np.dtype(s.lo.dtype)
    low, high = (np.asarray(a) for a in batch_devices.on_devices(_centre_bounds_rows, (s.real, s.lo, s.hi, s.n),
                                                                  devices, mode=mode))
    extent = (high - low).max(axis=1).astype(np.float64)  # in the boxes' dtype, then float, as the single
    cells = float(2 ** (int(bits) // 3))
    with np.errstate(divide="ignore"):
        grid = np.where(extent > 0, np.minimum(cells / extent, float(np.finfo(dtype).max)), 0.0)
    return low.astype(dtype), grid.astype(dtype)


def build_rows(config: BuilderConfig, s: Stacked, devices, mode: str) -> Any:
    """Trees (a BVH with a leading axis R) of the stacked inputs ``s``, one per row;
    ``mode``: ``"map"`` or ``"vmap"`` (:mod:`jaxbvh.batch.rows`)."""
    rows, cap = s.lo.shape[0], s.lo.shape[1]
    dt = s.lo.dtype
    max_leaf = np.full(rows, config.max_leaf, np.int32)
    ct, ci = np.full(rows, config.ct, dt), np.full(rows, config.ci, dt)
    if config.method in topdown.RULES:
        bins = config.bins if config.method == "binned" else 0
        if bins and cap * bins >= 2**31:
            raise ValueError(f"binned build of capacity {cap} with {bins} bins needs keys past int32; use fewer bins")
        return batch_devices.on_devices(_topdown_rows, (s.real, s.lo, s.hi, s.n, s.scale, max_leaf, ct, ci),
                                        devices, mode=mode, method=config.method, bins=bins)
    bits = config.morton_bits
    origin, grid = quantization_rows(s, bits, devices, mode)
    collapse = config.max_leaf > 1
    if config.method == "lbvh":
        with morton.x64():
            topo = batch_devices.on_devices(_lbvh_topology_rows, (s.real, s.lo, s.hi, s.n, origin, grid), devices,
                                            mode=mode, bits=bits)
        return batch_devices.on_devices(_lbvh_assemble_rows, (s.real, s.lo, s.hi, s.n) + tuple(topo)
                                        + (max_leaf, ct, ci, s.scale), devices,
                                        mode=mode, window=lbvh.window_size(cap), collapse=collapse)
    with morton.x64():
        order = batch_devices.on_devices(_morton_order_rows, (s.real, s.lo, s.hi, s.n, origin, grid), devices,
                                         mode=mode, bits=bits)
    return batch_devices.on_devices(_ploc_rows, (s.real, s.lo, s.hi, s.n, order, max_leaf, ct, ci, s.scale),
                                    devices, mode=mode, radius=config.radius, stages=ploc.stage_sizes(cap),
                                    collapse=collapse)


@dataclasses.dataclass(frozen=True)
class BuildResult:
    """What :func:`build` returns: the ``trees`` and the ``errors`` of meshes left out
    (position -> one-line message; empty unless ``errors="keep"``)."""

    trees: TreeBatch
    errors: dict


def build(meshes, config: BuilderConfig | str | None = None, *, method: str | None = None,
          batch: BatchConfig | None = None, devices=None, errors: str = "raise", on_chunk=None,
          triangles=None, **options) -> BuildResult:
    """Build a binary BVH for every mesh, in a few compiled calls (module docstring).

    Args:
      meshes: a list of ``(lo, hi)`` pairs of [n, 3] primitive boxes (sizes may differ)
        or of :class:`jaxbvh.io.Mesh` (their scene-relative boxes).
      config, method, options: the builder, as for :func:`jaxbvh.build` (a Config, or a
        method name and its knobs).
      batch: :class:`~jaxbvh.batch.plan.BatchConfig` (capacity groups, memory bound).
      devices: the devices to split the batch axis over (None: all of ``jax.devices()``;
        an int: the first that many).
      errors: ``"raise"`` or ``"keep"`` (module docstring).
      on_chunk: called as ``on_chunk(index)`` after every compiled call, ``index`` the
        input positions of the meshes it built.
      triangles: for a builder that needs them (``"sbvh"``, :data:`TRIANGLE_BUILDERS`):
        a list of [n, 3, 3] triangles, one per mesh, in the frame of its boxes (None:
        each mesh's ``local_triangles()``, so :class:`jaxbvh.io.Mesh` inputs need none).
        Ignored by the other builders.

    Returns:
      :class:`BuildResult`; ``result.trees.unstack()`` gives every built mesh's tree, in
      input order (a mesh left out is not in the batch: ``result.trees.size`` counts all).

    SBVH. Spatial splits have no batched core: each mesh is built by the single-mesh
    builder (:func:`jaxbvh.build` with its triangles, one compiled program per reference
    capacity), and the trees are grouped by their reference slots (:func:`sbvh_groups`).
    A mesh whose triangles are refused is an error like a bad mesh (``errors``).
    """
    config = builder_config(config, method, **options)
    batch = BatchConfig() if batch is None else batch
    devs = batch_devices.resolve(devices)
    meshes = list(meshes)
    inputs = check_inputs(meshes, errors)
    if config.method in TRIANGLE_BUILDERS:
        return sbvh_groups(meshes, inputs, config, triangles, errors, on_chunk)
    return BuildResult(build_checked(inputs, config, batch, devs, config.dtype, on_chunk), inputs.errors)


def mesh_triangles(mesh, given, i: int) -> np.ndarray:
    """The triangles of mesh ``i`` for a builder that needs them: ``given[i]`` when a list
    is given, else the mesh's ``local_triangles()`` (``ValueError`` for a box pair)."""
    if given is not None:
        return np.asarray(given[i])
    if hasattr(mesh, "local_triangles"):
        return mesh.local_triangles()
    raise ValueError(f"mesh {i}: method 'sbvh' needs the triangles: pass jaxbvh.io.Mesh inputs "
                     "or triangles=[tri, ...], one [n, 3, 3] array per mesh")


def sbvh_groups(meshes, inputs: Inputs, config: BuilderConfig, triangles, errors: str, on_chunk) -> BuildResult:
    """:func:`build` for a builder that needs the triangles (module docstring of
    :func:`build`, SBVH): each checked mesh built alone, the trees stacked in groups of
    equal reference slots.

    A tree with references has its reference slots as its capacity, which is not the
    capacity bucket of its triangle count, so a group's ``prims`` hold each tree's
    reference slots (:meth:`~jaxbvh.batch.TreeBatch.unstack` then keeps every tree as
    the single build gives it)."""
    if triangles is not None and len(triangles) != len(meshes):
        raise ValueError(f"batch: {len(meshes)} meshes but {len(triangles)} triangle arrays")
    bad = dict(inputs.errors)
    groups: dict[int, list] = {}
    for i in sorted(inputs.boxes):
        lo, hi = inputs.boxes[i]
        try:
            tri = mesh_triangles(meshes[i], triangles, i)
            tree = dispatch.build(lo, hi, config, triangles=tri)
        except ValueError as err:
            if errors == "raise":
                raise ValueError(f"mesh {i}: {err}") from None
            bad[i] = f"mesh {i}: {err}"
            continue
        tree = jax.tree_util.tree_map(np.asarray, jax.device_get(tree))
        slots = int(tree.prim_index.shape[0])
        groups.setdefault(slots, []).append((tree, i))
        if on_chunk is not None:
            on_chunk(np.array([i], np.int64))
    made = []
    for slots, parts in sorted(groups.items()):
        stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *[t for t, _ in parts])
        index = np.array([i for _, i in parts], np.int64)
        made.append(Group(stacked, index, np.full(index.size, slots, np.int64)))
    return BuildResult(TreeBatch(tuple(made), len(meshes)), bad)


def build_checked(inputs: Inputs, config: BuilderConfig, batch: BatchConfig, devs: tuple, dtype,
                  on_chunk=None) -> TreeBatch:
    """:func:`build` on checked inputs; a batch of every mesh in ``inputs.boxes``."""
    positions = np.array(sorted(inputs.boxes), np.int64)
    total = len(positions) + len(inputs.errors)
    if positions.size == 0:
        return TreeBatch((), total)
    sizes = [inputs.boxes[int(i)][0].shape[0] for i in positions]
    mode = batch_rows.resolve(batch.rows, devs)
    groups = {}
    for chunk in chunks(sizes, batch, BYTES_PER_SLOT["build"], len(devs)):
        rows = positions[chunk.filled]
        stacked = stack_inputs(inputs.boxes, rows, chunk.capacity, dtype, chunk.index.size)
        trees = jax.device_get(build_rows(config, stacked, devs, mode))
        real = chunk.index.size
        trees = jax.tree_util.tree_map(lambda a: np.asarray(a)[:real], trees)
        groups.setdefault(chunk.capacity, []).append((trees, positions[chunk.index],
                                                      np.asarray(stacked.n[:real], np.int64)))
        if on_chunk is not None:
            on_chunk(positions[chunk.index])
    return TreeBatch(tuple(_join(parts) for _, parts in sorted(groups.items())), total)


def _join(parts) -> Group:
    trees = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *[p[0] for p in parts])
    return Group(trees, np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]))


__all__ = ["build", "BuildResult", "check_inputs", "mesh_boxes", "mesh_triangles", "builder_config",
           "stack_inputs", "build_rows", "quantization_rows", "sbvh_groups"]
