"""NumPy twin of :mod:`jaxbvh.optimize.treelet`, written the slow, literal way (Karras & Aila 2013).

One treelet at a time: nodes in order of their height at the start of the pass (lowest
first, ids in increasing order within a height), each grown to ``n`` leaves by expanding
the largest-area treelet leaf, solved by the recursion over subsets with the same split
order and margins, and rebuilt breadth first with the same reuse of node ids.
:func:`brute_force` enumerates every binary tree over a treelet's leaves (the check the
tests make on the dynamic programme).
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import box_scale, half_area
from jaxbvh.numerics import min_gain as min_gain_of
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.walks import post_order


def splits(mask: int) -> list[int]:
    """Proper subsets of ``mask`` holding its lowest member, increasing."""
    low = mask & -mask
    return [p for p in range(1, mask) if p & mask == p and p & low]


class Tree:
    """Working copy: links, tight boxes, areas and area-weighted costs ``c(x) = S(x) C(x)``."""

    def __init__(self, tree, ct, ci):
        t = to_numpy(tree)
        self.source = t
        self.child = np.stack([t.left, t.right], axis=1).astype(np.int64)
        self.parent = np.asarray(t.parent).astype(np.int64).copy()
        self.lo = np.array(t.lo, copy=True)
        self.hi = np.array(t.hi, copy=True)
        self.root = int(t.root)
        self.count = np.asarray(t.prim_count)
        self.dtype = self.lo.dtype.type
        self.ct, self.ci = self.dtype(ct), self.dtype(ci)
        order = self.post_order()
        for n in order:
            if self.child[n, 0] >= 0:
                a, b = self.child[n]
                self.lo[n] = np.minimum(self.lo[a], self.lo[b])
                self.hi[n] = np.maximum(self.hi[a], self.hi[b])
        self.scale = box_scale(self.lo[self.root], self.hi[self.root])
        self.area = np.zeros(self.child.shape[0], self.lo.dtype)
        self.cost = np.zeros(self.child.shape[0], self.lo.dtype)
        for n in order:
            self.area[n] = self.area_of(self.lo[n], self.hi[n])
            if self.child[n, 0] < 0:
                self.cost[n] = self.ci * self.dtype(self.count[n]) * self.area[n]
            else:
                a, b = self.child[n]
                self.cost[n] = self.ct * self.area[n] + self.cost[a] + self.cost[b]

    def area_of(self, lo, hi):
        """Half surface area of the box ``lo``, ``hi`` [3], scaled by the tree's area scale,
        in its dtype."""
        return half_area(lo, hi, self.scale)

    def post_order(self):
        """Real node ids, children before parents, from the root."""
        return post_order(self.child, self.root)

    def heights(self):
        """``{node: height}``, leaves 0."""
        h = {}
        for n in self.post_order():
            h[n] = 0 if self.child[n, 0] < 0 else 1 + max(h[int(c)] for c in self.child[n])
        return h

    def sah(self):
        """The SAH of the working tree (the root's cost over its area; interior count for a
        zero-area root)."""
        s = self.area[self.root]
        if s > 0:
            return float(self.cost[self.root] / s)
        interior = sum(1 for n in self.post_order() if self.child[n, 0] >= 0)
        return float(self.ct * self.dtype(interior) + self.ci * self.dtype(self.count.sum()))

    def to_bvh(self):
        """The working tree as a :class:`~jaxbvh.tree.layout.BVH` (NumPy), on the input's
        other fields."""
        return self.source.replace(left=self.child[:, 0].astype(np.int32),
                                   right=self.child[:, 1].astype(np.int32),
                                   parent=self.parent.astype(np.int32),
                                   lo=self.lo.copy(), hi=self.hi.copy())


def form(t: Tree, root: int, n: int, min_gain: float):
    """The treelet of ``root``: ``(leaves, interior)`` lists (``interior[0] == root``);
    the leaf expanded next is the first whose area is within ``min_gain`` of the largest."""
    leaves = [int(t.child[root, 0]), int(t.child[root, 1])]
    interior = [root]
    while len(leaves) < n:
        areas = [t.area[x] for x in leaves if t.child[x, 0] >= 0]
        if not areas:
            break
        largest = max(areas)
        margin = largest - t.dtype(min_gain) * abs(largest)
        pick = next(j for j, x in enumerate(leaves) if t.child[x, 0] >= 0 and t.area[x] >= margin)
        x = leaves[pick]
        leaves[pick] = int(t.child[x, 0])
        leaves.append(int(t.child[x, 1]))
        interior.append(x)
    return leaves, interior


def solve(t: Tree, leaves, min_gain):
    """The recursion over subsets: ``(cost, split, lo, hi, area)`` dicts keyed by bitmask."""
    k = len(leaves)
    lo, hi, area, cost, split = {}, {}, {}, {}, {}
    for mask in range(1, 1 << k):
        idx = [j for j in range(k) if mask >> j & 1]
        lo[mask] = np.min(t.lo[[leaves[j] for j in idx]], axis=0)
        hi[mask] = np.max(t.hi[[leaves[j] for j in idx]], axis=0)
        area[mask] = t.area_of(lo[mask], hi[mask])
        if len(idx) == 1:
            cost[mask] = t.cost[leaves[idx[0]]]
    for size in range(2, k + 1):
        for mask in range(1, 1 << k):
            if bin(mask).count("1") != size:
                continue
            options = [(cost[p] + cost[mask ^ p], p) for p in splits(mask)]
            least = min(c for c, _ in options)
            margin = least + t.dtype(min_gain) * abs(least)
            split[mask] = next(p for c, p in options if c <= margin)
            cost[mask] = t.ct * area[mask] + least
    return cost, split, lo, hi, area


def restructure_node(t: Tree, root: int, n: int, min_gain) -> bool:
    """Solve the treelet of ``root`` and rebuild it if that pays; True if rebuilt."""
    leaves, interior = form(t, root, n, min_gain)
    a, b = (int(x) for x in t.child[root])
    current = t.ct * t.area[root] + t.cost[a] + t.cost[b]
    cost, split, lo, hi, area = solve(t, leaves, min_gain)
    full = (1 << len(leaves)) - 1
    if not cost[full] < current - t.dtype(min_gain) * abs(current):
        t.cost[root] = current
        return False
    queue = [full]  # queue[i] is the set of interior[i]
    for i, mask in enumerate(queue):
        node = interior[i]
        p = split[mask]
        for side, m in enumerate((p, mask ^ p)):
            if bin(m).count("1") == 1:
                c = leaves[m.bit_length() - 1]
            else:
                c = interior[len(queue)]
                queue.append(m)
            t.child[node, side] = c
            t.parent[c] = node
        t.lo[node], t.hi[node] = lo[mask], hi[mask]
        t.cost[node], t.area[node] = cost[mask], area[mask]
    return True


def restructure(tree, *, leaves=7, ct=1.0, ci=1.0, max_passes=8, min_gain=None):
    """Passes of treelet restructuring; returns ``(tree, info)`` with ``passes``,
    ``restructured`` (total), ``history`` (SAH after each pass) and ``sah``."""
    t = Tree(tree, ct, ci)
    min_gain = min_gain_of(t.lo.dtype) if min_gain is None else min_gain
    history, total = [], 0
    for _ in range(max_passes if leaves > 2 else 0):
        h = t.heights()
        order = sorted((n for n in h if h[n] > 0), key=lambda n: (h[n], n))
        changed = sum(restructure_node(t, n, leaves, min_gain) for n in order)
        total += changed
        history.append(t.sah())
        if changed == 0:
            break
    return t.to_bvh(), {"passes": len(history), "restructured": total, "history": history,
                        "sah": t.sah()}


def brute_force(t: Tree, leaves):
    """Least area-weighted cost of any binary tree over ``leaves`` (node ids), by
    enumerating every tree: ``(2k - 3)!!`` of them for ``k`` leaves."""
    def trees(items):
        if len(items) == 1:
            yield items[0], t.cost[items[0]], t.lo[items[0]], t.hi[items[0]]
            return
        first, rest = items[0], items[1:]
        # every split into two non-empty groups, each group once (first item on the left)
        for bits in range(0, 1 << len(rest)):
            left = [first] + [x for j, x in enumerate(rest) if bits >> j & 1]
            right = [x for j, x in enumerate(rest) if not bits >> j & 1]
            if not right:
                continue
            for lt, lc, llo, lhi in trees(left):
                for rt, rc, rlo, rhi in trees(right):
                    lo, hi = np.minimum(llo, rlo), np.maximum(lhi, rhi)
                    yield (lt, rt), t.ct * t.area_of(lo, hi) + lc + rc, lo, hi

    return min(trees(list(leaves)), key=lambda x: x[1])[:2]
