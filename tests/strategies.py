"""The suite's hypothesis strategies: the public kit's (:mod:`jaxbvh.testing.strategies`),
re-exported under the names test modules import (``from strategies import ...``)."""

from __future__ import annotations

from jaxbvh.testing.strategies import (  # noqa: F401
    SOUP_KINDS,
    STEP,
    UNIT_TRIANGLE,
    Broken,
    box_sets,
    boxes,
    broken_trees,
    lattice,
    scenes,
    transforms,
    trees,
    triangle_soups,
)
