"""Builders: a binary BVH from primitive boxes.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``dispatch``       :func:`build`, the one entry point: a Config in, a tree out
``configs``        one frozen Config per builder (:data:`BUILDERS`: method -> Config),
                   the only place their defaults are written
``inputs``         primitive boxes checked, cast and padded, as every builder takes them
``topdown``        the level-synchronous top-down engine: full-sweep SAH, binned SAH,
                   object median, and the randomized split hook GRASP uses
``morton``         Morton codes of box centres
``lbvh``           Karras' radix tree over Morton codes (bottom-up)
``ploc``           Meister & Bittner's locally ordered clustering (bottom-up)
``bottom_up``      the shared finish of the bottom-up builders (boxes, leaf collapse)
``sbvh``           spatial splits (Stich et al.): from triangles, references in several
                   leaves; ``sbvh_splits`` its split searches, ``sbvh_rules`` the clipping
``insertion``      Goldsmith & Salmon insertion (wide trees, Ng & Trifonov's GA uses it)
=================  =====================================================================

Each module's NumPy twin sits beside it as ``<module>_reference``.
"""

from jaxbvh.builders.configs import (
                                     ALL_BUILDERS,
                                     BOX_BUILDERS,
                                     BUILDERS,
                                     DEFAULT_BUILDER,
                                     TRIANGLE_BUILDERS,
                                     BinnedConfig,
                                     BuilderConfig,
                                     LBVHConfig,
                                     MedianConfig,
                                     PLOCConfig,
                                     SBVHConfig,
                                     SweepConfig,
)
from jaxbvh.builders.dispatch import build
from jaxbvh.builders.sbvh import SBVHBuild, build_sbvh

__all__ = ["ALL_BUILDERS", "BOX_BUILDERS", "TRIANGLE_BUILDERS", "BUILDERS", "DEFAULT_BUILDER", "BuilderConfig",
           "SweepConfig", "BinnedConfig", "MedianConfig", "LBVHConfig", "PLOCConfig", "SBVHConfig", "SBVHBuild",
           "build", "build_sbvh"]
