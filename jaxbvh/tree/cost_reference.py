"""Sequential NumPy twin of :mod:`jaxbvh.tree.cost`: costs by recursion over the tree, in float64.

Follows the definitions literally (see :mod:`jaxbvh.tree.cost`): surface areas in float64
without any rescaling, the zero-area rule for SAH, normalisation by the root's area.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import half_area
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.walks import post_order


def _area(lo, hi):
    return 2.0 * half_area(np.asarray(lo, np.float64), np.asarray(hi, np.float64))


def _children(t, node):
    return [int(c) for c in np.asarray(t.child)[node] if c >= 0]


def _postorder(t):
    """Nodes reachable from the root, children before parents (the last child's subtree
    first: the order the sums below were always taken in)."""
    return post_order(np.asarray(t.child), int(t.root), last_child_first=True)


def node_costs(tree, ct=1.0, ci=1.0) -> dict[int, float]:
    """SAH cost of every reachable node, ``{node: C(node)}`` (float64)."""
    t = to_numpy(tree)
    cost: dict[int, float] = {}
    for node in _postorder(t):
        kids = _children(t, node)
        if not kids:
            cost[node] = ci * float(t.prim_count[node])
            continue
        s = _area(t.lo[node], t.hi[node])
        if s > 0:
            cost[node] = ct + sum(_area(t.lo[c], t.hi[c]) * cost[c] for c in kids) / s
        else:
            cost[node] = ct + sum(cost[c] for c in kids)
    return cost


def sah(tree, ct=1.0, ci=1.0) -> float:
    """SAH of ``tree`` (binary or wide) by recursion, float64: the root's cost, a ratio of
    areas."""
    t = to_numpy(tree)
    return node_costs(t, ct, ci)[int(t.root)]


def ng_trifonov_cost(tree) -> float:
    """Ng & Trifonov's cost: interior areas summed over the root's area (float64)."""
    t = to_numpy(tree)
    root = int(t.root)
    interior = [n for n in _postorder(t) if _children(t, n)]
    s = _area(t.lo[root], t.hi[root])
    if s > 0:
        return sum(_area(t.lo[n], t.hi[n]) for n in interior) / s
    return float(len(interior))


def goldsmith_salmon_cost(tree) -> float:
    """Goldsmith & Salmon's cost of ``tree`` (float64), as
    :func:`jaxbvh.tree.cost.goldsmith_salmon_cost` defines it."""
    t = to_numpy(tree)
    root = int(t.root)
    total = 0.0
    unweighted = 0.0
    for n in _postorder(t):
        k = len(_children(t, n)) + (int(t.prim_count[n]) if t.prim_count[n] > 1 else 0)
        total += _area(t.lo[n], t.hi[n]) * k
        unweighted += k
    s = _area(t.lo[root], t.hi[root])
    return total / s if s > 0 else unweighted
