"""NumPy twin of :mod:`jaxbvh.builders.insertion`, written the slow, literal way (Goldsmith & Salmon 1987).

One object at a time, in the given order: walk down from the root, price the
candidates met on the way, insert at the cheapest, then grow the boxes above it. The
candidate costs, tie rules, node numbering and child-slot order are exactly those of
:mod:`jaxbvh.builders.insertion` (whose docstring states them), and every quantity is computed in
the boxes' dtype with the same expressions, so both give the same tree node by node.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import numpy as np

from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale
from jaxbvh.tree.layout import WideBVH


@dataclasses.dataclass
class _Tree:
    """The tree as it grows: leaf ``p`` is node ``p``, the ``j``-th interior node made is ``n + j``."""

    children: list      # [nodes] per node its child ids in slot order ([] for a leaf)
    parent: list        # [nodes] parent id, -1 for the root (and nodes not made yet)
    box_lo: np.ndarray  # [nodes, 3] boxes in the input dtype (empty box until made)
    box_hi: np.ndarray  # [nodes, 3]
    root: int           # the root's id
    next_id: int        # id of the next interior node


class _Pricing(NamedTuple):
    """The constants the costs are computed with, in the boxes' dtype."""

    dtype: Any         # the boxes' scalar type (np.float32 or np.float64)
    scale: Any         # the scene's power-of-two area scale
    near: Any          # 1 + TIE_TOLERANCE: costs within it tie
    max_children: int  # most children of a node


def _growth(t: _Tree, node, b_lo, b_hi, rules: _Pricing):
    """(area of node's box grown to hold b, the growth of the area; 0 if it holds b)."""
    u_lo, u_hi = np.minimum(t.box_lo[node], b_lo), np.maximum(t.box_hi[node], b_hi)
    grown = half_area(u_lo, u_hi, rules.scale)
    if (u_lo == t.box_lo[node]).all() and (u_hi == t.box_hi[node]).all():
        return grown, rules.dtype(0)
    return grown, grown - half_area(t.box_lo[node], t.box_hi[node], rules.scale)


def _next_child(t: _Tree, node, b_lo, b_hi, rules: _Pricing) -> int:
    """The child of ``node`` the walk goes on to: the one whose term grows least (a
    leaf's term becomes 2 x the pair's area); ties within the tolerance to the closest
    centre (L1, of the doubled centres), then the lowest slot."""
    dtype = rules.dtype
    b_centre = b_lo + b_hi
    rises = []
    for c in t.children[node]:
        c_grown, c_delta = _growth(t, c, b_lo, b_hi, rules)
        kc = len(t.children[c])
        rises.append(dtype(2) * c_grown if kc == 0 else dtype(kc) * c_delta)
    least = min(rises)
    tied = [s for s, r in enumerate(rises) if r <= least * rules.near]
    distance = []
    for s in tied:
        c = t.children[node][s]
        d = np.abs((t.box_lo[c] + t.box_hi[c]) - b_centre)
        distance.append(d[0] + d[1] + d[2])
    closest = min(distance)
    slot = tied[distance.index(closest)]  # first of the closest: lowest slot
    return t.children[node][slot]


def _best_place(t: _Tree, b_lo, b_hi, rules: _Pricing):
    """Walk down from the root pricing the candidates met: ``(cost increase, node)`` of
    the cheapest (a leaf: pair it with b; an interior node with room: b as one more child)."""
    dtype = rules.dtype
    near = rules.near
    # `inherited` is what the ancestors' terms grow by
    node, inherited = t.root, dtype(0)
    best, best_node = dtype(np.inf), -1
    for _ in range(len(t.children)):
        grown, delta = _growth(t, node, b_lo, b_hi, rules)
        k = len(t.children[node])
        if k == 0:  # a leaf: pair it with b under a new interior node
            candidate = inherited + dtype(2) * grown
            if candidate * near < best:
                best, best_node = candidate, node
            break
        own = dtype(k) * delta
        if k < rules.max_children:  # b as one more child of this node
            candidate = (inherited + own) + grown
            if candidate * near < best:
                best, best_node = candidate, node
        inherited = inherited + own
        node = _next_child(t, node, b_lo, b_hi, rules)
        # every deeper candidate costs at least `inherited`
        if inherited * near >= best:
            break
    return best, best_node


def _attach(t: _Tree, m: int, p: int, b_lo, b_hi) -> int:
    """Insert leaf ``p`` (box ``b_lo``, ``b_hi``) at node ``m``; returns the node whose box grows first (-1: none)."""
    if t.children[m]:  # b becomes the last child of m
        t.children[m].append(p)
        t.parent[p] = m
        return m
    # a new node v holds m (slot 0) and b (slot 1), in m's place
    v = t.next_id
    t.next_id += 1
    pm = t.parent[m]
    if pm >= 0:
        t.children[pm][t.children[pm].index(m)] = v
    else:
        t.root = v
    t.children[v] = [m, p]
    t.parent[v], t.parent[m], t.parent[p] = pm, v, v
    t.box_lo[v], t.box_hi[v] = np.minimum(t.box_lo[m], b_lo), np.maximum(t.box_hi[m], b_hi)
    return pm


def _grow_boxes(t: _Tree, start: int, b_lo, b_hi) -> None:
    """Grow the boxes from ``start`` up until one already holds b."""
    a = start
    for _ in range(len(t.children)):
        if a < 0 or ((t.box_lo[a] <= b_lo).all() and (t.box_hi[a] >= b_hi).all()):
            break
        t.box_lo[a], t.box_hi[a] = np.minimum(t.box_lo[a], b_lo), np.maximum(t.box_hi[a], b_hi)
        a = t.parent[a]


def _to_wide(t: _Tree, n: int, max_children: int) -> WideBVH:
    nodes = len(t.children)
    child = np.full((nodes, max_children), -1, np.int32)
    for node, kids in enumerate(t.children):
        child[node, :len(kids)] = kids
    count = (np.arange(nodes) < n).astype(np.int32)
    return WideBVH(child=child, parent=np.asarray(t.parent, np.int32), lo=t.box_lo, hi=t.box_hi,
                   prim_start=np.where(count > 0, np.arange(nodes), 0).astype(np.int32),
                   prim_count=count, prim_index=np.arange(n, dtype=np.int32), root=np.int32(t.root))


def build(prim_lo, prim_hi, order=None, *, max_children: int, trace: list | None = None) -> WideBVH:
    """Goldsmith–Salmon tree over ``prim_lo``, ``prim_hi`` [n, 3], inserting in ``order``.

    ``order``: a permutation of ``0 .. n-1`` (default: ``0 .. n-1``). Returns an
    unpadded NumPy :class:`~jaxbvh.tree.layout.WideBVH` with ``2n - 1`` nodes: leaf ``p`` is
    node ``p`` (primitive ``p``), the ``j``-th interior node made is node ``n + j``.
    ``trace``: if a list, one ``(primitive, node, kind, cost increase)`` per insertion
    after the first is appended (kind ``"child"`` or ``"pair"``), for tests.
    """
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    dtype = lo.dtype.type
    n = lo.shape[0]
    order = np.arange(n) if order is None else np.asarray(order)
    rules = _Pricing(dtype=dtype, scale=dtype(scene_scale(lo, hi)), near=dtype(1 + TIE_TOLERANCE),
                     max_children=max_children)
    nodes = 2 * n - 1
    t = _Tree(children=[[] for _ in range(nodes)], parent=[-1] * nodes,
              box_lo=np.full((nodes, 3), np.inf, lo.dtype), box_hi=np.full((nodes, 3), -np.inf, lo.dtype),
              root=int(order[0]), next_id=n)
    t.box_lo[:n], t.box_hi[:n] = lo, hi

    for p in (int(q) for q in order[1:]):
        b_lo, b_hi = lo[p], hi[p]
        best, m = _best_place(t, b_lo, b_hi, rules)
        if trace is not None:
            trace.append((p, m, "child" if t.children[m] else "pair", float(best)))
        _grow_boxes(t, _attach(t, m, p, b_lo, b_hi), b_lo, b_hi)
    return _to_wide(t, n, max_children)
