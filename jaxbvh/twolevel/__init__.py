"""Two-level BVHs over objects and instances, with partial re-braiding (Benthin et al. 2017).

=================  =====================================================================
module             what it holds
=================  =====================================================================
``rebraid``        :class:`TwoLevelBVH`, :func:`run` (a :class:`RebraidResult`), :func:`build`
                   (its tree), :func:`flatten`, :func:`sah`,
                   :func:`slots_of` (the BRef budget of a scene)
``objects``        one BVH per object, packed into a forest; instances and world boxes
``brefs``          the top level over build references that opens overlapping objects
                   (twin: ``brefs_reference``); one level of it in ``brefs_level``,
                   its segmented reductions and bin planes in ``brefs_segments``
``traversal``      closest- and any-hit rays through the two levels (:func:`trace`)
``native``         the same walk compiled by numba (the ``"native"`` engine)
=================  =====================================================================
"""

from jaxbvh.twolevel.rebraid import (RebraidResult, TwoLevelBVH, build, build_from, flatten, run, run_from, sah, slots_of,
                                     stored_nodes)
from jaxbvh.twolevel.traversal import any_hit, brute_force, closest_hit, stack_capacity, step_bound, trace, trace_batch

__all__ = ["RebraidResult", "TwoLevelBVH", "build", "build_from", "run", "run_from", "flatten", "sah", "slots_of", "stored_nodes", "brute_force",
           "closest_hit", "any_hit", "trace", "stack_capacity", "step_bound", "trace_batch"]
