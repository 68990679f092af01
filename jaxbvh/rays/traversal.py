"""Ray traversal of binary and wide BVHs, counting box and primitive tests (jitted).

Each ray walks the tree with a short stack and, when that spills, parent links. The loop
(:mod:`jaxbvh.rays.stack_walk`, shared with the two-level traversal; this module gives it
the tree and the primitives) steps ``lanes`` rays at once, and a lane whose ray ended
takes the next ray of the call (a wavefront: lanes do not idle behind the slowest ray);
the stacks are read and written only at their tops, so a step costs the same for any
stack capacity, and the capacity is a constant, so a lane's state and the compiled
program are the same for any depth. The tree is read in a packed layout (a node's
children, parent and child boxes in one row, a leaf's triangles side by side). Every
ray's walk does exactly one of three things per step:

* **node step** — pop ``(node, entry)``; if ``entry <= t_best`` the node is *visited*:
  a leaf opens its run of primitives, an interior node tests the boxes of all its real
  children (one *box test* each) and pushes the children it hits, nearest visited first;
* **primitive step** — test the next ``leaf_width`` primitives of the open leaf together
  (one *primitive test* each; any-hit mode counts those up to the first hit, as one by
  one would);
* **climb step** — only after the stack spilled (below): from the node last popped, test
  the boxes of its parent's children again (box tests) and push the next child in
  visiting order that the ray enters, or move up to the parent.

The root box is tested once before the loop. So for a binary tree
``box_tests = 1 + 2 * interior nodes visited``, and ``nodes_visited`` counts interior
nodes and leaves that passed the ``entry <= t_best`` check (a popped node whose entry
lies beyond the closest hit found since it was pushed is skipped, not counted).

Visiting order (front to back):

* binary nodes with a split axis (``tree.axis[n] >= 0``): the left (lower) child first
  when ``direction[axis] >= 0``, else the right child first — no distance needed;
* every other node (loaded trees have ``axis == -1``; all wide nodes): children in
  increasing box entry distance; ties go to the lower child slot.

Stack. ``capacity`` entries per ray, static, :data:`~jaxbvh.rays.stack_walk.STACK` by
default (at least ``k``). ``stack_capacity(tree) = (k - 1) * height + 1`` entries always
suffice (a node step pops one entry and pushes at most ``k``); with fewer, a push that
does not fit drops the oldest entries and, once the stack has run empty, the ray climbs
by the tree's ``parent`` links to what they held (:mod:`jaxbvh.rays.stack_walk`): the
hits, ``nodes_visited``, ``leaves_visited``, ``prim_tests`` and the all-hits lists are
those of a stack of ``stack_capacity`` entries (with skip flags, visits can only grow:
see the walk's docstring); ``box_tests`` add the boxes a climb tests again (the children
of every parent it passes). A balanced tree under the default never
climbs. ``stack_overflow`` stays False here (it reports a spill in walks without parent
links, :mod:`jaxbvh.twolevel.traversal`); the drivers raise on it unless
``allow_overflow=True``.

Step bound. In a valid tree a ray pops every node at most once, tests every primitive
slot at most once, and climbs up out of a node or pushes a node from a climb at most
once each, so a ray is cut off after ``3 N + P + 1`` steps (node pops, primitive tests
and climb steps; node and ``prim_index`` capacities, static): no tree file, however
broken (a node listed as its own child, a cycle, a wrong parent), can make it run
forever. A ray that reaches the bound sets ``step_limit``; the drivers raise
:class:`~jaxbvh.tree.validate.InvalidTreeError` for it (the commands also check every
tree they read before tracing it).

Primitive test. :func:`intersect_triangle` is Möller–Trumbore, two-sided, in the tree's
float dtype. It is not watertight: a ray through a shared edge can in rare cases slip
between both triangles (or hit both); we accept that for speed and simplicity, and it is
part of the tolerance when comparing with Embree. Boxes are tested with the robust slab
test (exit distance scaled by ``1 + 2 gamma(3)``, Ize 2013), so a box is never missed
because of rounding, and a zero direction component is replaced by a huge finite inverse
(no ``0 * inf``).

Hits. Ray interval is the open ``(t_min, t_max)``. Closest hit: smallest ``t``; equal
``t`` goes to the lower primitive id, so the answer does not depend on the visiting
order. Any hit: stops at the first hit (counters then depend on the order). All hits:
every hit is counted; the first ``max_hits`` in visiting order are listed, and
``hits_overflow`` says the list was too short.

Skip flags (Susano Pinto 2010, section 4.3). ``skip`` [N] bool, optional: a flagged
node's box is not tested, it is assumed hit (entered where its parent was; in distance
order it comes before its siblings; a climb enters it at ``t_min``). The node is
pushed and popped like any other but counts neither as a box test nor as a visited
node, so a binary tree with the nodes a collapse removed flagged
(:attr:`jaxbvh.collapse.CollapseResult.skip`) makes exactly the box tests, primitive
tests and visits of the wide tree, ray by ray, for all-hits queries (closest and any
hit visit in another order, so their counts may differ; their hits do not). The root's
box is always tested.

Engines. :func:`trace` runs this walk as a JAX program (``engine="jax"``) or as the same
walk compiled by numba for the CPU (``engine="native"``, :mod:`jaxbvh.rays.native`: the
same hits and counters ray by ray, many times the rays per CPU second);
``engine="auto"`` picks native for concrete arrays on the CPU
(:func:`jaxbvh.native.choose`).

Plugging in other primitives. The traversal never looks at triangles itself: it calls
``intersect(prims, prim_id, origin, direction) -> (t, u, v)`` (``t = inf`` for a miss)
with ``prims`` any pytree passed through ``jit``. A two-level tree needs more than a
primitive test (the ray changes frame below a top-level leaf, the stack carries the
instance): :mod:`jaxbvh.twolevel.traversal` gives the shared loop its own hooks.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import INV_BIG, robust_factor
from jaxbvh.program_store import stored_jit
from jaxbvh import native as engines
from jaxbvh.rays import native
from jaxbvh.rays.stack_walk import I32, LEAF_WIDTH, MODES, STACK, Hits, Hooks, Node, Ray, lanes_for, walk_rays
from jaxbvh.tree.layout import BVH, depth, to_jax
from jaxbvh.tree.validate import InvalidTreeError

BATCH = 16384
"""Rays per jitted call (the last call padded): lanes refill from the call's rays
(:func:`~jaxbvh.rays.stack_walk.walk_rays`), so a big call keeps them busy; the padding
rays end at once."""


# ----------------------------------------------------------------------------------
# Ray-box and ray-triangle tests
# ----------------------------------------------------------------------------------


def inverse_direction(direction):
    """``1 / direction`` with ``±INV_BIG`` for zero components (sign of the zero)."""
    big = jnp.asarray(INV_BIG, direction.dtype)
    safe = jnp.where(direction == 0, 1, direction)
    return jnp.where(direction == 0, jnp.copysign(big, direction), 1 / safe)


def slab(lo, hi, origin, inv_dir, t_min, t_max):
    """Robust slab test of boxes ``lo``, ``hi`` [..., 3] against one ray.

    Returns ``(hit, entry)`` [...]: whether the ray meets the box within
    ``[t_min, t_max]`` and where it enters (``max(near, t_min)``).
    """
    t0 = (lo - origin) * inv_dir
    t1 = (hi - origin) * inv_dir
    near = jnp.max(jnp.minimum(t0, t1), axis=-1)
    far = jnp.min(jnp.maximum(t0, t1), axis=-1) * robust_factor(lo.dtype)
    entry = jnp.maximum(near, t_min)
    return entry <= jnp.minimum(far, t_max), entry


def _cross(a, b):
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def moller_trumbore(v0, v1, v2, origin, direction):
    """Two-sided Möller–Trumbore test; corners [..., 3]. Returns ``(t, u, v)``.

    ``t = inf`` where the ray's line misses the triangle, is parallel to it, or the
    triangle is degenerate; otherwise ``t`` may be negative (behind the origin).
    """
    return moller_trumbore_edges(v0, v1 - v0, v2 - v0, origin, direction)


def moller_trumbore_edges(v0, e1, e2, origin, direction):
    """:func:`moller_trumbore` of the triangle with corner ``v0`` and edges ``e1 = v1 - v0``,
    ``e2 = v2 - v0`` [..., 3] (the packed layout stores the edges: the same numbers)."""
    p = _cross(direction, e2)
    det = _dot(e1, p)
    ok = det != 0
    inv_det = 1 / jnp.where(ok, det, 1)
    s = origin - v0
    u = _dot(s, p) * inv_det
    q = _cross(s, e1)
    v = _dot(direction, q) * inv_det
    t = _dot(e2, q) * inv_det
    hit = ok & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1)
    return jnp.where(hit, t, jnp.inf), u, v


def intersect_triangle(triangles, prim, origin, direction):
    """Leaf test for a triangle mesh: ``triangles`` [T, 3, 3] (tree frame), one id."""
    tri = triangles[prim]
    return moller_trumbore(tri[0], tri[1], tri[2], origin, direction)


# ----------------------------------------------------------------------------------
# One ray
# ----------------------------------------------------------------------------------


def stack_capacity(tree) -> int:
    """Stack entries that always suffice: ``(k - 1) * height + 1`` (host, static)."""
    height = int(np.max(depth(tree)))
    return (arity(tree) - 1) * max(height, 0) + 1


def max_steps(tree) -> int:
    """Loop steps one ray may take: ``3 N + P + 1`` (module docstring; static shapes)."""
    return 3 * int(tree.prim_count.shape[0]) + int(tree.prim_index.shape[0]) + 1


def arity(tree) -> int:
    """Child slots per node, ``k`` (host, static)."""
    return 2 if isinstance(tree, BVH) else int(np.asarray(tree.child).shape[1])


class Packed(NamedTuple):
    """The arrays the traversal reads, packed so that a step makes one read per node and
    one per leaf run.

    A popped node reads one row of ``node``: its children's boxes, then its children,
    ``prim_start``, ``prim_count``, split axis and parent, stored bit for bit in the
    float dtype (``int32`` in ``float32``, ``int64`` in ``float64``; :func:`node_fields`
    reads them back); a climb reads its parent there too. A leaf's triangles lie in
    ``prim_index`` order, one row per slot (first corner, the two edges from it, the
    primitive id stored bit for bit), with ``leaf_width - 1`` rows of padding so that
    any run of ``leaf_width`` slots from a real slot is one contiguous read.
    """

    node: Any      # float [N, 6 k + k + 4]: child lo, hi (k x 6; garbage where the child is -1), then meta
    slot_tri: Any  # float [P + leaf_width - 1, 10] v0, v1 - v0, v2 - v0, prim id; or None (another intersector)


def _int_view(dtype):
    """The integer type as wide as float ``dtype`` (the meta fields' bit-for-bit storage)."""
    return jnp.int32 if jnp.dtype(dtype).itemsize == 4 else jnp.int64


def pack(tree, prims, intersect, leaf_width: int = 1) -> Packed:
    """:class:`Packed` arrays of ``tree`` (traced inside the jitted call: O(N k + P))."""
    kids = tree.child
    k = kids.shape[1]
    dtype = tree.lo.dtype
    safe = jnp.maximum(kids, 0)
    axis = tree.axis if isinstance(tree, BVH) else jnp.full(kids.shape[0], -1, I32)
    meta = jnp.concatenate([kids, tree.prim_start[:, None], tree.prim_count[:, None], axis[:, None],
                            tree.parent[:, None]], axis=1).astype(_int_view(dtype))
    kid_box = jnp.concatenate([tree.lo[safe], tree.hi[safe]], axis=-1).reshape(-1, 6 * k)
    node = jnp.concatenate([kid_box, jax.lax.bitcast_convert_type(meta, dtype)], axis=1)
    slot_tri = None
    if intersect is intersect_triangle:
        prim = jnp.clip(tree.prim_index, 0, prims.shape[0] - 1)
        tri = prims[prim]  # in the triangles' own dtype, as ``intersect_triangle`` reads them
        ids = jax.lax.bitcast_convert_type(tree.prim_index.astype(_int_view(tri.dtype)), tri.dtype)
        rows = jnp.concatenate([tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], ids[:, None]], axis=1)
        slot_tri = jnp.pad(rows, ((0, max(int(leaf_width), 1) - 1), (0, 0)))
    return Packed(node, slot_tri)


def node_fields(packed: Packed, ref, k: int):
    """Node ``ref``'s row of ``packed.node``: ``(lo [k, 3], hi [k, 3], kids [k], prim_start,
    prim_count, split axis, parent)`` (ints int32)."""
    row = packed.node[ref]
    box = row[:6 * k].reshape(k, 6)
    meta = jax.lax.bitcast_convert_type(row[6 * k:], _int_view(row.dtype)).astype(I32)
    return box[:, :3], box[:, 3:], meta[:k], meta[k], meta[k + 1], meta[k + 2], meta[k + 3]


def _ray(tree, packed: Packed, prims, skip, origin, direction, t_min, t_max, i, *, intersect) -> Ray:
    """Ray ``i`` of ``origin``, ``direction`` [R, 3], ``t_min``, ``t_max`` [R] through
    ``tree``: its hooks and root test (:class:`~jaxbvh.rays.stack_walk.Ray`)."""
    dtype = tree.lo.dtype
    o = origin[i].astype(dtype)
    d = direction[i].astype(dtype)
    lo_t = t_min[i]
    hi_t = t_max[i]
    inv_dir = inverse_direction(d)
    root = tree.root
    root_hit, root_entry = slab(tree.lo[root], tree.hi[root], o, inv_dir, lo_t, hi_t)
    n_slots = tree.prim_index.shape[0]
    def apart(index):
        # the index made apart from the read (XLA never fuses a reduce into its user):
        # left to XLA, the cheap ops that make it are fused into the read and recomputed
        # for every element of the row (measured: the two reads took a third of a step,
        # bench/results/ray_anatomy.md). max(index, -1) is the index (indices are >= 0).
        return jnp.max(jnp.stack([index, jnp.full_like(index, -1)]), axis=0)

    def primitive(slot, _):
        slot = jnp.minimum(slot, n_slots - 1)
        prim = tree.prim_index[slot]
        t, u, v = intersect(prims, prim, o, d)
        return t, u, v, prim

    def run(start, _, width):
        # one contiguous read of the run's rows (padded: a run from a real slot fits)
        rows = jax.lax.dynamic_slice_in_dim(packed.slot_tri, apart(start), width, axis=0)
        t, u, v = moller_trumbore_edges(rows[:, 0:3], rows[:, 3:6], rows[:, 6:9], o, d)
        prim = jax.lax.bitcast_convert_type(rows[:, 9], _int_view(rows.dtype)).astype(I32)
        return t, u, v, prim

    def node(ref, _, entry, t_far):
        return _expand(packed, skip, apart(ref), entry, o, d, inv_dir, lo_t, t_far, binary=isinstance(tree, BVH))

    return Ray(Hooks(primitive, node, run if packed.slot_tri is not None else None), root, root_hit,
               root_entry, lo_t, hi_t)


def _expand(packed: Packed, skip, ref, entry, origin, direction, inv_dir, t_min, t_far, *, binary) -> Node:
    """The ``node`` hook of a binary or wide tree: node ``ref`` entered at ``entry``.

    With skip flags a flagged child is not tested but assumed hit, entered where this
    node was; a flagged node's own visit is not counted.
    """
    k = 2 if binary else (packed.node.shape[1] - 4) // 7
    lo, hi, kids, start, count, split, parent = node_fields(packed, ref, k)
    real = kids >= 0
    kid_hit, kid_entry = slab(lo, hi, origin, inv_dir[None, :], t_min, t_far)
    tested = real
    assumed = None
    if skip is not None:
        assumed = skip[ref]
        skipped = real & skip[jnp.maximum(kids, 0)]
        kid_hit = kid_hit | skipped
        kid_entry = jnp.where(skipped, entry, kid_entry)
        tested = real & ~skipped
    return Node(is_leaf=count > 0, leaf_start=start, leaf_count=count, leaf_tag=None,
                assumed=assumed, kids=kids, kid_tags=None, kid_hit=kid_hit & real,
                kid_entry=kid_entry, tested=tested, split=split if binary else None,
                direction=direction, parent=parent)


@partial(stored_jit, static_argnames=("intersect", "mode", "capacity", "max_hits", "lanes", "leaf_width"))
def trace_batch(tree, prims, origin, direction, t_min, t_max, skip=None, *,
                intersect=intersect_triangle, mode="closest", capacity=STACK, max_hits=16, lanes=None,
                leaf_width=LEAF_WIDTH):
    """Trace rays ``origin``, ``direction`` [R, 3] (tree frame) through ``tree``; jitted.

    ``prims``: what ``intersect`` reads (``triangles`` [T, 3, 3] for the default);
    ``t_min``, ``t_max``: scalars or [R]; ``mode``: one of :data:`MODES`;
    ``capacity``: static stack size (at least ``k``); ``max_hits``: list length for ``mode="all"``;
    ``skip``: optional [N] bool flags (module docstring); ``lanes``: rays in flight
    (:func:`~jaxbvh.rays.stack_walk.lanes_for`); ``leaf_width``: leaf slots tested per
    step. Returns :class:`Hits` with arrays [R]. The drivers below batch, pad and check.
    """
    r = origin.shape[0]
    dtype = tree.lo.dtype
    t_min = jnp.broadcast_to(jnp.asarray(t_min, dtype), (r,))
    t_max = jnp.broadcast_to(jnp.asarray(t_max, dtype), (r,))
    ray = partial(_ray, tree, pack(tree, prims, intersect, leaf_width), prims, skip, origin, direction, t_min, t_max,
                  intersect=intersect)
    return walk_rays(ray, r, mode=mode, capacity=capacity, max_hits=max_hits,
                     step_limit=max_steps(tree), lanes=lanes_for(r, capacity, lanes),
                     leaf_width=leaf_width)


# ----------------------------------------------------------------------------------
# Drivers: batching, padding, overflow check
# ----------------------------------------------------------------------------------


def engine_of(engine: str, tree, prims, origin, direction, *, intersect=intersect_triangle) -> str:
    """The engine :func:`trace` runs for these arguments: :func:`jaxbvh.native.choose`, the
    native engine only for the triangle test (``intersect``)."""
    return engines.choose(engine, tree, prims, origin, direction, supported=intersect is intersect_triangle)


def trace(tree, prims, origin, direction, *, mode: str = "closest", t_min=0.0, t_max=np.inf,
          intersect: Callable = intersect_triangle, capacity: int | None = None,
          max_hits: int = 16, batch: int = BATCH, allow_overflow: bool = False, skip=None,
          lanes: int | None = None, leaf_width: int = LEAF_WIDTH, on_batch: Callable[[int], None] | None = None,
          engine: str = engines.DEFAULT_ENGINE) -> Hits:
    """Trace any number of rays in batches of ``batch``; returns :class:`Hits` (NumPy).

    ``tree``: :class:`~jaxbvh.tree.layout.BVH` or :class:`~jaxbvh.tree.layout.WideBVH`;
    ``prims``: the primitives ``intersect`` reads (triangles [T, 3, 3] in the tree's
    frame for the default); ``origin``, ``direction``: [R, 3] in the tree's frame
    (directions need not be unit; ``t`` is in units of ``|direction|``).
    ``capacity``: stack entries per ray, :data:`~jaxbvh.rays.stack_walk.STACK` by default,
    at least ``k`` (module docstring, "Stack"); ``skip``: optional [N] bool per-node
    "assume hit" flags (module docstring, "Skip flags"). The last batch is padded so every
    batch has the same shape (one compile). Within a batch ``lanes`` rays are in flight
    and a lane whose ray ended takes the next one (:data:`BATCH`); ``leaf_width``: leaf
    slots tested per step.
    ``on_batch(n)`` (optional) is called after each batch with its number of rays (a
    progress bar). Raises ``RuntimeError`` on stack overflow unless ``allow_overflow``, and
    :class:`~jaxbvh.tree.validate.InvalidTreeError` when a ray reaches the step bound.
    ``engine``: ``"auto"``, ``"jax"`` or ``"native"`` (:mod:`jaxbvh.rays.native`: the same
    walk, hits and counters compiled by numba for the CPU; ``"auto"`` picks it where it can
    run, :func:`jaxbvh.native.choose`).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    engine = engine_of(engine, tree, prims, origin, direction, intersect=intersect)
    origin, direction = check_rays(origin, direction)
    capacity = STACK if capacity is None else int(capacity)
    if capacity < arity(tree):
        raise ValueError(f"capacity {capacity} is below the tree's {arity(tree)} children per node")
    if engine == "native":
        dtype = np.dtype(jax.dtypes.canonicalize_dtype(np.asarray(tree.lo).dtype))
        hits = native.trace(tree, prims, origin, direction, t_min, t_max, dtype=dtype, mode=mode,
                            capacity=capacity, max_hits=max_hits, step_limit=max_steps(tree),
                            skip=None if skip is None else np.asarray(_check_skip(skip, tree.prim_count.shape[0])),
                            leaf_width=leaf_width, batch=batch if on_batch is not None else None,
                            on_batch=on_batch)
    else:
        jtree = to_jax(tree)
        dtype = np.dtype(jtree.lo.dtype)
        skip = _check_skip(skip, jtree.prim_count.shape[0])
        jprims = jax.tree_util.tree_map(jnp.asarray, prims)

        def run(o, d, lo_t, hi_t):
            return trace_batch(jtree, jprims, o, d, lo_t, hi_t, skip, intersect=intersect, mode=mode,
                               capacity=capacity, max_hits=max_hits, lanes=lanes, leaf_width=leaf_width)

        hits = in_batches(run, origin, direction, t_min, t_max, batch=batch, dtype=dtype, on_batch=on_batch)
    if hits.step_limit.any():
        bad = np.flatnonzero(hits.step_limit)
        raise InvalidTreeError([f"traversal of {bad.size} ray(s) (first: {bad[:5].tolist()}) did not end "
                                f"within {max_steps(tree)} steps: the tree has a cycle or a shared node"])
    if not allow_overflow and hits.stack_overflow.any():
        bad = np.flatnonzero(hits.stack_overflow)
        raise RuntimeError(f"traversal stack of {capacity} entries overflowed on {bad.size} "
                           f"ray(s) (first: {bad[:5].tolist()}); pass a larger capacity")
    return hits


def check_rays(origin, direction):
    """``origin``, ``direction`` as NumPy arrays; ``ValueError`` unless both are [R, 3]."""
    origin = np.asarray(origin)
    direction = np.asarray(direction)
    if origin.ndim != 2 or origin.shape[1] != 3 or direction.shape != origin.shape:
        raise ValueError(f"origin and direction must both be [R, 3], got {origin.shape} "
                         f"and {direction.shape}")
    return origin, direction


def _check_skip(skip, nodes):
    """Skip flags as a JAX bool [nodes] array (None stays None); ``ValueError`` on a bad shape."""
    if skip is None:
        return None
    skip = np.asarray(skip, bool)
    if skip.shape != (nodes,):
        raise ValueError(f"skip must be bool [{nodes}] (one flag per node), got shape {skip.shape}")
    return jnp.asarray(skip)


def in_batches(run: Callable, origin, direction, t_min, t_max, *, batch: int, dtype,
               on_batch: Callable[[int], None] | None = None) -> Hits:
    """``run(origin, direction, t_min, t_max)`` on batches of ``batch`` rays; NumPy :class:`Hits` [R].

    ``origin``, ``direction``: NumPy [R, 3]; ``t_min``, ``t_max``: scalars or [R]. The
    last batch is padded with rays of an empty interval (``t_max = -1``: they stop at
    once), so every call has the same shapes (one compile); no rays make one padded
    call of one ray. ``run`` returns :class:`Hits` of the batch; the padding is cut off.
    ``on_batch(n)``, if given, is called after each batch with its ``n`` rays.
    """
    r = origin.shape[0]
    batch = max(1, min(batch, r))
    t_min = np.broadcast_to(np.asarray(t_min, dtype), (r,))
    t_max = np.broadcast_to(np.asarray(t_max, dtype), (r,))
    pieces = []
    for start in range(0, max(r, 1), batch):
        stop = min(start + batch, r)
        n = stop - start
        o = np.zeros((batch, 3), dtype)
        d = np.zeros((batch, 3), dtype)
        d[:, 0] = 1
        lo_t = np.zeros(batch, dtype)
        hi_t = np.full(batch, -1, dtype)
        o[:n], d[:n], lo_t[:n], hi_t[:n] = origin[start:stop], direction[start:stop], \
            t_min[start:stop], t_max[start:stop]
        pieces.append((n, run(o, d, lo_t, hi_t)))
        if on_batch is not None:
            jax.block_until_ready(pieces[-1][1])  # count a batch when it is done, not queued
            on_batch(n)
    return jax.tree_util.tree_map(
        lambda *parts: np.concatenate([np.asarray(p)[:n] for (n, _), p in zip(pieces, parts)]),
        *[h for _, h in pieces])


def closest_hit(tree, triangles, origin, direction, **kwargs) -> Hits:
    """Closest hit of every ray (:func:`trace` with ``mode="closest"``): ``triangles``
    [T, 3, 3], ``origin``, ``direction`` [R, 3] in the tree's frame; :class:`Hits` of [R]."""
    return trace(tree, triangles, origin, direction, mode="closest", **kwargs)


def any_hit(tree, triangles, origin, direction, **kwargs) -> Hits:
    """First hit found for every ray, e.g. for shadow rays (``mode="any"``); arrays as
    :func:`closest_hit`."""
    return trace(tree, triangles, origin, direction, mode="any", **kwargs)


def all_hits(tree, triangles, origin, direction, *, max_hits: int = 16, **kwargs) -> Hits:
    """Every hit along every ray: ``hit_count`` [R] and the first ``max_hits`` (``mode="all"``);
    arrays as :func:`closest_hit`."""
    return trace(tree, triangles, origin, direction, mode="all", max_hits=max_hits, **kwargs)
