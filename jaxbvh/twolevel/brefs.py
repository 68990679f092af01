"""Build references (BRefs) and the re-braiding top-level build (Benthin et al. 2017, §4-5).

A **BRef** is one subtree of one placed object: ``(forest node, instance, world box,
primitive count)`` (:mod:`jaxbvh.twolevel.objects` for the forest, the instances and the
conservative world boxes). The top-level builder starts with one BRef per instance (its
object's root) and splits them top-down, as a binned SAH builder over boxes does, while
*opening* BRefs that are too large: a BRef is replaced by the BRefs of its children, so
the top level can reach into the object BVHs where objects overlap.

The BRef array
==============
All BRefs live in one array of fixed capacity ``C`` (``budget`` x #instances, or
``capacity`` directly; :func:`scene_slots` is the default a scene gets from
:func:`jaxbvh.twolevel.build`, the paper's §5.2 rule scaled for small scenes). A *segment* is a contiguous piece ``[start, extra)`` of it owned by one node of
the top-level tree: its BRefs are ``[start, end)``, the rest ``[end, extra)`` is spare
room that opening may fill. The root segment is ``[0, C)`` with the instances' BRefs at
``[0, #instances)``. One step on a segment of ``count = end - start`` BRefs:

1. ``count == 1``: a top-level leaf that points at this BRef. Done.
2. Termination of opening (tested first, §4.4): if all BRefs belong to one instance, or
   if ``count <= 4`` and no two of their boxes overlap by more than ``overlap`` (default
   0.1) of the shorter extent on every axis, the segment drops its spare room: neither it
   nor anything below it opens again.
3. Opening (§4.2, §5.3), in rounds: with ``dim`` the axis of the largest extent ``ext``
   of the segment's box (the union of its BRef boxes before opening; lowest axis on
   ties), the *candidates* are the BRefs whose forest node is not a leaf and whose box is
   wider than ``threshold * ext`` along ``dim``. If they all fit into the spare room, all
   open; otherwise the widest that fit (width along ``dim``, ties to the lower slot). A
   candidate's slot takes its left child, its right child goes to ``end, end + 1, ...``
   in the order of the candidates' positions. Rounds repeat, against the same ``ext``,
   until no candidate is left, the room is full or ``rounds`` rounds are done (default
   64). Ours, beyond the paper (one level per split, all candidates or none): on the
   by-material cow, 0.731x the two-level SAH with one round and all-or-none, 0.699x
   widest-first, 0.669x with rounds (90 slots); fewer, wider BRefs elsewhere (the room
   of 254 small objects prefers ``rounds=1``, ``jaxbvh.twolevel.build``'s comparison
   then keeps the plain top level).
4. Binning (§4.3): ``bins`` equal bins per axis over the segment's BRef centres
   (``0.5 lo + 0.5 hi``); each bin counts the *primitives* of its BRefs, and the plane
   between bins ``k`` and ``k + 1`` costs ``A_L N_L + A_R N_R`` (half-areas of the two
   sides' boxes, their primitive counts). The cheapest plane wins; costs within a
   relative ``TIE_TOLERANCE`` (2^-20, as :mod:`jaxbvh.builders.topdown`) tie, and ties go to the
   lowest axis, then the lowest plane. Without any plane (all centres in one point) the
   first ``count // 2`` positions go left.
5. Partition (§5.2): stable (both sides keep their order). The spare room ``extra -
   end`` is split between the halves in proportion to the number of their BRefs that
   meet the opening criterion of step 3 measured against the half's own box (to the
   numbers of BRefs when neither has any): ``spare_L = min(floor(f32(w_L) / f32(w_L +
   w_R) * f32(spare)), spare)``. The left half becomes ``[start, start + n_L)`` with its
   room after it, the right half starts at ``start + n_L + spare_L``. So how much a
   subtree may open does not depend on the order segments are processed in.

BRef boxes
==========
A BRef's box is the world box of its node's triangles as its instance places them
(:func:`jaxbvh.twolevel.objects.bref_boxes`: one row per placed node, computed once by
:func:`jaxbvh.twolevel.objects.pack`, refit from the transformed triangles and widened
by the rounding margin): it contains every triangle below the node, a child's box lies
inside its parent's, so the flattened tree, which gives every node below a BRef its own
such box, stays valid (:func:`jaxbvh.twolevel.flatten`), and under the identity it is
the node's own box. Under a rotation the box of a node's 8 transformed corners is much
looser, and rotated instances reach the top level only through these boxes: with the
union of the corner boxes three levels down (rounds 3-5) the pile of 6 cows opened to
raw 0.960x the plain two-level SAH on world boxes but was worse in object frames, so the
plain top level was kept; with the exact boxes the re-braided one is lower on both and
kept. The engine and its twin read the same rows (a gather: exact in both).

Primitive counts are exact by default (``Forest.subtree_prims``); ``estimate=True``
uses the paper's estimate instead: the root has its object's count, a child gets
``max(parent // 2, 1)`` (binary object trees). ``threshold = inf`` never opens: the
plain two-level BVH over the instances (its array then has room for the instances only).

Level-synchronous. The JAX builder runs all segments of one level of the top-level
tree at once (segment reductions keyed by the segment's start position; the binning
sorts each axis by (segment, bin) and scans, so no segments x bins table is needed; its
sorts, and the widest-first ranking of step 3, sort plain int keys that encode the slot,
:mod:`jaxbvh.twolevel.brefs_segments`), in a ``while_loop`` bounded by ``C + 1`` levels
(reaching the bound raises); the levels where no segment has room left skip steps 2-3
and the spare split. It equals the recursive NumPy twin
:func:`jaxbvh.twolevel.brefs_reference.build_top_level` BRef by BRef: every BRef ends in the
same slot of the array with the same node, instance, box and count, and the top-level
trees are the same up to node numbering. Exactness: world boxes, centres, bins, opening
tests, overlap tests and the spare split are computed with operations that rounding
cannot make differ between XLA and NumPy (no product feeds an addition, see
:mod:`jaxbvh.twolevel.objects`); only the SAH costs can differ by an ulp, which the tie tolerance
absorbs.

Output (:class:`TopLevel`): a :class:`~jaxbvh.tree.layout.BVH` over the BRefs (node ids level by
level, root 0; every leaf holds exactly one BRef; ``axis`` is the split axis, -1 for a
split without a plane) and the BRefs compacted in array order, with the slot each one
had (``position``).

The engine sits beside this module: :mod:`jaxbvh.twolevel.brefs_level` (the loop state
and the steps of one level) and :mod:`jaxbvh.twolevel.brefs_segments` (segmented
reductions and the best bin plane of every segment); :func:`build_levels` is the
compiled loop over levels.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import take
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH, capacity_bucket
from jaxbvh.twolevel import brefs_level
from jaxbvh.twolevel.brefs_level import SMALL_SEGMENT, Build  # noqa: F401 (SMALL_SEGMENT: public here)
from jaxbvh.twolevel.config import DEFAULT_BINS, DEFAULT_OVERLAP, DEFAULT_ROUNDS, DEFAULT_THRESHOLD, RebraidConfig

DEFAULT_BUDGET = 4.0     # paper §5.2: 4 x #instances (the top-level engine's default)
PRIMS_PER_SLOT = 1000    # paper §5.2: #primitives / 1000 for trees over objects
ONCE_BUDGET = 16         # ours: slots per object placed once in a small scene (see scene_slots)
LEAST_PRIMS_PER_SLOT = 64  # ours: ... but never more slots than #primitives / 64


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TopLevel:
    """Result of the top-level build.

    ``top``: :class:`~jaxbvh.tree.layout.BVH` with ``2 C`` node slots whose leaves hold one BRef
    each (``prim_index`` entries are BRef ids). BRefs [C], compacted, padding after
    ``count``: ``node`` int32 forest node (-1 padding), ``instance`` int32, ``lo``, ``hi``
    [C, 3] scene-frame boxes (padding: the empty box), ``prims`` int32 primitive counts
    (exact or estimated), ``position`` int32 slot in the build array. ``count``: number
    of BRefs (int32 scalar); ``levels``: levels the build took; ``complete``: the loop
    ended because no segment was left, not at its bound (the driver raises otherwise).
    """

    top: Any
    node: Any
    instance: Any
    lo: Any
    hi: Any
    prims: Any
    position: Any
    count: Any
    levels: Any
    complete: Any


def check_options(threshold, budget, bins, overlap, rounds=DEFAULT_ROUNDS) -> None:
    """Raise ``ValueError`` naming a bad option (:class:`jaxbvh.twolevel.config.RebraidConfig`'s
    checks, which the command line runs too)."""
    RebraidConfig(threshold=threshold, budget=budget, top_bins=bins, overlap=overlap, rounds=rounds)


def brefs_capacity(n_instances: int, threshold: float, budget: float,
                   capacity: int | None = None) -> int:
    """Slots of the BRef array: ``capacity``, else ``ceil(budget * n)``; ``n`` when never opening."""
    if math.isinf(threshold):
        return n_instances
    if capacity is not None:
        if capacity < n_instances:
            raise ValueError(f"capacity {capacity} is below the {n_instances} instances")
        return int(capacity)
    return max(n_instances, int(math.ceil(budget * n_instances)))


def scene_slots(n_instances: int, n_prims: int, n_once: int, once_overlap: float = math.inf) -> int:
    """The default size of the BRef array for a scene (the paper's §5.2 rule, scaled down).

    ``n_instances`` instances, ``n_prims`` world triangles, ``n_once`` of the instances
    place an object no other instance uses; ``once_overlap``: the sum, over those, of
    their world box's half-area over the scene box's (how many of their boxes a random
    ray through the scene meets; inf: unknown, taken as overlapping).

    The paper allocates ``4 x #instances`` for trees over instances and ``#primitives /
    1000`` for trees over objects, a rule made for scenes of millions of triangles: it
    gives a 13k-triangle scene of 8 overlapping objects 13 slots, too few to open
    anything that matters. So the array gets the largest of ``4 x #instances`` of shared
    objects, ``#primitives / 1000`` and, for the objects placed once (the by-material
    kind, whose overlap only deep opening removes), the larger of 4 and 16 each, but
    never so many that a BRef stands for fewer than 64 triangles on average (which keeps
    the top level small beside the object trees) -- on a by-material fandisk 4, 16 and 64
    slots per object gave 0.86x, 0.81x and 0.79x the two-level SAH, most of the gain by
    16 -- scaled by ``min(1, once_overlap - 1)``, the boxes beyond the first that a ray
    meets: where their boxes tile the scene rather than overlap, opening gains little
    and a large array only costs top-level time (the drone's 39 parts, overlap 1.01:
    0.992x the two-level SAH at 511 slots, 6-7x the plain top level's time; a room of 254
    objects, overlap 0.75: no gain at 1,016 slots). At least one slot per instance.
    """
    once = max(4 * n_once, min(ONCE_BUDGET * n_once, n_prims // LEAST_PRIMS_PER_SLOT))
    scale = min(1.0, max(0.0, once_overlap - 1.0))
    paper = max(4 * (n_instances - n_once), math.ceil(n_prims / PRIMS_PER_SLOT))
    return int(max(n_instances, paper, math.floor(once * scale)))


def build_top_level(forest, instances, n_instances: int, *, threshold: float = DEFAULT_THRESHOLD,
                    budget: float = DEFAULT_BUDGET, capacity: int | None = None,
                    bins: int = DEFAULT_BINS, overlap: float = DEFAULT_OVERLAP,
                    estimate: bool = False, rounds: int = DEFAULT_ROUNDS,
                    array_size: int | None = None) -> TopLevel:
    """Re-braiding top-level build over the first ``n_instances`` instances (module docstring).

    ``forest``, ``instances``: :func:`jaxbvh.twolevel.objects.pack` output (NumPy or JAX arrays);
    ``threshold``: opening threshold, a fraction of the segment's largest extent (inf:
    plain two-level); ``budget``: BRef slots per instance (or ``capacity`` slots in all);
    ``bins``: SAH bins per axis; ``overlap``: "barely overlapping" tolerance of the
    <= 4-BRef termination test; ``estimate``: the paper's estimated primitive counts;
    ``rounds``: most rounds of opening per top-level node (step 3);
    ``array_size``: size of the arrays (default: the capacity bucket of the slots; a
    larger one changes nothing but the shapes, e.g. to compile once for many scenes).
    Returns a :class:`TopLevel` of JAX arrays.
    """
    return finished(launch_top_level(forest, instances, n_instances, threshold=threshold, budget=budget,
                                     capacity=capacity, bins=bins, overlap=overlap, estimate=estimate,
                                     rounds=rounds, array_size=array_size))


def launch_top_level(forest, instances, n_instances: int, *, threshold: float = DEFAULT_THRESHOLD,
                     budget: float = DEFAULT_BUDGET, capacity: int | None = None,
                     bins: int = DEFAULT_BINS, overlap: float = DEFAULT_OVERLAP,
                     estimate: bool = False, rounds: int = DEFAULT_ROUNDS,
                     array_size: int | None = None) -> TopLevel:
    """:func:`build_top_level` without waiting for it: JAX dispatches the build and
    returns at once, so a caller can start two builds (``jaxbvh.twolevel.build_from``: the
    plain and the re-braided top level) before waiting for either; pass the result to
    :func:`finished` before reading it."""
    check_options(threshold, budget, bins, overlap, rounds)
    if n_instances < 1:
        raise ValueError("a top level needs at least one instance")
    slots = brefs_capacity(n_instances, threshold, budget, capacity)
    cap = array_size_of(slots, array_size)
    dtype = np.asarray(forest.lo).dtype
    return build_levels(jax.tree_util.tree_map(jnp.asarray, without_triangles(forest)),
                        jax.tree_util.tree_map(jnp.asarray, instances), jnp.int32(n_instances),
                        jnp.int32(slots), jnp.asarray(threshold, dtype), jnp.asarray(overlap, dtype),
                        jnp.int32(rounds), cap=cap, bins=int(bins), estimate=bool(estimate))


def array_size_of(slots: int, array_size: int | None = None) -> int:
    """The size of a top-level build's arrays for ``slots`` BRef slots: their capacity
    bucket, or ``array_size`` where that is larger (:func:`build_top_level`)."""
    return max(capacity_bucket(slots), array_size or 0)


def cut_to(result: TopLevel, cap: int) -> TopLevel:
    """``result`` (a finished :class:`TopLevel` read to the host) with arrays of size
    ``cap`` (node arrays ``2 cap``): the result the build at array size ``cap`` returns,
    when it has at most ``cap`` BRefs (``ValueError`` otherwise). A larger array size
    changes nothing but the padding: nodes are numbered level by level from the root and
    BRefs compacted in array order, so the first ``2 cap`` nodes and ``cap`` BRefs are
    the same."""
    if int(result.count) > cap:
        raise ValueError(f"cut_to: {int(result.count)} BRefs do not fit {cap} slots")
    nodes = lambda x: np.asarray(x)[:2 * cap]  # noqa: E731
    brefs = lambda x: np.asarray(x)[:cap]  # noqa: E731
    t = result.top
    top = BVH(left=nodes(t.left), right=nodes(t.right), parent=nodes(t.parent), lo=nodes(t.lo), hi=nodes(t.hi),
              prim_start=nodes(t.prim_start), prim_count=nodes(t.prim_count), axis=nodes(t.axis),
              prim_index=brefs(t.prim_index), root=t.root)
    return dataclasses.replace(result, top=top, node=brefs(result.node), instance=brefs(result.instance),
                               lo=brefs(result.lo), hi=brefs(result.hi), prims=brefs(result.prims),
                               position=brefs(result.position))


def finished(result: TopLevel) -> TopLevel:
    """``result`` of :func:`launch_top_level` once the build has ended (waits for it);
    raises if its loop stopped at its bound (cannot happen: every level splits every
    segment of >= 2 BRefs)."""
    if not bool(result.complete):
        cap = result.node.shape[0]
        raise RuntimeError(f"top-level build stopped at its bound of {cap + 1} levels with segments left")
    return result


def without_triangles(forest):
    """``forest`` with a one-triangle stand-in for its triangles, which the top-level
    build never reads: moving them to the device for every build cost more than the
    build of a small scene's plain top level (drone: ~8 ms a call)."""
    if forest.triangles.shape[0] == 1:
        return forest
    return dataclasses.replace(forest, triangles=np.zeros((1, 3, 3), np.asarray(forest.lo).dtype))


# ----------------------------------------------------------------------------------
# the level-synchronous engine (one level: jaxbvh.twolevel.brefs_level)
# ----------------------------------------------------------------------------------


@partial(stored_jit, static_argnames=("cap", "bins", "estimate"))
def build_levels(forest, instances, n_inst, slots, threshold, overlap, rounds, *, cap, bins, estimate):
    """The compiled engine of :func:`build_top_level` (module docstring): a :class:`TopLevel`.

    ``forest``, ``instances``: :func:`jaxbvh.twolevel.objects.pack` output (JAX arrays);
    ``n_inst``, ``slots`` [] int32: instances and BRef slots used; ``threshold``,
    ``overlap`` []: in the boxes' dtype; ``rounds`` [] int32. Static: ``cap`` (array size), ``bins``,
    ``estimate``; everything else is traced, so one program serves every scene and
    setting of one shape.
    """
    state = brefs_level.initial(forest, instances, n_inst, slots, cap=cap)

    def level(s):
        return brefs_level.level(forest, instances, s, threshold, overlap, rounds, cap=cap, bins=bins,
                                 estimate=estimate)

    s = jax.lax.while_loop(lambda s: jnp.any(s.segs.live) & (s.level <= cap), level, state)
    return _compact(s, cap=cap)


def _compact(s: Build, *, cap) -> TopLevel:
    """The BRefs compacted in array order; leaves point at their BRef's new id."""
    C = cap
    i32 = jnp.int32
    dtype = s.refs.lo.dtype
    pos = jnp.arange(C, dtype=i32)
    r, t = s.refs, s.top
    used = r.node >= 0
    new_id = jnp.cumsum(used.astype(i32)) - 1
    dest = jnp.where(used, new_id, C)
    n_refs = jnp.sum(used, dtype=i32)
    leaf = t.prim_count > 0
    top = BVH(left=t.left, right=t.right, parent=t.parent, lo=t.lo, hi=t.hi,
              prim_start=jnp.where(leaf, take(new_id, t.prim_start, 0), 0), prim_count=t.prim_count,
              axis=t.axis, prim_index=jnp.where(pos < n_refs, pos, -1), root=i32(0))
    return TopLevel(
        top=top,
        node=jnp.full(C, -1, i32).at[dest].set(r.node, mode="drop"),
        instance=jnp.full(C, -1, i32).at[dest].set(r.inst, mode="drop"),
        lo=jnp.full((C, 3), jnp.inf, dtype).at[dest].set(r.lo, mode="drop"),
        hi=jnp.full((C, 3), -jnp.inf, dtype).at[dest].set(r.hi, mode="drop"),
        prims=jnp.zeros(C, i32).at[dest].set(r.prims, mode="drop"),
        position=jnp.full(C, -1, i32).at[dest].set(pos, mode="drop"),
        count=n_refs, levels=s.level, complete=~jnp.any(s.segs.live))
