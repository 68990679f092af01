"""NumPy twin of :mod:`jaxbvh.wide.collapse`, written the slow, literal way (Susano Pinto 2010).

* :func:`optimal` — Algorithm 3 as a memoised recursion over the tree (one table of
  ``K + 1`` costs per node, computed when first asked for), then back-tracking by a
  second recursion from the root.
* :func:`greedy` — Algorithm 2: ``pushup(node)`` with a first-in first-out queue,
  recursing into every child it keeps.
* :func:`qbvh` — every interior node at odd depth removed.

Same cost model, the same float type as the tree, the same area formula and the same tie
rule (:func:`jaxbvh.numerics.min_gain`, first candidate wins) as the JAX module, so both choose the same
tree. Results are plain Python: ``{node: [children]}`` for the kept interior nodes, in
the order the algorithm lists them (left to right for ``optimal`` and ``qbvh``; the
order of the queue for ``greedy``), turned into a :class:`~jaxbvh.tree.layout.WideBVH` on the
input's node ids by :func:`to_wide`.
"""

from __future__ import annotations

import sys
from collections import deque

import numpy as np

from jaxbvh.numerics import box_scale, half_area, min_gain
from jaxbvh.tree.layout import WideBVH, to_numpy
from jaxbvh.wide.box_tests import cost_table


class _Binary:
    """The input's links, leaf sizes and root-normalised areas ``a(n)`` (tree dtype)."""

    def __init__(self, tree):
        t = to_numpy(tree)
        self.t = t
        self.left = np.asarray(t.left)
        self.right = np.asarray(t.right)
        self.count = np.asarray(t.prim_count)
        self.root = int(t.root)
        self.f = np.asarray(t.lo).dtype.type
        lo, hi = np.asarray(t.lo), np.asarray(t.hi)
        scale = box_scale(lo[self.root], hi[self.root])
        self.area = {}
        root_area = half_area(lo[self.root], hi[self.root], scale)
        for n in self.nodes():
            s = half_area(lo[n], hi[n], scale)
            self.area[n] = s / root_area if root_area > 0 else self.f(1)
        sys.setrecursionlimit(max(sys.getrecursionlimit(), 4 * len(self.area) + 1000))

    def nodes(self):
        out, stack = [], [self.root]
        while stack:
            n = stack.pop()
            out.append(n)
            if not self.is_leaf(n):
                stack += [int(self.right[n]), int(self.left[n])]
        return out

    def is_leaf(self, n):
        return self.left[n] < 0

    def kids(self, n):
        return [int(self.left[n]), int(self.right[n])]


def _table(test_cost, k, f):
    return [f(x) for x in cost_table(test_cost, k)]


def _first_near_min(values, f):
    best = min(values)
    for i, v in enumerate(values):
        if v <= best * f(1 + min_gain(f)):
            return i, v
    return 0, values[0]


def optimal(tree, *, max_children=8, test_cost=None, max_leaf=1, ci=1.0):
    """Pinto's Algorithm 3: ``(cost, children, new_leaves)``.

    ``cost`` is ``g(root, 1)``; ``children`` ``{node: [children]}`` of the kept interior
    nodes; ``new_leaves`` the interior nodes turned into leaves (``max_leaf > 1``).
    """
    b = _Binary(tree)
    f, k = b.f, int(max_children)
    T = _table(test_cost, k, f)
    ci = f(ci)
    merge = int(max_leaf) > 1
    inf = f(np.inf)
    memo = {}  # node -> (cost [K+1], split [K+1], choice, primitives)

    def leaf_value(n):
        return b.area[n] * ci * f(b.count[n]) if merge else f(0)

    def R(node):
        if node in memo:
            return memo[node]
        if b.is_leaf(node):
            cost = [inf] * (k + 1)
            cost[1] = leaf_value(node)
            memo[node] = (cost, None, 1, int(b.count[node]))
            return memo[node]
        left, right = (R(c) for c in b.kids(node))
        cost, split = [inf] * (k + 1), [0] * (k + 1)
        for t in range(2, k + 1):
            sums = [left[0][i] + right[0][t - i] for i in range(1, t)]
            i, cost[t] = _first_near_min(sums, f)
            split[t] = i + 1
        kept = [b.area[node] * T[t] + cost[t] for t in range(2, k + 1)]
        i, value = _first_near_min(kept, f)
        choice = i + 2
        prims = left[3] + right[3]
        if merge and prims <= max_leaf:
            as_leaf = b.area[node] * ci * f(prims)
            if value > as_leaf * f(1 + min_gain(f)):
                choice, value = 0, as_leaf
        cost[1] = value
        memo[node] = (cost, split, choice, prims)
        return memo[node]

    total = R(b.root)[0][1]
    children, new_leaves = {}, []

    def entries(node, t):
        """The ``t`` entry points of ``node``'s subtree, left to right (back-tracking)."""
        if t == 1:
            keep(node)
            return [node]
        i = memo[node][1][t]
        left, right = b.kids(node)
        return entries(left, i) + entries(right, t - i)

    def keep(node):
        if b.is_leaf(node):
            return
        _, split, choice, _ = memo[node]
        if choice == 0:
            new_leaves.append(node)
            return
        i = split[choice]
        left, right = b.kids(node)
        children[node] = entries(left, i) + entries(right, choice - i)

    keep(b.root)
    return total, children, new_leaves


def greedy(tree, *, max_children=None):
    """Pinto's Algorithm 2 (pushup from the root): ``children`` ``{node: [children]}``."""
    b = _Binary(tree)
    f = b.f
    children = {}

    def pushup(node):
        q = deque(b.kids(node))
        kept = []
        while q:
            child = q.popleft()
            subchilds = 0 if b.is_leaf(child) else 2
            width = len(kept) + len(q) + 1
            fits = max_children is None or width - 1 + subchilds <= max_children
            # 1 + P(child|node) * subchilds >= subchilds, with P = a(child) / a(node)
            if (subchilds > 0 and fits and b.area[child] * f(subchilds)
                    >= b.area[node] * f(subchilds - 1) * f(1 - min_gain(f))):
                q.extend(b.kids(child))
            else:
                if not b.is_leaf(child):
                    pushup(child)
                kept.append(child)
        children[node] = kept

    if not b.is_leaf(b.root):
        pushup(b.root)
    return children


def qbvh(tree):
    """Every interior node at odd depth removed: ``children`` ``{node: [children]}``."""
    b = _Binary(tree)
    children = {}

    def visit(node):
        kids = []
        for c in b.kids(node):
            kids += [c] if b.is_leaf(c) else b.kids(c)
        children[node] = kids
        for c in kids:
            if not b.is_leaf(c):
                visit(c)

    if not b.is_leaf(b.root):
        visit(b.root)
    return children


def rcost(tree, children=None, new_leaves=(), *, test_cost=None, ci=1.0):
    """``(R, leaf_cost)`` of the input (``children`` None) or of a collapse of it."""
    b = _Binary(tree)
    f = b.f
    if children is None:
        children = {n: b.kids(n) for n in b.nodes() if not b.is_leaf(n)}
    k = max([len(c) for c in children.values()] + [2])
    T = _table(test_cost, k, f)
    r = sum((b.area[n] * T[len(c)] for n, c in children.items()), f(0))
    leaves = [n for kids in children.values() for n in kids if n not in children] or [b.root]
    sizes = {n: _subtree_prims(b, n) for n in leaves}
    return r, sum((b.area[n] * f(ci) * f(sizes[n]) for n in leaves), f(0))


def _subtree_prims(b, n):
    return int(b.count[n]) if b.is_leaf(n) else sum(_subtree_prims(b, c) for c in b.kids(n))


def to_wide(tree, children, new_leaves=(), arity=None) -> WideBVH:
    """The collapse as a :class:`~jaxbvh.tree.layout.WideBVH` on the input's node ids (NumPy)."""
    b = _Binary(tree)
    t = b.t
    n = b.left.shape[0]
    arity = arity or max([len(c) for c in children.values()] + [2])
    child = np.full((n, arity), -1, np.int32)
    parent = np.full(n, -1, np.int32)
    kept = {b.root}
    for node, kids in children.items():
        child[node, :len(kids)] = kids
        parent[kids] = node
        kept.update(kids)
    kept = np.array(sorted(kept))
    mask = np.zeros(n, bool)
    mask[kept] = True
    lo = np.where(mask[:, None], t.lo, np.inf).astype(t.lo.dtype)
    hi = np.where(mask[:, None], t.hi, -np.inf).astype(t.hi.dtype)
    start = np.zeros(n, np.int32)
    count = np.zeros(n, np.int32)
    prim_index = []
    for leaf in kept:
        if leaf in children:
            continue
        prims = _leaf_prims(b, int(leaf))
        start[leaf], count[leaf] = len(prim_index), len(prims)
        prim_index += prims
    slots = np.full(t.prim_index.shape[0], -1, np.int32)
    slots[:len(prim_index)] = prim_index
    return WideBVH(child=child, parent=parent, lo=lo, hi=hi, prim_start=start, prim_count=count,
                   prim_index=slots, root=np.int32(b.root))


def _leaf_prims(b, n):
    if b.is_leaf(n):
        s = int(b.t.prim_start[n])
        return [int(p) for p in b.t.prim_index[s:s + int(b.count[n])]]
    return [p for c in b.kids(n) for p in _leaf_prims(b, c)]
