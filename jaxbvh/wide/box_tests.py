"""The cost of testing a node's child boxes, ``T(k)``, that collapsing charges (Susano Pinto 2010).

A wide node with ``k`` children costs ``T(k)`` box tests: ``k`` on a scalar machine, or
``ceil(k / w)`` when ``w`` boxes are tested at once (SIMD). The collapsing DP
(:mod:`jaxbvh.wide.collapse`) and its NumPy twin both price nodes from the table
:func:`cost_table` makes, so both use one rule.
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import numpy as np


def node_test_cost(simd_width: int = 0) -> Callable:
    """``T(k)``: ``k`` for ``simd_width == 0``, else ``ceil(k / simd_width)`` (int arrays)."""
    w = int(simd_width)
    if w < 0:
        raise ValueError(f"simd_width must be >= 0, got {simd_width}")
    if w == 0:
        return _one_per_box
    return partial(_simd_groups, width=w)


def _one_per_box(k):
    return k


def _simd_groups(k, width):
    return (k + width - 1) // width


def cost_table(test_cost: Callable | None, k: int) -> np.ndarray:
    """``[T(0), ..., T(k)]`` float64 from ``test_cost`` (None: ``T(k) = k``), checked."""
    fn = test_cost or _one_per_box
    table = np.asarray(fn(np.arange(k + 1)), np.float64)
    if table.shape != (k + 1,):
        raise ValueError(f"test_cost must map an int array [k+1] to [k+1] costs, got shape {table.shape}")
    bad = ~np.isfinite(table[1:]) | (table[1:] < 0)
    if bad.any():
        raise ValueError(f"test_cost must be finite and >= 0; T({int(np.flatnonzero(bad)[0]) + 1}) = "
                         f"{table[1:][bad][0]}")
    table[0] = 0.0
    return table

