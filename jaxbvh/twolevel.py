"""Two-level BVHs over objects and instances, with partial re-braiding (Benthin et al. 2017).

A scene of objects placed by instances (:class:`jaxbvh.io.Mesh`: ``objects``,
``instances``) gets

1. one BVH per distinct object, built once by any of our builders (binned SAH by
   default, as the paper) -- in the object's own frame when several instances share it,
   in world space otherwise -- and packed into one forest (:mod:`jaxbvh.forest`);
2. a *top level*: a BVH over build references (BRefs: forest node, instance, world box,
   primitive count) that starts from one BRef per instance and, while splitting,
   *opens* BRefs that are large relative to their segment, so that overlapping objects
   are separated inside their own trees (:mod:`jaxbvh.brefs`; ``threshold = inf`` gives
   the plain two-level BVH, which never opens).

A scene with a single instance (a plain mesh is one object with one identity instance)
needs no top level, and none is built: its top level is one leaf naming the object's root.

Layout of :class:`TwoLevelBVH`
==============================
``top`` is a :class:`~jaxbvh.tree.BVH` over the BRefs (layout :mod:`jaxbvh.tree`, boxes
in the scene frame ``Mesh.frame``): every leaf holds exactly one BRef id. The BRefs
``bref_node`` / ``bref_instance`` / ``bref_lo`` / ``bref_hi`` / ``bref_prims`` [C] say
which forest node of which instance a leaf stands for (padding: node -1). ``forest`` and
``instances`` are :class:`~jaxbvh.forest.Forest` and :class:`~jaxbvh.forest.Instances`.
A top-level leaf *is* its BRef's forest node: its box is that node's world box, and
below it the object's own nodes follow, in the object's frame.

Traversal
=========
:func:`closest_hit` runs one ``while_loop`` per ray whose stack holds ``(node,
instance)`` pairs: top-level nodes (instance -1) are tested with the world ray; below a
top-level leaf the ray is mapped into the instance's object frame (``to_object``; the
direction is not normalised, so ``t`` is the same in both frames) and the object's nodes
and triangles are tested there. Each step is a node step or a primitive step, counted
as in :mod:`jaxbvh.traverse` (whose slab and Möller-Trumbore tests it reuses): the root
box test is one box test, an interior node adds one per child. The loop is bounded by
the number of steps a ray can take at most (every node and primitive of the flattened
tree once, plus one); a ray that would need more, or whose stack would overflow, is
reported and the driver raises. Primitive ids are world triangle ids (``Mesh.triangles``
order); equal ``t`` goes to the lower id.

Flattening and costs
====================
:func:`flatten` copies every BRef's subtree under its instance into one world-space
:class:`~jaxbvh.tree.BVH` (conservative world boxes, :func:`jaxbvh.forest.world_boxes`;
primitive ids in world order) that validates against ``Mesh.local_boxes()`` and saves in
the interchange form. :func:`sah` is the SAH of that tree: interior nodes and leaves of
two-level, re-braided and single BVHs costed on the same footing (the paper's Table 1).
For instanced nodes the world box is the conservative box of the transformed object box,
as the top level sees it.
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import brefs as _brefs
from jaxbvh.forest import Forest, Instances, ObjectTree, build_objects, pack, world_boxes
from jaxbvh.traverse import Hits, inverse_direction, moller_trumbore, slab
from jaxbvh.tree import BVH, capacity_bucket, concat_ranges, depth, pad_to, to_jax, to_numpy

__all__ = ["TwoLevelBVH", "build", "build_from", "flatten", "sah", "stored_nodes", "closest_hit",
           "brute_force", "stack_capacity", "step_bound"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TwoLevelBVH:
    """A two-level (possibly re-braided) BVH (layout: module docstring).

    ``top``: :class:`~jaxbvh.tree.BVH`; ``bref_node``, ``bref_instance``, ``bref_prims``
    [C] int32; ``bref_lo``, ``bref_hi`` [C, 3] float; ``bref_count`` int32 scalar;
    ``forest``: :class:`~jaxbvh.forest.Forest`; ``instances``:
    :class:`~jaxbvh.forest.Instances`; ``n_instances`` int32 scalar.
    """

    top: Any
    bref_node: Any
    bref_instance: Any
    bref_lo: Any
    bref_hi: Any
    bref_prims: Any
    bref_count: Any
    forest: Any
    instances: Any
    n_instances: Any


def _world_boxes_jit(lo, hi, to_scene, margin):
    return world_boxes(lo, hi, to_scene, margin)


_world_boxes_jit = jax.jit(_world_boxes_jit)


def _single_instance(forest: Forest, instances: Instances) -> TwoLevelBVH:
    """The top level of a one-instance scene: one leaf naming the object's root (no build)."""
    root = int(forest.root[instances.object[0]])
    lo, hi = _world_boxes_jit(forest.lo[root][None], forest.hi[root][None],
                              instances.to_scene[:1], instances.margin[:1])
    lo, hi = np.asarray(lo), np.asarray(hi)
    one = lambda v: np.full(1, v, np.int32)  # noqa: E731
    top = BVH(left=one(-1), right=one(-1), parent=one(-1), lo=lo, hi=hi, prim_start=one(0),
              prim_count=one(1), axis=one(-1), prim_index=one(0), root=np.int32(0))
    return TwoLevelBVH(top=top, bref_node=one(root), bref_instance=one(0), bref_lo=lo, bref_hi=hi,
                       bref_prims=one(int(forest.subtree_prims[root])), bref_count=np.int32(1),
                       forest=forest, instances=instances, n_instances=np.int32(1))


def build_from(mesh, trees: dict[int, ObjectTree], *, threshold: float = _brefs.DEFAULT_THRESHOLD,
               budget: float = _brefs.DEFAULT_BUDGET, capacity: int | None = None,
               top_bins: int = _brefs.DEFAULT_BINS, overlap: float = _brefs.DEFAULT_OVERLAP,
               estimate: bool = False, timings: dict | None = None,
               shapes: dict | None = None) -> TwoLevelBVH:
    """Pack already built object trees and build the top level (see :func:`build`).

    ``timings``, if given, receives ``pack`` and ``top`` seconds (arrays ready);
    ``shapes``: least array sizes ``{"nodes", "prims", "instances", "brefs"}`` (so that
    many scenes share one compiled top-level build and traversal).
    """
    _brefs.check_options(threshold, budget, top_bins, overlap)
    start = time.perf_counter()
    shapes = shapes or {}
    forest, instances = pack(mesh, trees, capacity=shapes)
    packed = time.perf_counter()
    n = len(mesh.instances)
    if n == 1:
        tl = _single_instance(forest, instances)
    else:
        result = jax.block_until_ready(_brefs.build_top_level(
            forest, instances, n, threshold=threshold, budget=budget, capacity=capacity,
            bins=top_bins, overlap=overlap, estimate=estimate, array_size=shapes.get("brefs")))
        tl = TwoLevelBVH(top=result.top, bref_node=result.node, bref_instance=result.instance,
                         bref_lo=result.lo, bref_hi=result.hi, bref_prims=result.prims,
                         bref_count=result.count, forest=forest, instances=instances,
                         n_instances=np.int32(n))
    if timings is not None:
        timings["pack"] = packed - start
        timings["top"] = time.perf_counter() - packed
    return tl


def build(mesh, *, threshold: float = _brefs.DEFAULT_THRESHOLD, budget: float = _brefs.DEFAULT_BUDGET,
          capacity: int | None = None, top_bins: int = _brefs.DEFAULT_BINS,
          overlap: float = _brefs.DEFAULT_OVERLAP, estimate: bool = False, method: str = "binned",
          max_leaf: int = 1, bins: int = 16, ct: float = 1.0, ci: float = 1.0, dtype=np.float32,
          world_space: bool = True, timings: dict | None = None) -> TwoLevelBVH:
    """Two-level BVH of ``mesh`` with re-braiding (module docstring).

    Object BVHs: ``method``, ``max_leaf``, ``bins``, ``ct``, ``ci`` as
    :func:`jaxbvh.build`, in ``dtype`` (float64 needs x64); ``world_space``: build objects
    placed by a single instance in world space (:mod:`jaxbvh.forest`). Top level: ``threshold``
    (opening threshold; inf: plain two-level), ``budget`` BRef slots per instance (or
    ``capacity`` in all), ``top_bins``, ``overlap``, ``estimate`` as
    :func:`jaxbvh.brefs.build_top_level`. ``timings``, if given, receives ``objects``,
    ``pack`` and ``top`` seconds.
    """
    _brefs.check_options(threshold, budget, top_bins, overlap)
    start = time.perf_counter()
    trees = build_objects(mesh, method=method, max_leaf=max_leaf, bins=bins, ct=ct, ci=ci, dtype=dtype,
                          world_space=world_space)
    if timings is not None:
        timings["objects"] = time.perf_counter() - start
    return build_from(mesh, trees, threshold=threshold, budget=budget, capacity=capacity,
                      top_bins=top_bins, overlap=overlap, estimate=estimate, timings=timings)


# ----------------------------------------------------------------------------------
# Flattening and costs
# ----------------------------------------------------------------------------------


def flatten(tl: TwoLevelBVH, *, pad: bool = True) -> BVH:
    """One world-space (scene-frame) :class:`~jaxbvh.tree.BVH` with the same nodes (NumPy).

    Top-level interior nodes keep their ids; a top-level leaf becomes the copy of its
    BRef's forest node, and the copies of the nodes below follow. Copies under a
    non-identity map get ``axis = -1`` (the object's split axis means nothing in world
    space). Primitive ids are world triangle ids. Padded to capacity buckets unless
    ``pad=False``.
    """
    t = to_numpy(tl)
    top, f, inst = t.top, t.forest, t.instances
    n_top = top.left.shape[0]
    top_leaf = np.flatnonzero(top.prim_count > 0)
    bref_of_leaf = top.prim_index[top.prim_start[top_leaf]]
    # breadth-first copy of every BRef's subtree: (forest node, instance, flat id)
    frontier_f = t.bref_node[bref_of_leaf].astype(np.int64)
    frontier_i = t.bref_instance[bref_of_leaf].astype(np.int64)
    frontier_id = top_leaf.astype(np.int64)
    copies_f, copies_i, copies_id, child_rows = [], [], [], []
    next_id = n_top
    for _ in range(f.left.shape[0] + 1):
        if frontier_f.size == 0:
            break
        copies_f.append(frontier_f), copies_i.append(frontier_i), copies_id.append(frontier_id)
        inner = f.left[frontier_f] >= 0
        k = int(inner.sum())
        ids_l = next_id + 2 * np.arange(k)
        next_id += 2 * k
        child_rows.append((frontier_id[inner], ids_l, ids_l + 1))
        frontier_f = np.concatenate([f.left[frontier_f[inner]], f.right[frontier_f[inner]]]).astype(np.int64)
        frontier_i = np.concatenate([frontier_i[inner], frontier_i[inner]])
        frontier_id = np.concatenate([ids_l, ids_l + 1])
        order = np.argsort(frontier_id)  # number each level by id, as our builders do
        frontier_f, frontier_i, frontier_id = frontier_f[order], frontier_i[order], frontier_id[order]
    cf, ci_, cid = (np.concatenate(a) for a in (copies_f, copies_i, copies_id))
    n_flat = next_id
    dtype = top.lo.dtype
    left = np.full(n_flat, -1, np.int32)
    right = np.full(n_flat, -1, np.int32)
    parent = np.full(n_flat, -1, np.int32)
    axis = np.full(n_flat, -1, np.int32)
    lo = np.full((n_flat, 3), np.inf, dtype)
    hi = np.full((n_flat, 3), -np.inf, dtype)
    # top-level nodes keep their ids (leaves are overwritten by their copies below)
    left[:n_top], right[:n_top], parent[:n_top], axis[:n_top] = top.left, top.right, top.parent, top.axis
    lo[:n_top], hi[:n_top] = top.lo, top.hi
    for rows, ids_l, ids_r in child_rows:
        left[rows], right[rows] = ids_l, ids_r
        parent[ids_l], parent[ids_r] = rows, rows
    size = capacity_bucket(cf.size)  # one compile per bucket
    pad_f = np.zeros(size, np.int64)
    pad_i = np.zeros(size, np.int64)
    pad_f[:cf.size], pad_i[:cf.size] = cf, ci_
    w_lo, w_hi = _world_boxes_jit(f.lo[pad_f], f.hi[pad_f], inst.to_scene[pad_i], inst.margin[pad_i])
    lo[cid], hi[cid] = np.asarray(w_lo)[:cf.size], np.asarray(w_hi)[:cf.size]
    exact = inst.margin[ci_] == 0
    axis[cid] = np.where(exact & (f.left[cf] >= 0), f.axis[cf], -1)
    # leaves: runs of world triangle ids
    count = np.zeros(n_flat, np.int32)
    start = np.zeros(n_flat, np.int32)
    is_leaf = f.prim_count[cf] > 0
    leaf_ids, leaf_f, leaf_i = cid[is_leaf], cf[is_leaf], ci_[is_leaf]
    counts = f.prim_count[leaf_f].astype(np.int64)
    count[leaf_ids] = counts
    start[leaf_ids] = np.cumsum(counts) - counts
    slots = concat_ranges(f.prim_start[leaf_f], counts)
    prim_index = (f.prim_index[slots] + np.repeat(inst.prim_shift[leaf_i], counts)).astype(np.int32)
    flat = BVH(left=left, right=right, parent=parent, lo=lo, hi=hi, prim_start=start, prim_count=count,
               axis=axis, prim_index=prim_index, root=np.int32(int(top.root)))
    if pad:
        flat = pad_to(flat, capacity_bucket(n_flat), capacity_bucket(prim_index.shape[0]))
    return flat


def sah(tl: TwoLevelBVH, ct: float = 1.0, ci: float = 1.0) -> float:
    """SAH of the flattened tree (:func:`flatten`): the paper's total SAH, on one footing."""
    import jaxbvh

    return float(jaxbvh.sah(to_jax(flatten(tl)), ct, ci))


def stored_nodes(tl: TwoLevelBVH) -> dict[str, int]:
    """Nodes kept in memory: ``top`` (real top-level nodes) and ``objects`` (forest nodes)."""
    t = to_numpy(tl)
    top = int(np.count_nonzero((t.top.left >= 0) | (t.top.prim_count > 0)))
    objects = int(np.count_nonzero((t.forest.left >= 0) | (t.forest.prim_count > 0)))
    return {"top": top, "objects": objects, "total": top + objects}


# ----------------------------------------------------------------------------------
# Traversal
# ----------------------------------------------------------------------------------


def stack_capacity(tl: TwoLevelBVH) -> int:
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


def step_bound(tl: TwoLevelBVH) -> int:
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
                leaves_visited=s["leaves_visited"], stack_overflow=s["stack_overflow"])
    return hits, busy(s)


@partial(jax.jit, static_argnames=("capacity",))
def trace_batch(tl, origin, direction, t_max, max_steps, *, capacity):
    """Closest hits of rays ``origin``, ``direction`` [R, 3] (scene frame) through ``tl``.

    ``t_max`` [R]; ``max_steps``: loop bound (:func:`step_bound`); ``capacity``: static
    stack size (:func:`stack_capacity`). Returns ``(Hits, step_overflow [R] bool)``.
    """
    one = partial(_trace_one, tl, max_steps=max_steps, capacity=capacity)
    return jax.vmap(one)(origin, direction, t_max)


def closest_hit(tl: TwoLevelBVH, origin, direction, *, batch: int = 256,
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
    hits, over = hits
    if hits.stack_overflow.any():
        bad = np.flatnonzero(hits.stack_overflow)
        raise RuntimeError(f"two-level traversal stack of {capacity} entries overflowed on "
                           f"{bad.size} ray(s) (first: {bad[:5].tolist()})")
    if over.any():
        bad = np.flatnonzero(over)
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
