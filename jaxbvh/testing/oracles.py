"""Answers computed the slow, sure way, to hold fast BVH code against.

Every oracle is plain NumPy or Python, written from the definitions (the NumPy
references of :mod:`jaxbvh`), and needs no tree where the answer does not depend on one:

* hits: :func:`closest_hits` and :func:`any_hits`, every ray against every triangle;
* costs: :func:`sah`, :func:`node_costs`, :func:`ng_trifonov_cost`,
  :func:`goldsmith_salmon_cost`, by recursion in float64;
* optima by enumeration on small inputs: :func:`optimal_tree` (the least SAH of any
  binary tree over a few primitives, the bound every builder and treelet optimizer
  meets), :func:`optimal_treelet` (the best rearrangement of a treelet of a given tree)
  and :func:`optimal_collapse` (the best wide tree a collapse of a binary tree can make).
"""

from __future__ import annotations

import itertools

import numpy as np

from jaxbvh.numerics import half_area
from jaxbvh.optimize.treelet_reference import Tree as TreeletTree
from jaxbvh.optimize.treelet_reference import brute_force as treelet_brute_force
from jaxbvh.rays.traversal_reference import brute_force_closest
from jaxbvh.tree.cost_reference import goldsmith_salmon_cost, ng_trifonov_cost, node_costs, sah
from jaxbvh.tree.interchange import from_interchange
from jaxbvh.tree.layout import to_numpy
from jaxbvh.wide.collapse_reference import rcost, to_wide

__all__ = ["closest_hits", "any_hits", "sah", "node_costs", "ng_trifonov_cost", "goldsmith_salmon_cost",
           "optimal_tree", "optimal_treelet", "optimal_collapse", "MAX_ENUMERATED"]

MAX_ENUMERATED = 8  # primitives or leaves enumerated at most: (2k - 3)!! trees, 135135 at k = 8


def closest_hits(triangles, origin, direction, *, t_min: float = 0.0, t_max: float = np.inf):
    """Closest hit of every ray against every triangle (Moeller-Trumbore in the
    triangles' dtype): ``(t, prim)`` [R] float, int32; a miss is ``(inf, -1)``; equal
    ``t``: the lower primitive id. ``triangles`` [T, 3, 3]; ``origin``, ``direction``
    [R, 3]; hits count for ``t_min < t < t_max``."""
    return brute_force_closest(triangles, origin, direction, t_min=t_min, t_max=t_max)


def any_hits(triangles, origin, direction, *, t_min: float = 0.0, t_max: float = np.inf) -> np.ndarray:
    """Whether each ray [R] hits any triangle for ``t_min < t < t_max`` (bool [R])."""
    return closest_hits(triangles, origin, direction, t_min=t_min, t_max=t_max)[1] >= 0


def _area(lo, hi) -> float:
    return float(2.0 * half_area(np.asarray(lo, np.float64), np.asarray(hi, np.float64)))


def _splits(items):
    """Every split of ``items`` into two non-empty groups, each split once."""
    first, rest = items[0], items[1:]
    for bits in range(1 << len(rest)):
        left = [first] + [x for j, x in enumerate(rest) if bits >> j & 1]
        right = [x for j, x in enumerate(rest) if not bits >> j & 1]
        if right:
            yield left, right


def _all_trees(items, lo, hi):
    """Every binary tree over ``items`` (indices into lo, hi): ``(shape, lo, hi)`` with
    shape an int (a leaf) or a pair of shapes."""
    if len(items) == 1:
        yield items[0], lo[items[0]], hi[items[0]]
        return
    for left, right in _splits(items):
        for ls, llo, lhi in _all_trees(left, lo, hi):
            for rs, rlo, rhi in _all_trees(right, lo, hi):
                yield (ls, rs), np.minimum(llo, rlo), np.maximum(lhi, rhi)


def _shape_cost(shape, lo, hi, leaf_cost, ct) -> tuple[float, np.ndarray, np.ndarray]:
    """Area-weighted cost ``sum over interior nodes of ct * area + sum over leaves of
    area * leaf cost`` of ``shape``, and its box."""
    if not isinstance(shape, tuple):
        return _area(lo[shape], hi[shape]) * leaf_cost[shape], lo[shape], hi[shape]
    a, alo, ahi = _shape_cost(shape[0], lo, hi, leaf_cost, ct)
    b, blo, bhi = _shape_cost(shape[1], lo, hi, leaf_cost, ct)
    box_lo, box_hi = np.minimum(alo, blo), np.maximum(ahi, bhi)
    return ct * _area(box_lo, box_hi) + a + b, box_lo, box_hi


def _check_small(k: int, what: str):
    if not 1 <= k <= MAX_ENUMERATED:
        raise ValueError(f"{what}: enumeration needs 1 .. {MAX_ENUMERATED} items, got {k}")


def optimal_tree(lo, hi, *, ct: float = 1.0, ci: float = 1.0):
    """The binary tree of least SAH over primitive boxes ``lo``, ``hi`` [k, 3] (k <= 8),
    one primitive per leaf, found by trying every tree.

    Returns ``(tree, cost)``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy, nodes in
    depth-first order, the boxes' dtype) and its SAH (float64, normalised by the root's
    area; the unnormalised sum when the root's area is 0). Ties: the first tree found.
    """
    lo, hi = np.asarray(lo), np.asarray(hi)
    k = lo.shape[0]
    _check_small(k, "optimal_tree")
    leaf_cost = [ci] * k
    best = min(_all_trees(list(range(k)), lo, hi), key=lambda x: _shape_cost(x[0], lo, hi, leaf_cost, ct)[0])
    child, start, count, prim_index, box_lo, box_hi = [], [], [], [], [], []

    def emit(shape):  # depth first; bounded by the shape's depth (at most k)
        i = len(child)
        child.append([-1, -1]), start.append(0), count.append(0), box_lo.append(None), box_hi.append(None)
        if not isinstance(shape, tuple):
            start[i], count[i] = len(prim_index), 1
            prim_index.append(shape)
            box_lo[i], box_hi[i] = lo[shape], hi[shape]
        else:
            a, b = emit(shape[0]), emit(shape[1])
            child[i] = [a, b]
            box_lo[i], box_hi[i] = np.minimum(box_lo[a], box_lo[b]), np.maximum(box_hi[a], box_hi[b])
        return i

    emit(best[0])
    tree = from_interchange(dict(child=np.array(child, np.int32), prim_start=np.array(start, np.int32),
                                 prim_count=np.array(count, np.int32), prim_index=np.array(prim_index, np.int32),
                                 lo=np.array(box_lo, lo.dtype), hi=np.array(box_hi, lo.dtype), root=np.int32(0)),
                            pad=False)
    return tree, sah(tree, ct, ci)


def optimal_treelet(tree, leaves, *, ct: float = 1.0, ci: float = 1.0):
    """The best binary tree over treelet leaves ``leaves`` (node ids of ``tree``, at most
    8; the subtrees under them stay as they are), by trying every tree.

    Returns ``(shape, cost)``: ``shape`` nested pairs of the leaf ids, ``cost`` the
    treelet's area-weighted cost ``sum over its interior nodes of ct * area + sum over
    its leaves of area * C(leaf)`` (``C`` the leaf subtree's SAH), divided by the tree
    root's area: the treelet's share of the tree's SAH (in the tree's dtype, as the
    treelet optimizer's NumPy twin computes areas; unnormalised if the root's area is 0).
    """
    _check_small(len(leaves), "optimal_treelet")
    t = TreeletTree(tree, ct, ci)
    shape, cost = treelet_brute_force(t, [int(x) for x in leaves])
    root_area = t.area[t.root]
    return shape, float(cost / root_area) if root_area > 0 else float(cost)


def optimal_collapse(tree, *, max_children: int = 4, test_cost=None):
    """The best wide tree a collapse of binary ``tree`` can make (Susano Pinto's cost, a
    child test cost ``test_cost`` per visited node), by trying
    every set of interior nodes to keep (the root always; at most 12 interior nodes).

    A kept node's children are its nearest kept descendants and the leaves below it
    through removed nodes, at most ``max_children`` of them; leaves stay leaves (so their
    cost is the same for every collapse and left out). Returns ``(wide tree, cost)``: a
    :class:`~jaxbvh.tree.layout.WideBVH` on the input's node ids and its node cost ``R``
    (root-normalised areas times the test cost, the tree's dtype), as
    :func:`jaxbvh.wide.collapse_reference.rcost` computes it. Ties: the first found.
    """
    t = to_numpy(tree)
    child = np.asarray(t.child)
    interior = [n for n in range(child.shape[0]) if (child[n] >= 0).any()]
    root = int(t.root)
    rest = [n for n in interior if n != root]
    if len(rest) > 12:
        raise ValueError(f"optimal_collapse: enumeration needs at most 13 interior nodes, got {len(rest) + 1}")

    def kids_of(n, kept):  # bounded by the tree's depth
        out = []
        for c in (int(x) for x in child[n] if x >= 0):
            out += [c] if c in kept or not (child[c] >= 0).any() else kids_of(c, kept)
        return out

    best = None
    for keep in itertools.product([False, True], repeat=len(rest)):
        kept = {root} | {n for n, k in zip(rest, keep) if k}
        children = {n: kids_of(n, kept) for n in kept}
        if max(len(c) for c in children.values()) > max_children:
            continue
        r, _ = rcost(t, children, test_cost=test_cost)
        if best is None or r < best[1]:
            best = (children, r)
    children, cost = best
    return to_wide(t, children, arity=max_children), cost
