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

:func:`check` first makes sure the arrays agree in shape and that the root and child
ids index them (if not, that is the only problem reported: the invariants index with
those ids), then runs one function per invariant (``_root_problems`` ...
``_box_problems``) and lists their problems in this order.
"""

from __future__ import annotations

from typing import Any, NamedTuple

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


class _Arrays(NamedTuple):
    """A tree's arrays on the host, ids as int64."""

    child: np.ndarray       # int64 [N, k], -1: no child
    parent: np.ndarray      # int64 [N], -1: none
    count: np.ndarray       # int64 [N] prim_count
    start: np.ndarray       # int64 [N] prim_start
    prim_index: np.ndarray  # int64 [P]
    lo: np.ndarray          # float [N, 3]
    hi: np.ndarray          # float [N, 3]
    root: int               # root node id


class _Links(NamedTuple):
    """What several invariants read, derived once the arrays' shapes and ids are sane."""

    n_child: np.ndarray  # int64 [N]: children listed per node
    real: np.ndarray     # bool [N]: the node has a child or a primitive (not padding)
    rows: np.ndarray     # int64 [E]: parent end of every child link
    kids: np.ndarray     # int64 [E]: child end of every child link
    visits: np.ndarray   # int64 [N]: times the walk from the root reached each node
    repeated: Any        # int64 [M] or None: nodes the walk reached again, where it stopped


class _Runs(NamedTuple):
    """The primitive slots of the reached leaves whose runs lie inside ``prim_index``."""

    past_end: np.ndarray  # int64 [L']: reached leaves whose run leaves prim_index
    leaves: np.ndarray    # int64 [L]: the other reached leaves
    owner: np.ndarray     # int64 [S]: leaf of each slot
    slots: np.ndarray     # int64 [S]: prim_index slots, leaf by leaf
    prims: np.ndarray     # int64 [S]: primitive ids in those slots


def check(tree, prim_lo=None, prim_hi=None, n_prims: int | None = None) -> list[str]:
    """All invariant violations of ``tree`` as readable lines (empty list: valid).

    ``prim_lo``, ``prim_hi``: [n, 3] primitive boxes in the tree's frame (optional; the
    leaf-contains-primitive check and the primitive count come from them).
    ``n_prims``: number of primitives when no boxes are given (default: the number the
    leaves reference). Problems come invariant by invariant (module docstring); arrays
    of the wrong shape, or ids that do not index them, are reported alone.
    """
    a = _arrays(tree)
    broken = _layout_problems(a)
    if broken:
        return broken
    links = _links(a)
    runs = _runs(a, links.visits)
    if prim_lo is not None:
        n_prims = int(np.asarray(prim_lo).shape[0])
    if n_prims is None:
        n_prims = int(runs.slots.size)
    return (_root_problems(a, links) + _reach_problems(a, links) + _parent_problems(a, links)
            + _kind_problems(a, links) + _primitive_problems(a, runs, n_prims)
            + _box_problems(a, links, runs, n_prims, prim_lo, prim_hi))


def _arrays(tree) -> _Arrays:
    t = to_numpy(tree)
    ids = lambda x: np.asarray(x).astype(np.int64)  # noqa: E731
    return _Arrays(child=ids(t.child), parent=ids(t.parent), count=ids(t.prim_count), start=ids(t.prim_start),
                   prim_index=ids(t.prim_index), lo=np.asarray(t.lo), hi=np.asarray(t.hi),
                   root=int(np.asarray(t.root)))


def _layout_problems(a: _Arrays) -> list[str]:
    """Arrays of one node count, a root and child ids inside it (else nothing else is
    checked: the invariants index with these ids)."""
    nodes = a.child.shape[0]
    if a.parent.shape != (nodes,) or a.count.shape != (nodes,) or a.start.shape != (nodes,) \
            or a.lo.shape != (nodes, 3) or a.hi.shape != (nodes, 3):
        return [f"array shapes disagree: child {a.child.shape}, parent {a.parent.shape}, "
                f"prim_count {a.count.shape}, prim_start {a.start.shape}, lo {a.lo.shape}, hi {a.hi.shape}"]
    if not 0 <= a.root < nodes:
        return [f"root {a.root} is outside the {nodes} nodes"]
    bad_ids = (a.child < -1) | (a.child >= nodes)
    if bad_ids.any():
        return [f"child ids out of range at node(s) {few_ids(np.flatnonzero(bad_ids.any(1)))}"]
    return []


def _links(a: _Arrays) -> _Links:
    """The child links, and a walk from the root level by level (bounded by the node
    count) that stops where a node is reached a second time."""
    has_child = a.child >= 0
    n_child = has_child.sum(axis=1)
    rows, cols = np.nonzero(has_child)
    nodes = a.child.shape[0]
    visits = np.zeros(nodes, np.int64)
    # stamp[i]: position of node i in the level last written; a level's ids are
    # distinct iff each finds its own position (O(level) per level, no sort)
    stamp = np.full(nodes, -1, np.int64)
    repeated = None
    frontier = np.array([a.root])
    for _ in range(nodes + 1):
        if frontier.size == 0:
            break
        visits[frontier] += 1  # distinct: checked below before it becomes the frontier
        nxt = a.child[frontier].ravel()
        nxt = nxt[nxt >= 0]
        position = np.arange(nxt.size)
        stamp[nxt] = position
        twice = stamp[nxt] != position
        before = visits[nxt] > 0
        if before.any() or twice.any():  # reached before, or twice in this level
            repeated = np.union1d(nxt[before], nxt[twice])
            break
        frontier = nxt
    return _Links(n_child=n_child, real=(n_child > 0) | (a.count > 0), rows=rows, kids=a.child[rows, cols],
                  visits=visits, repeated=repeated)


def _root_problems(a: _Arrays, links: _Links) -> list[str]:
    """1. The root is a real node without a parent."""
    problems = []
    if not links.real[a.root]:
        problems.append(f"root {a.root} is padding (no children, no primitives)")
    if a.parent[a.root] != -1:
        problems.append(f"parent of root {a.root} is {a.parent[a.root]}, expected -1")
    return problems


def _reach_problems(a: _Arrays, links: _Links) -> list[str]:
    """2. The walk from the root reaches every real node exactly once; padding is inert
    and unlinked."""
    problems = []
    if links.repeated is not None:
        problems.append(f"node(s) {few_ids(links.repeated)} reached more than "
                        "once from the root (cycle or shared child)")
    if (links.visits > 1).any():
        problems.append(f"node(s) {few_ids(np.flatnonzero(links.visits > 1))} reached more than once")
    unreached = links.real & (links.visits == 0)
    if unreached.any():
        problems.append(f"real node(s) {few_ids(np.flatnonzero(unreached))} not reachable from root {a.root}")
    pad = ~links.real
    if pad.any():
        pad_box = np.isfinite(a.lo[pad]).any(1) | np.isfinite(a.hi[pad]).any(1)
        if pad_box.any() or (a.parent[pad] != -1).any():
            problems.append(f"padding node(s) {few_ids(np.flatnonzero(pad)[pad_box | (a.parent[pad] != -1)])} "
                            "are not inert (need parent -1 and the empty box)")
    return problems


def _parent_problems(a: _Arrays, links: _Links) -> list[str]:
    """3. ``parent`` names the node that lists a node as its child, both ways."""
    problems = []
    wrong = a.parent[links.kids] != links.rows
    if wrong.any():
        problems.append(f"parent of node(s) {few_ids(links.kids[wrong])} does not name the node that lists "
                        "them as child")
    beyond = links.real & (a.parent >= a.parent.shape[0])
    if beyond.any():
        problems.append(f"node(s) {few_ids(np.flatnonzero(beyond))} name a parent outside the "
                        f"{a.parent.shape[0]} nodes")
    orphan = links.real & (a.parent >= 0) & ~beyond
    if orphan.any():
        listed = (a.child[a.parent[orphan]] == np.flatnonzero(orphan)[:, None]).any(1)
        if (~listed).any():
            problems.append(f"node(s) {few_ids(np.flatnonzero(orphan)[~listed])} name a parent that "
                            "does not list them as a child")
    return problems


def _kind_problems(a: _Arrays, links: _Links) -> list[str]:
    """4. Interior (two or more children, no primitives) or leaf (no children, count >= 1)."""
    problems = []
    both = (links.n_child > 0) & (a.count > 0)
    if both.any():
        problems.append(f"node(s) {few_ids(np.flatnonzero(both))} have both children and primitives")
    single = links.n_child == 1
    if single.any():
        problems.append(f"interior node(s) {few_ids(np.flatnonzero(single))} have only one child")
    if (a.count < 0).any():
        problems.append(f"negative prim_count at node(s) {few_ids(np.flatnonzero(a.count < 0))}")
    return problems


def _runs(a: _Arrays, visits) -> _Runs:
    leaves = np.flatnonzero((a.count > 0) & (visits > 0))
    past_end = (a.start[leaves] < 0) | (a.start[leaves] + a.count[leaves] > a.prim_index.shape[0])
    past, leaves = leaves[past_end], leaves[~past_end]
    if int(a.count[leaves].sum()):
        slots = concat_ranges(a.start[leaves], a.count[leaves])
        return _Runs(past, leaves, np.repeat(leaves, a.count[leaves]), slots, a.prim_index[slots])
    none = np.zeros(0, np.int64)
    return _Runs(past, leaves, none, none, none)


def _primitive_problems(a: _Arrays, runs: _Runs, n_prims: int) -> list[str]:
    """5. The reached leaves' runs name every primitive ``0 .. n_prims-1`` exactly once."""
    problems = []
    if runs.past_end.size:
        problems.append(f"leaf/leaves {few_ids(runs.past_end)} run past prim_index "
                        f"({a.prim_index.shape[0]} slots)")
    if runs.slots.size and np.bincount(runs.slots, minlength=a.prim_index.shape[0]).max() > 1:
        problems.append("leaves share prim_index slots")
    prims = runs.prims
    bad_prim = (prims < 0) | (prims >= n_prims)
    if bad_prim.any():
        problems.append(f"leaves reference primitive ids outside [0, {n_prims}): {few_ids(prims[bad_prim])}")
    seen = np.bincount(prims[~bad_prim], minlength=n_prims) if n_prims else np.zeros(0, np.int64)
    if (seen > 1).any():
        problems.append(f"primitive(s) {few_ids(np.flatnonzero(seen > 1))} referenced more than once")
    if (seen == 0).any():
        problems.append(f"primitive(s) {few_ids(np.flatnonzero(seen == 0))} referenced by no leaf")
    return problems


def _box_problems(a: _Arrays, links: _Links, runs: _Runs, n_prims: int, prim_lo, prim_hi) -> list[str]:
    """6. Real boxes are finite and not inverted, and contain their children's boxes and
    their primitives' boxes (when given), exactly."""
    problems = []
    lo, hi = a.lo, a.hi
    # each test first over the flat arrays (one fast pass, the usual answer is "none"),
    # then row by row only to name the nodes where it fails
    with np.errstate(invalid="ignore"):
        sound = np.isfinite(lo) & np.isfinite(hi) & (lo <= hi)
    if not sound[links.real].all():
        malformed = links.real & ~sound.all(1)
        problems.append(f"node(s) {few_ids(np.flatnonzero(malformed))} have non-finite or inverted boxes")
    rows, kids = links.rows, links.kids
    # np.take: several times faster than x[ids] on [N, 3] rows at millions of ids
    take = lambda x, ids: np.take(x, ids, axis=0)  # noqa: E731
    out = _outside(take(lo, kids), take(hi, kids), take(lo, rows), take(hi, rows))
    if out is not None:
        problems.append(f"box of node(s) {few_ids(rows[out])} does not contain the box of child(ren) "
                        f"{few_ids(kids[out])}")
    if prim_lo is not None and prim_hi is not None and runs.slots.size:
        plo, phi = np.asarray(prim_lo), np.asarray(prim_hi)
        ok = (runs.prims >= 0) & (runs.prims < n_prims)
        p, owner = (runs.prims, runs.owner) if ok.all() else (runs.prims[ok], runs.owner[ok])
        outside = _outside(take(plo, p), take(phi, p), take(lo, owner), take(hi, owner))
        if outside is not None:
            problems.append(f"leaf box(es) {few_ids(np.unique(owner[outside]))} do not contain "
                            f"primitive(s) {few_ids(p[outside])}")
    return problems


def _outside(inner_lo, inner_hi, outer_lo, outer_hi):
    """bool [E]: rows whose inner box [E, 3] is not inside the outer box (exact; a NaN
    compares as inside: the finiteness test names it); None when every row is inside."""
    below, above = inner_lo < outer_lo, inner_hi > outer_hi
    if not (below.any() or above.any()):
        return None
    return below.any(1) | above.any(1)


def validate(tree, prim_lo=None, prim_hi=None, n_prims: int | None = None):
    """Raise :class:`InvalidTreeError` listing every broken invariant; return the tree.

    Same arguments as :func:`check`.
    """
    problems = check(tree, prim_lo, prim_hi, n_prims)
    if problems:
        raise InvalidTreeError(problems)
    return tree
