"""Small helpers for comparing trees in tests."""

from __future__ import annotations

import sys

import numpy as np

import jaxbvh

# canonical() recurses once per level; set at import, not inside a test, so hypothesis
# does not warn that the limit changed under it
sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))


def canonical(tree, with_axis: bool = True):
    """Tree as nested tuples from the root: node ids and prim order inside leaves ignored.

    Interior: ``(axis, left, right, lo, hi)``; leaf: ``("leaf", sorted prims, lo, hi)``.
    """
    t = jaxbvh.to_numpy(tree)

    def rec(n):
        box = (tuple(np.asarray(t.lo[n]).tolist()), tuple(np.asarray(t.hi[n]).tolist()))
        if t.prim_count[n] > 0:
            s, c = int(t.prim_start[n]), int(t.prim_count[n])
            return ("leaf", tuple(sorted(t.prim_index[s:s + c].tolist())), box)
        return (int(t.axis[n]) if with_axis else None, rec(int(t.left[n])), rec(int(t.right[n])), box)

    return rec(int(t.root))


def random_tree(seed: int, n: int, max_leaf: int = 1, kind: str = "random", *, dtype=np.float32,
                nodes: int = 128, prims: int = 64):
    """Binary tree over ``n`` random boxes by recursive random splits of a permutation (a
    poor tree, with much to gain), node ids shuffled so they say nothing about the
    structure, root not 0; padded to ``nodes`` / ``prims`` (one capacity: one compile).

    ``kind``: "random" boxes; "grid" (snapped to a coarse grid: duplicates, flat boxes,
    many exact ties, exact arithmetic); "point" (every box one point: all areas zero).
    Leaves hold up to ``max_leaf`` primitives. Returns ``(tree, prim_lo, prim_hi)``.
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
    child, start, count, box_lo, box_hi, prim_index = [], [], [], [], [], []

    def make(ids):
        i = len(child)
        child.append([-1, -1]), start.append(0), count.append(0), box_lo.append(None), box_hi.append(None)
        if len(ids) == 1 or (len(ids) <= max_leaf and rng.random() < 0.5):
            start[i], count[i] = len(prim_index), len(ids)
            prim_index.extend(ids)
            box_lo[i], box_hi[i] = lo[ids].min(0), hi[ids].max(0)
        else:
            k = int(rng.integers(1, len(ids)))
            a, b = make(ids[:k]), make(ids[k:])
            child[i] = [a, b]
            box_lo[i], box_hi[i] = np.minimum(box_lo[a], box_lo[b]), np.maximum(box_hi[a], box_hi[b])
        return i

    make([int(p) for p in rng.permutation(n)])
    m = len(child)
    new = rng.permutation(m)
    old_child = np.array(child)
    ids = np.full((m, 2), -1, np.int32)
    for old in range(m):
        for side in range(2):
            c = old_child[old, side]
            ids[new[old], side] = new[c] if c >= 0 else -1
    inv = np.argsort(new)
    arrays = dict(child=ids, prim_start=np.array(start, np.int32)[inv],
                  prim_count=np.array(count, np.int32)[inv], prim_index=np.array(prim_index, np.int32),
                  lo=np.array(box_lo, dtype)[inv], hi=np.array(box_hi, dtype)[inv],
                  root=np.int32(new[0]))
    tree = jaxbvh.from_interchange(arrays, pad=False)
    return jaxbvh.tree.pad_to(tree, nodes, prims), lo, hi
