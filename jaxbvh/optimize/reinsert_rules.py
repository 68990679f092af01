"""The rules of parallel reinsertion that the optimizer and its NumPy twin share.

Which nodes are searched when (candidates by octaves of parent area below the root's,
coarse to fine) and how many of the moves found an iteration considers: both
:mod:`jaxbvh.optimize.reinsert` and :mod:`jaxbvh.optimize.reinsert_reference` follow
these, so they choose the same moves.
"""

from __future__ import annotations

import numpy as np

#: ``octaves`` at and above this: every node is a candidate (the threshold is 0)
ALL_OCTAVES = 4096


def move_width(capacity: int) -> int:
    """Moves considered per iteration: a static size from the capacity."""
    return int(min(capacity, max(4096, capacity // 32)))


def first_octaves(area, parent, root, first_fraction: float) -> int:
    """The fewest octaves of parent area (below the root's) that hold ``first_fraction``
    of the candidates (host; :data:`ALL_OCTAVES` for all of them)."""
    if first_fraction >= 1:
        return ALL_OCTAVES
    area, parent = np.asarray(area), np.asarray(parent)
    area_p = area[parent[parent >= 0]]
    root_area = float(area[int(root)])
    if root_area <= 0 or area_p.size == 0:
        return ALL_OCTAVES
    need = int(np.ceil(first_fraction * area_p.size))
    for octaves in range(0, 64):
        if int(np.sum(area_p >= np.ldexp(area.dtype.type(root_area), -octaves))) >= need:
            return octaves
    return ALL_OCTAVES
