"""Queries against a BVH: rays, closest point, box overlap, radius, with gradients.

``search``: :func:`closest_point`, :func:`overlap`, :func:`within` and :func:`raycast`
(closest or any hit, inside jit), jitted functions of
the tree and primitives, for use inside your own ``jit`` / ``vmap`` / ``grad`` (twin:
``search_reference``; the first three also run natively, ``engine=``: ``native_search``);
``parent_walk``: the stackless walk they share (state independent
of the tree's depth); ``geometry``: the per-primitive tests, differentiable (also
:func:`ray_hit`, a ray's hit distance and barycentrics on a chosen triangle);
``normals``: pseudonormals for signed distances. The ray queries :func:`closest_hit` and
:func:`any_hit` are :mod:`jaxbvh.rays`' own, re-exported. Guide: ``docs/queries.md``.
"""

from jaxbvh.queries.geometry import FEATURES, closest_on_triangle
from jaxbvh.queries.normals import pseudonormals
from jaxbvh.queries.rays import ray_hit
from jaxbvh.queries.search import Listed, PointHit, RayHit, closest_point, overlap, raycast, within
from jaxbvh.rays import Hits, any_hit, closest_hit

__all__ = ["FEATURES", "Hits", "Listed", "PointHit", "RayHit", "any_hit", "closest_hit", "closest_on_triangle",
           "closest_point", "overlap", "pseudonormals", "ray_hit", "raycast", "within"]
