"""The numerical rules every algorithm shares, in one place: ties, margins, area scale, dtypes.

JAX code and the NumPy twins both import these rules (and nothing else from each other),
so a rule is written once and both sides of an equality test apply the same one.

Ties and margins
================
XLA on CPU fuses multiply-adds, so one cost evaluated in two places (or in JAX and in
NumPy) can differ by an ulp; a decision that hinges on the last bit is neither
reproducible nor equal to its twin. Two rules keep decisions off the last bit:

* :data:`TIE_TOLERANCE` (``2^-20``, relative): builders count split costs this close as
  equal and break the tie by a stated order (:mod:`jaxbvh.builders.topdown`).
* :func:`min_gain` (``64 * eps`` of the float type, 7.6e-6 in float32): optimizers take
  a move only when it lowers a cost by more than this fraction of it, and collapsing
  counts costs within it as tied (:mod:`jaxbvh.optimize.rotate`,
  :mod:`jaxbvh.wide.collapse`).

Fused multiply-adds and sums under ``jax.vmap``
===============================================
The margins keep a decision off the last bit of one program's cost, but not off the
difference between two programs: ``step`` and ``jax.vmap(step)`` are compiled apart,
XLA fuses them differently, and where a product lands in one fusion with the add that
consumes it, LLVM contracts the two into a multiply-add (rounded once), elsewhere not
(tinybvh's legocar tree under annealing: 53 of 12,288 forest costs an ulp apart). A cost
that feeds a decision is therefore computed so that every program rounds it alike:
each product that feeds an add passes :func:`rounded` (rounded to its dtype on its
own, never contracted), and sums over an array run in one fixed order
(:func:`ordered_sum`: pairwise halving, not a reduction whose order XLA picks per
program). :func:`half_area` does both for its products; the optimizers' costs
(:mod:`jaxbvh.optimize.rotate_moves`, :mod:`jaxbvh.optimize.reinsert_moves`,
:mod:`jaxbvh.optimize.reinsert_search`) use them, so a vmapped step equals the step,
leaf for leaf (``tests/optimize/test_vmap_exact.py``).

Area scale
==========
Surface areas are computed from box extents multiplied by a power of two chosen from the
scene's (or the root's) largest extent, which brings that extent into [0.5, 1): no
float32 overflow at 1e30, no underflow at 1e-30, and scaling by a power of two is exact.
:func:`scene_scale` (host, NumPy) and :func:`extent_scale` (traceable) give the same
power; :func:`half_area` applies it.

Narrowing and subnormals
========================
:func:`round_down` and :func:`round_up` narrow coordinates to a float type with directed
rounding, so that a box narrowed ``lo`` down, ``hi`` up contains the given one
(:func:`jaxbvh.builders.inputs.narrow_outward`). Both also move subnormal results outward
to 0 or the smallest normal number: XLA on CPU flushes subnormals to zero in every
operation (min, max and compares included), so a subnormal coordinate reads as 0 inside
a compiled program. For the same reason :func:`scene_scale` is at most the largest
power of two finite in the boxes' dtype (an extent that is a difference of tiny normal
numbers can be subnormal).

Array steps
===========
Gathers with a fill value and prefix sums in the form XLA runs fast on CPU. The obvious
spellings are several times slower on XLA's CPU backend (measured on a 2-core x86-64
machine, 3M elements): ``x.at[i].get(mode="fill")`` 13 ms against 2.4 ms for a clipped
``take`` and a select (:func:`take`); ``jnp.cumsum`` 44 ms against 7 ms for
``lax.associative_scan`` (for short arrays inside loops the single cumsum op wins: each
of the scan's many small steps costs a launch).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import compile_cache

# the package's JAX code passes here before it compiles anything: the persistent
# compilation cache is on from then (idempotent; jaxbvh.compile_cache says when not)
compile_cache.enable_default()

#: relative tolerance within which two split costs count as a tie (builders)
TIE_TOLERANCE = 2.0 ** -20

#: the margin of :func:`min_gain`, in units of the float type's machine epsilon
MIN_GAIN_EPS = 64


def min_gain(dtype) -> float:
    """Relative margin a move must beat: ``64 * eps`` of ``dtype`` (7.6e-6 for float32).

    Also the relative tolerance within which collapsing and treelet costs tie.
    """
    return float(MIN_GAIN_EPS * np.finfo(np.dtype(dtype)).eps)


def working_dtype(dtype, given) -> np.dtype:
    """The float type a builder computes in: ``dtype`` if given, else float64 only when
    the input (``given``) is float64 and JAX's x64 mode is on, else float32.

    Raises ``ValueError`` for float64 without x64, or a type other than float32/64.
    """
    x64 = jax.config.jax_enable_x64
    if dtype is None:
        return np.dtype(np.float64) if (np.dtype(given) == np.float64 and x64) else np.dtype(np.float32)
    dtype = np.dtype(dtype)
    if dtype == np.float64 and not x64:
        raise ValueError("dtype float64 needs JAX's x64 mode: jax.config.update('jax_enable_x64', True)")
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    return dtype


def exponent_for_extent(m, dtype=np.float64) -> int:
    """The exponent ``k`` of :func:`scale_for_extent`: ``2^k`` brings an extent ``m > 0``
    into [0.5, 1); 0 when ``m <= 0`` (host); ``2^k`` at most the largest power of two
    finite in ``dtype``."""
    m = float(m)
    if not m > 0:
        return 0
    return min(-int(np.frexp(m)[1]), np.finfo(dtype).maxexp - 1, np.finfo(np.float64).maxexp - 1)


def scale_for_extent(m, dtype=np.float64) -> float:
    """Power of two that brings an extent ``m > 0`` into [0.5, 1); 1.0 when ``m <= 0``
    (host); at most the largest power of two finite in ``dtype``."""
    return float(np.ldexp(1.0, exponent_for_extent(m, dtype)))


def root_exponent(lo, hi) -> int:
    """The exponent ``k`` of the area scale of the box ``lo``, ``hi`` [3] (NumPy; usually
    the root's): ``2^k`` brings its largest extent, taken in float64, into [0.5, 1) (0 for
    a point). A host tree whose ``k > 0`` is small, perhaps subnormal, and scaling its
    boxes by ``2^k`` (exact) keeps them out of the range XLA flushes to zero (module
    docstring); an exponent, since ``2^k`` itself may not fit the boxes' type."""
    return exponent_for_extent(np.max(np.asarray(hi).astype(np.float64) - np.asarray(lo).astype(np.float64)))


def scene_scale(lo, hi) -> float:
    """Power of two that brings the largest extent of the box of all ``lo``, ``hi``
    [n, 3] into [0.5, 1) (host, NumPy, the extent in float64; 1.0 for a point), at most
    the largest power of two finite in their float dtype (module docstring)."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    dtype = lo.dtype if np.issubdtype(lo.dtype, np.floating) else np.float64
    return scale_for_extent(np.max(hi.max(0).astype(np.float64) - lo.min(0).astype(np.float64)), dtype)


def _directed(x, dtype, down: bool):
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    dtype = np.dtype(dtype)
    if x.dtype == dtype:  # exact already (the usual case: float32 boxes to a float32 build)
        y = x
    else:
        with np.errstate(over="ignore"):
            y = x.astype(dtype)
        # the comparison runs in the wider type, where every value of ``dtype`` is exact
        y = np.where(y > x, np.nextafter(y, dtype.type(-np.inf)), y) if down else \
            np.where(y < x, np.nextafter(y, dtype.type(np.inf)), y)
    tiny = np.finfo(dtype).tiny
    subnormal = (y != 0) & (np.abs(y) < tiny)
    if not subnormal.any():
        return np.asarray(y, dtype)
    positive, negative = subnormal & (y > 0), subnormal & (y < 0)
    return np.where(positive, dtype.type(0 if down else tiny),
                    np.where(negative, dtype.type(-tiny if down else 0), y)).astype(dtype)


def round_down(x, dtype) -> np.ndarray:
    """The largest value of ``dtype`` (a float type) that is at most ``x`` (NumPy, any
    float or integer array), a subnormal one replaced by 0 (positive) or minus the
    smallest normal number (negative); ``-inf`` below the range (module docstring)."""
    return _directed(x, dtype, down=True)


def round_up(x, dtype) -> np.ndarray:
    """The smallest value of ``dtype`` at least ``x``; a subnormal one replaced by the
    smallest normal number (positive) or 0 (negative); ``inf`` above the range."""
    return _directed(x, dtype, down=False)


def box_scale(lo, hi):
    """Host twin of :func:`extent_scale`: the scale of one box ``lo``, ``hi`` [3] (NumPy),
    its extent taken in the box's own dtype, returned as a scalar of that dtype."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    return lo.dtype.type(scale_for_extent(np.max(hi - lo)))


def extent_scale(lo, hi):
    """Power of two ``s`` with ``max(hi - lo) * s`` in [0.5, 1); 1 for an empty/point box.

    ``lo``, ``hi``: [3] corners of the box that sets the scale (usually the root's).
    Traceable; the result has ``lo``'s dtype.
    """
    m = jnp.max(hi - lo)
    _, exponent = jnp.frexp(jnp.where(m > 0, m, 1.0))
    return jnp.where(m > 0, jnp.ldexp(jnp.ones((), lo.dtype), -exponent), jnp.ones((), lo.dtype))


def rounded(x):
    """``x`` [...] as is, but rounded to its dtype where it is computed: a product passed
    through it is never contracted into a multiply-add with the add that consumes it
    (module docstring). A select on NaN (NaN stays NaN) that LLVM does not see through;
    NumPy arrays pass unchanged (NumPy never contracts)."""
    if isinstance(x, (np.ndarray, np.generic, float)):
        return x
    return jnp.where(jnp.isnan(x), jnp.asarray(jnp.nan, x.dtype), x)


def ordered_sum(x):
    """Sum of ``x`` [..., N] over its last axis in one fixed order, the same in every
    program (module docstring): pairwise halving over the axis padded with zeros to a
    power of two, ``log2 N`` elementwise adds. Traceable."""
    n = x.shape[-1]
    size = 1 << max(0, (n - 1).bit_length())
    if size > n:
        x = jnp.concatenate([x, jnp.zeros(x.shape[:-1] + (size - n,), x.dtype)], axis=-1)
    while x.shape[-1] > 1:
        half = x.shape[-1] // 2
        x = x[..., :half] + x[..., half:]
    return x[..., 0]


def half_area(lo, hi, scale=1.0):
    """Half surface area of boxes [..., 3] after scaling extents by ``scale``.

    Empty boxes (``hi < lo``, the padding box) have area 0. Traceable; on NumPy arrays
    it computes in NumPy (the twins use it so). Each product is :func:`rounded`, so
    every program (vmapped or not) and NumPy compute the same area.
    """
    xp = np if isinstance(lo, np.ndarray) and isinstance(hi, np.ndarray) else jnp
    d = xp.maximum((hi - lo) * scale, 0)
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    return rounded(dx * dy) + rounded(dy * dz) + rounded(dz * dx)


def take(values, index, fill):
    """``values[index]`` along axis 0, ``fill`` where ``index`` is outside ``[0, len)``.

    ``values`` [N, ...], ``index`` int [...]: the result has shape ``index.shape +
    values.shape[1:]``. No wrap-around of -1. A clamped gather and a select: the same
    result as ``mode="fill"`` with a smaller, faster program.
    """
    size = values.shape[0]
    inside = (index >= 0) & (index < size)
    got = jnp.take(values, jnp.clip(index, 0, size - 1), axis=0, mode="clip")
    return jnp.where(inside.reshape(inside.shape + (1,) * (values.ndim - 1)), got, fill)


def none_to_oob(index, size):
    """``-1`` ("none") as the out-of-range id ``size``: scatters with ``mode="drop"`` skip
    it and :func:`take` fills it (``-1`` would wrap around to the last entry)."""
    return jnp.where(index < 0, size, index)


def take_clipped(values, index):
    """``values[index]`` with ids clipped into range (callers mask the lanes that had none)."""
    return jnp.take(values, jnp.clip(index, 0, values.shape[0] - 1), axis=0, mode="clip")


# Ray tests (:mod:`jaxbvh.rays.traversal` and its twin)
#: finite stand-in for 1/0, so that (lo - origin) * inv never is 0 * inf = nan
INV_BIG = 1e30

def robust_factor(dtype) -> float:
    """``1 + 2 gamma(3)`` for ``dtype`` (Ize 2013): scale a slab exit to absorb rounding."""
    eps = float(np.finfo(dtype).eps) / 2
    gamma3 = 3 * eps / (1 - 3 * eps)
    return float(np.asarray(1 + 2 * gamma3, dtype))


SHORT = 16384  # below this, one cumsum op beats the scan's 2 log N small ones (loop bodies)


def inclusive_sum(flags):
    """Running sum [N] int32 of ``flags`` [N] (bool or int)."""
    flags = flags.astype(jnp.int32)
    if flags.shape[0] <= SHORT:
        return jnp.cumsum(flags)
    return jax.lax.associative_scan(jnp.add, flags)


def exclusive_sum(flags):
    """Sum [N] int32 of the ``flags`` before each position."""
    flags = flags.astype(jnp.int32)
    return inclusive_sum(flags) - flags


def on_device(value, dtype) -> jax.Array:
    """``value`` (a number or NumPy array) as a JAX array of ``dtype``, cast on the host.

    ``jnp.asarray(2.0, jnp.float32)``, ``jnp.int32(n)`` and ``jnp.full(...)`` outside a
    program each compile a small program (a conversion, a broadcast) in every new process
    that meets them: 30-100 ms cold, 20-45 ms to load from the cache, a dozen of them on an
    optimizer's first call. A NumPy array put on the device compiles nothing. Traceable
    (a constant in a traced program); ``value`` must be concrete."""
    return jax.device_put(np.asarray(value, dtype))
