"""The tree invariants, checked on the host after every operation that makes a tree.

A valid tree (binary or wide; layout in :mod:`jaxbvh.tree.layout`):

1. ``root`` is a real node with ``parent[root] == -1``.
2. Following children from the root reaches every real node exactly once (no cycles,
   no shared children); padding is inert (no children, count 0, empty box) and unlinked.
3. ``parent`` is consistent: ``parent[c] == n`` for every child ``c`` of ``n``.
4. Every node is either interior (at least two children, count 0) or a leaf (no
   children, count >= 1).
5. The leaves' runs of ``prim_index`` together name every primitive ``0 .. n-1``
   exactly once.
6. Every real box is well formed (``lo <= hi``, finite) and contains its children's
   boxes and, for a leaf, the boxes of its primitives (exactly, no tolerance).
"""

from __future__ import annotations

import numpy as np

from jaxbvh.tree.layout import concat_ranges, to_numpy


class InvalidTreeError(ValueError):
    """A tree breaks an invariant; ``problems`` lists each one found."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        shown = "\n  ".join(problems[:10])
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        super().__init__(f"invalid BVH ({len(problems)} problem(s)):\n  {shown}{more}")


def few_ids(ids, limit=5) -> str:
    """The first ``limit`` ids as text, with how many there are in all: for error messages."""
    ids = np.asarray(ids).ravel()
    text = ", ".join(str(int(i)) for i in ids[:limit])
    return text + (f", ... ({ids.size} in all)" if ids.size > limit else "")


def check(tree, prim_lo=None, prim_hi=None, n_prims: int | None = None) -> list[str]:
    """All invariant violations of ``tree`` as readable lines (empty list: valid).

    ``prim_lo``, ``prim_hi``: [n, 3] primitive boxes in the tree's frame (optional; the
    leaf-contains-primitive check and the primitive count come from them).
    ``n_prims``: number of primitives when no boxes are given (default: the number the
    leaves reference).
    """
    t = to_numpy(tree)
    child = np.asarray(t.child).astype(np.int64)
    parent = np.asarray(t.parent).astype(np.int64)
    count = np.asarray(t.prim_count).astype(np.int64)
    start = np.asarray(t.prim_start).astype(np.int64)
    prim_index = np.asarray(t.prim_index).astype(np.int64)
    lo, hi = np.asarray(t.lo), np.asarray(t.hi)
    nodes = child.shape[0]
    problems: list[str] = []

    if parent.shape != (nodes,) or count.shape != (nodes,) or start.shape != (nodes,) \
            or lo.shape != (nodes, 3) or hi.shape != (nodes, 3):
        return [f"array shapes disagree: child {child.shape}, parent {parent.shape}, "
                f"prim_count {count.shape}, prim_start {start.shape}, lo {lo.shape}, hi {hi.shape}"]
    root = int(np.asarray(t.root))
    if not 0 <= root < nodes:
        return [f"root {root} is outside the {nodes} nodes"]
    bad_ids = (child < -1) | (child >= nodes)
    if bad_ids.any():
        return [f"child ids out of range at node(s) {few_ids(np.flatnonzero(bad_ids.any(1)))}"]

    has_child = child >= 0
    n_child = has_child.sum(axis=1)
    real = (n_child > 0) | (count > 0)
    if not real[root]:
        problems.append(f"root {root} is padding (no children, no primitives)")
    if parent[root] != -1:
        problems.append(f"parent of root {root} is {parent[root]}, expected -1")

    # 2. reachability, each node once
    visits = np.zeros(nodes, np.int64)
    frontier = np.array([root])
    for _ in range(nodes + 1):
        if frontier.size == 0:
            break
        np.add.at(visits, frontier, 1)
        nxt = child[frontier].ravel()
        nxt = nxt[nxt >= 0]
        if (visits[nxt] > 0).any() or len(np.unique(nxt)) < len(nxt):
            problems.append(f"node(s) {few_ids(np.unique(nxt[visits[nxt] > 0]))} reached more than "
                            "once from the root (cycle or shared child)")
            break
        frontier = nxt
    if (visits > 1).any():
        problems.append(f"node(s) {few_ids(np.flatnonzero(visits > 1))} reached more than once")
    unreached = real & (visits == 0)
    if unreached.any():
        problems.append(f"real node(s) {few_ids(np.flatnonzero(unreached))} not reachable from root {root}")
    pad = ~real
    if pad.any():
        pad_box = np.isfinite(lo[pad]).any(1) | np.isfinite(hi[pad]).any(1)
        if pad_box.any() or (parent[pad] != -1).any():
            problems.append(f"padding node(s) {few_ids(np.flatnonzero(pad)[pad_box | (parent[pad] != -1)])} "
                            "are not inert (need parent -1 and the empty box)")

    # 3. parent links
    rows, cols = np.nonzero(has_child)
    kids = child[rows, cols]
    wrong = parent[kids] != rows
    if wrong.any():
        problems.append(f"parent of node(s) {few_ids(kids[wrong])} does not name the node that lists them as child")
    orphan = real & (parent >= 0)
    if orphan.any():
        p = parent[orphan]
        listed = (child[p] == np.flatnonzero(orphan)[:, None]).any(1)
        if (~listed).any():
            problems.append(f"node(s) {few_ids(np.flatnonzero(orphan)[~listed])} name a parent that "
                            "does not list them as a child")

    # 4. node kinds
    both = (n_child > 0) & (count > 0)
    if both.any():
        problems.append(f"node(s) {few_ids(np.flatnonzero(both))} have both children and primitives")
    single = n_child == 1
    if single.any():
        problems.append(f"interior node(s) {few_ids(np.flatnonzero(single))} have only one child")
    if (count < 0).any():
        problems.append(f"negative prim_count at node(s) {few_ids(np.flatnonzero(count < 0))}")

    # 5. primitives exactly once
    leaves = np.flatnonzero((count > 0) & (visits > 0))
    if prim_lo is not None:
        n_prims = int(np.asarray(prim_lo).shape[0])
    out_of_range = (start[leaves] < 0) | (start[leaves] + count[leaves] > prim_index.shape[0])
    if out_of_range.any():
        problems.append(f"leaf/leaves {few_ids(leaves[out_of_range])} run past prim_index "
                        f"({prim_index.shape[0]} slots)")
        leaves = leaves[~out_of_range]
    total = int(count[leaves].sum())
    if total:
        leaf_of_slot = np.repeat(leaves, count[leaves])
        slots = concat_ranges(start[leaves], count[leaves])
        prims = prim_index[slots]
    else:
        leaf_of_slot = slots = prims = np.zeros(0, np.int64)
    if n_prims is None:
        n_prims = total
    if len(np.unique(slots)) != len(slots):
        problems.append("leaves share prim_index slots")
    bad_prim = (prims < 0) | (prims >= n_prims)
    if bad_prim.any():
        problems.append(f"leaves reference primitive ids outside [0, {n_prims}): {few_ids(prims[bad_prim])}")
    seen = np.bincount(prims[~bad_prim], minlength=n_prims) if n_prims else np.zeros(0, np.int64)
    if (seen > 1).any():
        problems.append(f"primitive(s) {few_ids(np.flatnonzero(seen > 1))} referenced more than once")
    if (seen == 0).any():
        problems.append(f"primitive(s) {few_ids(np.flatnonzero(seen == 0))} referenced by no leaf")

    # 6. boxes
    r = np.flatnonzero(real)
    malformed = ~(np.isfinite(lo[r]).all(1) & np.isfinite(hi[r]).all(1) & (lo[r] <= hi[r]).all(1))
    if malformed.any():
        problems.append(f"node(s) {few_ids(r[malformed])} have non-finite or inverted boxes")
    out = (lo[kids] < lo[rows]).any(1) | (hi[kids] > hi[rows]).any(1)
    if out.any():
        problems.append(f"box of node(s) {few_ids(rows[out])} does not contain the box of child(ren) "
                        f"{few_ids(kids[out])}")
    if prim_lo is not None and prim_hi is not None and total:
        plo, phi = np.asarray(prim_lo), np.asarray(prim_hi)
        ok = ~bad_prim
        p, owner = prims[ok], leaf_of_slot[ok]
        outside = (plo[p] < lo[owner]).any(1) | (phi[p] > hi[owner]).any(1)
        if outside.any():
            problems.append(f"leaf box(es) {few_ids(np.unique(owner[outside]))} do not contain "
                            f"primitive(s) {few_ids(p[outside])}")
    return problems


def validate(tree, prim_lo=None, prim_hi=None, n_prims: int | None = None):
    """Raise :class:`InvalidTreeError` listing every broken invariant; return the tree.

    Same arguments as :func:`check`.
    """
    problems = check(tree, prim_lo, prim_hi, n_prims)
    if problems:
        raise InvalidTreeError(problems)
    return tree
