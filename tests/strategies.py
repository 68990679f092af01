"""Hypothesis strategies shared by the tests: triangle soups, plain and extreme.

Every coordinate is drawn by hypothesis (no seed handed to NumPy), so a failing case
shrinks: to fewer triangles, the plain kind, no scale or offset, and small round
coordinates.
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

SOUP_KINDS = ("random", "clustered", "flat", "degenerate", "one_point", "grid")
UNIT_TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
STEP = 2.0 ** -10  # coordinates are multiples of STEP / 512: sums and differences stay exact


def _lattice(shape, low: float, high: float):
    """float64 arrays of ``shape`` with elements in ``[low, high]``, multiples of :data:`STEP`.

    Integers, not floats: a failure shrinks to 0 and round values, and no coordinate is
    so small that float32 would hold it as a subnormal (XLA on CPU flushes those to 0; the
    scene frame keeps real scenes far from them). Every element is drawn on its own.
    """
    ints = hnp.arrays(np.int64, shape, elements=st.integers(round(low / STEP), round(high / STEP)),
                      fill=st.nothing())
    return st.builds(lambda a: a * STEP, ints)


def _flags(n: int):
    return hnp.arrays(np.bool_, n, elements=st.booleans(), fill=st.nothing())


@st.composite
def triangle_soups(draw, min_size: int = 1, max_size: int = 40, extreme: bool = True):
    """World-space triangles float64 [n, 3, 3].

    Mixes random triangles (centres in [-2, 2], sizes 1/512 .. 1) with clustered ones,
    degenerate ones (a repeated vertex, all three in one point of another triangle),
    every triangle in one point, flat scenes (one plane) and a coarse grid (many exact
    ties), and, with ``extreme``, scales of 1e-30 ... 1e30 and offsets up to 1e7 scene
    sizes.
    """
    n = draw(st.integers(min_size, max_size))
    kind = draw(st.sampled_from(SOUP_KINDS))
    if kind == "one_point":
        tri = np.broadcast_to(draw(_lattice(3, -2, 2)), (n, 3, 3)).copy()
    elif kind == "grid":  # many exact ties in centres and costs
        cells = draw(hnp.arrays(np.int64, (n, 1, 3), elements=st.integers(0, 2), fill=st.nothing()))
        tri = cells.astype(np.float64) + UNIT_TRIANGLE
    else:
        centres = draw(_lattice((n, 1, 3), -2, 2)) * (0.125 if kind == "clustered" else 1.0)
        size = 8.0 ** -draw(hnp.arrays(np.int64, (n, 1, 1), elements=st.integers(0, 3), fill=st.nothing()))
        tri = centres + draw(_lattice((n, 3, 3), -1, 1)) * size
        if kind == "flat":
            tri[..., 2] = 0.0
        if kind == "degenerate":
            line = draw(_flags(n))
            tri[line, 1] = tri[line, 0]  # a line or a point
            tri[draw(_flags(n)) & ~line] = tri[0, 0]  # a point shared with the first triangle
    if extreme:
        scale = 10.0 ** draw(st.sampled_from([0, -30, -10, 10, 30]))
        offset = draw(st.sampled_from([0.0, 1e7, -1e7]))  # in units of the scene size
        tri = (tri + offset) * scale
    return tri


def boxes(tri: np.ndarray):
    """World boxes (lo, hi) float64 [n, 3] of triangles [n, 3, 3]."""
    return tri.min(axis=1), tri.max(axis=1)


@st.composite
def box_sets(draw, min_size: int = 1, max_size: int = 40):
    """Float32 primitive boxes (lo, hi) [n, 3] in [-1.3, 1.3]: some points, and with a
    drawn flag centres snapped to a grid of quarters (shared centres, equal costs)."""
    n = draw(st.integers(min_size, max_size))
    centre = draw(_lattice((n, 3), -1, 1))
    half = draw(_lattice((n, 3), 0, 0.3)) * ~draw(_flags(n))[:, None]
    if draw(st.booleans()):
        centre = np.round(centre * 4) / 4
    return (centre - half).astype(np.float32), (centre + half).astype(np.float32)


# Tree files whose arrays have the wrong type or shape (the interchange reader's inputs)

#: every array an interchange tree file may hold (jaxbvh.tree.interchange)
TREE_FILE_KEYS = ("child", "prim_start", "prim_count", "prim_index", "lo", "hi", "root", "origin", "scale")
#: types an array of a hostile file may come in: every width of int, uint and float,
#: complex, bool and text (object arrays are pickles, refused before any array is read)
TREE_FILE_DTYPES = ("bool", "int8", "uint8", "int16", "int32", "uint32", "int64", "uint64", "float16",
                    "float32", "float64", "longdouble", "complex64", "<U8")
#: how an array's shape may be changed
TREE_FILE_SHAPES = ("same", "scalar", "one", "extra_axis", "one_fewer", "one_more")


def reshaped(a: np.ndarray, change: str) -> np.ndarray:
    """``a`` with its shape changed as ``change`` (:data:`TREE_FILE_SHAPES`) says."""
    flat = a.ravel()
    first = flat[:1] if flat.size else np.zeros(1, a.dtype)
    if change == "scalar":
        return first.reshape(())
    if change == "one":
        return first.reshape(1)
    if change == "extra_axis":
        return a[..., None]
    if change == "one_fewer":
        return a[:-1] if a.ndim else a.reshape(1)[:0]
    if change == "one_more":
        return np.concatenate([a, a[:1]]) if a.ndim else np.stack([a, a])
    return a


@st.composite
def tree_file_changes(draw, arrays: dict):
    """``(changed, changes)``: the interchange ``arrays`` (with a frame) with one to three of
    them stored in another type (:data:`TREE_FILE_DTYPES`) and/or shape
    (:data:`TREE_FILE_SHAPES`); ``changes`` lists ``(key, dtype, shape)``. Draws shrink to
    one array, its own type and shape."""
    keys = draw(st.lists(st.sampled_from(TREE_FILE_KEYS), min_size=1, max_size=3, unique=True))
    changed = {k: np.array(v) for k, v in arrays.items()}
    changes = []
    for key in keys:
        dtype = draw(st.sampled_from((None,) + TREE_FILE_DTYPES))
        shape = draw(st.sampled_from(TREE_FILE_SHAPES))
        a = changed[key]
        if dtype is not None:
            with np.errstate(all="ignore"):
                a = a.astype(dtype)
        changed[key] = reshaped(a, shape)
        changes.append((key, str(changed[key].dtype), shape))
    return changed, changes
