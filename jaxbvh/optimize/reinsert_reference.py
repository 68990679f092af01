"""NumPy twin of :mod:`jaxbvh.optimize.reinsert`, written the slow, literal way.

One candidate at a time: the same candidates (nodes of large parent area, by octaves),
the same bounded search (Meister & Bittner's traversal from the candidate's sibling up to
the root, the same pruning bound, the same step count and the same margins), the same
choice of moves (the first ``move_width`` found in id order, ranked by gain with ties
by id, then taken greedily in rank order when they lock no node a better taken move
locks) and then the taken moves applied one after the other in rank order, each
followed by a refit of the two paths it changed up to the root (the JAX version refits
the same nodes all at once, stopping below the common ancestor, whose box cannot
change). Layout, cost and rules: :mod:`jaxbvh.optimize.reinsert`.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import box_scale, half_area
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.optimize.reinsert_rules import (
    ALL_OCTAVES,
    DEFAULT_ESCALATE,
    DEFAULT_FIRST_FRACTION,
    escalate_for,
    first_octaves,
    move_width,
    widening_stop,
)
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.walks import post_order


class Tree:
    """Mutable working copy: ``child`` [N, 2], ``parent``, ``lo``, ``hi``, ``root``.

    Interior boxes are refitted to the union of their children on creation.
    """

    def __init__(self, tree):
        t = to_numpy(tree)
        self.source = t
        self.child = np.stack([t.left, t.right], axis=1).astype(np.int64)
        self.parent = np.asarray(t.parent).astype(np.int64).copy()
        self.lo = np.array(t.lo, copy=True)
        self.hi = np.array(t.hi, copy=True)
        self.root = int(t.root)
        self.count = np.asarray(t.prim_count)
        self.dtype = self.lo.dtype.type
        for n in self.post_order():
            self.refit(n)
        self.scale = box_scale(self.lo[self.root], self.hi[self.root])

    # -- boxes and areas -------------------------------------------------------------

    def area_of(self, lo, hi):
        """Half surface area of the box ``lo``, ``hi`` [3], scaled by the tree's area scale,
        in its dtype."""
        return half_area(lo, hi, self.scale)

    def area(self, n):
        """Half area of node ``n``'s box (:meth:`area_of`)."""
        return self.area_of(self.lo[n], self.hi[n])

    def merged_area(self, n, lo, hi):
        """Half area of the union of node ``n``'s box and the box ``lo``, ``hi``."""
        return self.area_of(np.minimum(self.lo[n], lo), np.maximum(self.hi[n], hi))

    def refit(self, n):
        """Node ``n``'s box made the union of its children's (a leaf keeps its box)."""
        if self.child[n, 0] >= 0:
            a, b = self.child[n]
            self.lo[n] = np.minimum(self.lo[a], self.lo[b])
            self.hi[n] = np.maximum(self.hi[a], self.hi[b])

    # -- structure ---------------------------------------------------------------------

    def is_leaf(self, n):
        """Whether node ``n`` has no children."""
        return self.child[n, 0] < 0

    def sibling(self, n):
        """The other child of ``n``'s parent."""
        p = self.parent[n]
        return int(self.child[p, 1] if self.child[p, 0] == n else self.child[p, 0])

    def post_order(self):
        """Real node ids, children before parents, from the root."""
        return post_order(self.child, self.root)

    def path_up(self, n, top):
        """``n``, its parent, ... up to ``top`` (inclusive)."""
        out = [int(n)]
        while out[-1] != top:
            out.append(int(self.parent[out[-1]]))
        return out

    def sah(self, ct, ci):
        """SAH by the recursive definition (:mod:`jaxbvh.tree.cost`), in the tree's dtype."""
        cost = {}
        ct, ci = self.dtype(ct), self.dtype(ci)
        for n in self.post_order():
            if self.is_leaf(n):
                cost[n] = ci * self.dtype(self.count[n])
                continue
            a, b = (int(x) for x in self.child[n])
            s = self.area(n)
            if s > 0:
                cost[n] = ct + (self.area(a) * cost[a] + self.area(b) * cost[b]) / s
            else:
                cost[n] = ct + cost[a] + cost[b]
        return float(cost[self.root])

    def to_bvh(self):
        """The working tree as a :class:`~jaxbvh.tree.layout.BVH` (NumPy), on the input's
        other fields."""
        return self.source.replace(left=self.child[:, 0].astype(np.int32),
                                   right=self.child[:, 1].astype(np.int32),
                                   parent=self.parent.astype(np.int32),
                                   lo=self.lo.copy(), hi=self.hi.copy(), root=np.int32(self.root))


# ----------------------------------------------------------------------------------
# The search
# ----------------------------------------------------------------------------------


def search(t: Tree, a: int, max_steps: int, min_gain: float):
    """Best new place for node ``a`` (not the root): ``(gain, out, lca, steps)``.

    ``out`` is the node ``a`` becomes the sibling of (-1 if no place gains more than the
    margin), ``lca`` the highest node of the search when ``out`` was found (the lowest
    common ancestor of ``a``'s parent and ``out``), ``gain`` the drop in the sum of
    interior areas (scaled half-areas), ``steps`` the steps taken (at most ``max_steps``).
    """
    dt = t.dtype
    p = int(t.parent[a])
    alo, ahi = t.lo[a], t.hi[a]
    area_p = t.area(p)
    base = area_p - t.area(a)
    out, high, down = t.sibling(a), p, True
    red = dt(0)
    hlo = np.full(3, np.inf, t.lo.dtype)
    hhi = np.full(3, -np.inf, t.lo.dtype)
    best, best_out, best_lca = dt(0), -1, -1
    steps = 0
    while steps < max_steps:
        steps += 1
        tol = dt(min_gain) * t.area(high)
        merged = t.merged_area(out, alo, ahi)
        if down:
            gain = area_p - merged + red
            if gain > best + tol:
                best, best_out, best_lca = gain, out, high
            red = red + (t.area(out) - merged)
            if t.is_leaf(out) or red + base <= best + tol:
                down = False
            else:
                out = int(t.child[out, 0])
            continue
        red = red - (t.area(out) - merged)
        up = int(t.parent[out])
        if up != high:
            if t.child[up, 0] == out:
                out, down = int(t.child[up, 1]), True
            else:
                out = up
            continue
        # back at the highest node: its box without a is the union seen so far
        hlo = np.minimum(hlo, t.lo[out])
        hhi = np.maximum(hhi, t.hi[out])
        if high != p:
            shrunk = t.area_of(hlo, hhi)
            gain = area_p + red + (t.area(high) - shrunk) - t.area_of(np.minimum(alo, hlo),
                                                                     np.maximum(ahi, hhi))
            if gain > best + tol:
                best, best_out, best_lca = gain, high, high
            red = red + (t.area(high) - shrunk)
        top = int(t.parent[high])
        if top < 0:
            break
        out, high, down = t.sibling(high), top, True
    return best, best_out, best_lca, steps


# ----------------------------------------------------------------------------------
# Conflicts and moves
# ----------------------------------------------------------------------------------


def lock_set(t: Tree, a: int, out: int, lca: int) -> set[int]:
    """Nodes a move locks: ``a``, its sibling, both paths up to ``lca``, and the parents
    of ``a``'s parent and of ``out`` (whose child links change)."""
    p = int(t.parent[a])
    nodes = {a, t.sibling(a), int(t.parent[p]), int(t.parent[out])}
    nodes.update(t.path_up(p, lca))
    nodes.update(t.path_up(out, lca))
    nodes.discard(-1)
    return nodes


def rank_key(gain) -> int:
    """The gain's exponent and first 7 mantissa bits as an integer (about 1%): closer
    gains tie (:func:`jaxbvh.optimize.reinsert.rank_key`)."""
    gain = np.asarray(gain)
    f32 = gain.dtype == np.float32
    return int(gain.view(np.int32 if f32 else np.int64)) >> ((23 if f32 else 52) - 7)


def rank_order(candidates):
    """Moves ``(gain, a, out, lca)`` sorted best first: gain descending (:func:`rank_key`),
    ties by id ``a``."""
    return sorted(candidates, key=lambda m: (-rank_key(m[0]), m[1]))


def select(t: Tree, candidates):
    """The greedy choice: moves in rank order, each taken when it locks no node that a
    move taken before it locks. Returns the taken moves, best first."""
    held, taken = set(), []
    for move in rank_order(candidates):
        nodes = lock_set(t, move[1], move[2], move[3])
        if held.isdisjoint(nodes):
            held |= nodes
            taken.append(move)
    return taken


def apply_move(t: Tree, a: int, out: int):
    """Reinsert ``a`` (with its subtree) as the sibling of ``out``, reusing ``a``'s parent.

    The parent ``p`` leaves its place to ``a``'s sibling and becomes the parent of ``a``
    and ``out`` where ``out`` was (``a`` keeps its side). Then the boxes on both changed
    paths are refitted, bottom-up, to the root.
    """
    p = int(t.parent[a])
    s = t.sibling(a)
    g = int(t.parent[p])
    side_s = 1 if t.child[p, 0] == a else 0
    if g >= 0:
        t.child[g, 0 if t.child[g, 0] == p else 1] = s
    else:
        t.root = s
    t.parent[s] = g
    up = int(t.parent[out])
    if up >= 0:
        t.child[up, 0 if t.child[up, 0] == out else 1] = p
    else:
        t.root = p
    t.parent[p] = up
    t.child[p, side_s] = out
    t.parent[out] = p
    for start in (p, g):
        n = start
        while n >= 0:
            t.refit(n)
            n = int(t.parent[n])


# ----------------------------------------------------------------------------------
# Iterations
# ----------------------------------------------------------------------------------


def candidates(t: Tree, octaves: int, settled=frozenset()):
    """Real nodes but the root whose parent's area is at least ``2^-octaves`` of the
    root's (every one from ``ALL_OCTAVES`` on), in id order, less those in ``settled``."""
    threshold = np.ldexp(t.area(t.root), -min(octaves, ALL_OCTAVES))
    return [a for a in range(t.child.shape[0])
            if a != t.root and t.parent[a] >= 0 and a not in settled
            and (octaves >= ALL_OCTAVES or t.area(int(t.parent[a])) >= threshold)]


def found_moves(t: Tree, nodes, max_steps: int, min_gain: float, width: int):
    """Search ``nodes``; the moves found ``[(gain, a, out, lca), ...]``, the first
    ``width`` in id order, and the set of nodes that found none."""
    found, idle = [], set()
    for a in nodes:
        gain, out, lca, _ = search(t, a, max_steps, min_gain)
        if out >= 0:
            found.append((gain, a, out, lca))
        else:
            idle.add(a)
    return sorted(found, key=lambda m: m[1])[:width], idle


def iteration(t: Tree, octaves: int, max_steps: int, min_gain: float, width: int, settled=frozenset()):
    """One parallel iteration done sequentially: search, select, apply in rank order.

    ``settled``: nodes not searched (their last search stands). Returns the applied
    moves ``[(gain, a, out, lca), ...]`` best first, the number of candidates searched
    and the settled nodes after: those and the nodes searched without a move, less the
    nodes the taken moves lock (before the moves) and their children (after).
    """
    nodes = candidates(t, octaves, settled)
    found, idle = found_moves(t, nodes, max_steps, min_gain, width)
    taken = select(t, found)
    locked = set()
    for _, a, out, lca in taken:
        locked |= lock_set(t, a, out, lca)
    for _, a, out, _ in taken:
        apply_move(t, a, out)
    touched = locked | {n for n in range(t.child.shape[0]) if t.parent[n] in locked}
    return taken, len(nodes), (set(settled) | idle) - touched


def reinsert(tree, *, ct=1.0, ci=1.0, max_iterations=1000, max_steps=1024,
             first_fraction=DEFAULT_FIRST_FRACTION, escalate=DEFAULT_ESCALATE, min_gain=None, settle=False,
             widen_until=None):
    """Parallel reinsertion, one move at a time; returns ``(tree, info)``.

    The schedule and defaults of :func:`jaxbvh.optimize.reinsert.reinsert`: candidates from the octaves
    :func:`jaxbvh.optimize.reinsert.first_octaves` gives, one more octave after an iteration that
    lowers the SAH by at most ``escalate`` (relative; None: by the node count,
    :func:`jaxbvh.optimize.reinsert_rules.escalate_for`), every node after one that takes no
    move, until an iteration over all nodes takes none (or ``max_iterations``); with
    ``settle``, the settled nodes are skipped (:func:`iteration`) until an iteration over
    every octave takes no move. With ``widen_until``, the run ends after an iteration that
    would widen the candidates when it searched at least that share of the nodes.
    ``info``: ``iterations``, ``moves`` (total), ``history`` (SAH after each iteration),
    ``taken`` (the moves of each iteration, best first), ``sah``.
    """
    t = Tree(tree)
    min_gain = default_min_gain(t.lo.dtype) if min_gain is None else min_gain
    width = move_width(t.child.shape[0])
    area = np.array([t.area(n) for n in range(t.child.shape[0])], t.lo.dtype)
    octaves = first_octaves(area, t.parent, t.root, first_fraction)
    nodes = sum(1 for a in range(t.child.shape[0]) if t.parent[a] >= 0)
    escalate = escalate_for(nodes, escalate)
    stop = widening_stop(widen_until, nodes)
    history, taken_all, settled = [], [], set()
    start = t.sah(ct, ci)
    for _ in range(max_iterations if ct > 0 else 0):
        taken, count, settled = iteration(t, octaves, max_steps, min_gain, width, settled if settle else set())
        taken_all.append(taken)
        history.append(t.sah(ct, ci))
        before = history[-2] if len(history) > 1 else start
        if not taken and count == nodes:
            break
        if not taken and octaves >= ALL_OCTAVES:
            settled = set()  # no move left among the unsettled nodes: search every node again
        if count < nodes and (not taken or before - history[-1] <= escalate * before):
            wider = octaves + 1 if taken and octaves < 64 else ALL_OCTAVES
            if wider != octaves and count >= stop:
                break  # widen_until: the run ends here instead of widening
            octaves = wider
    return t.to_bvh(), {"iterations": len(taken_all), "moves": sum(map(len, taken_all)),
                        "history": history, "taken": taken_all, "sah": t.sah(ct, ci)}


def apply_batch(tree, moves):
    """``tree`` (refitted) with the moves ``[(a, out), ...]`` applied one after the other.

    The check the tests make: the JAX iteration's batch, applied here in rank order,
    gives the tree the JAX iteration returns.
    """
    t = Tree(tree)
    for a, out in moves:
        apply_move(t, int(a), int(out))
    return t.to_bvh()
