"""Measuring a tree with rays: the empirical cost beside the SAH.

The SAH is a model: the expected cost ``Ct * (interior nodes visited) + Ci * (primitive
tests)`` of a random *line* through the root box that finds *every* hit. Real rays start
somewhere and stop at the closest hit, so their cost is lower and ranks trees a little
differently. :func:`measure` traces a ray set and reports, per ray, the mean number of
box tests, primitive tests, nodes and leaves visited, each with a normal-approximation
confidence interval (``mean ± z * sd / sqrt(R)``, default 95%), the empirical cost in the
SAH's units, and the tree's SAH.

Ray sets live in :mod:`jaxbvh.rays.generation`, traversal in :mod:`jaxbvh.rays.traversal`; both are
re-exported here so ``jaxbvh.rays`` is the one import a user needs.
"""

from __future__ import annotations

import math
import time

import jax
import numpy as np

from jaxbvh.native import DEFAULT_ENGINE
from jaxbvh.rays.generation import bounce_rays, camera_rays, random_rays
from jaxbvh.rays.traversal import (
    MODES,
    Hits,
    all_hits,
    any_hit,
    closest_hit,
    engine_of,
    intersect_triangle,
    moller_trumbore,
    stack_capacity,
    trace,
)
from jaxbvh.tree.cost import sah
from jaxbvh.tree.layout import to_numpy

__all__ = ["KINDS", "MODES", "Hits", "all_hits", "any_hit", "bounce_rays", "camera_rays",
           "closest_hit", "empirical_cost", "intersect_triangle", "make_rays", "mean_ci",
           "measure", "moller_trumbore", "random_rays", "stack_capacity", "trace"]

KINDS = ("random", "camera", "bounce")


def camera_size(n: int) -> tuple[int, int]:
    """``(width, height)`` of a 4:3 image with about ``n`` pixels."""
    height = max(1, round(math.sqrt(n * 3 / 4)))
    return max(1, round(height * 4 / 3)), height


def make_rays(key, kind: str, tree, triangles, n: int):
    """``n`` rays of ``kind`` (one of :data:`KINDS`) for ``tree`` over ``triangles``.

    Everything is in the tree's frame. Random rays fill the root box; camera rays frame
    the root box (about ``n`` of them, see :func:`camera_size`; ``key`` unused); bounce
    rays leave the surface of ``triangles`` [T, 3, 3]. Returns NumPy ``(origin,
    direction)`` [R, 3].
    """
    t = to_numpy(tree)
    root = int(t.root)
    lo, hi = t.lo[root], t.hi[root]
    dtype = t.lo.dtype
    if kind == "random":
        origin, direction = random_rays(key, lo, hi, n, dtype=dtype)
    elif kind == "camera":
        width, height = camera_size(n)
        origin, direction = camera_rays(lo, hi, width, height, dtype=dtype)
    elif kind == "bounce":
        origin, direction = bounce_rays(key, np.asarray(triangles, dtype), n)
    else:
        raise ValueError(f"ray kind must be one of {KINDS}, got {kind!r}")
    return np.asarray(origin), np.asarray(direction)


def mean_ci(values, z: float = 1.96) -> tuple[float, float]:
    """Mean of ``values`` and the half-width ``z * sd / sqrt(n)`` of its interval."""
    x = np.asarray(values, np.float64).ravel()
    if x.size == 0:
        return float("nan"), float("nan")
    half = z * float(x.std(ddof=1)) / math.sqrt(x.size) if x.size > 1 else float("inf")
    return float(x.mean()), half


def empirical_cost(hits: Hits, *, ct: float = 1.0, ci: float = 1.0, z: float = 1.96) -> dict:
    """Per-ray means with confidence half-widths, as ``{name: (mean, half_width)}``.

    Names: ``box_tests``, ``prim_tests``, ``nodes_visited``, ``leaves_visited``,
    ``interior_visited`` and ``cost = ct * interior_visited + ci * prim_tests`` (the
    SAH's units: the root counts as one interior visit, as ``Ct`` does in the SAH).
    """
    interior = np.asarray(hits.nodes_visited) - np.asarray(hits.leaves_visited)
    cost = ct * interior + ci * np.asarray(hits.prim_tests)
    return {
        "box_tests": mean_ci(hits.box_tests, z),
        "prim_tests": mean_ci(hits.prim_tests, z),
        "nodes_visited": mean_ci(hits.nodes_visited, z),
        "leaves_visited": mean_ci(hits.leaves_visited, z),
        "interior_visited": mean_ci(interior, z),
        "cost": mean_ci(cost, z),
    }


def measure(tree, triangles, origin, direction, *, mode: str = "closest", ct: float = 1.0,
            ci: float = 1.0, z: float = 1.96, **trace_kwargs) -> tuple[Hits, dict]:
    """Trace the rays and summarise: ``(hits, summary)``. ``trace_kwargs`` go to
    :func:`~jaxbvh.rays.traversal.trace` (``engine=``: both engines count alike).

    ``summary``: the :func:`empirical_cost` entries flattened to ``<name>`` (mean) and
    ``<name>_ci`` (half-width), plus ``rays``, ``engine`` (the one that ran: ``"jax"`` or
    ``"native"``), ``hit_fraction``, ``seconds`` (traversal
    only, after a warm-up batch that compiles), ``rays_per_second`` and ``sah``.
    """

    origin = np.asarray(origin)
    direction = np.asarray(direction)
    warm = min(origin.shape[0], trace_kwargs.get("batch", 256))
    trace(tree, triangles, origin[:warm], direction[:warm], mode=mode, **trace_kwargs)
    start = time.perf_counter()
    hits = trace(tree, triangles, origin, direction, mode=mode, **trace_kwargs)
    seconds = time.perf_counter() - start
    summary = {"rays": int(origin.shape[0]), "mode": mode,
               "engine": engine_of(trace_kwargs.get("engine", DEFAULT_ENGINE), tree, triangles, origin, direction,
                                   intersect=trace_kwargs.get("intersect", intersect_triangle)),
               "hit_fraction": float(np.mean(hits.prim >= 0)) if origin.shape[0] else 0.0}
    for name, (mean, half) in empirical_cost(hits, ct=ct, ci=ci, z=z).items():
        summary[name] = mean
        summary[name + "_ci"] = half
    summary["sah"] = float(jax.device_get(sah(jax.tree_util.tree_map(np.asarray, tree), ct, ci)))
    summary["seconds"] = seconds
    summary["rays_per_second"] = origin.shape[0] / seconds if seconds > 0 else float("inf")
    return hits, summary
