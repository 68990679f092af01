"""Spatial-split BVH (SBVH; Stich, Friedrich & Dietrich 2009), one level at a time (jitted).

A triangle that straddles a split plane can be *split*: each child keeps a reference to
it whose box is the box of the triangle's piece on its side. Trees get fewer overlapping
boxes where triangles are long, thin or large (CAD, architecture), at the price of more
references than triangles. The tree is an ordinary :class:`~jaxbvh.tree.layout.BVH`
whose ``prim_index`` may name a triangle in several leaves (a tree *with references*;
``jaxbvh.validate(..., references=True)`` checks it).

Entry. Spatial splits need the triangles, not only their boxes: :func:`build_sbvh` takes
``triangles`` [n, 3, 3], and ``jaxbvh.build(lo, hi, method="sbvh", triangles=tri)``
passes them on (``lo``, ``hi`` must be their boxes).

Rules (the NumPy twin :mod:`jaxbvh.builders.sbvh_reference` keeps the same ones; planes,
bins and clipping are written once in :mod:`jaxbvh.builders.sbvh_rules`). For every node,
over its references (box, triangle):

1. **Object split**: the binned builder's rule over the reference boxes' centres
   (:mod:`jaxbvh.builders.topdown`): ``B`` bins per axis over the centre bounds, the
   planes between them priced ``A_L N_L + A_R N_R``; least cost, ties (within
   ``TIE_TOLERANCE``) to the lowest axis, then the lowest plane.
2. **Spatial split**, tried only when the object split's two boxes overlap by more than
   ``alpha`` times the root's half-area (areas on the scene's scale): ``b`` equal bins
   of the node's box per axis, ``b`` = ``S`` (``spatial_bins``, default 4) for a node of
   at least ``S`` references, fewer for fewer but at least 4
   (:func:`jaxbvh.builders.sbvh_rules.spatial_bins`); a reference enters
   the bin of its box's low corner and leaves by the bin of its high corner; each bin's
   box is estimated from the reference's triangle corners and the crossings of the inner
   planes its box spans, clamped to the reference's box. Plane ``k`` (after bin ``k``)
   has ``N_L`` = entries at or before
   ``k``, ``N_R`` = exits after it, priced on the bins' boxes; the same tie rule. A
   plane is a candidate only if ``N_L < N`` and ``N_R < N`` (``N``: the node's
   references; :func:`jaxbvh.builders.sbvh_rules.separates`): no side gets every
   reference, so every split makes progress (seventh round: at ``max_leaf`` 1 two
   overlapping references were otherwise split spatially again and again, each side
   keeping both). It is taken when its cost times ``1 + TIE_TOLERANCE`` is below the
   object split's (ties go to the object split, which duplicates nothing).
3. **Reference unsplitting** (the paper's Section 4.4): a straddling reference goes
   whole to one side when that is cheaper (``C_1 = A(L + b) N_L + A_R (N_R - 1)``,
   ``C_2 = A_L (N_L - 1) + A(R + b) N_R`` against ``C_split = A_L N_L + A_R N_R``, by
   more than the tie tolerance; the left side wins a tie between them), each priced on
   its own against the split's totals. A straddler whose piece on one side clips to
   nothing (the plane within its box's rounding margin) goes whole to the other side.
   If unsplitting empties a side, it is not done; if a side is empty even then, the
   node takes its object split. Kept-split references are clipped: each side gets the
   box of the triangle's piece in its half-space (the plane included) intersected with
   the reference's box, which therefore always covers the triangle's part in the
   node's region (the rules module explains the rounding margin).
4. **Leaf test** as the other builders: one reference, or at most ``max_leaf`` and
   ``Ci N <= Ct + Ci cost / A`` within the tie tolerance, ``cost`` the split to be taken
   (``N`` counts references). A node whose centres all coincide (no object plane) is
   split into halves by triangle id, and tries no spatial split.
5. **Reference capacity**: ``R`` slots (``reference_capacity`` times ``n``). The nodes of
   a level ask, in node order, for the slots their spatial splits add; a node whose
   request, added to those before it on its level, exceeds the slots free at the
   level's start takes its object split instead, and the result says so
   (``out_of_capacity``).

The engine keeps every reference in a slot of fixed arrays ([R]) with the node that
holds it; one ``while_loop`` step builds one level: per-node reductions over the
references score both kinds of split for all open nodes at once, and a split
reference's second piece takes a fresh slot. The spatial search cuts each live
reference (one of a node that tries a spatial split) into one *piece* per axis and bin
it spans, walks the pieces in chunks of one size (a loop of as many steps as the level
needs) and scatters each piece's estimated box into its (bin, node, axis) cell
(:func:`jaxbvh.builders.sbvh_splits.spatial_split`); the sweeps over the bins are scans
over flat rows. Everything is written coordinate by coordinate on flat arrays: on XLA's CPU
backend, arrays with a trailing axis of 3, cumulative ops and fusions that concatenate
or shift ran 5-10x slower (profiled: they, not the segment reductions, made the first
version 20-40x slower than the binned build). Nodes are numbered level by level, root
0; the loop ends when a level opens no node (at most ``2 R`` levels: every level adds
nodes, and there are fewer than ``2 R``). The per-node arrays of a level have F slots,
F at least its open nodes, and its per-reference arrays M slots, M at least its
references. No result depends on F or M (padding slots hold no reference and no open
node; sums, minima and maxima are exact in any order), so which program a level runs in
changes its time, never the tree. The level is compiled for at most two (F, M)
(:func:`level_programs`), and each level runs in the first that holds it: the *narrow*
program compacts the level's references (a cumsum of the live slots and a scatter, no
sort) into M = :func:`live_slots` < R slots and has F = M / ``NARROW_NODE_DIVISOR``
node slots, so the references of finished leaves and the free slots (R is a capacity
bucket of twice the triangles, the builds use 1.1-1.3 times) cost nothing; the *wide*
one works on all R slots and takes any level. Inputs of at most ``SMALL_STAGE``
reference slots have the wide one only. Compile time, not run time, decides how many:
each program compiles the whole level once, and before the thirteenth round the level
was compiled for a tail and six stages of F (64, 256, 1,024, 2,048, 4,096, ...), about
62 CPU-s of a cold build of spot whose levels then run in 0.2 s; with one program they
run in about 0.4 s (``bench/profile_sbvh_compile.py``). The engine runs the levels from
the host in runs, one run a compiled loop over the levels of one program, each program
compiled on its first use (:func:`engine`): a build whose levels all fit the narrow
program compiles no other. The level is kept cheap to compile (one loop body for the
pieces, scans for the sweeps; not ~70-100 s with unrolled sweeps and a switch over six
piece-buffer sizes, docs/spatial-splits.md).
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders import sbvh_rules as rules
from jaxbvh.builders import sbvh_splits as splits
from jaxbvh.builders.configs import SBVHConfig
from jaxbvh.builders.inputs import narrow_triangles, widen_back
from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale, take, working_dtype
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH, capacity_bucket
from jaxbvh.tree.validate import few_ids

__all__ = ["SBVHBuild", "build_sbvh", "check_triangles", "reference_slots"]


class SBVHBuild(NamedTuple):
    """What :func:`build_sbvh` returns."""

    tree: BVH             # the BVH (JAX arrays; 2 R node slots, R primitive slots)
    references: Any       # int32: references used (>= n; the leaves' primitive total)
    spatial_splits: Any   # int32: nodes split by a spatial split
    out_of_capacity: Any  # bool: some node took an object split for want of reference slots


def check_triangles(triangles) -> np.ndarray:
    """Host-side check of ``triangles`` [n, 3, 3]; returns them as a NumPy float array.

    ``ValueError`` naming the problem: wrong shape, none, NaN or infinite coordinates.
    """
    tri = np.asarray(triangles)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape [n, 3, 3], got {tri.shape}")
    if tri.shape[0] == 0:
        raise ValueError("triangles: none given (n = 0); a BVH needs at least one")
    if not np.issubdtype(tri.dtype, np.floating):
        tri = tri.astype(np.float64)
    bad = ~np.isfinite(tri).all(axis=(1, 2))
    if bad.any():
        ids = np.flatnonzero(bad)
        raise ValueError(f"triangles: {ids.size} of {tri.shape[0]} have NaN or infinite coordinates "
                         f"(first: {few_ids(ids)})")
    return tri


def reference_slots(n: int, config: SBVHConfig, capacity: int | None = None) -> int:
    """Reference slots ``R`` for ``n`` triangles: ``capacity`` if given (at least ``n``),
    else ``ceil(reference_capacity * n)``, rounded up to a capacity bucket when ``pad``."""
    if capacity is not None:
        if capacity < n:
            raise ValueError(f"capacity {capacity} is below the {n} triangles")
        return int(capacity)
    slots = max(n, int(np.ceil(config.reference_capacity * n)))
    return capacity_bucket(slots) if config.pad else slots


def build_sbvh(triangles, config: SBVHConfig | None = None, *, capacity: int | None = None) -> SBVHBuild:
    """SBVH over ``triangles`` [n, 3, 3] (module docstring).

    Pass scene-relative coordinates (``jaxbvh.io.Mesh.local_triangles()``) for float32
    accuracy far from the origin. ``config``: an :class:`SBVHConfig` (default: its
    defaults). ``capacity``: reference slots in place of ``reference_capacity`` (inputs
    of many sizes then share one compiled program). Returns an :class:`SBVHBuild`.
    """
    config = SBVHConfig() if config is None else config
    if not isinstance(config, SBVHConfig):
        raise TypeError(f"config must be an SBVHConfig, got {type(config).__name__}")
    tri = check_triangles(triangles)
    dt = working_dtype(config.dtype, tri.dtype)
    # built on the triangles scaled near extent 1 and rounded, the boxes then moved back
    # and grown by the rounding: every leaf covers the triangles as given (issue 39)
    frame = narrow_triangles(tri, dt)
    tri = frame.triangles
    n = tri.shape[0]
    slots = reference_slots(n, config, capacity)
    lo, hi = tri.min(1), tri.max(1)
    scale = dt.type(scene_scale(lo, hi))
    threshold = dt.type(config.alpha) * half_area(lo.min(0), hi.max(0), scale)
    tri_p = np.zeros((slots, 3, 3), dt)  # padding triangles are never read: no reference names them
    tri_p[:n] = tri
    # NumPy values: the engine moves them to the device (a jnp scalar made here compiled
    # a program of its own)
    built = engine(tri_p, n, np.int32(config.max_leaf), dt.type(config.ct), dt.type(config.ci), dt.type(scale),
                   dt.type(threshold), bins=config.bins, spatial_bins=config.spatial_bins)
    return built._replace(tree=widen_back(built.tree, frame))


class _Scene(NamedTuple):
    """What every level reads and no level changes."""

    tri: Any        # [R, 3, 3] triangles (rows past n unused)
    columns: Any    # [9, R] the same, coordinate by coordinate (vertex k's coordinate c in row 3 k + c)
    scale: Any      # the scene's power-of-two area scale
    threshold: Any  # alpha times the root's half-area: overlap above which spatial splits are tried
    max_leaf: Any   # int32
    ct: Any         # SAH traversal and intersection costs (leaf test)
    ci: Any


class _State(NamedTuple):
    """The loop state. Reference arrays have R slots, node arrays 2 R; the open nodes of
    the level are the ids ``level_start .. next_free - 1``."""

    ref_prim: Any     # [R] int32 triangle of each reference, -1 for a free slot
    ref_lo: Any       # [R, 3] reference boxes (free: the empty box)
    ref_hi: Any
    ref_node: Any     # [R] int32 node holding the reference (2 R for a free slot)
    n_refs: Any       # int32 slots in use (they are the first ones)
    left: Any         # [2 R] int32 children, -1 for leaves and unused nodes
    right: Any
    parent: Any       # [2 R] int32, -1 for the root and unused nodes
    axis: Any         # [2 R] int32 split axis, -1 for leaves
    lo: Any           # [2 R, 3] node boxes, written when the node is open
    hi: Any
    prim_count: Any   # [2 R] int32 references of a leaf, 0 otherwise
    level_start: Any  # int32 first open node
    next_free: Any    # int32 first unused node id
    spatial: Any      # int32 spatial splits taken
    short: Any        # bool: a spatial split was refused for want of slots


def _initial(tri: np.ndarray, n: int) -> _State:
    """The state before the first level (root open, every triangle a reference), NumPy:
    made on the host and moved to the device, not compiled (issue 38: it was a program
    of its own, ~1 s of XLA on a first call)."""
    slots = tri.shape[0]
    nodes = 2 * slots
    dt = tri.dtype
    used = np.arange(slots) < n
    ints = np.full(nodes, -1, np.int32)
    return _State(
        ref_prim=np.where(used, np.arange(slots, dtype=np.int32), np.int32(-1)),
        ref_lo=np.where(used[:, None], tri.min(1), np.inf).astype(dt),
        ref_hi=np.where(used[:, None], tri.max(1), -np.inf).astype(dt),
        ref_node=np.where(used, 0, nodes).astype(np.int32), n_refs=np.int32(n),
        left=ints, right=ints.copy(), parent=ints.copy(), axis=ints.copy(),
        lo=np.full((nodes, 3), np.inf, dt), hi=np.full((nodes, 3), -np.inf, dt),
        prim_count=np.zeros(nodes, np.int32), level_start=np.int32(0), next_free=np.int32(1),
        spatial=np.int32(0), short=np.bool_(False))


def _no_spatial(slots, dt):
    """A :class:`~jaxbvh.builders.sbvh_splits.Split` of no candidate for every slot."""
    inf = jnp.full(slots, jnp.inf, dt)
    zi = jnp.zeros(slots, jnp.int32)
    box = jnp.zeros((slots, 3), dt)
    return splits.Split(inf, zi, zi, box, box, box, box, zi, zi)


class _View(NamedTuple):
    """The references a level works on: all R slots, or the level's own compacted into
    ``live`` slots (in slot order; padding: triangle -1, the empty box, node 2 R)."""

    prim: Any  # [M] int32 triangle
    lo: Any    # [M, 3] box
    hi: Any
    node: Any  # [M] int32 node holding it
    slot: Any  # [M] int32 its slot in the state (R for padding); None when M = R (the identity)


def _in_level(s: _State):
    """[R] bool: the references of the level's open nodes."""
    return (s.ref_node >= s.level_start) & (s.ref_node < s.next_free)


def _view(s: _State, live: int) -> _View:
    """The level's references in ``live`` slots (a cumsum compaction, no sort), or all R."""
    refs = s.ref_prim.shape[0]
    if live >= refs:
        return _View(s.ref_prim, s.ref_lo, s.ref_hi, s.ref_node, None)
    in_level = _in_level(s)
    rank = jnp.cumsum(in_level, dtype=jnp.int32) - 1
    slot = jnp.full(live, refs, jnp.int32).at[jnp.where(in_level, rank, live)].set(
        jnp.arange(refs, dtype=jnp.int32), mode="drop")
    return _View(take(s.ref_prim, slot, -1), take(s.ref_lo, slot, jnp.inf), take(s.ref_hi, slot, -jnp.inf),
                 take(s.ref_node, slot, 2 * refs), slot)


def _level(scene: _Scene, s: _State, *, bins: int, spatial_bins: int, slots: int, live: int) -> _State:
    """Build one level: every open node becomes a leaf or is split, its children open.

    ``slots``: F, at least the number of open nodes (static: the size of the per-node
    arrays of the split searches); ``live``: M, at least the level's references (static:
    the size of the per-reference arrays; M < R compacts them first).
    """
    refs = s.ref_prim.shape[0]
    nodes = 2 * refs
    dt = scene.tri.dtype
    view = _view(s, live)
    m = view.prim.shape[0]
    open_nodes = s.next_free - s.level_start
    in_level = (view.node >= s.level_start) & (view.node < s.next_free)
    seg = jnp.where(in_level, view.node - s.level_start, slots).astype(jnp.int32)
    slot_ids = jnp.arange(slots, dtype=jnp.int32)
    is_open = slot_ids < open_nodes
    count = splits.segment(jax.ops.segment_sum, in_level.astype(jnp.int32), seg, slots)
    node_lo = splits.segment(jax.ops.segment_min, view.lo, seg, slots)
    node_hi = splits.segment(jax.ops.segment_max, view.hi, seg, slots)

    obj, bin3 = splits.object_split(view.lo, view.hi, seg, slots, scene.scale, bins)
    found = obj.cost < jnp.inf
    tried = is_open & found & (count > 1) & (splits.overlap_area(obj, scene.scale) > scene.threshold)
    node_bins = rules.spatial_bins(count, spatial_bins)  # [F] fewer spatial bins for few references
    empty_bins = splits.Bins(jnp.zeros((m, 3), jnp.int32), jnp.zeros((m, 3), jnp.int32))
    spatial, ref_bins = jax.lax.cond(
        jnp.any(tried),
        lambda: splits.spatial_split(scene.columns, view.prim, view.lo, view.hi, seg, node_lo, node_hi, tried,
                                     node_bins, count, slots, scene.scale, spatial_bins),
        lambda: (_no_spatial(slots, dt), empty_bins))
    tol = jnp.asarray(1 + TIE_TOLERANCE, dt)
    use_spatial = tried & (spatial.cost * tol < obj.cost)
    best = jnp.where(use_spatial, spatial.cost, obj.cost)

    # the leaf test
    area = half_area(node_lo, node_hi, scene.scale)
    count_f = count.astype(dt)
    estimate = scene.ct + jnp.where(area > 0, scene.ci * best / jnp.where(area > 0, area, 1), scene.ci * count_f)
    sah_leaf = (scene.ci * count_f <= estimate * tol) | ~found
    leaf = is_open & ((count <= 1) | ((count <= scene.max_leaf) & sah_leaf))
    split = is_open & ~leaf
    wants = split & use_spatial

    def sides():
        return splits.spatial_sides(scene.columns, view.prim, view.lo, view.hi, seg, node_lo, node_hi, spatial,
                                    ref_bins, node_bins, slots, scene.scale, spatial_bins)

    def no_sides():
        none = jnp.zeros(m, bool)
        return (splits.Sides(none, none, view.lo, view.hi, view.lo, view.hi), jnp.zeros(slots, bool),
                jnp.zeros(slots, jnp.int32))

    side, ok, extra = jax.lax.cond(jnp.any(wants), sides, no_sides)
    asking = wants & ok
    asked = jnp.cumsum(jnp.where(asking, extra, 0))
    granted = asking & (asked <= refs - s.n_refs)
    short = s.short | jnp.any(asking & ~granted)

    # children: two per split node, in node order
    rank = jnp.cumsum(split.astype(jnp.int32)) - split
    left_id = jnp.where(split, s.next_free + 2 * rank, nodes)
    right_id = left_id + 1
    # halves by triangle id where no object plane was found (rare: computed only then)
    halves = split & ~found
    by_id = jax.lax.cond(jnp.any(halves), lambda: splits.rank_by_prim(view.prim, seg, slots),
                         lambda: jnp.zeros(m, jnp.int32))
    obj_axis_r = take(obj.axis, seg, 0)
    obj_left = jnp.take_along_axis(bin3, obj_axis_r[:, None], axis=1)[:, 0] <= take(obj.plane, seg, 0)
    obj_left = jnp.where(take(found, seg, False), obj_left, by_id < take(count // 2, seg, 0))
    spatial_r = take(granted, seg, False)
    goes_left = jnp.where(spatial_r, side.left, obj_left)
    goes_right = jnp.where(spatial_r, side.right, ~obj_left)
    moving = take(split, seg, False)
    both = moving & goes_left & goes_right
    # the upper piece of a split reference takes a fresh slot
    fresh = s.n_refs + jnp.cumsum(both.astype(jnp.int32)) - both
    fresh = jnp.where(both, fresh, refs)
    l_node, r_node = take(left_id, seg, nodes), take(right_id, seg, nodes)
    ref_node = jnp.where(moving, jnp.where(goes_left, l_node, r_node), view.node)
    ref_lo = jnp.where(both[:, None], side.left_lo, view.lo)
    ref_hi = jnp.where(both[:, None], side.left_hi, view.hi)
    if view.slot is not None:  # back into the state's slots (padding: slot R, dropped)
        ref_node = s.ref_node.at[view.slot].set(ref_node, mode="drop")
        ref_lo = s.ref_lo.at[view.slot].set(ref_lo, mode="drop")
        ref_hi = s.ref_hi.at[view.slot].set(ref_hi, mode="drop")
    ref_prim = s.ref_prim.at[fresh].set(view.prim, mode="drop")
    ref_node = ref_node.at[fresh].set(r_node, mode="drop")
    ref_lo = ref_lo.at[fresh].set(side.right_lo, mode="drop")
    ref_hi = ref_hi.at[fresh].set(side.right_hi, mode="drop")

    node = s.level_start + slot_ids
    at = jnp.where(is_open, node, nodes)  # scatter target of each open slot
    at_split = jnp.where(split, node, nodes)
    split_axis = jnp.where(granted, spatial.axis, jnp.where(found, obj.axis, 0))
    return _State(
        ref_prim=ref_prim, ref_lo=ref_lo, ref_hi=ref_hi, ref_node=ref_node,
        n_refs=s.n_refs + jnp.sum(both, dtype=jnp.int32),
        left=s.left.at[at_split].set(left_id, mode="drop"), right=s.right.at[at_split].set(right_id, mode="drop"),
        parent=s.parent.at[left_id].set(node, mode="drop").at[right_id].set(node, mode="drop"),
        axis=s.axis.at[at_split].set(split_axis, mode="drop"),
        lo=s.lo.at[at].set(node_lo, mode="drop"), hi=s.hi.at[at].set(node_hi, mode="drop"),
        prim_count=s.prim_count.at[jnp.where(leaf, node, nodes)].set(count, mode="drop"),
        level_start=s.next_free, next_free=s.next_free + 2 * jnp.sum(split, dtype=jnp.int32),
        spatial=s.spatial + jnp.sum(granted, dtype=jnp.int32), short=short)


def _tree(s: _State) -> BVH:
    """The BVH of a finished state (NumPy arrays): each leaf's references one contiguous
    run, leaves in node order. On the host: a stable sort and a prefix sum, not worth a
    compiled program (issue 38)."""
    nodes = s.left.shape[0]
    ref_node = np.asarray(s.ref_node)
    prim_count = np.asarray(s.prim_count)
    order = np.argsort(ref_node, kind="stable")  # free slots (node 2 R) last
    prim_start = (np.cumsum(prim_count) - prim_count).astype(np.int32)
    return BVH(left=s.left, right=s.right, parent=s.parent, lo=s.lo, hi=s.hi,
               prim_start=np.where(prim_count > 0, prim_start, np.int32(0)), prim_count=prim_count, axis=s.axis,
               prim_index=np.where(ref_node[order] < nodes, np.asarray(s.ref_prim)[order], np.int32(-1)),
               root=np.int32(0))


def engine(tri, n, max_leaf, ct, ci, scale, threshold, *, bins: int, spatial_bins: int) -> SBVHBuild:
    """The level-synchronous SBVH on prepared inputs (:func:`build_sbvh` makes them).

    ``tri`` [R, 3, 3]: the triangles in their first ``n`` rows, R the reference slots
    (NumPy or JAX); ``n`` int; ``max_leaf`` int32; ``ct``, ``ci``, ``scale``,
    ``threshold``: scalars in ``tri``'s dtype; ``bins`` and ``spatial_bins`` (the object split's bins, the spatial split's
    most) static. Returns an :class:`SBVHBuild`.

    Driven from the host in runs of levels (:func:`_levels`), one run a loop over the
    levels whose first fitting program (:func:`level_programs`) is one program, each
    program compiled on its first need (a build whose levels all fit the narrow one
    compiles no other). Each level runs in the first program that holds it, so the
    trees do not depend on how the levels are grouped into runs.
    """
    slots = tri.shape[0]
    tri_host = np.asarray(tri)
    # the scene and the first state made on the host and moved to the device, the sizes
    # of each next level read from the run before: no compiled program but the levels'
    scene = jax.device_put(_Scene(tri_host, tri_host.reshape(slots, 9).T.copy(), scale, threshold, max_leaf, ct,
                                  ci))
    state = jax.device_put(_initial(tri_host, int(n)))
    open_nodes, in_level = 1, int(n)
    programs = level_programs(slots)
    for _ in range(2 * slots + 1):  # a run takes at least one level; a tree of R slots has fewer
        if open_nodes == 0:
            s = jax.device_get(state)
            return SBVHBuild(jax.device_put(_tree(s)), s.n_refs, s.spatial, s.short)
        program = _fitting(open_nodes, in_level, programs).index(True)
        state, size = _levels(scene, state, bins=bins, spatial_bins=spatial_bins, program=program)
        open_nodes, in_level = (int(x) for x in size)  # waits for the run
    raise RuntimeError(f"SBVH engine: levels still open after {2 * slots + 1} runs (a bug: please report)")


def _size(s: _State):
    """The level's open nodes and references (int32 each)."""
    return s.next_free - s.level_start, jnp.sum(_in_level(s), dtype=jnp.int32)


def _fitting(open_nodes, in_level, programs) -> list:
    """Per program of ``programs``, whether it holds a level of ``open_nodes`` open nodes
    and ``in_level`` references (the one rule for the host, on ints, and the loop, on
    traced scalars)."""
    return [(open_nodes <= slots) & (in_level <= live) for slots, live in programs]


def _fits(s: _State, programs) -> Any:
    """[P] bool: which of ``programs`` hold the level's open nodes and references."""
    return jnp.stack(_fitting(*_size(s), programs))


@partial(stored_jit, static_argnames=("bins", "spatial_bins", "program"))
def _levels(scene: _Scene, state: _State, *, bins: int, spatial_bins: int, program: int):
    """Levels from ``state`` on, in program ``program`` of :func:`level_programs`, while
    the tree is not finished and that program is the first that holds the level:
    ``(state, (open nodes, references))`` of the level after them (the host's next pick)."""
    programs = level_programs(scene.tri.shape[0])
    slots, live = programs[program]
    cheaper = programs[:program]

    def more(s: _State):
        here = (s.next_free > s.level_start) & _fits(s, [(slots, live)])[0]
        return here & ~jnp.any(_fits(s, cheaper)) if cheaper else here

    level = partial(_level, scene, bins=bins, spatial_bins=spatial_bins, slots=slots, live=live)
    state = jax.lax.while_loop(more, level, state)
    return state, _size(state)


#: reference slots up to which the engine compiles one level program (all R slots)
SMALL_STAGE = 512
#: the narrow level program has live_slots / NARROW_NODE_DIVISOR node slots (:func:`level_programs`)
NARROW_NODE_DIVISOR = 2


def live_slots(refs: int) -> int:
    """Per-reference slots M of the level programs but the tail and the last for ``refs``
    reference slots: a capacity bucket of at least two thirds of them (a level whose
    references do not fit runs in the last program, which has all R). With the default
    ``reference_capacity`` (2, rounded up to a bucket) that is 1.3 to 2 references per
    triangle; the builds measured used 1.06 to 1.27."""
    return refs if refs <= SMALL_STAGE else min(refs, capacity_bucket(-(-2 * refs // 3)))


def level_programs(refs: int) -> list[tuple[int, int]]:
    """The (F, M) of the engine's compiled levels for ``refs`` reference slots, cheapest
    first: up to ``SMALL_STAGE`` slots one, ``(refs, refs)``; past it two, the *narrow*
    one (``live_slots / NARROW_NODE_DIVISOR`` node slots on ``live_slots`` compacted
    references) and the *wide* one (all ``refs`` slots uncompacted: any level fits it).

    Two programs, not one per level size: each compiles the whole level (some 3,600
    StableHLO ops, ~10 CPU-s of XLA on spot), and compiling was most of a cold build
    (thirteenth round: seven stage programs of 64 .. 4,096 node slots and a tail cost
    spot ~62 CPU-s cold for a 0.2 s build). The narrow program holds every level of the
    builds measured at ``max_leaf`` 4 (open nodes at most about half the references),
    so they compile one level; the wide one is compiled only for a level that does not
    fit (more references than ``live_slots``, or more open nodes than its node slots).
    The price: the top levels and the deep ones run on per-node arrays sized for the
    widest level (spot: 0.2 s to 0.38 s a build)."""
    if refs <= SMALL_STAGE:
        return [(refs, refs)]
    live = live_slots(refs)
    return [(max(1, live // NARROW_NODE_DIVISOR), live), (refs, refs)]
