"""Optimize every tree of a batch with any optimizer in one compiled call per chunk: :func:`optimize`.

Every optimizer of :data:`jaxbvh.optimize.OPTIMIZERS` (``hc``, ``sa``, ``reinsert``,
``treelet``, ``pipeline``) follows one protocol (:mod:`jaxbvh.optimize.protocol`) and
runs under the one batch driver, :func:`jaxbvh.optimize.driver.run_states`: each
tree's state is made by ``init`` on the host, the states of a chunk are stacked, and
one compiled call runs them, rows side by side (``"vmap"``) or one after another
(``"map"``, the single-tree program exactly), as :mod:`jaxbvh.batch.rows` picks for the
devices. Either way each tree's result is exactly its single-tree run
(:func:`jaxbvh.optimize.optimize` of the tree alone; tested node for node for every
optimizer). What this module adds to the driver is the layout of a batch of meshes:
the trees run at their group's capacity (:mod:`jaxbvh.batch.layout`; padding is inert,
and the results are cut back to each tree's own capacity by
:meth:`~jaxbvh.batch.TreeBatch.unstack`); chunks follow :mod:`jaxbvh.batch.plan` (the
memory bound with the optimizers' bytes per slot), their rows padded to a batch-size
bucket with filler rows that run no step; the batch axis splits over devices
(:mod:`jaxbvh.batch.devices`: each device's loop stops when its own trees are done).

Errors. With ``errors="keep"`` one bad tree fails alone and the rest is delivered: a
tree whose ``init`` raises is left out with its one-line message in
:attr:`BatchOptimizeResult.errors`, and a chunk whose compiled call raises is run
again one tree per call, so only the tree that fails is left out (its figures NaN /
-1 / False, its tree None in ``unstack()``). ``errors="raise"`` (the default) lets the first
error through, as the single run raises it.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import numpy as np

from jaxbvh.batch import devices as batch_devices
from jaxbvh.batch import rows as batch_rows
from jaxbvh.batch.layout import Group, TreeBatch
from jaxbvh.batch.plan import BYTES_PER_SLOT, BatchConfig, max_rows
from jaxbvh.batch.plan import batch_rows as rows_for
from jaxbvh.optimize import DEFAULT_METHOD, OPTIMIZERS, make_config
from jaxbvh.optimize.driver import run_states, stack_states
from jaxbvh.tree.layout import BVH


@dataclasses.dataclass(frozen=True)
class BatchOptimizeResult:
    """What :func:`optimize` returns: the optimized ``trees`` (a :class:`TreeBatch` with
    the input's groups, less any tree left out) and each mesh's figures, in input order
    (NaN / -1 / False for a mesh not in the batch or left out): ``sah``, ``sah_start``
    float64 [M]; ``steps``, ``moves`` int64 [M]; ``converged`` bool [M] (as
    :class:`~jaxbvh.optimize.protocol.OptimizeResult`); ``errors``: position -> one-line
    message of a tree left out (empty unless ``errors="keep"``, module docstring)."""

    trees: TreeBatch
    sah: np.ndarray
    sah_start: np.ndarray
    steps: np.ndarray
    moves: np.ndarray
    converged: np.ndarray
    errors: dict = dataclasses.field(default_factory=dict)


def _row(trees: BVH, i: int) -> BVH:
    return jax.tree_util.tree_map(lambda a: a[i], trees)


def one_line(exc: BaseException) -> str:
    """An exception as one line (its message, else its type's name)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def _run_chunk(optimizer, states: list, devs: tuple, mode: str, most: int):
    """The results of ``states`` (one per tree, NumPy, in order): one compiled call of
    the batch driver, the rows padded to a batch-size bucket by filler rows."""
    rows = min(rows_for(len(states), len(devs)), most)
    real = np.arange(rows) < len(states)
    stacked = stack_states(states + [states[0]] * (rows - len(states)))
    call = partial(batch_devices.on_devices, devices=devs) if len(devs) > 1 else None
    res = jax.device_get(run_states(optimizer, stacked, mode=mode, real=real, call=call))
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[: len(states)], res)


def _run_or_split(optimizer, rows: list, states: list, devs: tuple, mode: str, most: int, fail) -> list:
    """``[(rows, results)]`` of one chunk (``errors="keep"``, module docstring): one call
    for all its rows; if that call raises, one call per row, and a row whose own call
    raises goes to ``fail(row, exc)``. ``fail`` None (``errors="raise"``): the first
    error goes through."""
    try:
        return [(rows, _run_chunk(optimizer, states, devs, mode, most))]
    except Exception:  # noqa: BLE001 (find the tree that fails: one per call)
        if fail is None:
            raise
    done = []
    for r, state in zip(rows, states):
        try:
            done.append(([r], _run_chunk(optimizer, [state], devs, mode, most)))
        except Exception as exc:  # noqa: BLE001
            fail(r, exc)
    return done


def optimize(trees: TreeBatch, method: str = DEFAULT_METHOD, config=None, *, keys=None,
             batch: BatchConfig | None = None, devices=None, errors: str = "raise", on_chunk=None,
             **options) -> BatchOptimizeResult:
    """Run optimizer ``method`` on every tree of ``trees`` (module docstring).

    Args:
      trees: a :class:`~jaxbvh.batch.TreeBatch` (:func:`jaxbvh.batch.build`).
      method, config, options: as :func:`jaxbvh.optimize.optimize` (a name of
        ``OPTIMIZERS``, its Config, fields of it to set).
      keys: [M] ``jax.random`` keys, one per mesh, for ``"sa"`` (None: every tree gets
        ``init``'s default key, as the single run does).
      batch: :class:`~jaxbvh.batch.plan.BatchConfig` (its memory bound and ``rows``
        apply: the groups are the input's). devices: as :func:`jaxbvh.batch.build`.
      errors: ``"raise"`` or ``"keep"`` (module docstring).
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
    if errors not in ("raise", "keep"):
        raise ValueError(f"errors must be 'raise' or 'keep', got {errors!r}")
    if keys is not None and len(keys) != trees.size:
        raise ValueError(f"optimize: {trees.size} meshes but {len(keys)} keys")
    m = trees.size
    out = dict(sah=np.full(m, np.nan), sah_start=np.full(m, np.nan), steps=np.full(m, -1, np.int64),
               moves=np.full(m, -1, np.int64), converged=np.zeros(m, bool))
    failed: dict = {}

    def fail(position: int, exc: Exception) -> None:
        if errors == "raise":
            raise exc
        failed[position] = f"mesh {position}: {one_line(exc)}"

    groups = []
    for group in trees.groups:
        most = max_rows(group.capacity, BYTES_PER_SLOT["optimize"], batch.memory_mb, len(devs))
        parts = []  # (rows of the group, their results)
        for start in range(0, len(group), most):
            rows, states = [], []
            for r in range(start, min(start + most, len(group))):
                at = int(group.index[r])
                try:
                    states.append(optimizer.init(_row(group.trees, r), config, None if keys is None else keys[at]))
                    rows.append(r)
                except Exception as exc:  # noqa: BLE001 (that tree's error, errors="keep")
                    fail(at, exc)
            if rows:
                parts += _run_or_split(optimizer, rows, states, devs, mode, most, None if errors == "raise" else
                                       lambda r, exc, group=group: fail(int(group.index[r]), exc))
                if on_chunk is not None:
                    on_chunk(group.index[rows])
        for chunk_rows, res in parts:
            for field in out:
                out[field][group.index[chunk_rows]] = getattr(res, field)
        if parts:
            kept = np.concatenate([np.asarray(r, np.int64) for r, _ in parts])
            joined = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *[res.tree for _, res in parts])
            groups.append(Group(joined, group.index[kept], group.prims[kept]))
    return BatchOptimizeResult(TreeBatch(tuple(groups), m), **out, errors=dict(sorted(failed.items())))
