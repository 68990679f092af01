"""Builders: a binary BVH from primitive boxes.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``dispatch``       :func:`build` and :data:`BUILDERS`, the one entry point
``topdown``        the level-synchronous top-down engine: full-sweep SAH, binned SAH,
                   object median, and the randomized split hook GRASP uses
``morton``         Morton codes of box centres
``lbvh``           Karras' radix tree over Morton codes (bottom-up)
``ploc``           Meister & Bittner's locally ordered clustering (bottom-up)
``bottom_up``      the shared finish of the bottom-up builders (boxes, leaf collapse)
``insertion``      Goldsmith & Salmon insertion (wide trees, Ng & Trifonov's GA uses it)
=================  =====================================================================

Each module's NumPy twin sits beside it as ``<module>_reference``.
"""

from jaxbvh.builders.dispatch import BUILDERS, build

__all__ = ["BUILDERS", "build"]
