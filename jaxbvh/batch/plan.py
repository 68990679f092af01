"""Which meshes run together: capacity groups, then chunks of rows under a memory bound.

Groups. Meshes are sorted by size, largest first; the largest not yet placed opens a
group whose capacity is its own capacity bucket (:func:`jaxbvh.tree.layout.capacity_bucket`),
and every mesh whose own bucket is at least ``(1 - max_padding)`` of that capacity joins
it. So one giant mesh never pads the small ones, and ``max_padding`` trades compiles
(one program per group) against padded work: the default 0 gives one group per capacity
bucket (at most 1.5x padding, as a single tree has), 0.5 about one group per doubling
(at most 3x). On a CPU, padded slots cost as much as real ones (bench_batch.py: a batch
with 0.5 took 5x the loop of single builds), so the default pads no more than a single
build does.

Chunks. A group runs in chunks of ``rows`` trees, one compiled call each. ``rows`` is the
largest batch-size bucket (``1`` or a capacity bucket, times the device count, so
the batch axis splits evenly over devices) whose estimated memory,
``rows * capacity * bytes_per_slot``, stays under ``memory_mb``; every chunk but the
last is full, and the last is rounded up to a bucket too, so a group compiles at most
two programs. Rows past the real meshes are *filler* (copies of the chunk's first mesh)
whose results are dropped. ``bytes_per_slot`` is each operation's estimate of its
peak bytes per primitive slot (:data:`BYTES_PER_SLOT`, measured in
``bench/bench_batch.py``); a single tree larger than the bound still runs, alone.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxbvh.batch.rows import MODES
from jaxbvh.configs import Checked, knob, one_of, real
from jaxbvh.tree.layout import capacity_bucket

#: estimated peak bytes per primitive slot of one tree, by operation (float32; float64
#: needs about twice). Generous upper figures from the bench's peak-memory runs.
BYTES_PER_SLOT = {"build": 2048, "optimize": 16384, "collapse": 4096, "costs": 512, "trace": 4096}


@dataclasses.dataclass(frozen=True)
class BatchConfig(Checked):
    """How a batch is split into compiled calls (module docstring).

    ``memory_mb``: bound on one call's estimated peak memory, in MiB (MiB = 2^20 bytes).
    ``max_padding``: fraction of a group's capacity a member's own capacity bucket may
    leave unused (0: a group per capacity bucket).
    ``rows``: how a compiled call runs its rows (:mod:`jaxbvh.batch.rows`): ``"map"``
    one after another (a CPU), ``"vmap"`` side by side (a GPU), ``"auto"`` by the devices.
    """

    memory_mb: float = knob(1024.0, check=real(above=0.0), metavar="MB",
                            help="bound on one compiled call's estimated peak memory (MiB)")
    max_padding: float = knob(0.0, check=real(0.0, below=1.0), metavar="F",
                              help="fraction of a group's capacity a mesh may leave unused")
    rows: str = knob("auto", check=one_of(MODES), choices=MODES,
                     help="how a compiled call runs its rows: map (one after another; CPU), vmap (side "
                          "by side; GPU), auto (map on CPU devices)")


@dataclasses.dataclass(frozen=True)
class Chunk:
    """One compiled call: ``index`` [b] meshes (positions in the input) run as ``rows``
    rows (``rows >= b``; the rest filler) of ``capacity`` primitive slots."""

    capacity: int
    index: np.ndarray
    rows: int

    @property
    def filled(self) -> np.ndarray:
        """int64 [rows]: the mesh of every row, filler rows repeating the first."""
        out = np.full(self.rows, self.index[0], np.int64)
        out[: self.index.size] = self.index
        return out


def groups(sizes, max_padding: float) -> list[tuple[int, np.ndarray]]:
    """``[(capacity, index [b] int64), ...]`` by capacity, ascending (module docstring).

    ``sizes``: primitives of every mesh (each >= 1). Within a group the input order is kept.
    """
    sizes = np.asarray(sizes, np.int64)
    if sizes.ndim != 1 or sizes.size == 0:
        raise ValueError("groups: no meshes")
    own = np.array([capacity_bucket(int(n)) for n in sizes], np.int64)
    left = np.ones(sizes.size, bool)
    out = []
    while left.any():
        cap = int(own[left].max())
        member = left & (own >= cap * (1.0 - max_padding))
        out.append((cap, np.flatnonzero(member).astype(np.int64)))
        left &= ~member
    return out[::-1]


def batch_rows(count: int, devices: int) -> int:
    """Rows for ``count`` meshes on ``devices`` devices: per device 1 or a capacity bucket."""
    per_device = -(-count // devices)
    return devices * (1 if per_device <= 1 else capacity_bucket(per_device, minimum=2))


def max_rows(capacity: int, bytes_per_slot: int, memory_mb: float, devices: int) -> int:
    """Most rows of ``capacity`` slots a call may hold under ``memory_mb`` (a valid
    :func:`batch_rows` value; at least ``devices``: one tree per device always runs)."""
    fit = int(memory_mb * 2**20 // (capacity * bytes_per_slot))
    per_device = max(fit // devices, 1)
    best = 1
    while batch_rows(best + 1, 1) <= per_device:
        best = batch_rows(best + 1, 1)
    return devices * best


def chunks(sizes, config: BatchConfig, bytes_per_slot: int, devices: int = 1) -> list[Chunk]:
    """The compiled calls of a batch of meshes of ``sizes`` primitives (module docstring)."""
    if devices < 1:
        raise ValueError(f"devices must be >= 1, got {devices}")
    out = []
    for cap, index in groups(sizes, config.max_padding):
        most = max_rows(cap, bytes_per_slot, config.memory_mb, devices)
        for start in range(0, index.size, most):
            part = index[start:start + most]
            out.append(Chunk(cap, part, min(batch_rows(part.size, devices), most)))
    return out


def estimate_mb(chunk: Chunk, bytes_per_slot: int) -> float:
    """The estimated peak memory of a chunk, MiB."""
    return chunk.rows * chunk.capacity * bytes_per_slot / 2**20


def count_compiles(all_chunks) -> int:
    """Distinct (capacity, rows) shapes: the programs a run compiles (per operation)."""
    return len({(c.capacity, c.rows) for c in all_chunks})


__all__ = ["BatchConfig", "Chunk", "BYTES_PER_SLOT", "groups", "chunks", "batch_rows", "max_rows",
           "estimate_mb", "count_compiles"]
