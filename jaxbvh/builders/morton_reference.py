"""Sequential NumPy twin of :mod:`jaxbvh.builders.morton`: codes bit by bit, keys as Python integers.

Same grid, same key layout (documented in :mod:`jaxbvh.builders.morton`); the bit interleaving is
a loop over bits rather than magic masks, and the sort is Python's.
"""

from __future__ import annotations

import numpy as np


def quantize(lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    """Grid cell int64 [n, 3] of every centre (cubic grid over the centre box)."""
    dtype = lo.dtype
    per_axis = bits // 3
    centre = dtype.type(0.5) * lo + dtype.type(0.5) * hi
    origin = centre.min(axis=0)
    extent = float((centre.max(axis=0) - origin).max())
    if extent > 0:
        scale = dtype.type(min(float(2 ** per_axis) / extent, float(np.finfo(dtype).max)))
    else:
        scale = dtype.type(0.0)
    with np.errstate(over="ignore"):  # a huge scale may overflow to inf: clipped below
        cell = np.floor((centre - origin) * scale)
    return np.clip(cell, 0, 2 ** per_axis - 1).astype(np.int64)


def interleave(qx: int, qy: int, qz: int, per_axis: int) -> int:
    """Morton code: bit k of qx, qy, qz goes to bit 3k + 2, 3k + 1, 3k."""
    code = 0
    for k in range(per_axis):
        code |= ((qx >> k) & 1) << (3 * k + 2)
        code |= ((qy >> k) & 1) << (3 * k + 1)
        code |= ((qz >> k) & 1) << (3 * k)
    return code


def id_bits(n: int) -> int:
    """Bits a primitive id of ``n`` primitives takes in the low end of a sort key (at least
    1)."""
    return max(1, (n - 1).bit_length())


def code_length(n: int, bits: int) -> int:
    """Bits of the Morton code kept in a 63-bit key beside ``n`` primitive ids: ``bits``, or
    fewer when the ids need the room."""
    return min(bits, 63 - id_bits(n))


def keys(lo: np.ndarray, hi: np.ndarray, bits: int) -> list[int]:
    """The key of every primitive (a Python int < 2^63), in primitive order."""
    n = lo.shape[0]
    cells = quantize(lo, hi, bits)
    length = code_length(n, bits)
    out = []
    for i in range(n):
        code = interleave(int(cells[i, 0]), int(cells[i, 1]), int(cells[i, 2]), bits // 3)
        out.append(((code >> (bits - length)) << (63 - length)) | i)
    return out


def sorted_keys(lo: np.ndarray, hi: np.ndarray, bits: int):
    """``(keys sorted ascending, primitive ids in that order)``."""
    ks = sorted(keys(lo, hi, bits))
    mask = (1 << id_bits(lo.shape[0])) - 1
    return ks, [k & mask for k in ks]


def split_axis(key_a: int, key_b: int, n: int, bits: int) -> int:
    """Axis (0, 1, 2) of the first bit where two keys differ, or -1 when it is an id bit."""
    q = 63 - (key_a ^ key_b).bit_length()  # payload bit from the top (bit 63 is always 0)
    return q % 3 if q < code_length(n, bits) else -1
