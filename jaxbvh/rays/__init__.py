"""Rays: generation, traversal and the measured cost of a tree.

``generation``: random, camera and bounce rays; ``traversal``: closest, any and all hits
through a BVH (twin: ``traversal_reference``); ``stack_walk``: the bounded traversal loop
that ``traversal`` and :mod:`jaxbvh.twolevel.traversal` share; ``native``: the same walk
compiled by numba for the CPU (``engine=`` of the traversal functions); ``measure``: traversal
steps as an empirical cost beside the SAH.
"""

from jaxbvh.rays.generation import bounce_rays, camera_rays, random_rays
from jaxbvh.rays.measure import KINDS, camera_size, empirical_cost, make_rays, mean_ci, measure
from jaxbvh.rays.traversal import (
                                   MODES,
                                   Hits,
                                   all_hits,
                                   any_hit,
                                   closest_hit,
                                   intersect_triangle,
                                   moller_trumbore,
                                   stack_capacity,
                                   trace,
)

__all__ = ["bounce_rays", "camera_rays", "random_rays", "KINDS", "MODES", "Hits", "camera_size", "empirical_cost", "make_rays", "mean_ci", "measure",
           "all_hits", "any_hit", "closest_hit", "intersect_triangle", "moller_trumbore",
           "stack_capacity", "trace"]
