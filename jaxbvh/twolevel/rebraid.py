"""Two-level BVHs over objects and instances, with partial re-braiding (Benthin et al. 2017).

A scene of objects placed by instances (:class:`jaxbvh.io.meshes.Mesh`: ``objects``,
``instances``) gets

1. one BVH per distinct object, built once by any of our builders (binned SAH by
   default, as the paper) -- in the object's own frame when several instances share it,
   in world space otherwise -- and packed into one forest (:mod:`jaxbvh.twolevel.objects`);
2. a *top level*: a BVH over build references (BRefs: forest node, instance, world box,
   primitive count) that starts from one BRef per instance and, while splitting,
   *opens* BRefs that are large relative to their segment, so that overlapping objects
   are separated inside their own trees (:mod:`jaxbvh.twolevel.brefs`; ``threshold = inf`` gives
   the plain two-level BVH, which never opens).

A scene with a single instance (a plain mesh is one object with one identity instance)
needs no top level, and none is built: its top level is one leaf naming the object's root.

Layout of :class:`TwoLevelBVH`
==============================
``top`` is a :class:`~jaxbvh.tree.layout.BVH` over the BRefs (layout :mod:`jaxbvh.tree.layout`, boxes
in the scene frame ``Mesh.frame``): every leaf holds exactly one BRef id. The BRefs
``bref_node`` / ``bref_instance`` / ``bref_lo`` / ``bref_hi`` / ``bref_prims`` [C] say
which forest node of which instance a leaf stands for (padding: node -1). ``forest`` and
``instances`` are :class:`~jaxbvh.twolevel.objects.Forest` and :class:`~jaxbvh.twolevel.objects.Instances`.
A top-level leaf *is* its BRef's forest node: its box is that node's world box, and
below it the object's own nodes follow, in the object's frame.

Traversal (:mod:`jaxbvh.twolevel.traversal`)
=========================================
:func:`closest_hit` runs one ``while_loop`` per ray whose stack holds ``(node, tag)``
pairs: top-level nodes (tag -1) are tested with the world ray; below a top-level leaf the
ray is mapped into the instance of that leaf's BRef (the tag: the leaf it entered
through; ``to_object``; the direction is not normalised, so ``t`` is the same in both
frames) and the object's nodes and triangles are tested there. Each step is a node step,
a primitive step or a climb step, counted as in :mod:`jaxbvh.rays.traversal` (whose loop,
:mod:`jaxbvh.rays.stack_walk`, and slab and Möller-Trumbore tests it reuses): the root box
test is one box test, an interior node adds one per child. The stack is short and fixed
(``STACK`` entries, whatever the depth); a ray whose stack spilled climbs by parent links,
from an object's subtree back to the top-level leaf it entered through and on up the top
level. The loop is bounded by the number of steps a ray can take at most (every node of
the flattened tree popped, climbed out of and pushed from a climb at most once, every
primitive once, plus one); a ray that would need more is reported and the driver raises.
Primitive ids are world triangle ids (``Mesh.triangles`` order); equal ``t`` goes to the
lower id.

Flattening and costs
====================
:func:`flatten` copies every BRef's subtree under its instance into one world-space
:class:`~jaxbvh.tree.layout.BVH` (every object node with its BRef box, :func:`jaxbvh.twolevel.objects.bref_boxes`;
primitive ids in world order) that validates against ``Mesh.local_boxes()`` and saves in
the interchange form. :func:`sah` is the SAH of that tree: interior nodes and leaves of
two-level, re-braided and single BVHs costed on the same footing (the paper's Table 1).
For instanced nodes the world box is the BRef box (the box of the node's triangles as
its instance places them, :func:`jaxbvh.twolevel.objects.bref_boxes`), as the top level
sees it and tests it.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import warnings
from typing import Any, Callable

import jax
import numpy as np

from jaxbvh.builders.configs import BuilderConfig
from jaxbvh.configs import config_or_options
from jaxbvh.numerics import half_area
from jaxbvh.optimize.protocol import CompileClock, OptimizeResult, StepInfo, check_on_step
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import BVH, capacity_bucket, concat_ranges, depth, pad_to, to_jax, to_numpy
from jaxbvh.twolevel import brefs as _brefs
from jaxbvh.twolevel.config import RebraidConfig
from jaxbvh.twolevel.objects import Forest, Instances, ObjectTree, bref_boxes, build_objects, object_builder, pack


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TwoLevelBVH:
    """A two-level (possibly re-braided) BVH (layout: module docstring).

    ``top``: :class:`~jaxbvh.tree.layout.BVH`; ``bref_node``, ``bref_instance``, ``bref_prims``
    [C] int32; ``bref_lo``, ``bref_hi`` [C, 3] float; ``bref_count`` int32 scalar;
    ``forest``: :class:`~jaxbvh.twolevel.objects.Forest`; ``instances``:
    :class:`~jaxbvh.twolevel.objects.Instances`; ``n_instances`` int32 scalar.
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


def _single_instance(forest: Forest, instances: Instances) -> TwoLevelBVH:
    """The top level of a one-instance scene: one leaf naming the object's root (no build)."""
    root = int(forest.root[instances.object[0]])
    lo, hi = bref_boxes(instances, np.array([root]), np.array([0]))
    one = lambda v: np.full(1, v, np.int32)  # noqa: E731
    top = BVH(left=one(-1), right=one(-1), parent=one(-1), lo=lo, hi=hi, prim_start=one(0),
              prim_count=one(1), axis=one(-1), prim_index=one(0), root=np.int32(0))
    return TwoLevelBVH(top=top, bref_node=one(root), bref_instance=one(0), bref_lo=lo, bref_hi=hi,
                       bref_prims=one(int(forest.subtree_prims[root])), bref_count=np.int32(1),
                       forest=forest, instances=instances, n_instances=np.int32(1))


@dataclasses.dataclass(frozen=True, kw_only=True)
class RebraidResult(OptimizeResult):
    """What :func:`run` and :func:`run_from` return: the fields of every search
    (:class:`jaxbvh.optimize.protocol.OptimizeResult`) and re-braiding's own.

    Search fields: ``tree``: the :class:`TwoLevelBVH`; ``steps``: its stages run
    (``"objects"`` (:func:`run` only), ``"pack"``, ``"top"``), one
    :class:`~jaxbvh.optimize.protocol.StepInfo` each in ``trace`` (``moves`` of
    ``"top"``: the BRefs the kept top level opened beyond one per instance; ``sah``:
    NaN); ``sah``, ``sah_start``, ``cost_name``: None and ``history``: NaN [steps]
    (a build prices nothing; :func:`sah` costs the tree); ``stop``: ``"limit"``;
    ``seconds``: wall seconds of the whole build (arrays ready), ``compile_seconds``: the
    part spent compiling.

    Re-braiding's own: ``stage_seconds``: ``{stage: seconds}`` (``"top"`` includes the
    plain top level and the comparison of :func:`_keep_rebraided`); ``slots``: the BRef
    array's size; ``kept``: ``"rebraided"``, ``"two-level"`` (opening did not lower the
    SAH, or no slot was spare) or ``"single object"``.
    """

    stage_seconds: dict
    slots: int
    kept: str


def run_from(mesh, trees: dict[int, ObjectTree], config: RebraidConfig | None = None, *,
             capacity: int | None = None, shapes: dict | None = None,
             on_step: Callable[[StepInfo], None] | None = None, **options) -> RebraidResult:
    """Pack already built object trees and build the top level (see :func:`run`).

    ``config``: a :class:`~jaxbvh.twolevel.config.RebraidConfig` (None: its defaults), or
    its knobs as keyword ``options`` (``threshold``, ``budget``, ``top_bins``,
    ``overlap``, ``estimate``, ``rounds``). ``capacity``: BRef slots in all (instead of
    ``config.budget`` per instance). ``shapes``: least array sizes ``{"nodes", "prims",
    "instances", "brefs"}`` (so that many scenes share one compiled top-level build and
    traversal). ``on_step(info)``: called after each stage (:class:`RebraidResult`).
    """
    config = _config(config, options)
    check_on_step(on_step)
    with CompileClock() as clock:
        started = time.perf_counter()
        trace: list[StepInfo] = []
        tl, slots, kept = _build_from(mesh, trees, config, capacity, shapes, _reporter(trace, on_step, started))
    seconds = time.perf_counter() - started
    return _result(tl, trace, slots, kept, seconds, clock.seconds)


def _config(config, options) -> RebraidConfig:
    """``config``, or the RebraidConfig of keyword ``options`` (not both)."""
    return config_or_options(config, options, RebraidConfig)


def _reporter(trace: list, on_step, started: float):
    """``report(stage, moves)``: the StepInfo of a finished stage to ``trace`` and ``on_step``."""

    def report(stage: str, moves: int = 0) -> None:
        info = StepInfo("rebraid", stage, len(trace), math.nan, int(moves), time.perf_counter() - started)
        trace.append(info)
        if on_step is not None:
            on_step(info)

    return report


def _result(tl, trace, slots, kept, seconds, compile_seconds) -> RebraidResult:
    stage_seconds = dict(zip([i.stage for i in trace], np.diff([0.0] + [i.seconds for i in trace]).tolist()))
    return RebraidResult(tree=tl, sah=None, sah_start=None, cost_name=None, steps=len(trace),
                         history=np.full(len(trace), np.nan), converged=False, stop="limit", trace=tuple(trace),
                         seconds=seconds, compile_seconds=compile_seconds, stage_seconds=stage_seconds,
                         slots=slots, kept=kept)


def _build_from(mesh, trees, config: RebraidConfig, capacity, shapes, report):
    """``(TwoLevelBVH, slots, kept)`` of :func:`run_from`; ``report(stage, moves)`` after each stage."""
    threshold, budget = config.threshold, config.budget
    shapes = shapes or {}
    forest, instances = pack(mesh, trees, capacity=shapes)
    jax.block_until_ready((forest, instances))
    report("pack")
    n = len(mesh.instances)
    slots = slots_of(mesh, threshold, budget, capacity)
    if n == 1:
        tl, kept = _single_instance(forest, instances), "single object"
    else:
        top = dict(bins=config.top_bins, overlap=config.overlap, estimate=config.estimate, rounds=config.rounds,
                   array_size=shapes.get("brefs"))
        # on the device once for both top levels, without the triangles (not read there)
        nodes, placed = jax.device_put((_brefs.without_triangles(forest), instances))
        # NumPy from here: the comparison and the root box are a few small steps, each
        # cheaper on the host than as a dispatched device op (measured: 1-2 ms each)
        # both builds dispatched before waiting for either (JAX runs them asynchronously;
        # on a multi-core CPU the small plain one overlaps the re-braided one)
        opens = not math.isinf(threshold) and slots > n  # no spare slot: nothing can open
        braided = _brefs.launch_top_level(nodes, placed, n, threshold=threshold, capacity=slots,
                                          **top) if opens else None
        # the plain top level runs in the re-braided one's program (its arrays sized for
        # the re-braided BRefs; the extra slots stay padding) and is cut back to its own
        # size: one top-level program compiled per scene, not two (issue 38: each is
        # ~2,000 StableHLO ops, ~10 CPU-s of XLA on a by-material spot)
        plain_size = _brefs.array_size_of(n, top["array_size"])
        shared = dict(top, array_size=_brefs.array_size_of(slots, top["array_size"])) if opens else top
        plain = _brefs.launch_top_level(nodes, placed, n, threshold=math.inf, **shared)
        plain, braided = jax.device_get((_brefs.finished(plain), braided and _brefs.finished(braided)))
        plain = _brefs.cut_to(plain, plain_size)
        result, kept = plain, "two-level"
        if opens:
            braided = _same_root_box(braided, plain)
            if _keep_rebraided(braided, plain, forest, instances):
                result, kept = braided, "rebraided"
        tl = TwoLevelBVH(top=result.top, bref_node=result.node, bref_instance=result.instance,
                         bref_lo=result.lo, bref_hi=result.hi, bref_prims=result.prims,
                         bref_count=result.count, forest=forest, instances=instances,
                         n_instances=np.int32(n))
    report("top", int(tl.bref_count) - n)
    return tl, slots, kept


def _deprecated_dicts(timings, info, result: RebraidResult, caller: str) -> None:
    """Fill the old in-place ``timings`` and ``info`` dicts from ``result`` (with a warning)."""
    if timings is None and info is None:
        return
    warnings.warn(f"{caller}(timings=..., info=...) is deprecated: use twolevel.{caller.replace('build', 'run')}, "
                  "whose result has stage_seconds, slots and kept", DeprecationWarning, stacklevel=3)
    if timings is not None:
        timings.update(result.stage_seconds)
    if info is not None:
        info.update(slots=result.slots, kept=result.kept)


def build_from(mesh, trees: dict[int, ObjectTree], config: RebraidConfig | None = None, *,
               capacity: int | None = None, shapes: dict | None = None, timings: dict | None = None,
               info: dict | None = None, **options) -> TwoLevelBVH:
    """The tree of :func:`run_from` (same arguments); ``timings`` and ``info`` are
    deprecated (use :func:`run_from`'s ``stage_seconds``, ``slots`` and ``kept``): if given,
    ``timings`` receives ``pack`` and ``top`` seconds and ``info`` ``slots`` and ``kept``."""
    result = run_from(mesh, trees, config, capacity=capacity, shapes=shapes, **options)
    _deprecated_dicts(timings, info, result, "build_from")
    return result.tree


def slots_of(mesh, threshold: float = _brefs.DEFAULT_THRESHOLD, budget: float | None = None,
             capacity: int | None = None) -> int:
    """The BRef array's size for ``mesh``: ``capacity``, else ``budget`` x #instances, else
    the scene's default :func:`jaxbvh.twolevel.brefs.scene_slots`; #instances when
    ``threshold`` is inf (never opening)."""
    n = len(mesh.instances)
    if budget is None and capacity is None and not math.isinf(threshold):
        users: dict[int, int] = {}
        for obj, _ in mesh.instances:
            users[obj] = users.get(obj, 0) + 1
        once = [users[obj] == 1 for obj, _ in mesh.instances]
        capacity = _brefs.scene_slots(n, mesh.n_triangles, sum(once), _once_overlap(mesh, np.array(once)))
    return _brefs.brefs_capacity(n, threshold, _brefs.DEFAULT_BUDGET if budget is None else budget, capacity)


def _once_overlap(mesh, once) -> float:
    """Sum over the instances flagged in ``once`` [n] bool of their world box's
    half-area over the scene box's (float64). World boxes: of the 8 transformed corners
    of each object's box (exact under the identity, looser under a rotation), so
    O(instances + object vertices) and not O(triangles), which the top-level time of a
    large scene would notice (the drone's or the room's transformed vertices: milliseconds)."""
    verts = [np.asarray(v, np.float64) for v, _ in mesh.objects]
    starts = np.cumsum([0] + [v.shape[0] for v in verts[:-1]])
    every = np.concatenate(verts)
    which = np.array([obj for obj, _ in mesh.instances])
    low = np.minimum.reduceat(every, starts, axis=0)[which]  # [n, 3] object boxes by instance
    high = np.maximum.reduceat(every, starts, axis=0)[which]
    m = np.stack([t for _, t in mesh.instances]).astype(np.float64)  # [n, 4, 4]
    pick = np.array(list(itertools.product((0, 1), repeat=3)), bool)  # [8, 3]: high where True
    corners = np.where(pick[None], high[:, None], low[:, None])  # [n, 8, 3]
    world = corners @ m[:, :3, :3].transpose(0, 2, 1) + m[:, None, :3, 3]
    lo, hi = world.min(axis=1), world.max(axis=1)
    scene = _area(lo.min(axis=0), hi.max(axis=0))
    return float(_area(lo[once], hi[once]).sum() / scene) if scene > 0 else math.inf


# ----------------------------------------------------------------------------------
# Never worse than two-level
# ----------------------------------------------------------------------------------
#
# The flattened re-braided tree and the flattened plain two-level tree share every node
# strictly below the BRefs (in both, every object node has its BRef box,
# jaxbvh.twolevel.brefs "BRef boxes"). The plain tree has, besides its top level, the
# object nodes *above* the BRefs (the opened ones, each an interior node); the
# re-braided tree has its larger top level instead. With both roots on the same box the
# difference of their SAH (Ct = Ci = 1) is therefore exactly
#
#     1 / A_root * (sum of A over re-braided top interior nodes
#                   - sum of A over plain top interior nodes - sum of A over opened nodes)
#
# on world boxes. In object frames (what the traversal tests below a top-level leaf) a
# node below an object's root costs the area of its box as transformed, so the opened
# nodes below a root cost that, and every BRef below a root adds (A transformed - A BRef
# box) x its cost: a BRef is tested on its world box, where the plain tree tested the
# node in its object frame.
#
# O(BRefs) to compute, whatever the scene's size. Opening can make it positive: the top
# level bins BRefs by primitive count, a greedy and coarse estimate of what a subtree
# costs, so where it splits an opened node's children apart and then regroups them with
# other objects' pieces it builds a worse hierarchy than the object's own (measured: the
# drone at threshold 0.01, 1.04x two-level; a by-material tree in the tests). The top
# level is then the plain one.


def _same_root_box(braided, plain):
    """The re-braided top level with its root on the plain root's box (the union of the
    instances' world boxes, which contains every BRef's box): both trees' SAH then share
    one normaliser, and the re-braided SAH cannot rise because the root shrank."""
    top = braided.top
    root = int(plain.top.root)
    lo, hi = np.array(top.lo), np.array(top.hi)
    lo[int(top.root)], hi[int(top.root)] = plain.top.lo[root], plain.top.hi[root]
    return dataclasses.replace(braided, top=dataclasses.replace(top, lo=lo, hi=hi))


def _interior_area(top) -> float:
    """Sum of the half-areas of the interior nodes of a top level (float64)."""
    inner = np.asarray(top.left) >= 0
    return float(half_area(np.asarray(top.lo, np.float64)[inner], np.asarray(top.hi, np.float64)[inner]).sum())


def _opened_areas(node, instance, forest, instances) -> tuple[float, float]:
    """What the nodes above the BRefs ``(node, instance)`` [B] cost in the plain tree and
    the BRefs' own nodes cost there beyond their BRef boxes, on both footings of
    :func:`sah` (module comment above): ``(world, object)``, float64. World boxes: the
    half-areas of the opened nodes' BRef boxes. Object frames, where the plain tree tests
    nodes below an object's root in its object frame: those nodes costed by the area of
    their transformed box, plus for every BRef below its object's root (that area -
    BRef box half-area) x its cost (1 interior, its count a leaf; Ct = Ci = 1)."""
    node, instance = np.asarray(node, np.int64), np.asarray(instance, np.int64)
    parent = np.asarray(forest.parent)
    nf = parent.shape[0]
    pairs = []
    inst_f, node_f = instance, parent[node]
    for _ in range(nf + 1):  # bounded by the forest's depth
        ok = node_f >= 0
        inst_f, node_f = inst_f[ok], node_f[ok]
        if node_f.size == 0:
            break
        key = _unique(inst_f * nf + node_f)
        pairs.append(key)
        inst_f, node_f = key // nf, parent[key % nf]
    if not pairs:
        return 0.0, 0.0
    key = _unique(np.concatenate(pairs))
    i, n = key // nf, key % nf
    root = parent[n] < 0
    below = parent[node] >= 0
    b_n, b_i = node[below], instance[below]
    # the opened nodes and the BRefs below a root in one call each (half the fixed cost)
    every_n, every_i = np.concatenate([n, b_n]), np.concatenate([i, b_i])
    box_area = _area(*bref_boxes(instances, every_n, every_i))
    obj_area = _object_area(forest, instances, every_n, every_i)
    k = n.size
    tight = box_area[:k]
    loose = np.where(root, tight, obj_area[:k])
    cost = np.where(np.asarray(forest.left)[b_n] >= 0, 1.0, np.asarray(forest.prim_count)[b_n].astype(np.float64))
    extra = (obj_area[k:] - box_area[k:]) * cost
    return float(tight.sum()), float(loose.sum() + extra.sum())


def _unique(keys):
    """The sorted distinct values of the int array ``keys`` (``np.unique``'s result; a
    sort and a neighbour test, ~3x faster than ``np.unique`` on the ~1,000 keys of a walk step)."""
    keys = np.sort(keys)
    return keys[np.concatenate([[True], keys[1:] != keys[:-1]])] if keys.size else keys


def _object_area(forest, instances, n, i):
    """Half-areas of the parallelepipeds the object boxes of nodes ``n`` become under
    instances ``i`` (as :func:`sah` with ``boxes="object"``). Gathers before widening to
    float64 (the same values; the whole forest's boxes cost more to convert)."""
    ext = np.maximum(np.asarray(forest.hi)[n].astype(np.float64) - np.asarray(forest.lo)[n].astype(np.float64), 0)
    return _parallelepiped_area(np.asarray(instances.to_scene)[i][:, :, :3].astype(np.float64), ext)


def _parallelepiped_area(linear, ext):
    """Half surface areas [n] of the parallelepipeds that boxes of extents ``ext`` [n, 3]
    become under the linear maps ``linear`` [n, 3, 3] (float64; boxes stay boxes under
    axis-aligned scalings). The cross products and norms written out: ``np.cross`` and
    ``np.linalg.norm``'s operations in their order (the same bits), without their
    per-call overhead."""
    e = [[linear[:, r, k] * ext[:, k] for r in range(3)] for k in range(3)]  # e[k][r]: row r of edge k

    def norm_of_cross(a, b):
        c0 = a[1] * b[2] - a[2] * b[1]
        c1 = a[2] * b[0] - a[0] * b[2]
        c2 = a[0] * b[1] - a[1] * b[0]
        return np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)

    return norm_of_cross(e[0], e[1]) + norm_of_cross(e[1], e[2]) + norm_of_cross(e[2], e[0])


def _area(lo, hi):
    return half_area(np.asarray(lo, np.float64), np.asarray(hi, np.float64))


def _keep_rebraided(braided, plain, forest, instances) -> bool:
    """The re-braided top level lowers the SAH (module comment above) on both footings of
    :func:`sah`, by more than rounding could account for (1e-6 relative; ties keep the
    plain one)."""
    count = int(braided.count)
    if count == int(plain.count):
        return False  # nothing opened: the same BRefs, and the plain top level is as good
    node, instance = np.asarray(braided.node)[:count], np.asarray(braided.instance)[:count]
    added = _interior_area(braided.top)
    # lower on both footings: world boxes (the paper's Table 1) and object frames (what the
    # two-level traversal tests below a BRef; under rotations the two can disagree)
    return all(added < (_interior_area(plain.top) + opened) * (1 - 1e-6)
               for opened in _opened_areas(node, instance, forest, instances))


def run(mesh, builder: BuilderConfig | None = None, config: RebraidConfig | None = None, *,
        capacity: int | None = None, dtype=None, world_space: bool = True, shapes: dict | None = None,
        on_step: Callable[[StepInfo], None] | None = None, **options) -> RebraidResult:
    """Two-level BVH of ``mesh`` with re-braiding (module docstring), as a :class:`RebraidResult`.

    Object BVHs: ``builder``, a builder Config (None:
    :data:`jaxbvh.twolevel.objects.DEFAULT_BUILDER`, binned SAH with one primitive per
    leaf; the older keywords ``method``, ``max_leaf``, ``bins``, ``ct``, ``ci`` make one,
    :func:`jaxbvh.twolevel.objects.object_builder`), in ``dtype`` (None: the builder's,
    float32 unless it says float64, which needs x64); ``world_space``: build objects
    placed by a single instance in world space (:mod:`jaxbvh.twolevel.objects`). Top
    level: ``config``, a :class:`~jaxbvh.twolevel.config.RebraidConfig` (threshold,
    budget, top_bins, overlap, estimate, rounds; None: its defaults, or those knobs as
    keywords), ``capacity``: BRef slots in all instead of ``config.budget`` per instance
    (neither: the scene's default, :func:`jaxbvh.twolevel.brefs.scene_slots`);
    ``shapes`` as :func:`run_from`. ``on_step(info)``: called after each stage. The
    re-braided top level is kept only where it lowers the SAH below the plain two-level
    one (else the plain one is returned, ``result.kept == "two-level"``).
    """
    top_options = {k: options.pop(k) for k in list(options) if k in _CONFIG_KNOBS}
    config = _config(config, top_options)
    builder = object_builder(builder, **options)  # refused before any work
    check_on_step(on_step)
    with CompileClock() as clock:
        started = time.perf_counter()
        trace: list[StepInfo] = []
        report = _reporter(trace, on_step, started)
        trees = jax.block_until_ready(build_objects(mesh, builder, dtype=dtype, world_space=world_space))
        report("objects")
        tl, slots, kept = _build_from(mesh, trees, config, capacity, shapes, report)
    seconds = time.perf_counter() - started
    return _result(tl, trace, slots, kept, seconds, clock.seconds)


#: the keywords :func:`run` and :func:`build` take as RebraidConfig knobs (the rest make the builder)
_CONFIG_KNOBS = frozenset(f.name for f in dataclasses.fields(RebraidConfig))


def build(mesh, builder: BuilderConfig | None = None, config: RebraidConfig | None = None, *,
          capacity: int | None = None, dtype=None, world_space: bool = True, timings: dict | None = None,
          info: dict | None = None, **options) -> TwoLevelBVH:
    """The tree of :func:`run` (same arguments); ``timings`` and ``info`` are deprecated (use
    :func:`run`'s ``stage_seconds``, ``slots`` and ``kept``): if given, ``timings``
    receives ``objects``, ``pack`` and ``top`` seconds and ``info`` ``slots`` and ``kept``."""
    result = run(mesh, builder, config, capacity=capacity, dtype=dtype, world_space=world_space, **options)
    _deprecated_dicts(timings, info, result, "build")
    return result.tree


# ----------------------------------------------------------------------------------
# Flattening and costs
# ----------------------------------------------------------------------------------


def flatten(tl: TwoLevelBVH, *, pad: bool = True) -> BVH:
    """One world-space (scene-frame) :class:`~jaxbvh.tree.layout.BVH` with the same nodes (NumPy).

    Top-level interior nodes keep their ids; a top-level leaf becomes the copy of its
    BRef's forest node, and the copies of the nodes below follow. Copies under a
    non-identity map get ``axis = -1`` (the object's split axis means nothing in world
    space). Primitive ids are world triangle ids. Padded to capacity buckets unless
    ``pad=False``.
    """
    flat, _ = _flatten(tl)
    if pad:
        flat = pad_to(flat, capacity_bucket(flat.left.shape[0]), capacity_bucket(flat.prim_index.shape[0]))
    return flat


def _flatten(tl):
    """The unpadded flattened tree and its copies: ``(forest node, instance, flat id)`` arrays."""
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
    # every copy gets its BRef box (jaxbvh.twolevel.brefs "BRef boxes"): a child's lies
    # inside its parent's, and a BRef's own node has the top-level leaf's box
    lo[cid], hi[cid] = bref_boxes(inst, cf, ci_)
    lo[top_leaf], hi[top_leaf] = top.lo[top_leaf], top.hi[top_leaf]
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
    return flat, (cf, ci_, cid)


def sah(tl: TwoLevelBVH, ct: float = 1.0, ci: float = 1.0, *, boxes: str = "world") -> float:
    """SAH of the two-level tree: interior nodes and leaves, ``Ct``, ``Ci`` as :mod:`jaxbvh.tree.cost`.

    ``boxes="world"`` (the default, the paper's Table 1 footing): the SAH of the
    flattened tree (:func:`flatten`), every node with its world box, instanced nodes
    with their BRef boxes. ``boxes="object"``: the cost of the traversal this
    module runs, which tests the nodes below a top-level leaf in their object frame:
    such a node is hit by a random line with the probability of its box *as
    transformed* (a parallelepiped, whose surface area replaces the conservative box's;
    Cauchy's formula), so this SAH is usually below the world one (under a rotation the
    box of a node's placed triangles is mostly larger than the parallelepiped) and equals
    it when every object is built in world space. Zero-area nodes follow :mod:`jaxbvh.tree.cost`.
    """

    if boxes == "world":
        return float(sah_of(to_jax(flatten(tl)), ct, ci))
    if boxes != "object":
        raise ValueError(f"boxes must be 'world' or 'object', got {boxes!r}")
    flat, (cf, ci_, cid) = _flatten(tl)
    t = to_numpy(tl)
    lo, hi = flat.lo.astype(np.float64), flat.hi.astype(np.float64)

    area = half_area(lo, hi)
    # copies below a BRef's root are tested in their object frame
    below = np.ones(cid.size, bool)
    below[: int(np.count_nonzero(t.top.prim_count > 0))] = False  # the first copies are the roots
    f_lo, f_hi = t.forest.lo[cf[below]].astype(np.float64), t.forest.hi[cf[below]].astype(np.float64)
    ext = np.maximum(f_hi - f_lo, 0)
    linear = t.instances.to_scene[ci_[below]][:, :, :3].astype(np.float64)
    area[cid[below]] = _parallelepiped_area(linear, ext)
    cost = np.where(flat.prim_count > 0, ci * flat.prim_count.astype(np.float64), ct)
    level = depth(flat)
    for k in range(int(level.max()), -1, -1):
        nodes = np.flatnonzero((level == k) & (flat.left >= 0))
        l, r = flat.left[nodes], flat.right[nodes]
        own = area[nodes]
        weighted = (area[l] * cost[l] + area[r] * cost[r]) / np.where(own > 0, own, 1)
        cost[nodes] = ct + np.where(own > 0, weighted, cost[l] + cost[r])
    return float(cost[int(flat.root)])


def stored_nodes(tl: TwoLevelBVH) -> dict[str, int]:
    """Nodes kept in memory: ``top`` (real top-level nodes) and ``objects`` (forest nodes)."""
    t = to_numpy(tl)
    top = int(np.count_nonzero((t.top.left >= 0) | (t.top.prim_count > 0)))
    objects = int(np.count_nonzero((t.forest.left >= 0) | (t.forest.prim_count > 0)))
    return {"top": top, "objects": objects, "total": top + objects}


# traversal lives in its own module; re-exported here so jaxbvh.twolevel is the one import
