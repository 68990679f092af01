"""The native engine of :func:`~jaxbvh.queries.closest_point`, :func:`~jaxbvh.queries.overlap`
and :func:`~jaxbvh.queries.within`: the same walk, compiled by numba, one query at a time.

Each query here follows :mod:`jaxbvh.queries.parent_walk` step for step (children by
order key then slot, culled when the walk would enter them, one primitive or one node
move per step, the same four counters and the same step bound ``2 N + P + 2``, after
which ``step_limit`` is set) with :mod:`jaxbvh.queries.geometry`'s formulas written out
in scalars in the tree's float dtype (float32 or float64: the two signatures compiled),
so the results equal the JAX engine's field for field; the tests hold them equal to
each other and to the NumPy twin :mod:`jaxbvh.queries.search_reference`. Out-of-range
node or primitive ids (a broken tree) are read as JAX reads them (negative from the end,
then clamped), so a broken tree gives the same cut-off walk here as there, never a read
outside an array.

One kernel serves the three queries (``mode``: closest point, box overlap, radius over
triangles, radius over boxes), so a process compiles (or loads from numba's cache, in
jaxbvh's cache folder: :func:`jaxbvh.native.numba`) one function per dtype. numba is
imported by :func:`kernel`, on the first native call, never by importing this module.
The entry points take and return NumPy arrays; :mod:`jaxbvh.queries.search` picks the
engine (:func:`jaxbvh.native.choose`) and wraps the results.
"""

from __future__ import annotations

import functools

import numpy as np

from jaxbvh import native

__all__ = ["closest_point", "kernel", "lists"]

#: the kernel's ``mode``: what one query is
CLOSEST, OVERLAP, WITHIN_TRIANGLES, WITHIN_BOXES = 0, 1, 2, 3


@functools.cache
def kernel():
    """The numba kernel (compiled, or loaded from numba's cache, on first use)."""
    return _make(native.numba())


def _make(numba):
    # the helpers become module globals, not closure cells: numba's on-disk cache cannot
    # find a closure's entry again in a new process (its key holds the cells' objects)
    global _at, _box_distance2, _closest_on_triangle, _child_boxes
    # on disk where jaxbvh.native set numba's cache up (nowhere with jaxbvh's cache off)
    jit = numba.njit(cache=native.caching(), nogil=True)

    @jit
    def _at(i, n):
        # JAX's gather: a negative index counts from the end, then clamped into [0, n)
        if i < 0:
            i += n
        return min(max(i, 0), n - 1)

    @jit
    def _box_distance2(p, lo, hi, zero):
        # geometry.box_distance2: gap summed x, y, z in that order
        total = zero
        for a in range(3):
            g = lo[a] - p[a]
            h = p[a] - hi[a]
            if h > g:
                g = h
            if g < zero:
                g = zero
            total = total + g * g
        return total

    @jit
    def _closest_on_triangle(p, a, b, c, zero, one):
        # geometry.closest_on_triangle, in scalars: (d2, q0, q1, q2, u, v, feature)
        ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        ap0, ap1, ap2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
        n0, n1, n2 = ab1 * ac2 - ab2 * ac1, ab2 * ac0 - ab0 * ac2, ab0 * ac1 - ab1 * ac0
        nn = n0 * n0 + n1 * n1 + n2 * n2
        if nn > zero:
            x0, x1, x2 = ap1 * ac2 - ap2 * ac1, ap2 * ac0 - ap0 * ac2, ap0 * ac1 - ap1 * ac0
            u = (x0 * n0 + x1 * n1 + x2 * n2) / nn
            y0, y1, y2 = ab1 * ap2 - ab2 * ap1, ab2 * ap0 - ab0 * ap2, ab0 * ap1 - ab1 * ap0
            v = (y0 * n0 + y1 * n1 + y2 * n2) / nn
            if u >= zero and v >= zero and u + v <= one:
                q0, q1, q2 = a[0] + u * ab0 + v * ac0, a[1] + u * ab1 + v * ac1, a[2] + u * ab2 + v * ac2
                e0, e1, e2 = p[0] - q0, p[1] - q1, p[2] - q2
                return e0 * e0 + e1 * e1 + e2 * e2, q0, q1, q2, u, v, 0
        # edges ab, bc, ca; ties to the first
        best = zero
        q0 = q1 = q2 = t_best = zero
        edge = -1
        for i in range(3):
            if i == 0:
                s, e = a, b
            elif i == 1:
                s, e = b, c
            else:
                s, e = c, a
            d0, d1, d2 = e[0] - s[0], e[1] - s[1], e[2] - s[2]
            dd = d0 * d0 + d1 * d1 + d2 * d2
            t = zero
            if dd != zero:
                t = ((p[0] - s[0]) * d0 + (p[1] - s[1]) * d1 + (p[2] - s[2]) * d2) / dd
            if t < zero:
                t = zero
            if t > one:
                t = one
            if t <= zero:
                r0, r1, r2 = s[0], s[1], s[2]
            elif t >= one:
                r0, r1, r2 = e[0], e[1], e[2]
            else:
                r0, r1, r2 = s[0] + t * d0, s[1] + t * d1, s[2] + t * d2
            e0, e1, e2 = p[0] - r0, p[1] - r1, p[2] - r2
            dist = e0 * e0 + e1 * e1 + e2 * e2
            if edge < 0 or dist < best:
                best, q0, q1, q2, t_best, edge = dist, r0, r1, r2, t, i
        if edge == 0:
            u, v = t_best, zero
        elif edge == 1:
            u, v = one - t_best, t_best
        else:
            u, v = zero, one - t_best
        if t_best <= zero:
            feature = 4 + edge
        elif t_best >= one:
            feature = 4 + (edge + 1) % 3
        else:
            feature = 1 + edge
        e0, e1, e2 = p[0] - q0, p[1] - q1, p[2] - q2
        return e0 * e0 + e1 * e1 + e2 * e2, q0, q1, q2, u, v, feature

    @jit
    def _child_boxes(mode, child, lo, hi, here, qa, qb, qr, best, zero, key, keep):
        # the order key and keep flag of every child slot of node ``here`` (Hooks.boxes)
        k = child.shape[1]
        n = lo.shape[0]
        for j in range(k):
            c = _at(max(child[here, j], 0), n)  # a missing child reads node 0's box, as in JAX
            if mode == OVERLAP:
                key[j] = zero
                meets = True
                for a in range(3):
                    if not (lo[c, a] <= qb[a] and qa[a] <= hi[c, a]):
                        meets = False
                keep[j] = meets
            else:
                key[j] = _box_distance2(qa, lo[c], hi[c], zero)
                keep[j] = key[j] <= (best if mode == CLOSEST else qr)

    @jit
    def run(mode, child, parent, lo, hi, prim_start, prim_count, prim_index, root, triangles, p_lo, p_hi,
            q_a, q_b, q_r, capacity, zero, one, best_prim, best_d2, prims, count, counts, cut):
        """All queries of one batch (module docstring); results into the arrays passed."""
        n_nodes, k = child.shape
        n_slots = prim_index.shape[0]
        n_tri = triangles.shape[0]
        n_box = p_lo.shape[0]
        limit = 2 * n_nodes + n_slots + 2
        key = np.empty(k, lo.dtype)
        keep = np.empty(k, np.bool_)
        rank = np.empty(k, np.int64)
        root_c = _at(root, n_nodes)
        for qi in range(q_a.shape[0]):
            qa, qb, qr = q_a[qi], q_b[qi], q_r[qi]
            best, bprim = qr, -1  # closest point: the best d2 so far (max_d2 at first), its triangle
            n_found = 0
            if mode != CLOSEST:
                for s in range(capacity):
                    prims[qi, s] = -1
            # the root (walk's state before the loop)
            if mode == OVERLAP:
                root_keep = True
                for a in range(3):
                    if not (lo[root_c, a] <= qb[a] and qa[a] <= hi[root_c, a]):
                        root_keep = False
            else:
                root_keep = _box_distance2(qa, lo[root_c], hi[root_c], zero) <= qr
            root_leaf = prim_count[root_c] > 0
            node, up = root, root_leaf
            leaf_pos = leaf_end = 0
            if root_keep and root_leaf:
                leaf_pos = prim_start[root_c]
                leaf_end = leaf_pos + prim_count[root_c]
            box_tests, prim_tests = 1, 0
            nodes_visited = 1 if root_keep else 0
            leaves_visited = 1 if root_keep and root_leaf else 0
            done = not root_keep
            steps = 0
            while not done and steps < limit:
                steps += 1
                if leaf_pos < leaf_end:
                    # primitive step
                    prim = prim_index[min(max(leaf_pos, 0), n_slots - 1)]
                    prim_tests += 1
                    leaf_pos += 1
                    if mode == CLOSEST:
                        tri = triangles[_at(max(prim, 0), n_tri)]
                        d2 = _closest_on_triangle(qa, tri[0], tri[1], tri[2], zero, one)[0]
                        if d2 < best or (d2 == best and (bprim < 0 or prim < bprim)):
                            best, bprim = d2, prim
                    else:
                        if mode == WITHIN_TRIANGLES:
                            tri = triangles[_at(max(prim, 0), n_tri)]
                            hit = _closest_on_triangle(qa, tri[0], tri[1], tri[2], zero, one)[0] <= qr
                        else:
                            b = _at(max(prim, 0), n_box)
                            if mode == WITHIN_BOXES:
                                hit = _box_distance2(qa, p_lo[b], p_hi[b], zero) <= qr
                            else:
                                hit = True
                                for a in range(3):
                                    if not (p_lo[b, a] <= qb[a] and qa[a] <= p_hi[b, a]):
                                        hit = False
                        if hit:
                            for s in range(capacity):
                                if prims[qi, s] == prim:
                                    hit = False
                        if hit:
                            if n_found < capacity:
                                prims[qi, n_found] = prim
                            n_found += 1
                    continue
                if up and node == root:
                    done = True
                    break
                # node move: look at the children of ``here``
                here = parent[_at(node, n_nodes)] if up else node
                here_c = _at(max(here, 0), n_nodes)
                _child_boxes(mode, child, lo, hi, here_c, qa, qb, qr, best, zero, key, keep)
                real = 0
                for j in range(k):
                    if child[here_c, j] >= 0:
                        real += 1
                box_tests += real
                for j in range(k):
                    r = 0
                    for i in range(k):
                        if child[here_c, i] >= 0 and (key[i] < key[j] or (key[i] == key[j] and i < j)):
                            r += 1
                    rank[j] = r
                came_from = -1
                if up:
                    came_from = 0
                    for j in range(k):
                        if child[here_c, j] == node:
                            came_from += rank[j]
                nxt_slot = -1
                for j in range(k):
                    if child[here_c, j] >= 0 and keep[j] and rank[j] > came_from:
                        if nxt_slot < 0 or rank[j] < rank[nxt_slot]:
                            nxt_slot = j
                if nxt_slot < 0:
                    node, up = here, True
                    continue
                nxt = child[here_c, nxt_slot]
                nxt_c = _at(nxt, n_nodes)
                nodes_visited += 1
                node = nxt
                up = prim_count[nxt_c] > 0
                if up:
                    leaves_visited += 1
                    leaf_pos = prim_start[nxt_c]
                    leaf_end = leaf_pos + prim_count[nxt_c]
            counts[qi, 0] = box_tests
            counts[qi, 1] = prim_tests
            counts[qi, 2] = nodes_visited
            counts[qi, 3] = leaves_visited
            cut[qi] = not done
            best_prim[qi] = bprim
            best_d2[qi] = best
            count[qi] = n_found

    @jit
    def finish(points, triangles, best_prim, zero, one, distance, u, v, q, feature):
        # the answer on the chosen triangle (search._closest_one): d2, q, u, v, feature
        n_tri = triangles.shape[0]
        for qi in range(points.shape[0]):
            prim = best_prim[qi]
            if prim < 0:
                continue
            tri = triangles[_at(prim, n_tri)]
            d2, q0, q1, q2, uu, vv, f = _closest_on_triangle(points[qi], tri[0], tri[1], tri[2], zero, one)
            distance[qi] = np.sqrt(d2) if d2 > zero else zero
            q[qi, 0], q[qi, 1], q[qi, 2] = q0, q1, q2
            u[qi], v[qi], feature[qi] = uu, vv, f

    return run, finish


def _arrays(tree):
    """The tree as the kernel reads it: ``(child [N, k], parent, lo, hi, prim_start,
    prim_count, prim_index, root)``, C-contiguous, ids int32, boxes in the tree's dtype."""
    def ids(a):
        return np.ascontiguousarray(np.asarray(a), np.int32)

    lo = np.ascontiguousarray(np.asarray(tree.lo))
    if hasattr(tree, "left"):
        child = np.stack([ids(tree.left), ids(tree.right)], axis=1)
    else:
        child = ids(tree.child)
    return (child, ids(tree.parent), lo, np.ascontiguousarray(np.asarray(tree.hi), lo.dtype), ids(tree.prim_start),
            ids(tree.prim_count), ids(tree.prim_index), int(np.asarray(tree.root)))


#: the float dtypes the kernels are compiled for (a tree of another goes to the JAX engine)
DTYPES = (np.float32, np.float64)


def supports(tree) -> bool:
    """Whether the kernels take ``tree`` (its boxes' float dtype; traced trees too)."""
    return np.dtype(tree.lo.dtype) in DTYPES


def _dtype(tree):
    dtype = np.asarray(tree.lo).dtype
    if dtype not in DTYPES:
        raise TypeError(f"the native engine takes float32 or float64 trees, got {dtype}")
    return dtype


def closest_point(tree, triangles, points, max_d2, pseudonormals=None):
    """Closest triangle to each of ``points`` [n, 3] within ``max_d2`` [n] (squared, tree dtype):
    a dict of NumPy arrays, the fields of :class:`~jaxbvh.queries.search.PointHit` flat [n]."""
    run, finish = kernel()
    dtype = _dtype(tree)
    zero, one = dtype.type(0), dtype.type(1)
    arrays = _arrays(tree)
    tri = np.ascontiguousarray(np.asarray(triangles), dtype).reshape(-1, 3, 3)
    if tri.shape[0] == 0:
        tri = np.zeros((1, 3, 3), dtype)
    points = np.ascontiguousarray(points, dtype)
    n = points.shape[0]
    no_boxes = np.zeros((1, 3), dtype)
    prim = np.empty(n, np.int32)
    best = np.empty(n, dtype)
    counts = np.empty((n, 4), np.int32)
    cut = np.empty(n, np.bool_)
    run(CLOSEST, *arrays, tri, no_boxes, no_boxes, points, points, np.ascontiguousarray(max_d2, dtype), 0,
        zero, one, prim, best, np.empty((n, 1), np.int32), np.empty(n, np.int32), counts, cut)
    distance = np.full(n, np.inf, dtype)
    u, v = np.zeros(n, dtype), np.zeros(n, dtype)
    q = np.full((n, 3), np.nan, dtype)
    feature = np.full(n, -1, np.int32)
    finish(points, tri, prim, zero, one, distance, u, v, q, feature)
    if pseudonormals is not None:
        hit = prim >= 0
        normal = np.asarray(pseudonormals)[np.maximum(prim, 0), np.maximum(feature, 0)].astype(dtype)
        side = (points[:, 0] - q[:, 0]) * normal[:, 0] + (points[:, 1] - q[:, 1]) * normal[:, 1] + \
            (points[:, 2] - q[:, 2]) * normal[:, 2]
        distance = np.where(hit & (side < 0), -distance, distance)
    return dict(distance=distance, prim=prim, u=u, v=v, point=q, feature=feature, box_tests=counts[:, 0],
                prim_tests=counts[:, 1], nodes_visited=counts[:, 2], leaves_visited=counts[:, 3], step_limit=cut)


def lists(tree, prims, mode, q_a, q_b, q_r, capacity):
    """The list queries (``mode``: OVERLAP with boxes ``q_a``, ``q_b`` [n, 3]; WITHIN_* with
    points ``q_a`` and squared radii ``q_r`` [n]); ``prims`` triangles [T, 3, 3] or boxes
    ``(lo, hi)``: a dict of NumPy arrays, the fields of :class:`~jaxbvh.queries.search.Listed`."""
    run, _ = kernel()
    dtype = _dtype(tree)
    zero, one = dtype.type(0), dtype.type(1)
    as_boxes = isinstance(prims, (tuple, list))
    if as_boxes:
        p_lo = np.ascontiguousarray(np.asarray(prims[0]), dtype)
        p_hi = np.ascontiguousarray(np.asarray(prims[1]), dtype)
        tri = np.zeros((1, 3, 3), dtype)
    else:
        tri = np.ascontiguousarray(np.asarray(prims), dtype)
        p_lo, p_hi = np.ascontiguousarray(tri.min(axis=1)), np.ascontiguousarray(tri.max(axis=1))
    if mode != OVERLAP:
        mode = WITHIN_BOXES if as_boxes else WITHIN_TRIANGLES
    if p_lo.shape[0] == 0:
        p_lo = p_hi = np.zeros((1, 3), dtype)
    n = q_a.shape[0]
    listed = np.empty((n, capacity), np.int32)
    count = np.empty(n, np.int32)
    counts = np.empty((n, 4), np.int32)
    cut = np.empty(n, np.bool_)
    run(mode, *_arrays(tree), tri, p_lo, p_hi, np.ascontiguousarray(q_a, dtype), np.ascontiguousarray(q_b, dtype),
        np.ascontiguousarray(q_r, dtype), capacity, zero, one, np.empty(n, np.int32), np.empty(n, dtype), listed,
        count, counts, cut)
    return dict(prims=listed, count=count, overflow=count > capacity, box_tests=counts[:, 0],
                prim_tests=counts[:, 1], nodes_visited=counts[:, 2], leaves_visited=counts[:, 3], step_limit=cut)
