"""NumPy twin of :mod:`jaxbvh.rays.traversal`, written the slow, literal way.

One ray at a time, a Python list as the stack (with ``capacity``: the oldest entry
dropped when a push does not fit, then a climb by parent links once the list runs
empty), the same visiting order, the same counters and the same float arithmetic (tree
dtype, same operation order), so the counts of :func:`jaxbvh.rays.traversal.trace` must
equal these ray by ray. Also the brute-force closest hit over every triangle, the
independent check of the hits.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

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


class _Tree(NamedTuple):
    """A tree's arrays in NumPy."""

    child: np.ndarray       # int [N, k], -1: none
    parent: np.ndarray      # int [N], -1: the root
    axis: Any               # int [N] split axis (binary trees) or None (wide trees)
    lo: np.ndarray          # float [N, 3]
    hi: np.ndarray          # float [N, 3]
    start: np.ndarray       # int [N] prim_start
    count: np.ndarray       # int [N] prim_count
    prim_index: np.ndarray  # int [P]
    root: int
    skip: Any               # bool [N] "assume hit" flags or None


def _tree_arrays(tree, skip=None) -> _Tree:
    return _Tree(child=np.asarray(tree.child), parent=np.asarray(tree.parent), axis=np.asarray(tree.axis) if hasattr(tree, "axis") else None,
                 lo=np.asarray(tree.lo), hi=np.asarray(tree.hi), start=np.asarray(tree.prim_start),
                 count=np.asarray(tree.prim_count), prim_index=np.asarray(tree.prim_index),
                 root=int(np.asarray(tree.root)), skip=None if skip is None else np.asarray(skip, bool))


@dataclasses.dataclass
class _Ray:
    """One ray's state while it walks the tree (changed in place)."""

    origin: np.ndarray     # float [3]
    direction: np.ndarray  # float [3]
    inv_dir: np.ndarray    # float [3]
    t_min: Any             # float: open interval start
    t_max: Any             # float: open interval end
    robust: Any            # float: the slab test's robust factor
    interval_end: Any      # float: culling distance (closest: the best hit so far)
    best_t: Any            # float: the closest hit so far
    steps_left: int        # the JAX loop's bound: a node pop or a primitive test is one step
    t: Any = np.inf        # the hit reported (closest, or first in any-hit mode)
    prim: int = -1
    u: Any = 0.0
    v: Any = 0.0
    box_tests: int = 1     # the root's box
    prim_tests: int = 0
    nodes_visited: int = 0
    leaves_visited: int = 0
    stack_overflow: bool = False
    step_limit: bool = False
    hit_count: int = 0     # all-hits mode: hits seen
    hit_list: list = dataclasses.field(default_factory=list)  # all-hits mode: (prim, t), first max_hits

    def slab(self, tree: _Tree, node, t_max):
        return _slab(tree.lo[node], tree.hi[node], self.origin, self.inv_dir, self.t_min, t_max, self.robust)


def trace_ray(tree, triangles, origin, direction, *, mode="closest", t_min=0.0,
              t_max=np.inf, capacity=None, max_hits=16, skip=None) -> dict:
    """Trace one ray; returns the same fields as :class:`jaxbvh.rays.traversal.Hits` (scalars).

    ``skip``: optional [N] bool, nodes whose box is not tested but assumed hit (entered
    where the node that lists them was); they are not counted as visited. ``capacity``:
    stack entries (None: unbounded); a push beyond it drops the oldest entry, and when
    the stack runs empty after that the ray climbs from the last node popped: at each
    parent it tests the children's boxes again and goes on with the next child in
    visiting order the ray enters, else moves up (the root: done).
    """
    a = tree if isinstance(tree, _Tree) else _tree_arrays(tree, skip)
    dtype = a.lo.dtype
    f = dtype.type
    origin = np.asarray(origin, dtype)
    direction = np.asarray(direction, dtype)
    ray = _Ray(origin=origin, direction=direction, inv_dir=_inverse_direction(direction), t_min=f(t_min),
               t_max=f(t_max), robust=f(robust_factor(dtype)), interval_end=f(t_max), best_t=f(t_max),
               steps_left=3 * a.child.shape[0] + a.prim_index.shape[0] + 1, t=f(np.inf), u=f(0), v=f(0))
    capacity = capacity if capacity is not None else 1 << 30
    hit, entry = ray.slab(a, a.root, ray.t_max)
    stack = [(a.root, entry)] if hit else []
    spilled = False
    last = a.root  # the node last popped, or climbed to
    while stack or spilled:
        ray.steps_left -= 1
        if ray.steps_left < 0:
            ray.step_limit = True
            break
        if not stack:  # climb
            if last == a.root:
                break
            up = int(a.parent[last])
            kids = _children(a, ray, up, ray.t_min)
            mine = next(i for i, item in enumerate(kids) if item[2] == last)
            later = [(c, entry_c) for _, _, c, hit_c, entry_c in kids[mine + 1:] if hit_c]
            if later:
                stack.append(later[0])
                continue
            last = up
            if up == a.root:
                break
            continue
        node, entry = stack.pop()
        last = node
        if not entry <= ray.interval_end:
            continue  # entered beyond the closest hit found since it was pushed
        if a.skip is None or not a.skip[node]:
            ray.nodes_visited += 1
        if a.count[node] > 0:
            ray.leaves_visited += 1
            if _visit_leaf(a, triangles, ray, node, mode, max_hits):
                break  # any-hit mode: the first hit ends the ray
            continue
        hits = [(c, entry_c) for _, _, c, hit_c, entry_c in _children(a, ray, node, entry) if hit_c]
        for c, entry_c in reversed(hits):  # nearest on top
            stack.append((c, entry_c))
            if len(stack) > capacity:
                del stack[0]  # the oldest entry: the climb finds it again
                spilled = True
    return finish(ray, mode, max_hits)


def _visit_leaf(a: _Tree, triangles, ray: _Ray, node, mode, max_hits) -> bool:
    """Test the leaf's primitives in order; True when an any-hit ray found its hit."""
    for slot in range(a.start[node], a.start[node] + a.count[node]):
        ray.steps_left -= 1
        prim = int(a.prim_index[slot])
        tri = triangles[prim]
        t, u, v = moller_trumbore(tri[0], tri[1], tri[2], ray.origin, ray.direction)
        ray.prim_tests += 1
        if not (t > ray.t_min and t < ray.t_max):
            continue
        if mode == "any":
            ray.t, ray.prim, ray.u, ray.v = t, prim, u, v
            return True
        if mode == "all":
            if any(p == prim for p, _ in ray.hit_list):
                continue  # the same triangle from another leaf (a tree with references)
            ray.hit_count += 1
            if len(ray.hit_list) < max_hits:
                ray.hit_list.append((prim, t))
        if t < ray.best_t or (t == ray.best_t and prim < ray.prim):
            ray.best_t = t
            ray.t, ray.prim, ray.u, ray.v = t, prim, u, v
            if mode == "closest":
                ray.interval_end = t
    return False


def _children(a: _Tree, ray: _Ray, node, entry) -> list:
    """Every child of ``node`` as ``(key, slot, child, hit, entry)``, in visiting order.

    A skip-flagged child is not tested: assumed hit, entered at ``entry`` (the node's),
    and first in distance order (key ``-inf``).
    """
    k = a.child.shape[1]
    kids = []
    for slot in range(k):
        c = int(a.child[node, slot])
        if c < 0:
            continue
        assumed = a.skip is not None and a.skip[c]
        if assumed:
            hit, entry_c = True, entry  # not tested: assumed hit where this node was
        else:
            ray.box_tests += 1
            hit, entry_c = ray.slab(a, c, ray.interval_end)
        if a.axis is not None and a.axis[node] >= 0:
            lower_first = ray.direction[a.axis[node]] >= 0
            key = slot if lower_first else k - 1 - slot
        else:
            key = -np.inf if assumed else entry_c
        kids.append((key, slot, c, hit, entry_c))
    kids.sort(key=lambda item: (item[0], item[1]))  # visiting order
    return kids


def finish(ray: _Ray, mode, max_hits) -> dict:
    """The ray's result record (the fields of :class:`jaxbvh.rays.traversal.Hits`)."""
    out = dict(t=ray.t, prim=ray.prim, u=ray.u, v=ray.v, box_tests=ray.box_tests, prim_tests=ray.prim_tests,
               nodes_visited=ray.nodes_visited, leaves_visited=ray.leaves_visited,
               stack_overflow=ray.stack_overflow, step_limit=ray.step_limit)
    if mode == "all":
        out.update(hit_count=ray.hit_count, hit_prims=[p for p, _ in ray.hit_list],
                   hit_t=[t for _, t in ray.hit_list], hits_overflow=ray.hit_count > max_hits)
    return out


def trace(tree, triangles, origin, direction, *, skip=None, **kwargs) -> list[dict]:
    """:func:`trace_ray` for every ray of ``origin``, ``direction`` [R, 3]."""
    a = _tree_arrays(tree, skip)
    triangles = np.asarray(triangles, a.lo.dtype)
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
