"""Morton codes of primitive centres, and the sorted 64-bit keys the bottom-up builders start from.

LBVH (:mod:`jaxbvh.builders.lbvh`) and PLOC (:mod:`jaxbvh.builders.ploc`) both begin by ordering the
primitives along the Morton (Z-order) curve: one sort, after which primitives close in
space are mostly close in the array.

Codes
=====
Centres are ``0.5 * lo + 0.5 * hi`` (as in :mod:`jaxbvh.builders.topdown`). Each coordinate is
quantized on a cubic grid over the box of all centres (the scene frame):
``q = floor((c - origin) * scale)`` clipped to ``[0, 2^b - 1]``, with ``origin`` the
lowest centre per axis and ``scale = 2^b / E`` for ``E`` the centre box's largest
extent, so cells are cubes and a flat axis simply uses fewer cells. ``b = 10`` gives
30-bit codes, ``b = 21`` 63-bit codes; the bits of ``qx``, ``qy``, ``qz`` are
interleaved with ``x`` most significant (bit ``3k + 2`` of a code is bit ``k`` of ``qx``).
:func:`quantization` computes ``scale`` on the host in the boxes' dtype from the exact
centre bounds, so the NumPy reference (:mod:`jaxbvh.builders.morton_reference`) quantizes
identically.

Keys
====
The sort key of a primitive is one unsigned 64-bit word::

    bit 63             0 (1 for padding slots: they sort last and share no prefix with a primitive)
    bits 62 .. 63-L    the top L bits of the Morton code, L = min(code bits, 63 - s)
    bits s-1 .. 0      the primitive id, s = max(1, bit_length(n - 1))

so all keys are distinct, equal codes are ordered by id (Karras' tie-break for duplicate
codes), and the radix tree of :mod:`jaxbvh.builders.lbvh` is simply the radix tree of the keys.
30-bit codes always fit whole; 63-bit codes keep their top ``63 - s`` bits (43 bits,
14 per axis, for a million primitives: far finer than the spacing of the primitives).
The key of the *first differing bit* of two keys tells which axis separates them:
payload bit ``q`` from the top (``q = clz(a ^ b) - 1``) is axis ``q % 3`` when
``q < L``, and the id (no axis) otherwise.

Why 64 bits and x64. XLA on CPU sorts a single integer array several times faster than
it sorts keys with a payload (an argsort), so the id travels inside the key and one
sort of one array gives the order. JAX has 64-bit integers only in x64 mode, so the
functions that touch keys are traced inside :func:`x64` (a ``jax.enable_x64`` scope);
they take and return float arrays in the caller's dtype and 32-bit integers, so the
caller's mode does not matter.
"""

from __future__ import annotations

import contextlib
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.program_store import stored_jit

CODE_BITS = (30, 63)
PAD_BIT = np.uint64(1) << np.uint64(63)


def x64():
    """The scope the key functions are traced and run in (module docstring: why)."""
    return jax.enable_x64(True) if not jax.config.jax_enable_x64 else contextlib.nullcontext()


def check_code_bits(bits: int) -> int:
    """The Morton code length ``bits`` as an int, if it is one of :data:`CODE_BITS`; else
    ``ValueError`` naming ``morton_bits``."""
    if int(bits) not in CODE_BITS:
        raise ValueError(f"morton_bits must be one of {', '.join(map(str, CODE_BITS))}, got {bits}")
    return int(bits)


@stored_jit
def centre_bounds(lo, hi, n):
    """Lowest and highest centre [3] each of the first ``n`` of ``lo``, ``hi`` [cap, 3] (exact)."""
    centre = 0.5 * lo + 0.5 * hi
    is_prim = (jnp.arange(lo.shape[0]) < n)[:, None]
    return (jnp.min(jnp.where(is_prim, centre, jnp.inf), axis=0),
            jnp.max(jnp.where(is_prim, centre, -jnp.inf), axis=0))


def quantization(lo, hi, n: int, bits: int):
    """``(origin [3], scale)`` of the cubic grid over the centres of the first ``n`` boxes.

    ``lo``, ``hi`` [cap, 3] in the working dtype (JAX or NumPy). The centre bounds come
    from :func:`centre_bounds` (a jitted pass); ``scale`` is computed on the host in the
    boxes' dtype, as the NumPy reference does, and capped at the dtype's largest finite
    value, so a tiny centre box never makes it infinite (``0 * inf`` would be NaN); all
    centres in one point give ``scale = 0``, every code 0.
    """
    dtype = np.dtype(lo.dtype)
    low, high = (np.asarray(a) for a in centre_bounds(jnp.asarray(lo), jnp.asarray(hi), jnp.int32(n)))
    extent = float((high - low).max())
    cells = float(2 ** (int(bits) // 3))
    scale = min(cells / extent, float(np.finfo(dtype).max)) if extent > 0 else 0.0
    return low.astype(dtype), dtype.type(scale)


def spread_bits(x, bits_per_axis: int):
    """Bits of ``x`` (uint64 array, each < ``2^bits_per_axis``) moved to every third position.

    Bit ``k`` of ``x`` lands on bit ``3k``; ``bits_per_axis`` is 10 (30-bit codes) or 21
    (63-bit codes). Traceable inside :func:`x64` (uint64).
    """
    if bits_per_axis == 10:
        masks = ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249))
    else:  # 21
        masks = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                 (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249))
    for shift, mask in masks:
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def id_bits(n):
    """``s = max(1, bit_length(n - 1))`` (traced): bits of the id field of a key."""
    m = jnp.maximum(jnp.asarray(n, jnp.int32) - 1, 1).astype(jnp.uint32)
    return (32 - jax.lax.clz(m)).astype(jnp.int32)


def code_length(n, bits: int):
    """``L = min(bits, 63 - s)`` (traced): how many top code bits a key keeps."""
    return jnp.minimum(bits, 63 - id_bits(n))


def keys(lo, hi, n, origin, scale, *, bits: int):
    """Unsorted keys uint64 [cap] of primitive boxes ``lo``, ``hi`` [cap, 3] (first ``n`` real).

    Traceable only inside :func:`x64`. ``origin`` [3], ``scale``: from
    :func:`quantization`, in the boxes' dtype.
    """
    cap = lo.shape[0]
    ids = jnp.arange(cap, dtype=jnp.uint64)
    is_prim = jnp.arange(cap) < n
    per_axis = bits // 3
    centre = 0.5 * lo + 0.5 * hi
    cell = jnp.floor((centre - origin) * scale)
    cell = jnp.where(is_prim[:, None], jnp.clip(cell, 0, 2 ** per_axis - 1), 0).astype(jnp.uint64)
    code = ((spread_bits(cell[:, 0], per_axis) << np.uint64(2))
            | (spread_bits(cell[:, 1], per_axis) << np.uint64(1)) | spread_bits(cell[:, 2], per_axis))
    length = code_length(n, bits).astype(jnp.uint64)
    top = (code >> (np.uint64(bits) - length)) << (np.uint64(63) - length)
    return jnp.where(is_prim, top | ids, PAD_BIT | ids)


def sort_keys(key, n):
    """``(sorted keys uint64 [cap], order int32 [cap])``: one sort; ``order[p]`` is the id at position p.

    Padding positions (``p >= n``) get ``order[p] = p``, a padding slot, so gathering
    boxes by ``order`` keeps padding inert.
    """
    key = jnp.sort(key)
    mask = (jnp.uint64(1) << id_bits(n).astype(jnp.uint64)) - np.uint64(1)
    pos = jnp.arange(key.shape[0], dtype=jnp.int32)
    order = jnp.where(pos < n, (key & mask).astype(jnp.int32), pos)
    return key, order


def morton_order(lo, hi, n, origin, scale, *, bits: int):
    """Primitive ids int32 [cap] in Morton order (padding last); a jitted call in the x64 scope."""
    with x64():
        return _morton_order(lo, hi, jnp.int32(n), origin, scale, bits=bits)


@partial(stored_jit, static_argnames=("bits",))
def _morton_order(lo, hi, n, origin, scale, *, bits):
    return sort_keys(keys(lo, hi, n, origin, scale, bits=bits), n)[1]
