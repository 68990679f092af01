"""Valid trees made from explicit choices, and one named defect planted in a valid tree.

Both are plain NumPy and take their random choices from a :class:`Choices` object, so the
same construction serves :func:`jaxbvh.testing.strategies.trees` (every choice drawn by
hypothesis, so a failure shrinks) and :func:`random_tree` (choices from a seeded NumPy
generator, for tests that want one tree per seed).

A tree is made by splitting a permutation of the primitives recursively: a group becomes
a leaf (one to ``max_leaf`` primitives) or is cut into 2 .. ``arity`` contiguous parts.
Node ids are then shuffled (so ids say nothing about the structure and the root is any
node), the leaves' runs are placed in ``prim_index`` in a shuffled order, and the arrays
are padded with inert entries (layout: :mod:`jaxbvh.tree.layout`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxbvh.tree.interchange import from_interchange
from jaxbvh.tree.layout import BVH, WideBVH, pad_to, to_numpy

#: Each defect :func:`plant_defect` can plant, and a fragment of the line
#: :func:`jaxbvh.check` writes for it.
DEFECTS = {
    "cycle": "reached more than once",
    "shared_child": "reached more than once",
    "lost_primitive": "referenced by no leaf",
    "duplicated_primitive": "referenced more than once",
    "child_outside_box": "does not contain the box of child",
    "nan_box": "non-finite",
    "primitive_outside_leaf": "do not contain primitive",
}
#: The defects that need an interior node (a tree that is not a single leaf).
NEED_INTERIOR = ("cycle", "shared_child", "child_outside_box")


class Choices:
    """Where a tree's random choices come from; this base class draws from a NumPy
    generator (``rng``) in the order :func:`random_tree` has always used."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def permutation(self, n: int) -> list[int]:
        """A permutation of ``range(n)``."""
        return [int(i) for i in self.rng.permutation(n)]

    def make_leaf(self, size: int, max_leaf: int) -> bool:
        """Whether a group of ``size`` primitives (1 < size <= max_leaf) becomes one leaf."""
        return bool(self.rng.random() < 0.5)

    def cuts(self, size: int, arity: int) -> list[int]:
        """Increasing cut points in ``1 .. size - 1``: ``1 .. arity - 1`` of them."""
        if arity == 2:
            return [int(self.rng.integers(1, size))]
        parts = int(self.rng.integers(2, min(arity, size) + 1))
        return sorted(int(c) for c in self.rng.choice(np.arange(1, size), parts - 1, replace=False))

    def index(self, n: int) -> int:
        """An integer in ``0 .. n - 1``."""
        return int(self.rng.integers(0, n))


class Built(NamedTuple):
    """A tree made by :func:`make_tree` and the primitive boxes it was made over."""

    tree: BVH | WideBVH  # NumPy arrays; BVH for arity 2, else WideBVH
    lo: np.ndarray       # [n, 3] primitive box corners, the tree's dtype
    hi: np.ndarray       # [n, 3]


def make_tree(lo, hi, choices: Choices, *, max_leaf: int = 1, arity: int = 2, shuffle_runs: bool = False,
              nodes: int | None = None, prims: int | None = None) -> Built:
    """A valid tree over primitive boxes ``lo``, ``hi`` [n, 3] (n >= 1, any float dtype).

    Leaves hold 1 .. ``max_leaf`` primitives, interior nodes 2 .. ``arity`` children.
    Boxes are the exact unions of the primitive boxes. ``shuffle_runs``: leaves' runs in
    ``prim_index`` in a drawn order (else in the order leaves were made). ``nodes``,
    ``prims``: capacity to pad to (default: no padding). Returns :class:`Built`.
    """
    lo, hi = np.asarray(lo), np.asarray(hi)
    n = lo.shape[0]
    if n < 1 or lo.shape != (n, 3) or hi.shape != (n, 3):
        raise ValueError(f"make_tree: need boxes [n >= 1, 3], got lo {lo.shape}, hi {hi.shape}")
    if arity < 2 or max_leaf < 1:
        raise ValueError(f"make_tree: need arity >= 2 and max_leaf >= 1, got {arity}, {max_leaf}")
    child: list[list[int]] = []  # children of each node in order of making
    runs: list[list[int]] = []   # primitives of each node (leaves only)
    box_lo, box_hi = [], []

    # bounded: every call makes one node and the groups it splits into are smaller
    def make(ids: list[int]) -> int:
        i = len(child)
        child.append([]), runs.append([]), box_lo.append(None), box_hi.append(None)
        if len(ids) == 1 or (len(ids) <= max_leaf and choices.make_leaf(len(ids), max_leaf)):
            runs[i] = ids
            box_lo[i], box_hi[i] = lo[ids].min(0), hi[ids].max(0)
            return i
        bounds = [0] + choices.cuts(len(ids), arity) + [len(ids)]
        kids = [make(ids[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
        child[i] = kids
        box_lo[i] = np.min([box_lo[k] for k in kids], axis=0)
        box_hi[i] = np.max([box_hi[k] for k in kids], axis=0)
        return i

    make(choices.permutation(n))
    m = len(child)
    new = choices.permutation(m)  # new id of each node: ids say nothing about the structure
    width = 2 if arity == 2 else arity
    ids = np.full((m, width), -1, np.int32)
    start, count = np.zeros(m, np.int32), np.zeros(m, np.int32)
    leaves = [old for old in range(m) if runs[old]]
    order = [leaves[j] for j in choices.permutation(len(leaves))] if shuffle_runs else leaves
    prim_index, at = [], 0
    for old in order:
        start[new[old]], count[new[old]] = at, len(runs[old])
        prim_index += runs[old]
        at += len(runs[old])
    for old in range(m):
        ids[new[old], :len(child[old])] = [new[c] for c in child[old]]
    inv = np.argsort(new)
    arrays = dict(child=ids, prim_start=start, prim_count=count, prim_index=np.array(prim_index, np.int32),
                  lo=np.array(box_lo, lo.dtype)[inv], hi=np.array(box_hi, lo.dtype)[inv], root=np.int32(new[0]))
    tree = from_interchange(arrays, pad=False)
    if nodes is not None or prims is not None:
        tree = pad_to(tree, nodes or m, prims or n)
    return Built(tree, lo, hi)


def random_tree(seed: int, n: int, max_leaf: int = 1, kind: str = "random", *, dtype=np.float32,
                nodes: int = 128, prims: int = 64):
    """Binary tree over ``n`` random boxes (a poor tree, with much to gain), from a seed.

    ``kind``: "random" boxes; "grid" (snapped to a coarse grid: duplicates, flat boxes,
    many exact ties, exact arithmetic); "point" (every box one point: all areas zero).
    Padded to ``nodes`` / ``prims`` (one capacity: one compiled program for many trees).
    Returns ``(tree, prim_lo, prim_hi)``. Prefer :func:`jaxbvh.testing.strategies.trees`
    in a hypothesis test: its failures shrink.
    """
    rng = np.random.default_rng(seed)
    if kind == "grid":
        lo = rng.integers(0, 3, (n, 3)).astype(dtype)
        hi = lo + rng.integers(0, 2, (n, 3)).astype(dtype)
    elif kind == "point":
        lo = hi = np.broadcast_to(rng.normal(size=3), (n, 3)).astype(dtype)
    elif kind == "random":
        lo = rng.uniform(-5, 5, (n, 3)).astype(dtype)
        hi = lo + rng.exponential(1.0, (n, 3)).astype(dtype)
    else:
        raise ValueError(f"kind must be random, grid or point, got {kind!r}")
    built = make_tree(lo, hi, Choices(rng), max_leaf=max_leaf, nodes=nodes, prims=prims)
    return built.tree, built.lo, built.hi


def renumber(tree, choices: Choices):
    """The same tree (NumPy) with node ids permuted (the root moves with them) and the
    leaves' runs moved to new places in ``prim_index``: what a reader of another library's
    trees must accept. Padding is dropped; the capacity stays the same."""
    t = to_numpy(tree)
    child = np.asarray(t.child)
    count, start, index = np.asarray(t.prim_count), np.asarray(t.prim_start), np.asarray(t.prim_index)
    nodes = child.shape[0]
    new = np.array(choices.permutation(nodes))  # old id -> new id
    inv = np.argsort(new)
    moved = child[inv]
    leaves = np.flatnonzero(count > 0)
    runs, at = np.zeros(nodes, np.int32), 0
    prim_index = np.full(index.shape[0], -1, np.int32)
    for j in choices.permutation(len(leaves)):
        leaf = leaves[j]
        prim_index[at:at + count[leaf]] = index[start[leaf]:start[leaf] + count[leaf]]
        runs[leaf], at = at, at + count[leaf]
    arrays = dict(child=np.where(moved >= 0, new[np.maximum(moved, 0)], -1).astype(np.int32),
                  prim_start=runs[inv], prim_count=count[inv].astype(np.int32), prim_index=prim_index,
                  lo=np.asarray(t.lo)[inv], hi=np.asarray(t.hi)[inv], root=np.int32(new[int(t.root)]))
    return from_interchange(arrays, pad=False)


# ----------------------------------------------------------------------------------
# Defects
# ----------------------------------------------------------------------------------

class _Links(NamedTuple):
    """A tree's structure as Python lists (real nodes only)."""

    child: np.ndarray  # int [N, k] (a writable copy)
    parent: dict       # node -> parent (-1 for the root)
    interior: list     # interior node ids, increasing
    leaves: list       # leaf node ids, increasing


def _links(t) -> _Links:
    child = np.array(t.child)
    parent, interior, leaves = {int(t.root): -1}, [], []
    stack = [int(t.root)]
    for _ in range(child.shape[0]):  # bounded: a valid tree has at most N nodes
        if not stack:
            break
        node = stack.pop()
        kids = [int(c) for c in child[node] if c >= 0]
        (interior if kids else leaves).append(node)
        for c in kids:
            parent[c] = node
            stack.append(c)
    return _Links(child, parent, sorted(interior), sorted(leaves))


def _ancestors(links: _Links, node: int) -> list[int]:
    """``node`` and its ancestors up to the root."""
    out = [node]
    while links.parent[out[-1]] >= 0:
        out.append(links.parent[out[-1]])
    return out


def _subtree(links: _Links, node: int) -> set:
    """``node`` and every node under it."""
    out, stack = set(), [node]
    for _ in range(links.child.shape[0]):  # bounded: a valid tree has at most N nodes
        if not stack:
            break
        x = stack.pop()
        out.add(x)
        stack += [int(c) for c in links.child[x] if c >= 0]
    return out


def _with_child(t, child):
    if isinstance(t, BVH):
        return t.replace(left=child[:, 0].copy(), right=child[:, 1].copy())
    return t.replace(child=child)


def plant_defect(tree, lo, hi, defect: str, choices: Choices):
    """``(tree, lo, hi)`` with one ``defect`` of :data:`DEFECTS` planted in a valid tree.

    ``tree`` must be valid over primitive boxes ``lo``, ``hi`` [n, 3] and hold at least
    two primitives. Only the arrays the defect needs change (``parent`` stays as it was,
    so a changed child link also leaves ``parent`` inconsistent, as a buggy builder
    would). The result breaks the invariant :data:`DEFECTS` names.
    """
    t = to_numpy(tree)
    t = t.replace(**{f: np.array(getattr(t, f)) for f in ("lo", "hi", "parent", "prim_start", "prim_count",
                                                        "prim_index")})
    lo, hi = np.array(lo), np.array(hi)
    links = _links(t)
    if defect not in DEFECTS:
        raise ValueError(f"defect must be one of {', '.join(DEFECTS)}, got {defect!r}")
    if not links.interior and t.prim_count[int(t.root)] < 2:
        raise ValueError("plant_defect: the tree needs at least two primitives")
    if defect in NEED_INTERIOR and not links.interior:
        raise ValueError(f"plant_defect: a {defect} needs an interior node; the tree is one leaf")
    if defect in ("cycle", "shared_child"):
        node = links.interior[choices.index(len(links.interior))]
        slots = np.flatnonzero(links.child[node] >= 0)
        slot = int(slots[choices.index(len(slots))])
        above = _ancestors(links, node)
        if defect == "cycle":
            target = above[choices.index(len(above))]  # the node itself or an ancestor
        else:
            # a node that stays reachable another way (not above, not under the replaced
            # child): the walk reaches it twice
            under = _subtree(links, int(links.child[node, slot]))
            others = [x for x in links.interior + links.leaves if x not in above and x not in under]
            target = others[choices.index(len(others))]
        links.child[node, slot] = target
        return _with_child(t, links.child), lo, hi
    if defect == "lost_primitive":
        many = [x for x in links.leaves if t.prim_count[x] > 1]
        if many:
            t.prim_count[many[choices.index(len(many))]] -= 1  # its last primitive is lost
            return t, lo, hi
        # every leaf holds one primitive: splice a leaf and its parent out, the sibling
        # takes the parent's place (boxes above still contain it)
        leaf = links.leaves[choices.index(len(links.leaves))]
        up = links.parent[leaf]
        kids = [int(c) for c in links.child[up] if c >= 0 and c != leaf]
        if len(kids) == 1:
            keep, grand = kids[0], links.parent[up]
            gone = [leaf, up]
            if grand < 0:
                t = t.replace(root=np.int32(keep))
            else:
                links.child[grand][links.child[grand] == up] = keep
            t.parent[keep] = grand
        else:  # a wide node keeps its other children
            row = [c for c in links.child[up] if c >= 0 and c != leaf]
            links.child[up] = row + [-1] * (links.child.shape[1] - len(row))
            gone = [leaf]
        for x in gone:  # now padding: inert and unlinked
            links.child[x] = -1
            t.parent[x], t.prim_count[x], t.prim_start[x] = -1, 0, 0
            t.lo[x], t.hi[x] = np.inf, -np.inf
        return _with_child(t, links.child), lo, hi
    if defect == "duplicated_primitive":
        # a leaf's run moves to the end of prim_index with its first primitive again
        leaf = links.leaves[choices.index(len(links.leaves))]
        s, c = int(t.prim_start[leaf]), int(t.prim_count[leaf])
        run = t.prim_index[s:s + c]
        t = t.replace(prim_index=np.concatenate([t.prim_index, run, run[:1]]).astype(np.int32))
        t.prim_start[leaf], t.prim_count[leaf] = t.prim_index.shape[0] - c - 1, c + 1
        return t, lo, hi
    axis = choices.index(3)
    if defect == "child_outside_box":
        # a child grows one step past its parent's box (its own children stay inside it)
        node = [x for x in links.interior + links.leaves if links.parent[x] >= 0]
        node = node[choices.index(len(node))]
        t.hi[node, axis] = np.nextafter(t.hi[links.parent[node], axis], t.hi.dtype.type(np.inf))
        return t, lo, hi
    if defect == "nan_box":
        node = (links.interior + links.leaves)[choices.index(len(links.interior) + len(links.leaves))]
        (t.lo if choices.index(2) else t.hi)[node, axis] = np.nan
        return t, lo, hi
    # primitive_outside_leaf: a primitive's box reaches one step past its leaf's box
    leaf = links.leaves[choices.index(len(links.leaves))]
    s = int(t.prim_start[leaf])
    prim = int(t.prim_index[s + choices.index(int(t.prim_count[leaf]))])
    hi = hi.copy()
    hi[prim, axis] = np.nextafter(t.hi[leaf, axis], t.hi.dtype.type(np.inf))
    return t, lo, hi
