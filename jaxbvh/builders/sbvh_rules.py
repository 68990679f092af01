"""The geometric rules of spatial splits, shared by :mod:`jaxbvh.builders.sbvh` and its twin.

Written once for NumPy and JAX arrays alike (``xp`` is chosen from the inputs), so the
JAX engine and the NumPy twin bin, place planes and clip with the same expressions.

Planes and bins. A node's spatial bins along axis ``a`` split its box ``[lo, lo + ext]``
into ``B`` equal slabs; plane ``j`` (``0 .. B``) sits at ``lo + (ext * j) / B`` and the
bin of a coordinate ``x`` is ``floor((x - lo) * B / ext)`` clipped to ``[0, B - 1]`` (the
same formula as the binned object split's, :mod:`jaxbvh.builders.topdown`).

Spatial bins of a node (:func:`spatial_bins`): ``B`` (``SBVHConfig.spatial_bins``) for a
node of at least ``B`` references, one per reference below that, and never fewer than
``SPATIAL_MIN_BINS`` (or ``B`` if smaller). Deep in the tree a node holds a few
references that span most of its box: with ``B`` bins each is cut into nearly ``B``
pieces per axis, and the spatial search works per piece (legocar, depth 12: 28 pieces
per reference with 16 bins, 16 with this rule); a plane per reference is as many
candidates as the references can tell apart. The object split has its own bins
(``SBVHConfig.bins``, those of ``method="binned"``). At the default ``B`` = 4 (twelfth
round; tinybvh's ``BuildHQ`` uses 8) every node gets 4: the engine's per-node cells and
sweeps are sized by ``B``, and 16 spatial bins cost legocar 1.7x the build time of 4
for an SAH 0.6% higher (fandisk and rocker-arm: 1.9% and 2.1% lower; docs/spatial-splits.md).

Progress (:func:`separates`, seventh round). A spatial plane is a candidate only if each
side gets fewer references than the node has (``N_L < N``, ``N_R < N``, counts before
unsplitting, which only lowers them). Without it, a node whose references all cross
every plane (two triangles of a thin quad along a diagonal) splits into two children of
the same references with smaller clipped boxes, and at ``max_leaf`` 1, where the leaf
test cannot stop it, again and again: legocar's tree went 25 levels deep with 1.69
references per triangle (1.22 and 20 levels with the rule; SAH +0.1%). The paper and
tinybvh's ``BuildHQ`` stop such nodes by the SAH leaf test alone.

Clipping (why a reference box covers its piece of the triangle). The part of a triangle
on one side of a plane is a convex polygon whose corners are the triangle's corners on
that side (the plane included) and the points where edges cross the plane. Its box is
the box of those points; the crossing's coordinate on the split axis is the plane
itself (exact), the other two are interpolated, which rounds: they are widened by
``CLIP_MARGIN_EPS`` machine epsilons of ``|v_i| + |v_j|`` (the interpolation's error is
below 5 of them), so the box never misses a sliver of the triangle. The result is
intersected with the reference's box: a reference covers the triangle's part inside the
half-spaces of its ancestors' spatial splits, and clipping keeps that true for each
child. No product feeds an add directly (XLA on CPU would fuse the two into a
multiply-add, rounded once, which NumPy does not): JAX and NumPy compute the same boxes.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

#: a node's spatial bins: one per SPATIAL_REFS_PER_BIN of its references (:func:`spatial_bins`) ...
SPATIAL_REFS_PER_BIN = 1
#: ... at least SPATIAL_MIN_BINS, at most the configured ``bins``
SPATIAL_MIN_BINS = 4

#: widening of interpolated clip coordinates, in machine epsilons of ``|v_i| + |v_j|``
CLIP_MARGIN_EPS = 8

EDGES = ((0, 1), (1, 2), (2, 0))  # a triangle's edges as vertex pairs


def _xp(*arrays):
    return np if all(isinstance(a, (np.ndarray, np.generic, float, int)) for a in arrays) else jnp


def _full(xp, divisor, like):
    """``divisor`` with the shape of ``like``, as an array XLA cannot see as a broadcast.

    XLA rewrites a division by a broadcast value into a multiplication by its
    reciprocal, which rounds differently from NumPy's division; ``like - like`` is 0
    for finite values and XLA does not fold it (it would be NaN for inf).
    """
    return divisor if xp is np else divisor + (like - like)


def spatial_bins(count, bins: int):
    """Spatial bins of a node of ``count`` references (int, or an int array [...]): the
    configured ``bins`` (``SBVHConfig.spatial_bins``) at most, fewer for few references
    (see the module docstring)."""
    xp = _xp(count)
    return xp.clip(xp.asarray(count) // SPATIAL_REFS_PER_BIN, min(SPATIAL_MIN_BINS, bins), bins).astype(xp.int32)


def separates(n_left, n_right, count):
    """Whether a spatial plane with ``n_left`` and ``n_right`` references on its sides
    (entries at or before it, exits after it) may split a node of ``count``: each side
    gets fewer than all of them (any equal shapes; see the module docstring)."""
    return (n_left < count) & (n_right < count)


def plane_at(lo, ext, j, bins: int):
    """Position of spatial plane ``j`` of a node whose box on the axis is ``[lo, lo + ext]``."""
    xp = _xp(lo, ext, j)
    dt = lo.dtype
    steps = ext * xp.asarray(j, dt)
    return lo + steps / _full(xp, xp.asarray(bins, dt), steps)  # a division before the add: no fused multiply-add


def bin_of(x, lo, ext, bins: int):
    """Spatial bin (int32) of coordinate ``x`` in a node of box ``[lo, lo + ext]`` (``ext > 0``;
    0 where it is not)."""
    xp = _xp(x, lo, ext)
    dt = x.dtype
    raw = xp.floor((x - lo) * xp.asarray(bins, dt) / _full(xp, xp.where(ext > 0, ext, xp.ones((), dt)), x))
    return xp.where(ext > 0, xp.clip(raw, 0, bins - 1), 0).astype(xp.int32)


def axis_coordinate(points, axis_mask):
    """Coordinate on the axis of ``axis_mask`` ([..., 3] one-hot bool) of ``points`` [..., k, 3]."""
    xp = _xp(points)
    return xp.where(axis_mask[..., None, :], points, 0).sum(-1)


def crossing_coordinate(v_i, v_j, a_i, p, denominator):
    """A coordinate of the point where edge ``v_i -> v_j`` meets plane ``p`` (``a_i``: the
    edge's start on the split axis, ``denominator``: ``a_j - a_i``); elementwise, any
    equal shapes (:func:`crossings` and the engine's per-coordinate arrays share it)."""
    # a division last, never a product, before the add: XLA cannot fuse it into a
    # multiply-add, so JAX rounds as NumPy does
    return v_i + ((v_j - v_i) * (p - a_i)) / denominator


def clip_margin(v_i, v_j):
    """Widening of an interpolated crossing coordinate: ``CLIP_MARGIN_EPS`` eps of ``|v_i| + |v_j|``."""
    xp = _xp(v_i, v_j)
    # 8 eps is a power of two: the product is exact, fused or not
    return xp.asarray(CLIP_MARGIN_EPS * np.finfo(v_i.dtype).eps, v_i.dtype) * (xp.abs(v_i) + xp.abs(v_j))


def crossings(tri, axis_mask, plane):
    """Where the edges of ``tri`` [..., 3, 3] cross ``plane`` [...] on the one-hot axis
    ``axis_mask`` [..., 3]: ``(lo, hi, crosses)``, the widened crossing points [..., 3, 3]
    (per edge; on the axis exactly ``plane``) and which edges cross strictly [..., 3]."""
    xp = _xp(tri, plane)
    dt = tri.dtype
    va = axis_coordinate(tri, axis_mask)  # [..., 3] vertex coordinates on the axis
    i = np.array([e[0] for e in EDGES])
    j = np.array([e[1] for e in EDGES])
    a_i, a_j = va[..., i], va[..., j]
    p = plane[..., None]
    crosses = ((a_i < p) & (a_j > p)) | ((a_i > p) & (a_j < p))
    v_i, v_j = tri[..., i, :], tri[..., j, :]
    denominator = _full(xp, xp.where(crosses, a_j - a_i, xp.ones((), dt))[..., None], v_i)
    x = crossing_coordinate(v_i, v_j, a_i[..., None], p[..., None], denominator)
    margin = clip_margin(v_i, v_j)
    on_axis = axis_mask[..., None, :]
    x_lo = xp.where(on_axis, p[..., None], x - margin)
    x_hi = xp.where(on_axis, p[..., None], x + margin)
    return x_lo, x_hi, crosses


def halfspace_box(tri, axis_mask, plane, below, ref_lo, ref_hi):
    """Box of the part of triangle ``tri`` [..., 3, 3] on one side of ``plane`` [...]
    (``below`` [...] bool: ``x_a <= plane``, else ``x_a >= plane``), intersected with the
    reference box ``ref_lo``, ``ref_hi`` [..., 3]; ``lo > hi`` somewhere when empty."""
    xp = _xp(tri, plane, ref_lo)
    dt = tri.dtype
    va = axis_coordinate(tri, axis_mask)
    p = plane[..., None]
    b = below[..., None]
    inside = xp.where(b, va <= p, va >= p)  # [..., 3] vertices on the kept side
    x_lo, x_hi, crosses = crossings(tri, axis_mask, plane)
    inf = xp.asarray(np.inf, dt)
    lo = xp.minimum(xp.where(inside[..., None], tri, inf).min(-2), xp.where(crosses[..., None], x_lo, inf).min(-2))
    hi = xp.maximum(xp.where(inside[..., None], tri, -inf).max(-2), xp.where(crosses[..., None], x_hi, -inf).max(-2))
    return xp.maximum(lo, ref_lo), xp.minimum(hi, ref_hi)
