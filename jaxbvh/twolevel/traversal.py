"""Closest-hit traversal of two-level BVHs through instance transforms (jitted).

The algorithm, the stack of ``(node, instance)`` pairs and the step bound are described
in :mod:`jaxbvh.twolevel.rebraid` (section "Traversal"); the tree is a
:class:`jaxbvh.twolevel.rebraid.TwoLevelBVH`. Slab and Möller-Trumbore tests and the
:class:`~jaxbvh.rays.traversal.Hits` record come from :mod:`jaxbvh.rays.traversal`.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.rays.traversal import Hits, inverse_direction, moller_trumbore, slab
from jaxbvh.tree.layout import depth, to_jax, to_numpy


def stack_capacity(tl) -> int:
    """Stack entries that always suffice: top-level height + tallest object tree + 1."""
    t = to_numpy(tl)
    top_height = int(np.max(depth(t.top)))
    f = t.forest
    height = 0
    for r in np.asarray(f.root):
        if r < 0:
            continue
        # depth below each root: walk the object's nodes level by level
        frontier, d = np.array([r]), 0
        while frontier.size and d <= f.left.shape[0]:
            kids = np.concatenate([f.left[frontier], f.right[frontier]])
            frontier = kids[kids >= 0]
            d += 1
        height = max(height, d - 1)
    return top_height + height + 1


def step_bound(tl) -> int:
    """Most loop steps a ray can take: every node and primitive of the flattened tree once, + 1."""
    t = to_numpy(tl)
    f = t.forest
    # object trees are contiguous blocks of the forest starting at their roots
    objs = np.flatnonzero(f.root >= 0)
    objs = objs[np.argsort(f.root[objs])]
    real = ((f.left >= 0) | (f.prim_count > 0)).astype(np.int64)
    obj_nodes = np.zeros(f.root.shape[0], np.int64)
    obj_prims = np.zeros(f.root.shape[0], np.int64)
    obj_nodes[objs] = np.add.reduceat(real, f.root[objs])
    obj_prims[objs] = np.add.reduceat(f.prim_count.astype(np.int64), f.root[objs])
    n = int(t.n_instances)
    used = t.instances.object[:n]
    top = int(np.count_nonzero((t.top.left >= 0) | (t.top.prim_count > 0)))
    return int(top + obj_nodes[used].sum() + obj_prims[used].sum() + 1)


def _trace_one(tl, origin, direction, t_max, max_steps, *, capacity):
    top, f, inst = tl.top, tl.forest, tl.instances
    dtype = top.lo.dtype
    i32 = jnp.int32
    n_top = top.left.shape[0]
    n_inst = inst.object.shape[0]
    # one extra map, the identity, for the top level (instance -1)
    eye = jnp.zeros((1, 3, 4), dtype).at[0, :, :3].set(jnp.eye(3, dtype=dtype))
    to_object = jnp.concatenate([inst.to_object, eye])
    origin = origin.astype(dtype)
    direction = direction.astype(dtype)
    t_min = jnp.zeros((), dtype)
    slot_ids = jnp.arange(2)

    def ray_in(k):
        m = to_object[jnp.where(k >= 0, k, n_inst)]
        return m[:, :3] @ origin + m[:, 3], m[:, :3] @ direction

    inv_dir = inverse_direction(direction)
    root = top.root
    root_hit, root_entry = slab(top.lo[root], top.hi[root], origin, inv_dir, t_min, t_max)
    state = dict(
        sp=jnp.where(root_hit, 1, 0).astype(i32),
        stack_ref=jnp.zeros(capacity, i32).at[0].set(root),
        stack_inst=jnp.full(capacity, -1, i32),
        stack_entry=jnp.full(capacity, jnp.inf, dtype).at[0].set(root_entry),
        leaf_pos=i32(0), leaf_end=i32(0), leaf_inst=i32(0),
        t=t_max, prim=i32(-1), u=jnp.zeros((), dtype), v=jnp.zeros((), dtype),
        box_tests=i32(1), prim_tests=i32(0), nodes_visited=i32(0), leaves_visited=i32(0),
        stack_overflow=jnp.zeros((), bool), steps=i32(0),
    )

    def busy(s):
        return (s["sp"] > 0) | (s["leaf_pos"] < s["leaf_end"])

    def cond(s):
        return busy(s) & (s["steps"] < max_steps)

    def body(s):
        s = dict(s)
        s["steps"] = s["steps"] + 1
        in_leaf = s["leaf_pos"] < s["leaf_end"]

        # primitive step, in the leaf's object frame
        o_k, d_k = ray_in(s["leaf_inst"])
        g = f.prim_index[jnp.minimum(s["leaf_pos"], f.prim_index.shape[0] - 1)]
        tri = f.triangles[jnp.maximum(g, 0)]
        t, u, v = moller_trumbore(tri[0], tri[1], tri[2], o_k, d_k)
        world = g + inst.prim_shift[s["leaf_inst"]]
        valid = in_leaf & (t > t_min) & (t < t_max)
        take = valid & ((t < s["t"]) | ((t == s["t"]) & (world < s["prim"])))
        s["t"] = jnp.where(take, t, s["t"])
        s["prim"] = jnp.where(take, world, s["prim"])
        s["u"] = jnp.where(take, u, s["u"])
        s["v"] = jnp.where(take, v, s["v"])
        s["prim_tests"] = s["prim_tests"] + in_leaf.astype(i32)
        s["leaf_pos"] = s["leaf_pos"] + in_leaf.astype(i32)

        # node step: a top-level node, or a forest node of an instance
        pop = ~in_leaf
        top_i = jnp.maximum(s["sp"] - 1, 0)
        ref = s["stack_ref"][top_i]
        visit = pop & (s["stack_entry"][top_i] <= s["t"])
        is_top = ref < n_top
        tid = jnp.where(is_top, ref, 0)
        top_leaf = is_top & (top.prim_count[tid] > 0)
        b = top.prim_index[top.prim_start[tid]]
        fid = jnp.where(is_top, jnp.where(top_leaf, tl.bref_node[b], 0), ref - n_top)
        k = jnp.where(top_leaf, tl.bref_instance[b], jnp.where(is_top, -1, s["stack_inst"][top_i]))
        in_forest = ~is_top | top_leaf
        fid = jnp.maximum(fid, 0)
        f_count = f.prim_count[fid]
        is_leaf = in_forest & (f_count > 0)
        s["nodes_visited"] = s["nodes_visited"] + visit.astype(i32)
        open_leaf = visit & is_leaf
        s["leaves_visited"] = s["leaves_visited"] + open_leaf.astype(i32)
        s["leaf_pos"] = jnp.where(open_leaf, f.prim_start[fid], s["leaf_pos"])
        s["leaf_end"] = jnp.where(open_leaf, f.prim_start[fid] + f_count, s["leaf_end"])
        s["leaf_inst"] = jnp.where(open_leaf, k, s["leaf_inst"])

        kids = jnp.where(in_forest, jnp.stack([f.left[fid], f.right[fid]]),
                         jnp.stack([top.left[tid], top.right[tid]]))
        real = kids >= 0
        safe = jnp.maximum(kids, 0)
        box_lo = jnp.where(in_forest, f.lo[jnp.minimum(safe, f.lo.shape[0] - 1)],
                           top.lo[jnp.minimum(safe, n_top - 1)])
        box_hi = jnp.where(in_forest, f.hi[jnp.minimum(safe, f.hi.shape[0] - 1)],
                           top.hi[jnp.minimum(safe, n_top - 1)])
        o_n, d_n = ray_in(jnp.where(in_forest, k, -1))
        kid_hit, kid_entry = slab(box_lo, box_hi, o_n, inverse_direction(d_n)[None, :], t_min, s["t"])
        expand = visit & ~is_leaf
        kid_hit = kid_hit & real & expand
        s["box_tests"] = s["box_tests"] + jnp.where(expand, jnp.sum(real), 0).astype(i32)
        split = jnp.where(in_forest, f.axis[fid], top.axis[tid])
        lower_first = d_n[jnp.maximum(split, 0)] >= 0
        by_axis = jnp.where(lower_first, slot_ids, 1 - slot_ids).astype(dtype)
        key = jnp.where(split >= 0, by_axis, kid_entry)
        before = (key[:, None] < key[None, :]) | ((key[:, None] == key[None, :])
                                                  & (slot_ids[:, None] < slot_ids[None, :]))
        rank = jnp.sum(kid_hit[:, None] & before, axis=0)
        n_push = jnp.sum(kid_hit).astype(i32)
        pos = top_i + n_push - 1 - rank
        fits = pos < capacity
        pos = jnp.where(kid_hit & fits, pos, capacity)
        refs = jnp.where(in_forest, kids + n_top, kids)
        s["stack_ref"] = s["stack_ref"].at[pos].set(refs, mode="drop")
        s["stack_inst"] = s["stack_inst"].at[pos].set(jnp.where(in_forest, k, -1), mode="drop")
        s["stack_entry"] = s["stack_entry"].at[pos].set(kid_entry, mode="drop")
        s["stack_overflow"] = s["stack_overflow"] | jnp.any(kid_hit & ~fits)
        s["sp"] = jnp.where(pop, jnp.minimum(top_i + n_push, capacity), s["sp"])
        return s

    s = jax.lax.while_loop(cond, body, state)
    hit = s["prim"] >= 0
    hits = Hits(t=jnp.where(hit, s["t"], jnp.inf), prim=s["prim"], u=s["u"], v=s["v"],
                box_tests=s["box_tests"], prim_tests=s["prim_tests"], nodes_visited=s["nodes_visited"],
                leaves_visited=s["leaves_visited"], stack_overflow=s["stack_overflow"], step_limit=busy(s))
    return hits


@partial(jax.jit, static_argnames=("capacity",))
def trace_batch(tl, origin, direction, t_max, max_steps, *, capacity):
    """Closest hits of rays ``origin``, ``direction`` [R, 3] (scene frame) through ``tl``.

    ``t_max`` [R]; ``max_steps``: loop bound (:func:`step_bound`); ``capacity``: static
    stack size (:func:`stack_capacity`). Returns :class:`~jaxbvh.rays.traversal.Hits` (``step_limit``:
    the ray was still busy at the bound).
    """
    one = partial(_trace_one, tl, max_steps=max_steps, capacity=capacity)
    return jax.vmap(one)(origin, direction, t_max)


def closest_hit(tl, origin, direction, *, batch: int = 256,
                capacity: int | None = None) -> Hits:
    """Closest hit of every ray through the two-level tree (module docstring); NumPy :class:`Hits`.

    Rays are in the scene frame (``Mesh.frame``), ``t`` in units of ``|direction|``,
    ``prim`` a world triangle id (-1: miss). Raises ``RuntimeError`` if a ray overflows
    its stack or its step bound.
    """
    origin = np.asarray(origin)
    direction = np.asarray(direction)
    if origin.ndim != 2 or origin.shape[1] != 3 or direction.shape != origin.shape:
        raise ValueError(f"origin and direction must both be [R, 3], got {origin.shape} and {direction.shape}")
    capacity = stack_capacity(tl) if capacity is None else capacity
    bound = np.int32(step_bound(tl))
    jtl = to_jax(tl)
    dtype = np.dtype(jtl.top.lo.dtype)
    r = origin.shape[0]
    batch = max(1, min(batch, r))
    pieces = []
    for start in range(0, max(r, 1), batch):
        n = min(start + batch, r) - start
        o = np.zeros((batch, 3), dtype)
        d = np.zeros((batch, 3), dtype)
        d[:, 0] = 1
        t_max = np.full(batch, -1, dtype)  # padding rays: empty interval
        o[:n], d[:n], t_max[:n] = origin[start:start + n], direction[start:start + n], np.inf
        pieces.append((n, trace_batch(jtl, o, d, t_max, bound, capacity=capacity)))
    hits = jax.tree_util.tree_map(lambda *parts: np.concatenate([np.asarray(p)[:n] for (n, _), p in
                                                                 zip(pieces, parts)]),
                                  *[h for _, h in pieces])
    if hits.stack_overflow.any():
        bad = np.flatnonzero(hits.stack_overflow)
        raise RuntimeError(f"two-level traversal stack of {capacity} entries overflowed on "
                           f"{bad.size} ray(s) (first: {bad[:5].tolist()})")
    if hits.step_limit.any():
        bad = np.flatnonzero(hits.step_limit)
        raise RuntimeError(f"two-level traversal passed its bound of {int(bound)} steps on "
                           f"{bad.size} ray(s) (first: {bad[:5].tolist()}): the tree is malformed")
    return hits


def brute_force(triangles, origin, direction, *, batch: int = 1024):
    """Closest hit of every ray against every triangle: ``(t, prim)`` NumPy [R] (inf, -1: miss).

    ``triangles`` [T, 3, 3] in the rays' frame; equal ``t`` goes to the lower id. For tests.
    """
    tri = jnp.asarray(triangles)
    dtype = tri.dtype
    ts, ps = [], []
    for s in range(0, origin.shape[0], batch):
        t, p = _brute_chunk(tri, jnp.asarray(origin[s:s + batch], dtype),
                            jnp.asarray(direction[s:s + batch], dtype))
        ts.append(np.asarray(t))
        ps.append(np.asarray(p))
    return np.concatenate(ts), np.concatenate(ps)


@jax.jit
def _brute_chunk(tri, origin, direction):
    t, _, _ = jax.vmap(lambda o, d: moller_trumbore(tri[:, 0], tri[:, 1], tri[:, 2], o, d))(origin, direction)
    t = jnp.where(t > 0, t, jnp.inf)
    best = jnp.min(t, axis=1)
    prim = jnp.argmax(t == best[:, None], axis=1).astype(jnp.int32)
    return best, jnp.where(best < jnp.inf, prim, -1)
