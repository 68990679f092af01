"""NumPy twin of :mod:`jaxbvh.queries.search` and its walk: one query at a time, written literally.

The walk (:mod:`jaxbvh.queries.parent_walk`'s rules: children by order key then slot,
culled when the walk would enter them, one primitive or one node move per step, the same
counters and step bound) and the per-primitive geometry (:mod:`jaxbvh.queries.geometry`'s
formulas, written again here in NumPy scalars) are independent statements that the tests
hold equal to the JAX code, query by query. :func:`jaxbvh.queries.search.raycast` runs
the rays' walk; its twin is :mod:`jaxbvh.rays.traversal_reference`.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.tree.layout import BVH, to_numpy


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])



def closest_on_triangle(p, a, b, c):
    """``(d2, q, u, v, feature)`` of the closest point on triangle ``a, b, c`` to ``p``
    (NumPy [3] arrays of one float dtype; the rules of :mod:`jaxbvh.queries.geometry`)."""
    ab, ac, ap = b - a, c - a, p - a
    n = _cross(ab, ac)
    nn = _dot(n, n)
    if nn > 0:
        u = _dot(_cross(ap, ac), n) / nn
        v = _dot(_cross(ab, ap), n) / nn
        if u >= 0 and v >= 0 and u + v <= 1:
            q = a + u * ab + v * ac
            return _dot(p - q, p - q), q, u, v, 0
    best = None
    # edges ab, bc, ca in order; ties to the first; (start feature, end feature, edge feature)
    for i, (s, e, fs, fe) in enumerate(((a, b, 4, 5), (b, c, 5, 6), (c, a, 6, 4))):
        d = e - s
        dd = _dot(d, d)
        t = min(max(_dot(p - s, d) / dd if dd != 0 else p.dtype.type(0), 0), 1)
        q = s if t <= 0 else e if t >= 1 else s + t * d
        d2 = _dot(p - q, p - q)
        if best is None or d2 < best[0]:
            feature = fs if t <= 0 else fe if t >= 1 else 1 + i
            u, v = ((t, 0), (1 - t, t), (0, 1 - t))[i]
            best = (d2, q, p.dtype.type(u), p.dtype.type(v), feature)
    return best


def box_distance2(p, lo, hi):
    """Squared distance from ``p`` [3] to the box ``lo``, ``hi`` [3] (0 inside)."""
    gap = np.maximum(np.maximum(lo - p, p - hi), 0)
    return _dot(gap, gap)


def walk(tree, boxes, primitive, found, stop=None):
    """One stackless walk of ``tree`` (NumPy). ``boxes(lo, hi, found) -> (key, keep)`` for
    one child box; ``primitive(found, prim) -> found``; ``stop(found)``: the query is
    answered (optional). Returns ``(found, counts, step_limit)`` with ``counts`` a dict of
    the four counters."""
    t = to_numpy(tree)
    child = np.stack([t.left, t.right], axis=1) if isinstance(t, BVH) else t.child
    root = int(t.root)
    limit = 2 * child.shape[0] + t.prim_index.shape[0] + 2
    counts = dict(box_tests=1, prim_tests=0, nodes_visited=0, leaves_visited=0)
    if not boxes(t.lo[root], t.hi[root], found)[1]:
        return found, counts, False
    counts["nodes_visited"] = 1
    node, up = root, bool(t.prim_count[root] > 0)
    pending = []  # primitive slots of the open leaf
    if up:
        counts["leaves_visited"] = 1
        pending = list(range(t.prim_start[root], t.prim_start[root] + t.prim_count[root]))
    steps = 0
    while steps < limit:
        if pending:
            found = primitive(found, int(t.prim_index[pending.pop(0)]))
            counts["prim_tests"] += 1
            steps += 1
            if stop is not None and stop(found):
                return found, counts, False
            continue
        if up and node == root:
            return found, counts, False
        here = int(t.parent[node]) if up else node
        kids = [int(k) for k in child[max(here, 0)]]
        counts["box_tests"] += sum(k >= 0 for k in kids)
        tested = {slot: boxes(t.lo[k], t.hi[k], found) for slot, k in enumerate(kids) if k >= 0}
        order = sorted(tested, key=lambda slot: (tested[slot][0], slot))
        after = order[order.index(kids.index(node)) + 1:] if up and node in kids else order
        kept = [slot for slot in after if tested[slot][1]]
        steps += 1
        if not kept:
            node, up = here, True
            continue
        node = kids[kept[0]]
        counts["nodes_visited"] += 1
        up = bool(t.prim_count[node] > 0)
        if up:
            counts["leaves_visited"] += 1
            pending = list(range(t.prim_start[node], t.prim_start[node] + t.prim_count[node]))
    return found, counts, True


def closest_point(tree, triangles, point, max_distance=np.inf):
    """Closest triangle to ``point`` [3]: ``(prim, distance, counts, step_limit)`` (prim -1:
    none within ``max_distance``); arithmetic in the tree's dtype."""
    dtype = np.asarray(to_numpy(tree).lo).dtype
    tri = np.asarray(triangles, dtype)
    p = np.asarray(point, dtype)
    max_d2 = dtype.type(np.inf) if np.isinf(max_distance) else dtype.type(max_distance) ** 2

    def boxes(lo, hi, found):
        key = box_distance2(p, lo, hi)
        return key, key <= found[0]

    def primitive(found, prim):
        d2 = closest_on_triangle(p, *tri[prim])[0]
        if d2 < found[0] or (d2 == found[0] and (found[1] < 0 or prim < found[1])):
            return d2, prim
        return found

    (d2, prim), counts, limit = walk(tree, boxes, primitive, (max_d2, -1))
    return prim, (np.sqrt(d2) if prim >= 0 else np.inf), counts, limit


def _listing(tree, test, boxes, capacity):
    listed, count = [], 0

    def primitive(found, prim):
        nonlocal count
        if test(prim) and prim not in listed:
            count += 1
            if len(listed) < capacity:
                listed.append(prim)
        return found

    _, counts, limit = walk(tree, lambda lo, hi, _: boxes(lo, hi), primitive, None)
    return listed + [-1] * (capacity - len(listed)), count, counts, limit


def _prim_box(prims, prim, dtype):
    if isinstance(prims, (tuple, list)):
        return np.asarray(prims[0][prim], dtype), np.asarray(prims[1][prim], dtype)
    tri = np.asarray(prims[prim], dtype)
    return tri.min(axis=0), tri.max(axis=0)


def overlap(tree, prims, lo, hi, capacity):
    """Primitives whose box meets box ``lo``, ``hi`` [3]: ``(list, count, counts, step_limit)``."""
    dtype = np.asarray(to_numpy(tree).lo).dtype
    q_lo, q_hi = np.asarray(lo, dtype), np.asarray(hi, dtype)

    def meets(b_lo, b_hi):
        return bool(np.all((b_lo <= q_hi) & (q_lo <= b_hi)))

    return _listing(tree, lambda prim: meets(*_prim_box(prims, prim, dtype)),
                    lambda b_lo, b_hi: (0, meets(b_lo, b_hi)), capacity)


def within(tree, prims, point, radius, capacity):
    """Primitives within ``radius`` of ``point`` [3]: ``(list, count, counts, step_limit)``."""
    dtype = np.asarray(to_numpy(tree).lo).dtype
    p = np.asarray(point, dtype)
    r2 = dtype.type(radius) * dtype.type(radius)

    def test(prim):
        if isinstance(prims, (tuple, list)):
            return box_distance2(p, *_prim_box(prims, prim, dtype)) <= r2
        return closest_on_triangle(p, *np.asarray(prims[prim], dtype))[0] <= r2

    def boxes(b_lo, b_hi):
        key = box_distance2(p, b_lo, b_hi)
        return key, key <= r2

    return _listing(tree, test, boxes, capacity)
