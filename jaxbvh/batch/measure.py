"""Costs, traversal and collapsing over a batch of trees: :func:`costs`, :func:`trace`, :func:`collapse`.

* :func:`costs`: the SAH and the papers' costs (:mod:`jaxbvh.tree.cost`) of every tree,
  each cost function vmapped over a group: one compiled call per group and cost.
* :func:`trace`: a ray set per tree (``origin``, ``direction`` [R, 3] each, the same
  ``R`` for all), :func:`jaxbvh.rays.traversal.trace_batch` vmapped over the trees of a
  group (triangles padded to the group's capacity: padded primitive slots are never
  referenced), in slices of ``rays_per_call`` rays; every tree's hits and counts
  equal the single-tree :func:`jaxbvh.rays.traversal.trace` (tested). The stack is the
  ray walk's fixed one (:data:`jaxbvh.rays.stack_walk.STACK`, climbing by parent links
  where it spills), as the single trace's: one compiled program for any depth. Under
  ``engine="native"`` (or ``"auto"`` on a CPU with numba) each tree is traced by the
  native engine instead (:mod:`jaxbvh.rays.native`), mesh after mesh.
* :func:`collapse`: Pinto's collapse (:func:`jaxbvh.wide.collapse`) of every tree. Its
  level schedule is made on the host from each tree's depths, so this is a loop of
  single-tree calls (one compile per capacity), not one vmapped call.

The twin of each is the single-tree function itself, run tree by tree in the tests.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import native as engines
from jaxbvh.batch import devices as batch_devices
from jaxbvh.batch.layout import TreeBatch
from jaxbvh.rays.stack_walk import STACK
from jaxbvh.rays import native as rays_native
from jaxbvh.rays.traversal import check_rays, intersect_triangle, max_steps, trace_batch
from jaxbvh.tree.cost import goldsmith_salmon_cost, ng_trifonov_cost, sah
from jaxbvh.tree.layout import to_numpy
from jaxbvh.wide.collapse import collapse as collapse_one

COSTS = ("sah", "ng_trifonov", "goldsmith_salmon")


def _cost_rows(trees, ct, ci):
    return (jax.vmap(sah)(trees, ct, ci), jax.vmap(ng_trifonov_cost)(trees), jax.vmap(goldsmith_salmon_cost)(trees))


def costs(trees: TreeBatch, ct: float = 1.0, ci: float = 1.0, *, devices=None) -> dict[str, np.ndarray]:
    """``{"sah", "ng_trifonov", "goldsmith_salmon"}``: float64 [M] per mesh (NaN for a mesh
    left out), each as :func:`jaxbvh.all_costs` gives it for the tree alone."""
    devs = batch_devices.resolve(devices)
    out = {name: np.full(trees.size, np.nan) for name in COSTS}
    for group in trees.groups:
        rows, pad = _padded_rows(len(group), len(devs))
        t = host_rows(group.trees, rows)
        dt = t.lo.dtype
        ct_r, ci_r = np.full(rows.size, ct, dt), np.full(rows.size, ci, dt)
        values = jax.device_get(batch_devices.on_devices(_cost_rows, (t, ct_r, ci_r), devs))
        for name, v in zip(COSTS, values):
            out[name][group.index] = np.asarray(v, np.float64)[: len(group)]
    return out


def host_rows(trees, rows):
    """The stacked ``trees`` at ``rows`` [R], picked on the host (NumPy): JAX indexing
    would compile a gather per array and shape, which costs more than the pick itself
    in a process that has to load every program anew (a cluster worker)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[rows], to_numpy(trees))


def _padded_rows(count: int, devices: int):
    """Row ids [R] of a group of ``count`` on ``devices`` (filler rows repeat row 0)."""
    total = -(-count // devices) * devices
    rows = np.zeros(total, np.int64)
    rows[:count] = np.arange(count)
    return rows, total - count


def _trace_rows(trees, triangles, origin, direction, *, mode, capacity, max_hits):
    def one(tree, tri, o, d):
        return trace_batch(tree, tri, o, d, 0.0, jnp.inf, intersect=intersect_triangle, mode=mode,
                           capacity=capacity, max_hits=max_hits)
    return jax.vmap(one)(trees, triangles, origin, direction)


def trace(trees: TreeBatch, triangles, origin, direction, *, mode: str = "closest", max_hits: int = 16,
          rays_per_call: int = 256, devices=None, engine: str = engines.DEFAULT_ENGINE,
          errors: str = "raise") -> list:
    """Trace each mesh's rays through its tree; a list of per-mesh ``Hits`` (NumPy, [R] each).

    ``triangles``: per mesh [n, 3, 3] in the tree's frame; ``origin``, ``direction``: per
    mesh [R, 3] (one R for all meshes). ``mode``: ``"closest"``, ``"any"``, ``"all"``.
    Counts per tree: ``hits.box_tests.sum()`` etc. A mesh left out gets None. A broken
    tree (a ray past the step bound; a stack overflow): ``errors="raise"`` (default)
    raises naming the first such mesh, like the single trace; ``errors="keep"`` gives that
    mesh None, delivers the others, and warns once naming every mesh it left out and why
    (as :func:`jaxbvh.batch.build`'s ``errors``). ``engine``:
    ``"auto"``, ``"jax"`` or ``"native"`` (:func:`jaxbvh.native.choose`): the native
    engine traces mesh after mesh with :mod:`jaxbvh.rays.native` (the same hits and
    counters; ``rays_per_call`` and ``devices`` then change nothing).
    """
    if errors not in ("raise", "keep"):
        raise ValueError(f"errors must be 'raise' or 'keep', got {errors!r}")
    if not len(triangles) == len(origin) == len(direction) == trees.size:
        raise ValueError(f"trace: {trees.size} meshes but {len(triangles)} triangle sets, "
                         f"{len(origin)} origins and {len(direction)} directions")
    rays = [check_rays(o, d) for o, d in zip(origin, direction)]
    if len({o.shape[0] for o, _ in rays}) > 1:
        raise ValueError("trace: every mesh needs the same number of rays")
    failed = {}  # mesh -> why it was left out (errors="keep")

    def checked(hits, mesh: int, capacity: int):
        try:
            _check_hits(hits, mesh, capacity)
        except (ValueError, RuntimeError) as exc:
            if errors == "raise":
                raise
            failed[mesh] = str(exc)
            return None
        return hits

    if engines.choose(engine, triangles, origin, direction) == "native":
        out = _trace_native(trees, triangles, rays, checked, mode=mode, max_hits=max_hits)
    else:
        out = _trace_jax(trees, triangles, rays, checked, mode=mode, max_hits=max_hits,
                         rays_per_call=rays_per_call, devices=devices)
    if failed:
        warnings.warn(f"trace: {len(failed)} mesh(es) left out (None): " + "; ".join(failed[m] for m in sorted(failed)),
                      stacklevel=2)
    return out


def _trace_jax(trees: TreeBatch, triangles, rays, checked, *, mode, max_hits, rays_per_call, devices) -> list:
    """:func:`trace` on the JAX engine: each group's trees in compiled calls of
    ``rays_per_call`` rays per mesh; ``checked(hits, mesh, capacity)`` keeps or drops a mesh."""
    devs = batch_devices.resolve(devices)
    out = [None] * trees.size
    for group in trees.groups:
        capacity = STACK  # at least every tree's arity (binary trees)
        rows, _ = _padded_rows(len(group), len(devs))
        t = host_rows(group.trees, rows)
        dt = np.dtype(t.lo.dtype)
        tri = np.zeros((rows.size, group.capacity, 3, 3), dt)
        for k, r in enumerate(rows):
            mesh_tri = np.asarray(triangles[int(group.index[r])], dt)
            tri[k, : mesh_tri.shape[0]] = mesh_tri
        o = np.stack([rays[int(group.index[r])][0] for r in rows]).astype(dt)
        d = np.stack([rays[int(group.index[r])][1] for r in rows]).astype(dt)
        parts = []
        for start in range(0, o.shape[1], rays_per_call):
            stop = min(start + rays_per_call, o.shape[1])
            o_s, d_s = _pad_rays(o[:, start:stop], rays_per_call), _pad_rays(d[:, start:stop], rays_per_call)
            hits = jax.device_get(batch_devices.on_devices(
                _trace_rows, (t, tri, o_s, d_s), devs, mode=mode, capacity=capacity, max_hits=max_hits))
            parts.append(jax.tree_util.tree_map(lambda a, n=stop - start: np.asarray(a)[:, :n], hits))
        hits = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *parts)
        for k in range(len(group)):
            one = jax.tree_util.tree_map(lambda a, k=k: a[k], hits)
            out[int(group.index[k])] = checked(one, int(group.index[k]), capacity)
    return out


def _trace_native(trees: TreeBatch, triangles, rays, checked, *, mode, max_hits) -> list:
    """:func:`trace` on the native engine: each mesh's padded tree row as the JAX engine
    reads it (the same step bound), its own triangles, one kernel call per mesh."""
    out = [None] * trees.size
    for group in trees.groups:
        t = to_numpy(group.trees)
        dt = np.dtype(jax.dtypes.canonicalize_dtype(np.asarray(t.lo).dtype))
        for k in range(len(group)):
            mesh = int(group.index[k])
            tree = jax.tree_util.tree_map(lambda a, k=k: np.asarray(a)[k], t)
            o, d = rays[mesh]
            one = rays_native.trace(tree, np.asarray(triangles[mesh], dt), o, d, 0.0, np.inf, dtype=dt, mode=mode,
                                    capacity=STACK, max_hits=max_hits, step_limit=max_steps(tree))
            out[mesh] = checked(one, mesh, STACK)
    return out


def _pad_rays(a: np.ndarray, length: int) -> np.ndarray:
    """[B, r, 3] rays padded to [B, length, 3] with copies of the first ray (one shape: one compile)."""
    if a.shape[1] == length:
        return a
    pad = np.repeat(a[:, :1], length - a.shape[1], axis=1)
    return np.concatenate([a, pad], axis=1)


def _check_hits(hits, mesh: int, capacity: int) -> None:
    if np.asarray(hits.step_limit).any():
        raise ValueError(f"trace: mesh {mesh}: a ray did not end within the step bound (a broken tree)")
    if np.asarray(hits.stack_overflow).any():
        raise RuntimeError(f"trace: mesh {mesh}: the traversal stack of {capacity} entries overflowed")


def collapse(trees: TreeBatch, method: str = "dp", **options) -> list:
    """Pinto's collapse of every tree (module docstring): a list of ``CollapseResult`` in
    input order, each :func:`jaxbvh.collapse` of the mesh's own tree (None: left out)."""
    return [None if t is None else collapse_one(t, method, **options) for t in trees.unstack()]
