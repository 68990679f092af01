"""Primitive boxes as every builder takes them: checked on the host, narrowed to the
working dtype with outward rounding, padded to a capacity with empty boxes (inert:
``+inf`` lo, ``-inf`` hi).

Narrowing (issue 39). A builder's leaf box is the min/max of its primitives' boxes as the
builder received them, so those boxes must contain the boxes as given: float64 boxes
rounded to the *nearest* float32 could end inside their primitives (an object of extent
1 at offset 1e7 missed by 0.5, at scale 1e30 by 3.8e22). :func:`narrow_outward` rounds
``lo`` down and ``hi`` up instead, and also replaces subnormal coordinates, outward, by 0
or the smallest normal number: XLA on CPU flushes subnormals to zero in every operation
(a min or max included), which at 1e-40 broke every builder (boxes that missed their
primitives, child ids out of range). Every builder's tree therefore contains the boxes
as given, at any offset and scale the working dtype can represent; coordinates beyond
its range are refused. Where rounding grows the boxes by a visible part of the scene
(far from the origin, or below the normal range) the tree is valid but coarse, and
:func:`narrow_outward` warns once, saying what to do: pass scene-relative coordinates
(:meth:`jaxbvh.io.Mesh.local_boxes`) or build in float64.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import on_device, round_down, round_up, scene_scale, working_dtype
from jaxbvh.tree.layout import capacity_bucket
from jaxbvh.tree.validate import few_ids


def check_prim_boxes(prim_lo, prim_hi, what: str = "primitive boxes"):
    """Host-side check of ``prim_lo``, ``prim_hi`` [n, 3]; returns them as NumPy arrays.

    Raises ``ValueError`` naming the problem: wrong shape, no primitives, NaN/inf
    (with how many and which), or ``lo > hi``.
    """
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    if lo.ndim != 2 or lo.shape[-1] != 3 or lo.shape != hi.shape:
        raise ValueError(f"{what}: lo and hi must both have shape [n, 3], got {lo.shape} and {hi.shape}")
    if lo.shape[0] == 0:
        raise ValueError(f"{what}: no primitives (n = 0); a BVH needs at least one")
    if not (np.issubdtype(lo.dtype, np.floating) and np.issubdtype(hi.dtype, np.floating)):
        lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    bad = ~(np.isfinite(lo).all(1) & np.isfinite(hi).all(1))
    if bad.any():
        ids = np.flatnonzero(bad)
        raise ValueError(f"{what}: {ids.size} of {lo.shape[0]} have NaN or infinite coordinates "
                         f"(first: {few_ids(ids)})")
    inverted = (lo > hi).any(1)
    if inverted.any():
        ids = np.flatnonzero(inverted)
        raise ValueError(f"{what}: {ids.size} have lo > hi (first: {few_ids(ids)})")
    return lo, hi


_OR_FLOAT64 = {True: " or build in float64 (x64)", False: ""}

#: :func:`narrow_outward` warns when rounding grows a box by more than this part of the scene's extent
COARSE_FRACTION = 2.0 ** -10


def _beyond(what: str, dtype) -> str:
    big = float(np.finfo(dtype).max)
    return (f"{what}: coordinates beyond {np.dtype(dtype).name}'s range (+-{big:.3g}); scale the scene down"
            + (" or build in float64 (jax.config.update('jax_enable_x64', True))" if dtype == np.float32 else ""))


def narrow_outward(lo, hi, dtype, what: str = "primitive boxes"):
    """``lo``, ``hi`` [..., 3] (any float type) as ``dtype`` [..., 3], rounded outward:
    ``lo`` down, ``hi`` up, subnormals to 0 or the smallest normal number (module
    docstring), so each new box contains the given one. Exact (no change) for boxes
    already in ``dtype`` with normal or zero coordinates.

    ``ValueError`` when a coordinate is beyond ``dtype``'s range; a ``UserWarning`` when
    a box grows by more than :data:`COARSE_FRACTION` of the scene's extent.
    """
    dtype = np.dtype(dtype)
    lo, hi = np.asarray(lo), np.asarray(hi)
    new_lo, new_hi = round_down(lo, dtype), round_up(hi, dtype)
    if not (np.isfinite(new_lo).all() and np.isfinite(new_hi).all()):
        raise ValueError(_beyond(what, dtype))
    if lo.size and (new_lo.dtype != lo.dtype or (new_lo != lo).any() or (new_hi != hi).any()):
        grown = max(float(np.max(lo.astype(np.float64) - new_lo)), float(np.max(new_hi - hi.astype(np.float64))))
        extent = float(np.max(hi.max(0).astype(np.float64) - lo.min(0).astype(np.float64)))
        if grown > COARSE_FRACTION * extent:
            warnings.warn(f"{what}: rounding to {dtype.name} grew boxes by up to {grown:.3g} in a scene of "
                          f"extent {extent:.3g}; the tree holds every primitive but is coarse. Pass "
                          f"scene-relative coordinates (jaxbvh.io.Mesh.local_boxes(), or subtract the "
                          f"scene's centre and scale it near 1){_OR_FLOAT64[dtype == np.float32]}", stacklevel=4)
    return new_lo, new_hi


def prepare(prim_lo, prim_hi, *, pad: bool = True, capacity: int | None = None, dtype=None):
    """Checked, cast and padded builder inputs ``(lo, hi, n, scale)``.

    ``lo``, ``hi``: [capacity, 3] JAX arrays (padding: the empty box); ``n``: int32
    primitive count; ``scale``: the scene's power-of-two area scale. The capacity is
    ``capacity`` if given (>= n; one compile for inputs of many sizes), else the capacity
    bucket of ``n`` (``pad=True``) or ``n``. ``dtype``: float32 (None) or float64 (needs
    x64); the boxes are narrowed to it outward (:func:`narrow_outward`). Errors:
    :func:`check_prim_boxes`, :func:`narrow_outward`, and a capacity below ``n``.
    """
    lo, hi = check_prim_boxes(prim_lo, prim_hi)
    dt = working_dtype(dtype, lo.dtype)
    lo, hi = narrow_outward(lo, hi, dt)
    n = lo.shape[0]
    cap = int(capacity) if capacity is not None else (capacity_bucket(n) if pad else n)
    if cap < n:
        raise ValueError(f"capacity {cap} is below the {n} primitives")
    lo_p = np.full((cap, 3), np.inf, dt)
    hi_p = np.full((cap, 3), -np.inf, dt)
    lo_p[:n], hi_p[:n] = lo, hi
    # on the host: jnp.int32(n) and jnp.asarray(x, dt) would each compile a conversion
    return (jax.device_put(lo_p), jax.device_put(hi_p), on_device(n, np.int32),
            on_device(scene_scale(lo, hi), dt))


class TriangleFrame(NamedTuple):
    """Triangles as the SBVH engine takes them (:func:`narrow_triangles`)."""

    triangles: np.ndarray  # [n, 3, 3] in the working dtype: the given ones times ``unit``, rounded to nearest
    unit: float            # power of two the coordinates were multiplied by (exact)
    slack: float           # largest rounding error of a coordinate, in the scaled frame (float64; 0: exact)


def narrow_triangles(tri, dtype, what: str = "triangles") -> TriangleFrame:
    """The SBVH's inputs: ``tri`` [n, 3, 3] (checked, any float type) multiplied by the
    power of two ``unit`` that brings the scene's extent near 1 (exact: clipping then
    neither overflows at 1e30 nor flushes its margins to zero at 1e-37), rounded to
    nearest in ``dtype`` with subnormals set to 0 (XLA flushes them), and the largest
    rounding error ``slack``. Clipping needs the triangles themselves, which cannot be
    rounded outward; :func:`widen_back` therefore grows the tree's boxes by ``slack``:
    a point of a given triangle lies within ``slack`` (per coordinate) of the point of
    the rounded triangle with the same barycentric coordinates, which the engine's
    boxes cover. ``ValueError`` beyond ``dtype``'s range; the warning of
    :func:`narrow_outward` when ``slack`` makes the tree coarse.
    """
    dtype = np.dtype(dtype)
    tri = np.asarray(tri)
    wide = np.result_type(tri.dtype, np.float64)
    exact = tri.astype(wide)
    if tri.size and float(np.max(np.abs(exact))) > float(np.finfo(dtype).max):
        raise ValueError(_beyond(what, dtype))
    unit = scene_scale(exact.min(1), exact.max(1))
    scaled = exact * wide.type(unit)  # a power of two: exact in float64 and wider
    with np.errstate(over="ignore"):
        near = scaled.astype(dtype)
    if not np.isfinite(near).all():
        raise ValueError(f"{what}: the scene's coordinates are too far from the origin for {dtype.name} "
                         f"(beyond {float(np.finfo(dtype).max):.3g} times its extent); pass scene-relative "
                         f"coordinates (jaxbvh.io.Mesh.local_triangles())")
    near = np.where(np.abs(near) < np.finfo(dtype).tiny, dtype.type(0), near)
    slack = float(np.max(np.abs(scaled - near))) if tri.size else 0.0
    extent = float(np.max(scaled.max((0, 1)) - scaled.min((0, 1)))) if tri.size else 0.0
    if slack > COARSE_FRACTION * extent:
        warnings.warn(f"{what}: rounding to {dtype.name} moved vertices by up to {slack / unit:.3g} in a scene of "
                      f"extent {extent / unit:.3g}; the tree covers every triangle but is coarse. Pass "
                      f"scene-relative coordinates (jaxbvh.io.Mesh.local_triangles())"
                      f"{_OR_FLOAT64[dtype == np.float32]}",
                      stacklevel=4)
    return TriangleFrame(near, unit, slack)


def widen_back(tree, frame: TriangleFrame):
    """``tree`` (built on ``frame.triangles``) in the given triangles' frame: real boxes
    divided by ``frame.unit`` and grown by ``frame.slack`` (:func:`narrow_triangles`),
    rounded outward to the tree's dtype. Each box grows by the same amount, so parents
    still contain their children. The tree unchanged when the frame is exact."""
    if frame.unit == 1.0 and frame.slack == 0.0:
        return tree
    dtype = np.dtype(tree.lo.dtype)

    def moved(x, down: bool):
        x = np.asarray(x).astype(np.float64)
        real = np.isfinite(x)  # the padding's infinite boxes stay as they are
        y = np.where(real, x, 0.0)
        y = y - frame.slack if down else y + frame.slack
        if frame.slack:  # one float64 step past the subtraction's rounding
            y = np.nextafter(y, -np.inf if down else np.inf)
        y = (round_down if down else round_up)(y / frame.unit, dtype)  # the division is exact
        if not np.isfinite(y[real]).all():  # grown past the range by the slack
            raise ValueError(_beyond("triangles", dtype))
        return jnp.asarray(np.where(real, y, x).astype(dtype))

    return dataclasses.replace(tree, lo=moved(tree.lo, True), hi=moved(tree.hi, False))
