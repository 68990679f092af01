"""Closest- and any-hit traversal of two-level BVHs through instance transforms.

The algorithm and the stack of ``(node, tag)`` pairs are described in
:mod:`jaxbvh.twolevel.rebraid` (section "Traversal"); the stack is short and fixed
(:data:`~jaxbvh.rays.stack_walk.STACK` entries, whatever the depth), and a ray whose stack
spilled climbs by parent links: the top level's, the forest's, and from an object's
subtree back to the top-level leaf it was entered through (the tag); the tree is a
:class:`jaxbvh.twolevel.rebraid.TwoLevelBVH`. The loop is :func:`jaxbvh.rays.stack_walk.walk_rays`,
the one-level traversal's own, with this module's hooks (``_primitive``, ``_expand``);
slab and Möller-Trumbore tests, ray checks and batching come from
:mod:`jaxbvh.rays.traversal`.

Engines (:func:`trace`, ``engine=``): ``"jax"`` runs :func:`trace_batch`, the jitted walk
(the one to call inside a ``jit`` / ``vmap``); ``"native"`` runs the same walk compiled
by numba (:mod:`jaxbvh.twolevel.native`: equal hits and counters, many times the rays
per CPU second, ``bench/results/bench_twolevel_native.md``); ``"auto"`` picks by
:func:`jaxbvh.native.choose`, the one rule of every query. The NumPy twin is
:mod:`jaxbvh.twolevel.traversal_reference`.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh import native as engines
from jaxbvh.program_store import stored_jit
from jaxbvh.rays.stack_walk import LEAF_WIDTH, STACK, Hits, Hooks, Node, Ray, lanes_for, walk_rays
from jaxbvh.rays.traversal import check_rays, in_batches, inverse_direction, moller_trumbore, slab
from jaxbvh.tree.layout import depth, to_jax, to_numpy
from jaxbvh.tree.validate import InvalidTreeError
from jaxbvh.twolevel import native as twolevel_native


MODES = ("closest", "any")
"""The two-level walk's modes (closest hit; any hit, e.g. shadow rays: the first found)."""


def stack_capacity(tl) -> int:
    """Stack entries with which no ray ever climbs: top-level height + tallest object
    tree + 1 (the walk's default is :data:`~jaxbvh.rays.stack_walk.STACK`, whatever the
    depth: a spill climbs by parent links)."""
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
    """Most loop steps a ray can take: every node of the flattened tree popped, climbed
    out of and pushed from a climb at most once each, every primitive tested once, + 1
    (as :func:`jaxbvh.rays.traversal.max_steps`)."""
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
    return int(3 * (top + obj_nodes[used].sum()) + obj_prims[used].sum() + 1)


def _ray(tl, origin, direction, t_max, i) -> Ray:
    """Ray ``i`` of ``origin``, ``direction`` [R, 3], ``t_max`` [R] through the
    two-level tree ``tl`` (scene frame): its hooks and root test.

    Stack entries are ``(reference, tag)``: a reference below ``n_top`` is a top-level
    node (tag -1), ``n_top + f`` is forest node ``f`` entered through the top-level leaf
    ``tag`` (its BRef names the instance, hence the frame, and the forest node the leaf
    stands for: the way back up, for the parent-link climb).
    """
    dtype = tl.top.lo.dtype
    inst = tl.instances
    n_inst = inst.object.shape[0]
    # one extra map, the identity, for the top level (instance -1)
    eye = jnp.zeros((1, 3, 4), dtype).at[0, :, :3].set(jnp.eye(3, dtype=dtype))
    to_object = jnp.concatenate([inst.to_object, eye])
    o = origin[i].astype(dtype)
    d = direction[i].astype(dtype)
    hi_t = t_max[i].astype(dtype)
    t_min = jnp.zeros((), dtype)

    def ray_in(k):
        """The ray in instance ``k``'s object frame (``k = -1``: the scene frame)."""
        m = to_object[jnp.where(k >= 0, k, n_inst)]
        # written out, not ``m[:, :3] @ o``: one summation order, the native engine's and the twin's
        return (m[:, 0] * o[0] + m[:, 1] * o[1] + m[:, 2] * o[2] + m[:, 3],
                m[:, 0] * d[0] + m[:, 1] * d[1] + m[:, 2] * d[2])

    def primitive(slot, leaf):
        return _primitive(tl, ray_in, slot, leaf)

    def node(ref, leaf, entry, t_far):
        return _expand(tl, ray_in, ref, leaf, t_min, t_far)

    top = tl.top
    root_hit, root_entry = slab(top.lo[top.root], top.hi[top.root], o, inverse_direction(d), t_min, hi_t)
    return Ray(Hooks(primitive, node), top.root, root_hit, root_entry, t_min, hi_t)


def _bref_of(tl, leaf):
    """The BRef of top-level leaf ``leaf`` (-1: none, read as leaf 0)."""
    top = tl.top
    return top.prim_index[top.prim_start[jnp.maximum(leaf, 0)]]


def _primitive(tl, ray_in, slot, leaf):
    """The ``primitive`` hook: forest ``prim_index`` slot ``slot`` reached through the
    top-level leaf ``leaf`` (its instance's frame); returns ``(t, u, v, world triangle id)``."""
    f = tl.forest
    k = tl.bref_instance[_bref_of(tl, leaf)]
    o_k, d_k = ray_in(k)
    g = f.prim_index[jnp.minimum(slot, f.prim_index.shape[0] - 1)]
    tri = f.triangles[jnp.maximum(g, 0)]
    t, u, v = moller_trumbore(tri[0], tri[1], tri[2], o_k, d_k)
    return t, u, v, g + tl.instances.prim_shift[k]


def _expand(tl, ray_in, ref, leaf, t_min, t_far) -> Node:
    """The ``node`` hook: a top-level node (tested with the scene ray), or a forest node
    reached through the top-level leaf ``leaf`` (tested in its instance's object frame).
    A top-level leaf stands for the forest node of its BRef under the BRef's instance.
    The parent: a top-level node's (tag -1); a forest node's, or the top-level leaf it
    was entered through when its parent is the node that leaf stands for."""
    top, f = tl.top, tl.forest
    n_top = top.left.shape[0]
    is_top = ref < n_top
    tid = jnp.where(is_top, ref, 0)
    top_leaf = is_top & (top.prim_count[tid] > 0)
    entered = jnp.where(top_leaf, tid, leaf)  # the top-level leaf this forest node is reached through
    b = _bref_of(tl, entered)
    fid = jnp.where(is_top, jnp.where(top_leaf, tl.bref_node[b], 0), ref - n_top)
    in_forest = ~is_top | top_leaf
    k = jnp.where(in_forest, tl.bref_instance[b], -1)
    fid = jnp.maximum(fid, 0)
    f_count = f.prim_count[fid]

    kids = jnp.where(in_forest, jnp.stack([f.left[fid], f.right[fid]]),
                     jnp.stack([top.left[tid], top.right[tid]]))
    real = kids >= 0
    safe = jnp.maximum(kids, 0)
    box_lo = jnp.where(in_forest, f.lo[jnp.minimum(safe, f.lo.shape[0] - 1)],
                       top.lo[jnp.minimum(safe, n_top - 1)])
    box_hi = jnp.where(in_forest, f.hi[jnp.minimum(safe, f.hi.shape[0] - 1)],
                       top.hi[jnp.minimum(safe, n_top - 1)])
    o_n, d_n = ray_in(k)
    kid_hit, kid_entry = slab(box_lo, box_hi, o_n, inverse_direction(d_n)[None, :], t_min, t_far)
    up = f.parent[fid]
    back_to_top = is_top | (up == tl.bref_node[b]) | (up < 0)
    parent = jnp.where(is_top, top.parent[tid], jnp.where(back_to_top, entered, n_top + up))
    return Node(is_leaf=in_forest & (f_count > 0), leaf_start=f.prim_start[fid], leaf_count=f_count,
                leaf_tag=entered, assumed=None, kids=jnp.where(in_forest, kids + n_top, kids),
                kid_tags=jnp.where(in_forest, entered, -1), kid_hit=kid_hit & real, kid_entry=kid_entry,
                tested=real, split=jnp.where(in_forest, f.axis[fid], top.axis[tid]), direction=d_n,
                parent=parent, parent_tag=jnp.where(back_to_top, -1, entered))


@partial(stored_jit, static_argnames=("mode", "capacity", "lanes", "leaf_width"))
def trace_batch(tl, origin, direction, t_max, max_steps, *, mode="closest", capacity, lanes=None,
                leaf_width=LEAF_WIDTH):
    """Closest (``mode="closest"``) or any hits (``"any"``) of rays ``origin``,
    ``direction`` [R, 3] (scene frame) through ``tl``: the JAX engine, usable inside
    ``jit`` / ``vmap`` (the tree a pytree argument).

    ``t_max`` [R]; ``max_steps``: loop bound (:func:`step_bound`); ``capacity``: static
    stack size (:data:`~jaxbvh.rays.stack_walk.STACK` by default in :func:`trace`:
    a spilled stack climbs by parent links, so one program serves every depth). Returns :class:`~jaxbvh.rays.traversal.Hits` (``step_limit``:
    the ray was still busy at the bound).
    """
    if mode not in MODES:
        raise ValueError(f"two-level mode must be one of {MODES}, got {mode!r}")
    r = origin.shape[0]
    return walk_rays(partial(_ray, tl, origin, direction, t_max), r, mode=mode, capacity=capacity,
                     max_hits=0, step_limit=max_steps, lanes=lanes_for(r, capacity, lanes),
                     leaf_width=leaf_width, tagged=True, climbs=True)


def trace(tl, origin, direction, *, mode: str = "closest", batch: int = 256, capacity: int | None = None,
          engine: str = engines.DEFAULT_ENGINE) -> Hits:
    """Closest or any hit of every ray through the two-level tree (module docstring); NumPy :class:`Hits`.

    ``origin``, ``direction``: [R, 3] float, in the scene frame (``Mesh.frame``); ``t`` in
    units of ``|direction|``, ``prim`` a world triangle id (-1: miss). ``mode``:
    ``"closest"`` or ``"any"`` (stops at the first hit found). ``capacity``: stack
    entries per ray (:data:`~jaxbvh.rays.stack_walk.STACK`: whatever the depth; a ray whose
    stack spills climbs by parent links, with the same hits and primitive tests).
    ``batch``: rays per jitted call (JAX engine). ``engine``: ``"auto"``, ``"jax"`` or
    ``"native"`` (:mod:`jaxbvh.twolevel.native`: the same walk, hits and counters,
    compiled by numba for the CPU; ``"auto"`` picks it where it can run,
    :func:`jaxbvh.native.choose`). Raises
    :class:`~jaxbvh.tree.validate.InvalidTreeError` if a ray passes its step bound (a
    malformed tree).
    """
    if mode not in MODES:
        raise ValueError(f"two-level mode must be one of {MODES}, got {mode!r}")
    engine = engines.choose(engine, tl, origin, direction)
    origin, direction = check_rays(origin, direction)
    capacity = STACK if capacity is None else int(capacity)
    if capacity < 2:
        raise ValueError(f"capacity {capacity} is below the tree's 2 children per node")
    bound = step_bound(tl)
    if engine == "native":
        dtype = np.dtype(jax.dtypes.canonicalize_dtype(np.asarray(tl.top.lo).dtype))
        hits = twolevel_native.trace(tl, origin, direction, np.full(origin.shape[0], np.inf, dtype), dtype=dtype,
                                     mode=mode, capacity=capacity, step_limit=bound)
    else:
        jtl = to_jax(tl)

        def run(o, d, _, t_max):
            return trace_batch(jtl, o, d, t_max, np.int32(bound), mode=mode, capacity=capacity)

        hits = in_batches(run, origin, direction, 0.0, np.inf, batch=batch, dtype=np.dtype(jtl.top.lo.dtype))
    if hits.step_limit.any():
        bad = np.flatnonzero(hits.step_limit)
        raise InvalidTreeError([f"two-level traversal passed its bound of {int(bound)} steps on "
                                f"{bad.size} ray(s) (first: {bad[:5].tolist()}): the tree is malformed"])
    return hits


def closest_hit(tl, origin, direction, **kwargs) -> Hits:
    """Closest hit of every ray (:func:`trace` with ``mode="closest"``)."""
    return trace(tl, origin, direction, mode="closest", **kwargs)


def any_hit(tl, origin, direction, **kwargs) -> Hits:
    """Some hit of every ray, the first the walk finds (:func:`trace` with ``mode="any"``):
    shadow rays."""
    return trace(tl, origin, direction, mode="any", **kwargs)


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


@stored_jit
def _brute_chunk(tri, origin, direction):
    t, _, _ = jax.vmap(lambda o, d: moller_trumbore(tri[:, 0], tri[:, 1], tri[:, 2], o, d))(origin, direction)
    t = jnp.where(t > 0, t, jnp.inf)
    best = jnp.min(t, axis=1)
    prim = jnp.argmax(t == best[:, None], axis=1).astype(jnp.int32)
    return best, jnp.where(best < jnp.inf, prim, -1)
