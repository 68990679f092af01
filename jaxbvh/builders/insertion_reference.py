"""NumPy twin of :mod:`jaxbvh.builders.insertion`, written the slow, literal way (Goldsmith & Salmon 1987).

One object at a time, in the given order: walk down from the root, price the
candidates met on the way, insert at the cheapest, then grow the boxes above it. The
candidate costs, tie rules, node numbering and child-slot order are exactly those of
:mod:`jaxbvh.builders.insertion` (whose docstring states them), and every quantity is computed in
the boxes' dtype with the same expressions, so both give the same tree node by node.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale
from jaxbvh.tree.layout import WideBVH


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
    scale = dtype(scene_scale(lo, hi))
    near = dtype(1 + TIE_TOLERANCE)
    nodes = 2 * n - 1
    children: list[list[int]] = [[] for _ in range(nodes)]
    parent = [-1] * nodes
    box_lo = np.full((nodes, 3), np.inf, lo.dtype)
    box_hi = np.full((nodes, 3), -np.inf, lo.dtype)
    box_lo[:n], box_hi[:n] = lo, hi
    root = int(order[0])
    next_id = n

    for p in (int(q) for q in order[1:]):
        b_lo, b_hi = lo[p], hi[p]
        b_centre = b_lo + b_hi

        def growth(node):
            """(area of node's box grown to hold b, the growth of the area; 0 if it holds b)."""
            u_lo, u_hi = np.minimum(box_lo[node], b_lo), np.maximum(box_hi[node], b_hi)
            grown = half_area(u_lo, u_hi, scale)
            if (u_lo == box_lo[node]).all() and (u_hi == box_hi[node]).all():
                return grown, dtype(0)
            return grown, grown - half_area(box_lo[node], box_hi[node], scale)

        # walk down from the root; `inherited` is what the ancestors' terms grow by
        node, inherited = root, dtype(0)
        best, best_node = dtype(np.inf), -1
        for _ in range(nodes):
            grown, delta = growth(node)
            k = len(children[node])
            if k == 0:  # a leaf: pair it with b under a new interior node
                candidate = inherited + dtype(2) * grown
                if candidate * near < best:
                    best, best_node = candidate, node
                break
            own = dtype(k) * delta
            if k < max_children:  # b as one more child of this node
                candidate = (inherited + own) + grown
                if candidate * near < best:
                    best, best_node = candidate, node
            inherited = inherited + own
            # the child whose term grows least (a leaf's term becomes 2 x the pair's area)
            rises = []
            for c in children[node]:
                c_grown, c_delta = growth(c)
                kc = len(children[c])
                rises.append(dtype(2) * c_grown if kc == 0 else dtype(kc) * c_delta)
            least = min(rises)
            tied = [s for s, r in enumerate(rises) if r <= least * near]
            distance = []
            for s in tied:
                c = children[node][s]
                d = np.abs((box_lo[c] + box_hi[c]) - b_centre)
                distance.append(d[0] + d[1] + d[2])
            closest = min(distance)
            slot = tied[distance.index(closest)]  # first of the closest: lowest slot
            node = children[node][slot]
            # every deeper candidate costs at least `inherited`
            if inherited * near >= best:
                break

        if trace is not None:
            kind = "pair" if not children[best_node] else "child"
            trace.append((p, best_node, kind, float(best)))
        m = best_node
        if children[m]:  # b becomes the last child of m
            children[m].append(p)
            parent[p] = m
            start = m
        else:  # a new node v holds m (slot 0) and b (slot 1), in m's place
            v = next_id
            next_id += 1
            pm = parent[m]
            if pm >= 0:
                children[pm][children[pm].index(m)] = v
            else:
                root = v
            children[v] = [m, p]
            parent[v], parent[m], parent[p] = pm, v, v
            box_lo[v], box_hi[v] = np.minimum(box_lo[m], b_lo), np.maximum(box_hi[m], b_hi)
            start = pm
        # grow the boxes above the insertion point until one already holds b
        a = start
        for _ in range(nodes):
            if a < 0 or ((box_lo[a] <= b_lo).all() and (box_hi[a] >= b_hi).all()):
                break
            box_lo[a], box_hi[a] = np.minimum(box_lo[a], b_lo), np.maximum(box_hi[a], b_hi)
            a = parent[a]

    child = np.full((nodes, max_children), -1, np.int32)
    for node, kids in enumerate(children):
        child[node, :len(kids)] = kids
    count = (np.arange(nodes) < n).astype(np.int32)
    return WideBVH(child=child, parent=np.asarray(parent, np.int32), lo=box_lo, hi=box_hi,
                   prim_start=np.where(count > 0, np.arange(nodes), 0).astype(np.int32),
                   prim_count=count, prim_index=np.arange(n, dtype=np.int32), root=np.int32(root))
