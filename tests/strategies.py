"""The suite's hypothesis strategies: the public kit's (:mod:`jaxbvh.testing.strategies`),
re-exported under the names test modules import (``from strategies import ...``), and hostile
tree files for the interchange reader's tests."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from jaxbvh.testing.strategies import (  # noqa: F401
    SOUP_KINDS,
    STEP,
    UNIT_TRIANGLE,
    Broken,
    box_sets,
    boxes,
    broken_trees,
    lattice,
    scenes,
    transforms,
    trees,
    triangle_soups,
)

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
