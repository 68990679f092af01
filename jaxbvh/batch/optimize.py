"""Optimize every tree of a batch with any optimizer in one compiled call per chunk: :func:`optimize`.

Every optimizer of :data:`jaxbvh.optimize.OPTIMIZERS` (``hc``, ``sa``, ``reinsert``,
``treelet``, ``pipeline``) follows one protocol (:mod:`jaxbvh.optimize.protocol`): each
tree's state is made by ``init`` on the host (:func:`jaxbvh.optimize.driver.init_batch`),
and the states of a chunk are stacked. How the compiled call runs them follows
:mod:`jaxbvh.batch.rows`: ``"vmap"`` runs one ``while_loop`` of ``step`` vmapped until
every state is done, then ``result`` vmapped (a done state is a fixed point of ``step``,
``keep_if_done``, so a tree that has converged stops changing while the others go on);
``"map"`` runs each row's own ``while_loop`` and ``result``, one row after another, the
single-tree program exactly. Either way each tree's result is exactly its single-tree run
(:func:`jaxbvh.optimize.optimize` of the tree alone; tested node for node for every
optimizer). The trees run at their group's capacity (:mod:`jaxbvh.batch.layout`);
padding is inert, and the results are cut back to each tree's own capacity by
:meth:`~jaxbvh.batch.TreeBatch.unstack`.

Chunks follow :mod:`jaxbvh.batch.plan` (the memory bound with the optimizers' bytes per
slot) and the batch axis splits over devices (:mod:`jaxbvh.batch.devices`): each
device's loop stops when its own trees are done.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.batch import devices as batch_devices
from jaxbvh.batch import rows as batch_rows
from jaxbvh.batch.layout import Group, TreeBatch
from jaxbvh.batch.plan import BYTES_PER_SLOT, BatchConfig, max_rows
from jaxbvh.batch.plan import batch_rows as rows_for
from jaxbvh.batch.rows import each_row
from jaxbvh.optimize import DEFAULT_METHOD, OPTIMIZERS, make_config
from jaxbvh.optimize.driver import stack_states
from jaxbvh.tree.layout import BVH


@dataclasses.dataclass(frozen=True)
class BatchOptimizeResult:
    """What :func:`optimize` returns: the optimized ``trees`` (a :class:`TreeBatch` with
    the input's groups) and each mesh's figures, in input order (NaN / -1 / False for a
    mesh not in the batch): ``sah``, ``sah_start`` float64 [M]; ``steps``, ``moves``
    int64 [M]; ``converged`` bool [M] (as :class:`~jaxbvh.optimize.protocol.OptimizeResult`)."""

    trees: TreeBatch
    sah: np.ndarray
    sah_start: np.ndarray
    steps: np.ndarray
    moves: np.ndarray
    converged: np.ndarray


def _run_rows(real, states, *, mode, step, result):
    """Every row's ``step`` until it is done, then its ``result`` (batched; ``mode``:
    :mod:`jaxbvh.batch.rows`)."""
    if mode == "vmap":  # one loop for all rows, until the last is done (done rows are fixed points)
        states = jax.lax.while_loop(lambda s: ~jnp.all(s.progress.done), jax.vmap(step), states)
        return jax.vmap(result)(states)

    def run_one(state):  # the single-tree run: its own loop, only the branches it takes
        return result(jax.lax.while_loop(lambda s: ~s.progress.done, step, state))

    return each_row(run_one, mode)(real, states)


def _row(trees: BVH, i: int) -> BVH:
    return jax.tree_util.tree_map(lambda a: a[i], trees)


def optimize(trees: TreeBatch, method: str = DEFAULT_METHOD, config=None, *, keys=None,
             batch: BatchConfig | None = None, devices=None, on_chunk=None, **options) -> BatchOptimizeResult:
    """Run optimizer ``method`` on every tree of ``trees`` (module docstring).

    Args:
      trees: a :class:`~jaxbvh.batch.TreeBatch` (:func:`jaxbvh.batch.build`).
      method, config, options: as :func:`jaxbvh.optimize.optimize` (a name of
        ``OPTIMIZERS``, its Config, fields of it to set).
      keys: [M] ``jax.random`` keys, one per mesh, for ``"sa"`` (None: every tree gets
        ``init``'s default key, as the single run does).
      batch: :class:`~jaxbvh.batch.plan.BatchConfig` (its memory bound and ``rows``
        apply: the groups are the input's). devices: as :func:`jaxbvh.batch.build`.
      on_chunk: called as ``on_chunk(index)`` after every compiled call, ``index`` the
        input positions of the meshes it optimized.

    Returns:
      :class:`BatchOptimizeResult`.
    """
    config = make_config(method, config, **options)
    optimizer = OPTIMIZERS[method]
    batch = BatchConfig() if batch is None else batch
    devs = batch_devices.resolve(devices)
    mode = batch_rows.resolve(batch.rows, devs)
    if not isinstance(trees, TreeBatch):
        raise ValueError(f"trees must be a jaxbvh.batch.TreeBatch, got {type(trees).__name__}")
    if keys is not None and len(keys) != trees.size:
        raise ValueError(f"optimize: {trees.size} meshes but {len(keys)} keys")
    m = trees.size
    out = dict(sah=np.full(m, np.nan), sah_start=np.full(m, np.nan), steps=np.full(m, -1, np.int64),
               moves=np.full(m, -1, np.int64), converged=np.zeros(m, bool))
    groups = []
    for group in trees.groups:
        most = max_rows(group.capacity, BYTES_PER_SLOT["optimize"], batch.memory_mb, len(devs))
        parts = []
        for start in range(0, len(group), most):
            rows = np.arange(start, min(start + most, len(group)))
            filled = np.full(min(rows_for(rows.size, len(devs)), most), rows[0])
            filled[: rows.size] = rows
            states = stack_states(optimizer.init(_row(group.trees, int(r)), config,
                                                 None if keys is None else keys[int(group.index[r])])
                                  for r in filled)
            real = np.arange(filled.size) < rows.size
            res = jax.device_get(batch_devices.on_devices(_run_rows, (real, states), devs, mode=mode,
                                                          step=optimizer.step, result=optimizer.result))
            res = jax.tree_util.tree_map(lambda a: np.asarray(a)[: rows.size], res)
            at = group.index[rows]
            for field in out:
                out[field][at] = getattr(res, field)
            parts.append(res.tree)
            if on_chunk is not None:
                on_chunk(at)
        joined = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *parts)
        groups.append(Group(joined, group.index, group.prims))
    return BatchOptimizeResult(TreeBatch(tuple(groups), m), **out)
