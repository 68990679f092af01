"""How one compiled call runs its rows: side by side (``vmap``) or one after another (``map``).

A batch call holds ``R`` rows (trees or meshes) of one capacity. Two ways to run them
in one compiled program:

* ``"vmap"``: :func:`jax.vmap` of the one-row function. Every operation works on all
  rows at once, which fills a wide device (a GPU), but under ``vmap`` a ``lax.cond``
  on a per-row value becomes a ``select`` (both branches run for every row) and a
  ``while_loop`` runs every row until the slowest one is done. On a CPU, which has no
  width for extra rows to fill, that is pure loss (``bench/bench_batch.py``: the
  pipeline over 8 meshes took 12 s per row vmapped, against 0.7 s per mesh alone).
* ``"map"``: :func:`jax.lax.map` of the one-row function: a compiled loop over the
  rows, each running the *single-tree program* (its own loop lengths, only the branch
  it takes). No Python or dispatch per row; the work is the loop of single calls'
  work. Filler rows (padding the batch axis to a bucket) are passed over by a
  ``lax.cond`` on an unbatched flag, so they cost nothing (the optimizers' batch
  driver, :func:`jaxbvh.optimize.driver.run_states`, runs its rows the same two ways
  and starts its filler rows done instead, which skips them in either mode).

``"auto"`` picks ``"map"`` when every device is a CPU and ``"vmap"`` otherwise. Both
give the same results, row for row, as the single-tree call (each row is computed by
the same one-row function; tested).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

MODES = ("auto", "map", "vmap")  # the choices of BatchConfig.rows (module docstring)


def resolve(mode: str, devices) -> str:
    """``"map"`` or ``"vmap"`` for ``mode`` on ``devices`` (module docstring)."""
    if mode not in MODES:
        raise ValueError(f"rows must be one of {', '.join(MODES)}, got {mode!r}")
    if mode != "auto":
        return mode
    return "map" if all(d.platform == "cpu" for d in devices) else "vmap"


def each_row(fn: Callable, mode: str) -> Callable:
    """``fn`` of one row's arrays as a function ``(real, *args)`` of batched arrays.

    ``real``: bool [R], False for a filler row (its outputs are then zeros under
    ``"map"``, ``fn``'s under ``"vmap"``: either way they are dropped). Every leaf of
    ``args`` has the batch axis first.
    """
    if mode == "vmap":
        return lambda real, *args: jax.vmap(fn)(*args)
    if mode != "map":
        raise ValueError(f"each_row: mode must be 'map' or 'vmap', got {mode!r}")

    def mapped(real, *args):
        one = jax.tree_util.tree_map(lambda a: a[0], args)
        shapes = jax.eval_shape(fn, *one)

        def row(item):
            is_real, row_args = item
            # an unbatched flag: a true cond, so a filler row runs nothing
            return jax.lax.cond(is_real, lambda a: fn(*a),
                                lambda a: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes),
                                row_args)

        return jax.lax.map(row, (real, args))

    return mapped


__all__ = ["MODES", "resolve", "each_row"]
