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

Several hosts: start every process with :func:`jax.distributed.initialize` first; then
``jax.devices()`` lists the devices of all hosts and the same code shards over them,
every process getting the whole batch back (``process_allgather``; not tested here: one
host only; ``docs/batches.md``).
"""

from __future__ import annotations

from functools import lru_cache, partial
from typing import Callable

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "batch"  # the mesh axis name the batch axis is split over


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
