"""NumPy twin of :mod:`jaxbvh.rays.traversal`, written the slow, literal way.

One ray at a time, a Python list as the stack, the same visiting order, the same
counters and the same float arithmetic (tree dtype, same operation order), so the
counts of :func:`jaxbvh.rays.traversal.trace` must equal these ray by ray. Also the
brute-force closest hit over every triangle, the independent check of the hits.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import INV_BIG, robust_factor


def _inverse_direction(direction):
    out = np.empty_like(direction)
    for axis in range(3):
        if direction[axis] == 0:
            out[axis] = np.copysign(direction.dtype.type(INV_BIG), direction[axis])
        else:
            out[axis] = direction.dtype.type(1) / direction[axis]
    return out


def _slab(lo, hi, origin, inv_dir, t_min, t_max, robust):
    t0 = (lo - origin) * inv_dir
    t1 = (hi - origin) * inv_dir
    near = np.max(np.minimum(t0, t1))
    far = np.min(np.maximum(t0, t1)) * robust
    entry = max(near, t_min)
    return bool(entry <= min(far, t_max)), entry


def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1],
                     a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]], dtype=a.dtype)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def moller_trumbore(v0, v1, v2, origin, direction):
    """Two-sided Möller–Trumbore for one triangle; ``(t, u, v)``, ``t = inf`` on a miss."""
    e1 = v1 - v0
    e2 = v2 - v0
    p = _cross(direction, e2)
    det = _dot(e1, p)
    if det == 0:
        return np.inf, 0.0, 0.0
    inv_det = direction.dtype.type(1) / det
    s = origin - v0
    u = _dot(s, p) * inv_det
    q = _cross(s, e1)
    v = _dot(direction, q) * inv_det
    t = _dot(e2, q) * inv_det
    if u >= 0 and u <= 1 and v >= 0 and u + v <= 1:
        return t, u, v
    return np.inf, u, v


def _tree_arrays(tree, skip=None):
    child = np.asarray(tree.child)
    axis = np.asarray(tree.axis) if hasattr(tree, "axis") else None
    return dict(child=child, axis=axis, lo=np.asarray(tree.lo), hi=np.asarray(tree.hi),
                start=np.asarray(tree.prim_start), count=np.asarray(tree.prim_count),
                prim_index=np.asarray(tree.prim_index), root=int(np.asarray(tree.root)),
                skip=None if skip is None else np.asarray(skip, bool))


def trace_ray(tree, triangles, origin, direction, *, mode="closest", t_min=0.0,
              t_max=np.inf, capacity=None, max_hits=16, skip=None) -> dict:
    """Trace one ray; returns the same fields as :class:`jaxbvh.rays.traversal.Hits` (scalars).

    ``skip``: optional [N] bool, nodes whose box is not tested but assumed hit (entered
    where the node that lists them was); they are not counted as visited.
    """
    a = tree if isinstance(tree, dict) else _tree_arrays(tree, skip)
    skip = a["skip"]
    dtype = a["lo"].dtype
    f = dtype.type
    origin = np.asarray(origin, dtype)
    direction = np.asarray(direction, dtype)
    t_min, t_max = f(t_min), f(t_max)
    robust = f(robust_factor(dtype))
    inv_dir = _inverse_direction(direction)
    child, axis = a["child"], a["axis"]
    k = child.shape[1]
    capacity = capacity if capacity is not None else 1 << 30
    out = dict(t=f(np.inf), prim=-1, u=f(0), v=f(0), box_tests=1, prim_tests=0,
               nodes_visited=0, leaves_visited=0, stack_overflow=False, step_limit=False)
    # the JAX loop's bound: a node pop or a primitive test is one step
    steps_left = child.shape[0] + a["prim_index"].shape[0] + 1
    hit_list = []
    hit_count = 0
    best_t = t_max  # the closest hit so far; also the interval's end except in "all" mode
    interval_end = t_max

    root = a["root"]
    hit, entry = _slab(a["lo"][root], a["hi"][root], origin, inv_dir, t_min, t_max, robust)
    stack = [(root, entry)] if hit else []
    while stack:
        steps_left -= 1
        if steps_left < 0:
            out["step_limit"] = True
            break
        node, entry = stack.pop()
        if not entry <= interval_end:
            continue  # entered beyond the closest hit found since it was pushed
        if skip is None or not skip[node]:
            out["nodes_visited"] += 1
        count = a["count"][node]
        if count > 0:
            out["leaves_visited"] += 1
            for slot in range(a["start"][node], a["start"][node] + count):
                steps_left -= 1
                prim = int(a["prim_index"][slot])
                tri = triangles[prim]
                t, u, v = moller_trumbore(tri[0], tri[1], tri[2], origin, direction)
                out["prim_tests"] += 1
                if not (t > t_min and t < t_max):
                    continue
                if mode == "any":
                    out.update(t=t, prim=prim, u=u, v=v)
                    return _finish(out, mode, hit_list, hit_count, max_hits)
                if mode == "all":
                    hit_count += 1
                    if len(hit_list) < max_hits:
                        hit_list.append((prim, t))
                if t < best_t or (t == best_t and prim < out["prim"]):
                    best_t = t
                    out.update(t=t, prim=prim, u=u, v=v)
                    if mode == "closest":
                        interval_end = t
            continue
        kids = []
        for slot in range(k):
            c = int(child[node, slot])
            if c < 0:
                continue
            if skip is not None and skip[c]:
                hit, entry_c = True, entry  # not tested: assumed hit where this node was
            else:
                out["box_tests"] += 1
                hit, entry_c = _slab(a["lo"][c], a["hi"][c], origin, inv_dir, t_min,
                                     interval_end, robust)
            if not hit:
                continue
            if axis is not None and axis[node] >= 0:
                lower_first = direction[axis[node]] >= 0
                key = slot if lower_first else k - 1 - slot
            else:
                key = entry_c
            kids.append((key, slot, c, entry_c))
        kids.sort(key=lambda item: (item[0], item[1]))  # visiting order
        for _, _, c, entry_c in reversed(kids):  # nearest on top
            if len(stack) >= capacity:
                out["stack_overflow"] = True
                continue
            stack.append((c, entry_c))
    return _finish(out, mode, hit_list, hit_count, max_hits)


def _finish(out, mode, hit_list, hit_count, max_hits):
    if mode == "all":
        out["hit_count"] = hit_count
        out["hit_prims"] = [p for p, _ in hit_list]
        out["hit_t"] = [t for _, t in hit_list]
        out["hits_overflow"] = hit_count > max_hits
    return out


def trace(tree, triangles, origin, direction, *, skip=None, **kwargs) -> list[dict]:
    """:func:`trace_ray` for every ray of ``origin``, ``direction`` [R, 3]."""
    a = _tree_arrays(tree, skip)
    triangles = np.asarray(triangles, a["lo"].dtype)
    return [trace_ray(a, triangles, o, d, **kwargs) for o, d in zip(origin, direction)]


def brute_force_closest(triangles, origin, direction, *, t_min=0.0, t_max=np.inf):
    """Closest hit of every ray against every triangle, no tree (vectorised over both).

    ``triangles`` [T, 3, 3], ``origin``, ``direction`` [R, 3]; returns ``(t, prim)``
    [R] with the same tie rule as the traversal (equal ``t``: lower id; miss: inf, -1).
    """
    tri = np.asarray(triangles)
    dtype = tri.dtype
    o = np.asarray(origin, dtype)[:, None, :]
    d = np.asarray(direction, dtype)[:, None, :]
    v0, v1, v2 = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    e1, e2 = v1 - v0, v2 - v0

    def cross(x, y):
        return np.stack([x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1],
                         x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
                         x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]], axis=-1)

    def dot(x, y):
        return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]

    p = cross(np.broadcast_to(d, np.broadcast_shapes(d.shape, e2.shape)), e2)
    det = dot(e1, p)
    ok = det != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = dtype.type(1) / np.where(ok, det, dtype.type(1))
        s = o - v0
        u = dot(s, p) * inv_det
        q = cross(s, np.broadcast_to(e1, s.shape))
        v = dot(np.broadcast_to(d, q.shape), q) * inv_det
        t = dot(np.broadcast_to(e2, q.shape), q) * inv_det
    hit = ok & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > t_min) & (t < t_max)
    t = np.where(hit, t, np.inf)
    prim = np.argmin(t, axis=1)  # first (lowest id) among equal minima
    best = t[np.arange(t.shape[0]), prim]
    return best, np.where(np.isfinite(best), prim, -1).astype(np.int32)
