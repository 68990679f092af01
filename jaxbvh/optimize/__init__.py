"""Optimizers of a built tree: every method, one entry point.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``pipeline``       :func:`optimize`, the one-call entry point, and the default pipeline
``rotate``         Kensler's tree rotations: hill climbing and simulated annealing
``reinsert``       parallel reinsertion (Meister & Bittner 2018)
``treelet``        treelet restructuring (Karras & Aila 2013)
``schedules``      annealing temperature schedules, optax style
=================  =====================================================================

Each optimizer's NumPy twin sits beside it as ``<module>_reference``.
"""

from jaxbvh.optimize.pipeline import (
    METHODS,
    PIPELINE_MAX_ROUNDS,
    PIPELINE_ROUND_GAIN,
    PIPELINE_TREELET_PASSES,
    OptimizeResult,
    optimize,
)

__all__ = ["METHODS", "PIPELINE_MAX_ROUNDS", "PIPELINE_ROUND_GAIN", "PIPELINE_TREELET_PASSES", "OptimizeResult", "optimize"]
