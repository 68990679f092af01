"""The batch axis over devices: every compiled batch call runs under :func:`on_devices`.

With one device a call is the batched function (its rows mapped or vmapped,
:mod:`jaxbvh.batch.rows`), jitted. With several, the function is wrapped in
:func:`jax.shard_map` over a one-axis :class:`jax.sharding.Mesh` named ``"batch"``:
every argument and result is split along its leading (batch) axis, each device runs the
batched function on its own rows, and no device waits for another's
loops (a tree's ``while_loop`` stops when *its device's* trees are done). The rows of a
call are a multiple of the device count (:func:`jaxbvh.batch.plan.batch_rows`). Each row
is computed by the same program whichever device holds it, so one device and several
give identical trees (tested on two fake CPU devices).

CPU cores: XLA runs one compiled program on about one core, so on a CPU a batch with
one device leaves the other cores idle. :func:`use_cpu_cores`, called before JAX's
first operation, splits the CPU into one JAX device per core; the batch axis is then
split over them like over several GPUs (``jaxbvh batch`` does it by default).

Several hosts: a batch of files runs on a Dask cluster (:mod:`jaxbvh.batch.runs`,
``docs/cluster.md``), each worker with its own devices. Under :func:`jax.distributed.initialize`
``jax.devices()`` would list every host's devices and :func:`on_devices` gathers the
results on every process (``process_allgather``), but that SPMD mode is not tested here
and not documented as a recipe.
"""

from __future__ import annotations

import os
import re
from functools import lru_cache, partial
from typing import Callable

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "batch"  # the mesh axis name the batch axis is split over


def cpu_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where the
    platform has none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def use_cpu_cores(count: int | None = None) -> int:
    """Split JAX's CPU into ``count`` devices (None: one per core, :func:`cpu_cores`) so
    that a batch's rows run on every core (module docstring); returns the CPU device count.

    Call it before JAX's first operation (importing :mod:`jaxbvh` runs none): JAX fixes
    its devices then. Afterwards, ``count`` None keeps the devices JAX has, and any other
    count is a ``ValueError``. With ``count`` None a device count already set in
    ``XLA_FLAGS`` (``--xla_force_host_platform_device_count``) is kept. Single-tree
    calls are unchanged (they run on the first device); a machine with a GPU still
    batches over its GPUs (``jax.devices()``).
    """
    if count is not None and (isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1):
        raise ValueError(f"cpu devices must be a whole number >= 1, got {count!r}")
    flagged = re.search(r"--xla_force_host_platform_device_count=(\d+)", os.environ.get("XLA_FLAGS", ""))
    if count is None and flagged:
        count = int(flagged.group(1))
    wanted = cpu_cores() if count is None else int(count)
    try:
        jax.config.update("jax_num_cpu_devices", wanted)
    except RuntimeError:  # JAX has started: its CPU devices are fixed
        have = len(jax.devices("cpu"))
        if count is not None and have != wanted:
            raise ValueError(f"cpu devices: JAX has started with {have} CPU device(s), so {wanted} cannot be set; "
                             "call use_cpu_cores before JAX's first operation") from None
        return have
    return wanted


def resolve(devices=None) -> tuple:
    """``devices`` as a tuple of JAX devices: None means all of ``jax.devices()``; an int
    the first that many; a list is taken as given. ``ValueError`` for none or too many."""
    if devices is None:
        return tuple(jax.devices())
    if isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        if not 1 <= devices <= jax.device_count():
            raise ValueError(f"devices must be between 1 and {jax.device_count()}, got {devices}")
        return tuple(jax.devices()[: int(devices)])
    devices = tuple(devices)
    if not devices:
        raise ValueError("devices: an empty list")
    return devices


@lru_cache(maxsize=None)
def _compiled(fn: Callable, static: tuple, devices: tuple) -> Callable:
    body = partial(fn, **dict(static))
    if len(devices) == 1:
        return jax.jit(body)
    mesh = Mesh(np.array(devices), (AXIS,))
    # every value is split along the batch axis (varying over devices), nothing to check
    return jax.jit(jax.shard_map(body, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS), check_vma=False))


def on_devices(fn: Callable, args: tuple, devices: tuple, **static):
    """``fn(*args, **static)`` compiled, its leading axis split over ``devices``.

    ``fn``: a function of batched arrays (every leaf of ``args`` and of the result has the
    batch axis first, its length a multiple of ``len(devices)``); ``static``: hashable
    keyword settings fixed at compile time. One program per (fn, static, devices) and shape.
    """
    call = _compiled(fn, tuple(sorted(static.items())), tuple(devices))
    if len(devices) > 1:
        sharding = NamedSharding(Mesh(np.array(devices), (AXIS,)), P(AXIS))
        args = jax.device_put(args, sharding)
    out = call(*args)
    if jax.process_count() > 1:  # several hosts: every process gets the whole batch back
        out = multihost_utils.process_allgather(out, tiled=True)
    return out
