"""Host tree walks (NumPy): post-order for the twins that edit a tree in place, levels
by depth for everything that needs a node's depth or a breadth-first sweep."""

from __future__ import annotations

import numpy as np


def post_order(child, root, *, last_child_first: bool = False) -> list:
    """Node ids of the tree under ``root`` in post-order: each node's subtrees in column
    order (left, then right; ``last_child_first``: the last column's first), then the node.

    ``child`` [N, k] int: the children of each node (-1: none; none at all: a leaf).
    Iterative, so deep trees do not hit Python's recursion limit; the order is the one a
    recursive visit takes.
    """
    # each row in the order its children are pushed (popped in reverse); Python lists
    # index ~5x faster than NumPy rows
    pushed = (np.asarray(child) if last_child_first else np.asarray(child)[:, ::-1]).tolist()
    out, stack = [], [(root, False)]
    while stack:
        n, expanded = stack.pop()
        kids = [c for c in pushed[n] if c >= 0]
        if expanded or not kids:
            out.append(n)
            continue
        stack.append((n, True))
        stack.extend((c, False) for c in kids)
    return out


def levels(child, roots) -> list:
    """Node ids by depth below ``roots`` (depth 0), as int64 arrays: each level the
    children of the one before, column by column of ``child`` [N, k] int (-1: none;
    for two columns all left children, then all right ones).

    Bounded: at most ``N + 1`` levels, so links that hold a cycle end the walk there
    (a forest has at most ``N`` levels: more means a cycle).
    """
    child = np.asarray(child)
    out, frontier = [], np.asarray(roots, np.int64).ravel()
    for _ in range(child.shape[0] + 1):
        if frontier.size == 0:
            break
        out.append(frontier)
        kids = child[frontier].T.ravel()
        frontier = kids[kids >= 0].astype(np.int64)
    return out


def depths(child, roots, dtype=np.int64) -> np.ndarray:
    """Depth of every node [N] below ``roots`` (:func:`levels`); -1 for the nodes not
    reached."""
    out = np.full(np.shape(child)[0], -1, dtype)
    for d, ids in enumerate(levels(child, roots)):
        out[ids] = d
    return out
