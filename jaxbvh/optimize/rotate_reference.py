"""NumPy twin of :mod:`jaxbvh.optimize.rotate`, written the slow, literal way (Kensler 2008).

One node at a time, in post-order (children before parent), exactly as the paper
describes: at each interior node recompute its cost, try the six moves, apply the chosen
one. Same move order, same slot swaps, same cost formula and the same relative margin
``min_gain`` as the JAX version, so both give the same tree pass by pass; annealing
takes its Exp(1) draws ``-log(xi)`` from :func:`jaxbvh.draws.annealing_draws`, indexed
``draws[node, move]``.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import box_scale, half_area
from jaxbvh.numerics import min_gain as min_gain_of
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.walks import post_order


class _Tree:
    """Mutable working copy: child [N, 2], parent, lo, hi, cost."""

    def __init__(self, tree, ct, ci):
        t = to_numpy(tree)
        self.source = t
        self.child = np.stack([t.left, t.right], axis=1).astype(np.int64)
        self.parent = np.asarray(t.parent).astype(np.int64).copy()
        self.lo = np.array(t.lo, copy=True)
        self.hi = np.array(t.hi, copy=True)
        self.root = int(t.root)
        self.dtype = self.lo.dtype.type
        self.ct = self.dtype(ct)
        self.ci = self.dtype(ci)
        self.scale = box_scale(self.lo[self.root], self.hi[self.root])
        self.count = np.asarray(t.prim_count)
        self.cost = np.zeros(self.child.shape[0], self.lo.dtype)
        for n in self.post_order():
            if self.child[n, 0] < 0:
                self.cost[n] = self.ci * self.dtype(self.count[n])
            else:
                a, b = self.child[n]
                self.cost[n] = self.node_cost(self.area_of(self.lo[n], self.hi[n]),
                                              self.area(a), self.cost[a], self.area(b), self.cost[b])

    def area_of(self, lo, hi):
        return half_area(lo, hi, self.scale)

    def area(self, n):
        return self.area_of(self.lo[n], self.hi[n])

    def node_cost(self, parent_area, area_a, cost_a, area_b, cost_b):
        if parent_area > 0:
            return self.ct + (area_a * cost_a + area_b * cost_b) / parent_area
        return self.ct + (cost_a + cost_b)

    def post_order(self):
        """Node ids in post-order, children first (computed before the pass starts).

        A move at a node only rearranges its own, already visited, subtree, so the order
        computed up front is the order a recursive visit would take.
        """
        return post_order(self.child, self.root)

    def to_bvh(self):
        return self.source.replace(left=self.child[:, 0].astype(np.int32),
                                   right=self.child[:, 1].astype(np.int32),
                                   parent=self.parent.astype(np.int32),
                                   lo=self.lo.copy(), hi=self.hi.copy())


def _candidates(t: _Tree, n):
    """For each legal move: (move, slot a, slot b, cost of n after, changed nodes)."""
    L, R = (int(x) for x in t.child[n])
    LL, LR = (int(x) for x in t.child[L])
    RL, RR = (int(x) for x in t.child[R])
    n_area = t.area(n)

    def part(x):
        return t.lo[x], t.hi[x], t.area(x), t.cost[x]

    def combine(a, b):
        lo = np.minimum(a[0], b[0])
        hi = np.maximum(a[1], b[1])
        area = t.area_of(lo, hi)
        return lo, hi, area, t.node_cost(area, a[2], a[3], b[2], b[3])

    def cost_n(a, b):
        return t.node_cost(n_area, a[2], a[3], b[2], b[3])

    out = []
    if RL >= 0:
        new_r = combine(part(L), part(RR))
        out.append((0, (n, 0), (R, 0), cost_n(part(RL), new_r), {R: new_r}))
        new_r = combine(part(RL), part(L))
        out.append((1, (n, 0), (R, 1), cost_n(part(RR), new_r), {R: new_r}))
    if LL >= 0:
        new_l = combine(part(R), part(LR))
        out.append((2, (n, 1), (L, 0), cost_n(new_l, part(LL)), {L: new_l}))
        new_l = combine(part(LL), part(R))
        out.append((3, (n, 1), (L, 1), cost_n(new_l, part(LR)), {L: new_l}))
    if LL >= 0 and RL >= 0:
        new_l, new_r = combine(part(RL), part(LR)), combine(part(LL), part(RR))
        out.append((4, (L, 0), (R, 0), cost_n(new_l, new_r), {L: new_l, R: new_r}))
        new_l, new_r = combine(part(RR), part(LR)), combine(part(RL), part(LL))
        out.append((5, (L, 0), (R, 1), cost_n(new_l, new_r), {L: new_l, R: new_r}))
    return out


def _visit(t: _Tree, n, min_gain, temperature=None, draws=None):
    """Recompute ``C(n)``, choose and apply a move; returns True if one was applied."""
    L, R = (int(x) for x in t.child[n])
    current = t.node_cost(t.area(n), t.area(L), t.cost[L], t.area(R), t.cost[R])
    tol = t.dtype(min_gain) * abs(current)
    candidates = _candidates(t, n)
    chosen = None
    if temperature is None:
        # hill climbing: least cost; among costs within tol of it, the first in move order
        improving = [c for c in candidates if c[3] < current - tol]
        if improving:
            least = min(c[3] for c in improving)
            chosen = next(c for c in improving if c[3] <= least + tol)
    else:
        best = current
        for c in candidates:
            delta = c[3] - best
            accept = False
            if temperature > 0:
                # xi < exp(-delta / T) as delta < T E, E = -log(xi) the shared Exp(1) draw
                reach = temperature * draws[n, c[0]]
                excess = t.dtype(0) if delta <= tol else delta  # ties count as 0
                accept = excess < reach
            if delta < -tol or accept:
                best, chosen = c[3], c
    if chosen is None:
        t.cost[n] = current
        return False
    _, (na, sa), (nb, sb), cost, changed = chosen
    a, b = t.child[na, sa], t.child[nb, sb]
    t.child[na, sa], t.child[nb, sb] = b, a
    t.parent[b], t.parent[a] = na, nb
    for node, (lo, hi, _, c) in changed.items():
        t.lo[node], t.hi[node], t.cost[node] = lo, hi, c
    t.cost[n] = cost
    return True


def hill_climb(tree, *, ct=1.0, ci=1.0, max_passes=1000, min_gain=None, split_axes=False):
    """Sequential hill climbing; returns ``(tree, info)`` with ``info`` a dict of
    ``passes``, ``moves`` (total), ``history`` (SAH after each pass), ``sah``."""
    t = _Tree(tree, ct, ci)
    min_gain = min_gain_of(t.lo.dtype) if min_gain is None else min_gain
    history, total, passes = [], 0, 0
    while passes < max_passes:
        moves = sum(_visit(t, n, min_gain) for n in t.post_order() if t.child[n, 0] >= 0)
        passes += 1
        total += moves
        history.append(float(t.cost[t.root]))
        if moves == 0:
            break
    out = t.to_bvh()
    if split_axes:
        out = assign_split_axes(out)
    return out, {"passes": passes, "moves": total, "history": history,
                 "sah": float(t.cost[t.root])}


def anneal(tree, draws, schedule, steps, *, ct=1.0, ci=1.0, keep_best=True, max_quench=1000,
           min_gain=None, split_axes=False):
    """Sequential simulated annealing.

    ``draws(i)``: the [N, 6] Exp(1) draws of pass ``i`` (e.g. ``lambda i:
    np.asarray(jaxbvh.draws.annealing_draws(key, i, N))``); ``schedule(i)``: the
    temperature of pass ``i < steps``; afterwards ``T = 0`` until a pass makes no move.
    Returns ``(tree, info)`` like :func:`hill_climb`.
    """
    t = _Tree(tree, ct, ci)
    min_gain = min_gain_of(t.lo.dtype) if min_gain is None else min_gain
    history, total, i, moves = [], 0, 0, 0
    best_cost, best = t.cost[t.root], t.to_bvh()
    while i < steps + max_quench and (i == 0 or i < steps or moves > 0):
        temperature = t.dtype(max(float(schedule(i)), 0.0)) if i < steps else t.dtype(0)
        u = np.asarray(draws(i)) if temperature > 0 else None
        moves = sum(_visit(t, n, min_gain, temperature, u)
                    for n in t.post_order() if t.child[n, 0] >= 0)
        total += moves
        i += 1
        history.append(float(t.cost[t.root]))
        if keep_best and t.cost[t.root] < best_cost:
            best_cost, best = t.cost[t.root], t.to_bvh()
    if keep_best:
        out, sah = best, float(best_cost)
    else:
        out, sah = t.to_bvh(), float(t.cost[t.root])
    if split_axes:
        out = assign_split_axes(out)
    return out, {"passes": i, "moves": total, "history": history, "sah": sah}


def assign_split_axes(tree):
    """Kensler's final pass, one node at a time (rule: :func:`jaxbvh.tree.split_axes.split_axis_rule`)."""
    t = to_numpy(tree)
    left, right, axis = t.left.copy(), t.right.copy(), np.full_like(t.axis, -1)
    for n in range(left.shape[0]):
        a, b = int(left[n]), int(right[n])
        if a < 0:
            continue
        gaps = [max(t.lo[b, k] - t.hi[a, k], t.lo[a, k] - t.hi[b, k]) for k in range(3)]
        k = int(np.argmax(gaps))
        axis[n] = k
        if t.lo[a, k] + t.hi[a, k] > t.lo[b, k] + t.hi[b, k]:
            left[n], right[n] = b, a
    return t.replace(left=left, right=right, axis=axis)
