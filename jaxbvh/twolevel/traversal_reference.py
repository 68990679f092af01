"""NumPy twin of :mod:`jaxbvh.twolevel.traversal`, written the slow, literal way.

One ray at a time, a Python list of ``((reference, tag), entry)`` as the stack (with
``capacity``: the oldest entry dropped when a push does not fit, then a climb by parent
links once the list runs empty: up the forest, from an object's subtree back to the
top-level leaf it was entered through, up the top level), the same visiting order, the
same counters and the same float arithmetic (the tree's dtype; the instance transform
and Möller–Trumbore in the same operation order), so the hits and counters of
:func:`jaxbvh.twolevel.traversal.trace` equal these ray by ray (distances to the last
bit where XLA contracts a multiply-add; the native engine, which does not, equals them
bit for bit). References: a top-level node ``n`` is ``n`` (tag -1); forest node ``f``
reached through the top-level leaf ``leaf`` is ``n_top + f`` with tag ``leaf``.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.numerics import robust_factor
# the one-level twin's ray arithmetic: the same inverse direction and slab test
from jaxbvh.rays.traversal_reference import _inverse_direction as _inverse
from jaxbvh.rays.traversal_reference import _slab, moller_trumbore


class _Scene:
    """The tree's arrays in NumPy, floats in ``dtype``, and the ray's frames."""

    def __init__(self, tl, dtype):
        self.top, self.forest = tl.top, tl.forest
        self.n_top = int(np.asarray(tl.top.left).shape[0])
        self.root = int(np.asarray(tl.top.root))
        self.bref_node = np.asarray(tl.bref_node)
        self.bref_instance = np.asarray(tl.bref_instance)
        self.to_object = np.asarray(tl.instances.to_object, dtype)
        self.prim_shift = np.asarray(tl.instances.prim_shift)
        self.tri = np.asarray(tl.forest.triangles, dtype)
        self.dtype = dtype

    def bref(self, leaf):
        """The BRef of top-level leaf ``leaf``."""
        return int(self.top.prim_index[self.top.prim_start[max(leaf, 0)]])

    def frame(self, k, origin, direction):
        """The ray in instance ``k``'s object frame (-1: the scene frame, mapped by the
        identity as the JAX walk maps it) and its inverse direction."""
        m = np.eye(3, 4, dtype=self.dtype) if k < 0 else self.to_object[k]
        o = np.array([m[a, 0] * origin[0] + m[a, 1] * origin[1] + m[a, 2] * origin[2] + m[a, 3] for a in range(3)],
                     self.dtype)
        d = np.array([m[a, 0] * direction[0] + m[a, 1] * direction[1] + m[a, 2] * direction[2] for a in range(3)],
                     self.dtype)
        return o, d, _inverse(d)

    def look(self, ref, tag):
        """Node ``(ref, tag)``: ``(arrays, row, entered, k, parent)`` where ``arrays`` is the
        top level or the forest, ``row`` the node's row there, ``entered`` the top-level
        leaf it is reached through, ``k`` its instance (-1: scene frame) and ``parent``
        the ``(reference, tag)`` above it (a top-level leaf stands for its BRef's forest
        node; a forest node whose parent is that node climbs back to the leaf)."""
        if ref < self.n_top:
            parent = (int(self.top.parent[ref]), -1)
            if self.top.prim_count[ref] == 0:
                return self.top, ref, tag, -1, parent
            b = self.bref(ref)
            return self.forest, int(self.bref_node[b]), ref, int(self.bref_instance[b]), parent
        f = ref - self.n_top
        b = self.bref(tag)
        up = int(self.forest.parent[f])
        parent = (tag, -1) if up < 0 or up == self.bref_node[b] else (self.n_top + up, tag)
        return self.forest, f, tag, int(self.bref_instance[b]), parent


def _children(s: _Scene, ray, node, t_far, counts):
    """The children of ``node`` (a ``(reference, tag)``) in visiting order as
    ``((reference, tag), hit, entry)``, and the node's parent; counts the box tests."""
    arrays, row, entered, k, parent = s.look(*node)
    o, d, inv = s.frame(k, *ray["world"])
    in_forest = arrays is s.forest
    kids = []
    for slot, c in enumerate((int(arrays.left[row]), int(arrays.right[row]))):
        if c < 0:
            continue
        counts["box_tests"] += 1
        hit, entry = _slab(np.asarray(arrays.lo[c], s.dtype), np.asarray(arrays.hi[c], s.dtype), o, inv,
                           ray["t_min"], t_far, ray["robust"])
        if arrays.axis[row] >= 0:  # by slot along the split axis
            key = slot if d[int(arrays.axis[row])] >= 0 else 1 - slot
        else:
            key = entry
        ref = (s.n_top + c, entered) if in_forest else (c, -1)
        kids.append((key, slot, ref, hit, entry))
    kids.sort(key=lambda item: (item[0], item[1]))
    return [(ref, hit, entry) for _, _, ref, hit, entry in kids], parent


def trace_ray(s: _Scene, origin, direction, *, mode="closest", capacity=None, step_limit) -> dict:
    """Trace one scene-frame ray; the fields of :class:`~jaxbvh.rays.stack_walk.Hits` (scalars)."""
    f = s.dtype.type
    origin = np.asarray(origin, s.dtype)
    direction = np.asarray(direction, s.dtype)
    ray = dict(world=(origin, direction), t_min=f(0), robust=f(robust_factor(s.dtype)))
    counts = dict(box_tests=1, prim_tests=0, nodes_visited=0, leaves_visited=0)
    t_max = f(np.inf)
    found = dict(t=t_max, prim=-1, u=f(0), v=f(0))
    capacity = capacity if capacity is not None else 1 << 30
    steps = 0
    hit, entry = _slab(np.asarray(s.top.lo[s.root], s.dtype), np.asarray(s.top.hi[s.root], s.dtype), origin,
                       _inverse(direction), ray["t_min"], t_max, ray["robust"])
    root = (s.root, -1)
    stack = [(root, entry)] if hit else []
    spilled = False
    last, up = root, None  # the node last popped (or climbed to) and the node above it
    done = False
    while (stack or spilled) and not done:
        if steps >= step_limit:
            return dict(found, t=found["t"] if found["prim"] >= 0 else f(np.inf), **counts, stack_overflow=False,
                        step_limit=True)
        steps += 1
        if not stack:  # climb: the next child after ``last`` that the ray enters, else up
            if last[0] == s.root:
                break
            kids, parent = _children(s, ray, up, found["t"], counts)
            mine = next((i for i, (ref, _, _) in enumerate(kids) if ref == last), len(kids))
            later = [(ref, entry_c) for ref, hit_c, entry_c in kids[mine + 1:] if hit_c]
            if later:
                stack.append(later[0])
                continue
            if up[0] == s.root:
                break
            last, up = up, parent
            continue
        node, entry = stack.pop()
        arrays, row, entered, k, parent = s.look(*node)
        last, up = node, parent
        if not entry <= found["t"]:
            continue  # entered beyond the closest hit found since it was pushed
        counts["nodes_visited"] += 1
        if arrays is s.forest and arrays.prim_count[row] > 0:
            counts["leaves_visited"] += 1
            o, d, _ = s.frame(k, origin, direction)
            start = int(arrays.prim_start[row])
            for slot in range(start, start + int(arrays.prim_count[row])):
                g = int(arrays.prim_index[slot])
                tri = s.tri[g]
                t, u, v = moller_trumbore(tri[0], tri[1], tri[2], o, d)
                counts["prim_tests"] += 1
                steps += 1
                if not (t > ray["t_min"] and t < t_max):
                    continue
                prim = g + int(s.prim_shift[k])
                if mode == "any" or t < found["t"] or (t == found["t"] and prim < found["prim"]):
                    found.update(t=f(t), prim=prim, u=f(u), v=f(v))
                if mode == "any":
                    done = True
                    break
            continue
        kids, _ = _children(s, ray, node, found["t"], counts)
        for ref, hit_c, entry_c in reversed(kids):  # nearest on top
            if hit_c:
                stack.append((ref, entry_c))
                if len(stack) > capacity:
                    del stack[0]  # the oldest entry: the climb finds it again
                    spilled = True
    return dict(found, t=found["t"] if found["prim"] >= 0 else f(np.inf), **counts, stack_overflow=False,
                step_limit=False)


def trace(tl, origin, direction, *, dtype, **kwargs) -> list[dict]:
    """:func:`trace_ray` for every ray of ``origin``, ``direction`` [R, 3] (scene frame)
    through the two-level tree ``tl`` (NumPy arrays), floats in ``dtype``; ``kwargs``:
    ``mode``, ``capacity``, ``step_limit``."""
    s = _Scene(tl, np.dtype(dtype))
    return [trace_ray(s, o, d, **kwargs) for o, d in zip(origin, direction)]
