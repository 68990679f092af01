"""Hypothesis strategies for BVH code: triangle soups, scenes, box sets, valid and broken trees.

Every coordinate and every structural choice is drawn by hypothesis (no seed handed to
NumPy), so a failing case shrinks: to fewer triangles, the plain kind, no scale or
offset, small round coordinates, a tree with fewer nodes. Needs ``hypothesis``
(``pip install jaxbvh[testing]``).

=========================  ==============================================================
strategy                   draws
=========================  ==============================================================
:func:`triangle_soups`     world triangles float64 [n, 3, 3]: random, clustered, flat,
                           degenerate, one point, grid ties; scales 1e-30 .. 1e30, far
                           offsets
:func:`scenes`             :class:`jaxbvh.io.meshes.Mesh` with several objects and
                           instances (rotations, mirrors, scales, translations)
:func:`box_sets`           primitive boxes ``(lo, hi)`` float32 [n, 3]
:func:`trees`              :class:`~jaxbvh.testing.trees.Built`: a valid tree of any arity
                           and node order, and its primitive boxes
:func:`broken_trees`       :class:`Broken`: a tree with one named defect
                           (:data:`jaxbvh.testing.trees.DEFECTS`)
:func:`renumbered`         the same tree with other node ids and run places
=========================  ==============================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from hypothesis import assume
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jaxbvh.io.meshes import Mesh
from jaxbvh.scenes import assemble
from jaxbvh.testing.trees import DEFECTS, NEED_INTERIOR, Built, Choices, make_tree, plant_defect, renumber
from jaxbvh.tree.layout import BVH, WideBVH, pad_to

SOUP_KINDS = ("random", "clustered", "flat", "degenerate", "one_point", "grid")
UNIT_TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
STEP = 2.0 ** -10  # coordinates are multiples of STEP / 512: sums and differences stay exact


def lattice(shape, low: float, high: float):
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
    """World-space triangles float64 [n, 3, 3], ``min_size <= n <= max_size``.

    Mixes random triangles (centres in [-2, 2], sizes 1/512 .. 1) with clustered ones,
    degenerate ones (a repeated vertex, all three in one point of another triangle),
    every triangle in one point, flat scenes (one plane) and a coarse grid (many exact
    ties), and, with ``extreme``, scales of 1e-30 ... 1e30 and offsets up to 1e7 scene
    sizes. Shrinks towards few plain triangles at scale 1 with round coordinates.
    """
    n = draw(st.integers(min_size, max_size))
    kind = draw(st.sampled_from(SOUP_KINDS))
    if kind == "one_point":
        tri = np.broadcast_to(draw(lattice(3, -2, 2)), (n, 3, 3)).copy()
    elif kind == "grid":  # many exact ties in centres and costs
        cells = draw(hnp.arrays(np.int64, (n, 1, 3), elements=st.integers(0, 2), fill=st.nothing()))
        tri = cells.astype(np.float64) + UNIT_TRIANGLE
    else:
        centres = draw(lattice((n, 1, 3), -2, 2)) * (0.125 if kind == "clustered" else 1.0)
        size = 8.0 ** -draw(hnp.arrays(np.int64, (n, 1, 1), elements=st.integers(0, 3), fill=st.nothing()))
        tri = centres + draw(lattice((n, 3, 3), -1, 1)) * size
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
    """World boxes ``(lo, hi)`` float64 [n, 3] of triangles [n, 3, 3]."""
    tri = np.asarray(tri)
    return tri.min(axis=1), tri.max(axis=1)


@st.composite
def box_sets(draw, min_size: int = 1, max_size: int = 40, extreme: bool = False):
    """Float32 primitive boxes ``(lo, hi)`` [n, 3] in [-1.3, 1.3]: some points, and with a
    drawn flag centres snapped to a grid of quarters (shared centres, equal costs). With
    ``extreme``, scaled by one of 1e-30, 1e-10, 1e10, 1e30 (or not), then cast (rounding
    keeps ``lo <= hi``)."""
    n = draw(st.integers(min_size, max_size))
    centre = draw(lattice((n, 3), -1, 1))
    half = draw(lattice((n, 3), 0, 0.3)) * ~draw(_flags(n))[:, None]
    if draw(st.booleans()):
        centre = np.round(centre * 4) / 4
    scale = 10.0 ** draw(st.sampled_from([0, -30, -10, 10, 30])) if extreme else 1.0
    return ((centre - half) * scale).astype(np.float32), ((centre + half) * scale).astype(np.float32)


@st.composite
def _rotation(draw):
    """A 3x3 rotation float64: a signed axis permutation (exact) or a general one from a
    drawn quaternion; shrinks to the identity."""
    if not draw(st.booleans()):
        perm = draw(st.permutations(range(3)))
        signs = draw(st.sampled_from([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)]))  # det +1
        m = np.zeros((3, 3))
        m[np.arange(3), perm] = signs
        return m * np.linalg.det(m)  # an odd permutation flips the sign back to det +1
    q = draw(hnp.arrays(np.int64, 4, elements=st.integers(-8, 8), fill=st.nothing())).astype(np.float64)
    if not q.any():
        return np.eye(3)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@st.composite
def transforms(draw, extreme: bool = False):
    """A 4x4 affine transform float64: rotation, uniform scale 1/8 .. 8, an optional
    mirror, translation in [-4, 4]^3 (with ``extreme``, up to 1e6); shrinks to identity."""
    m = draw(_rotation()) * 2.0 ** draw(st.integers(-3, 3))
    if draw(st.booleans()):
        m[:, 0] = -m[:, 0]  # a mirror: the scene flips the instance's winding
    out = np.eye(4)
    out[:3, :3] = m
    out[:3, 3] = draw(lattice(3, -4, 4)) * (10.0 ** draw(st.sampled_from([0, 3, 6])) if extreme else 1.0)
    return out


@st.composite
def scenes(draw, max_objects: int = 3, max_instances: int = 6, max_triangles: int = 8, extreme: bool = False):
    """A :class:`~jaxbvh.io.meshes.Mesh` of 1 .. ``max_objects`` objects (each a soup of
    1 .. ``max_triangles`` triangles, no extreme scale) placed by 1 .. ``max_instances``
    instances (:func:`transforms`; every object placed at least once)."""
    n_obj = draw(st.integers(1, max_objects))
    objects = []
    for _ in range(n_obj):
        tri = draw(triangle_soups(1, max_triangles, extreme=False))
        objects.append((tri.reshape(-1, 3), np.arange(3 * tri.shape[0], dtype=np.int32).reshape(-1, 3)))
    placed = draw(st.lists(st.integers(0, n_obj - 1), min_size=0, max_size=max(0, max_instances - n_obj)))
    which = draw(st.permutations(list(range(n_obj)) + placed))
    instances = [(o, draw(transforms(extreme=extreme))) for o in which]
    mesh: Mesh = assemble(objects, instances, name="drawn")
    return mesh


class _Drawn(Choices):
    """A tree's choices drawn by hypothesis (so the tree shrinks with its example)."""

    def __init__(self, draw):
        self.draw = draw

    def permutation(self, n: int) -> list[int]:
        return list(self.draw(st.permutations(range(n))))

    def make_leaf(self, size: int, max_leaf: int) -> bool:
        return self.draw(st.booleans())

    def cuts(self, size: int, arity: int) -> list[int]:
        parts = self.draw(st.integers(2, min(arity, size)))
        return sorted(self.draw(st.lists(st.integers(1, size - 1), min_size=parts - 1, max_size=parts - 1,
                                         unique=True)))

    def index(self, n: int) -> int:
        return self.draw(st.integers(0, n - 1))


@st.composite
def trees(draw, min_size: int = 1, max_size: int = 24, *, arity: int | None = 2, max_leaf: int | None = None,
          padding: bool = True, boxes=None):
    """A valid tree and its primitive boxes: :class:`~jaxbvh.testing.trees.Built`.

    Primitive boxes from :func:`box_sets` (or the strategy ``boxes`` drawing ``(lo, hi)``),
    split recursively by drawn cuts into interior nodes of 2 .. ``arity`` children
    (``arity=None``: drawn from 2, 3, 4, 8) and leaves of 1 .. ``max_leaf`` primitives
    (None: drawn, 1 .. 4); node ids shuffled (any root), leaves' runs in a shuffled order
    in ``prim_index``, and with ``padding`` inert padding nodes and slots. A
    :class:`~jaxbvh.tree.layout.BVH` for arity 2, else a :class:`~jaxbvh.tree.layout.WideBVH`.
    """
    lo, hi = draw(boxes if boxes is not None else box_sets(min_size, max_size))
    k = arity if arity is not None else draw(st.sampled_from([2, 3, 4, 8]))
    leaf = max_leaf if max_leaf is not None else draw(st.integers(1, 4))
    n = lo.shape[0]
    extra_nodes, extra_prims = (draw(st.integers(0, 8)), draw(st.integers(0, 4))) if padding else (0, 0)
    built = make_tree(lo, hi, _Drawn(draw), max_leaf=leaf, arity=k, shuffle_runs=True)
    nodes = built.tree.parent.shape[0]
    if extra_nodes or extra_prims:
        built = built._replace(tree=pad_to(built.tree, nodes + extra_nodes, n + extra_prims))
    return built


@st.composite
def renumbered(draw, tree):
    """``tree`` with drawn node ids and leaf-run places
    (:func:`jaxbvh.testing.trees.renumber`): the same tree to :func:`assert_same_tree`."""
    return renumber(tree, _Drawn(draw))


class Broken(NamedTuple):
    """A tree with one planted defect, as :func:`broken_trees` draws it."""

    tree: BVH | WideBVH  # NumPy arrays
    lo: np.ndarray       # [n, 3] primitive boxes (the defect may move one of them)
    hi: np.ndarray       # [n, 3]
    defect: str          # a key of jaxbvh.testing.trees.DEFECTS


@st.composite
def broken_trees(draw, defects=tuple(DEFECTS), min_size: int = 2, max_size: int = 16, arity: int | None = 2):
    """A :class:`Broken` tree: a valid tree from :func:`trees` with one defect drawn from
    ``defects`` planted in it (:func:`jaxbvh.testing.trees.plant_defect`)."""
    if min_size < 2:
        raise ValueError(f"broken_trees: min_size must be >= 2 (a defect needs two primitives), got {min_size}")
    defect = draw(st.sampled_from(list(defects)))
    built: Built = draw(trees(min_size, max_size, arity=arity))
    if defect in NEED_INTERIOR:
        assume(built.tree.prim_count[int(built.tree.root)] == 0)  # needs an interior node
    tree, lo, hi = plant_defect(built.tree, built.lo, built.hi, defect, _Drawn(draw))
    return Broken(tree, lo, hi, defect)
