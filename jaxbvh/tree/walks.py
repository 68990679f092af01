"""Tree walks shared by the NumPy twins that edit a tree in place."""

from __future__ import annotations


def post_order(child, root) -> list:
    """Node ids of the tree under ``root`` in post-order, children first (left, then right).

    ``child`` [N, 2] int: the children of each node (-1: a leaf). Iterative, so deep trees
    do not hit Python's recursion limit; the order is the one a recursive visit takes.
    """
    out, stack = [], [(root, False)]
    while stack:
        n, expanded = stack.pop()
        if expanded or child[n, 0] < 0:
            out.append(n)
            continue
        stack.append((n, True))
        stack.append((int(child[n, 1]), False))
        stack.append((int(child[n, 0]), False))
    return out
