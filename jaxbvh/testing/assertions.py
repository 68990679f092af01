"""Assertions about trees that say what is wrong in one line (each raises ``AssertionError``).

* :func:`assert_valid_tree` -- the invariants of :mod:`jaxbvh.tree.validate` (structure,
  primitives, boxes containing children and primitives exactly; ``references=True``,
  ``triangles=`` for trees with references, an SBVH's).
* :func:`assert_same_tree` -- two trees node for node, up to node numbering.
* :func:`assert_costs_close` -- two SAH costs (of trees, or numbers) within ``rtol``.

They work on any tree in the layout of :mod:`jaxbvh.tree.layout` (binary or wide, NumPy
or JAX arrays), including trees read from another library's interchange ``.npz``
(:func:`jaxbvh.load`).
"""

from __future__ import annotations

import numpy as np

from jaxbvh.tree.cost_reference import sah as exact_sah
from jaxbvh.tree.layout import to_numpy
from jaxbvh.tree.validate import check


def _is_tree(tree, name: str = "tree"):
    """Refuse what is not a tree in one line (``jaxbvh.load`` returns ``(tree, frame)``)."""
    if not all(hasattr(tree, f) for f in ("child", "parent", "prim_count", "prim_index", "root")):
        hint = " (jaxbvh.load returns (tree, frame))" if isinstance(tree, tuple) else ""
        raise TypeError(f"{name}: expected a BVH or WideBVH, got {type(tree).__name__}{hint}")


def assert_valid_tree(tree, lo=None, hi=None, n_prims: int | None = None, *, references: bool = False,
                      triangles=None) -> None:
    """Fail unless ``tree`` is a valid BVH over primitive boxes ``lo``, ``hi`` [n, 3]
    (given in the tree's frame; optional: without them only ``n_prims`` primitives, or
    as many as the leaves reference, are expected, and primitive containment is not
    checked). The message names the first broken invariant and counts the others.

    ``references``: the tree may name a primitive in several leaves (an SBVH's spatial
    splits: each leaf box then holds a piece of the primitive, not all of it);
    ``triangles`` [n, 3, 3] (the tree's frame) adds the check that a triangle's leaf
    boxes together cover it. Both as :func:`jaxbvh.check`, which does the checking."""
    _is_tree(tree)
    problems = check(tree, lo, hi, n_prims, references=references, triangles=triangles)
    if problems:
        more = f" (and {len(problems) - 1} more: {'; '.join(problems[1:3])})" if len(problems) > 1 else ""
        raise AssertionError(f"invalid BVH: {problems[0]}{more}")


def _node_text(kind: str, value) -> str:
    if kind == "leaf":
        return f"leaf of primitives {list(value)}"
    return f"interior node of {value} children"


def _box(t, n, boxes: bool):
    if not boxes:
        return None
    return np.asarray(t.lo[n]).tolist(), np.asarray(t.hi[n]).tolist()


def canonical(tree, *, boxes: bool = True, child_order: bool = True, with_axis: bool = False):
    """``tree`` as nested tuples from the root, free of node ids: a leaf is
    ``("leaf", sorted primitive ids, box)``, an interior node ``("node", children...,
    box)`` with ``box = (lo, hi)`` as lists (None without ``boxes``). Children keep their
    order unless ``child_order=False`` (then they are sorted); ``with_axis`` puts a binary
    node's split axis after ``"node"``. Two trees that differ only
    in node numbering and in the order of primitives inside leaves are equal."""
    t = to_numpy(tree)
    child = np.asarray(t.child)
    out: dict[int, tuple] = {}
    stack = [(int(t.root), False)]
    for _ in range(4 * child.shape[0] + 2):  # bounded: each node is pushed twice at most in a valid tree
        if not stack:
            break
        n, done = stack.pop()
        kids = [int(c) for c in child[n] if c >= 0]
        if not done:
            stack.append((n, True))
            stack += [(c, False) for c in kids if c not in out]
            continue
        if not kids:
            s, c = int(t.prim_start[n]), int(t.prim_count[n])
            out[n] = ("leaf", tuple(sorted(int(p) for p in t.prim_index[s:s + c])), _box(t, n, boxes))
        else:
            parts = [out[c] for c in kids]
            head = ("node", int(t.axis[n])) if with_axis else ("node",)
            out[n] = (*head, *(parts if child_order else sorted(parts, key=repr)), _box(t, n, boxes))
    else:
        raise AssertionError("canonical: the tree is not a tree (cycle or shared child); check it first")
    return out[int(t.root)]


def _first_difference(a, b, path: str):
    """``(path, what a has, what b has)`` of the first difference of two canonical forms."""
    if a[0] != b[0]:
        return path, _node_text(a[0], a[1] if a[0] == "leaf" else len(a) - 2), \
            _node_text(b[0], b[1] if b[0] == "leaf" else len(b) - 2)
    if a[0] == "leaf":
        if a[1] != b[1]:
            return path, _node_text("leaf", a[1]), _node_text("leaf", b[1])
    else:
        if len(a) != len(b):
            return path, _node_text("node", len(a) - 2), _node_text("node", len(b) - 2)
        for i, (x, y) in enumerate(zip(a[1:-1], b[1:-1])):
            found = _first_difference(x, y, f"{path}.{i}")
            if found:
                return found
    if a[-1] != b[-1]:
        return path, f"box {a[-1]}", f"box {b[-1]}"
    return None


def assert_same_tree(a, b, *, boxes: bool = True, child_order: bool = True, references: bool = False) -> None:
    """Fail unless trees ``a`` and ``b`` are the same node for node, up to node numbering
    (and the order of primitives inside a leaf): same shape from the root, same
    primitives in each leaf, and with ``boxes`` bit-equal boxes. ``child_order=False``
    also ignores the order of each node's children; ``references``: the trees may name a
    primitive in several leaves (SBVH; :func:`assert_valid_tree`). The message gives the
    path from the root (``root.1.0``: the root's second child's first child) and what
    each tree has."""
    for name, tree in (("first", a), ("second", b)):
        _is_tree(tree, f"{name} tree")
        problems = check(tree, references=references)
        if problems:
            raise AssertionError(f"{name} tree is invalid: {problems[0]}")
    found = _first_difference(canonical(a, boxes=boxes, child_order=child_order),
                              canonical(b, boxes=boxes, child_order=child_order), "root")
    if found:
        path, x, y = found
        raise AssertionError(f"trees differ at {path}: {x} vs {y}")


def assert_costs_close(a, b, rtol: float = 1e-6, *, ct: float = 1.0, ci: float = 1.0) -> None:
    """Fail unless the SAH costs of ``a`` and ``b`` agree within relative tolerance
    ``rtol``. Each is a tree (costed exactly, in float64, by the NumPy reference: node
    cost ``ct`` per traversal step, ``ci`` per primitive, normalised by the root's area)
    or a number (a cost someone reported)."""
    def cost(x):
        return float(x) if np.ndim(x) == 0 and not hasattr(x, "root") else exact_sah(x, ct, ci)

    ca, cb = cost(a), cost(b)
    if not (np.isfinite(ca) and np.isfinite(cb)):
        raise AssertionError(f"costs are not finite: {ca!r} vs {cb!r}")
    diff = abs(ca - cb) / max(abs(ca), abs(cb), np.finfo(np.float64).tiny)
    if diff > rtol:
        raise AssertionError(f"SAH costs differ: {ca!r} vs {cb!r} (relative difference {diff:.3g} > rtol {rtol:g})")
