"""Object BVHs packed into one forest, and the instances that place them in a scene.

A scene (:class:`jaxbvh.io.meshes.Mesh`) holds distinct *objects* (vertices, faces in object
space) and *instances* (object id, 4x4 transform), in the world triangle order of
:attr:`Mesh.triangles`: instance ``i`` owns the triangles ``prim_offset[i] ..
prim_offset[i] + faces of its object``, in the object's face order. This module builds
one BVH per object, once, in the object's own frame, and packs all of them into one
:class:`Forest` of fixed-shape arrays so that one jitted function reaches any object node.

Layout
======
:class:`Forest` is the :class:`~jaxbvh.tree.layout.BVH` layout (:mod:`jaxbvh.tree.layout`) for many
trees at once: object ``o``'s nodes keep the order its builder gave them and are offset
by the nodes of the objects before it; ``root`` [O] names each object's root.
``prim_index`` holds *object-triangle ids*: indices into ``triangles`` [T, 3, 3], the
triangles of all objects in their object frames, concatenated in object order.
``subtree_prims`` [N] counts the primitives under every node (exact; a BRef's primitive
count, :mod:`jaxbvh.twolevel.brefs`). Arrays are padded to capacity buckets with inert entries.

:class:`Instances` [I] hold, per instance, its ``object``, the affine map ``to_scene``
[I, 3, 4] from the object's frame to the scene frame (:attr:`Mesh.frame`, where all
world-space boxes live), its inverse ``to_object`` (rays go this way), the relative
``margin`` its world boxes are widened by (0 for an exact, identity map) and
``prim_shift``: the world triangle id of object-triangle ``g`` under instance ``i`` is
``g + prim_shift[i]``.

Frames
======
An object is *built in world space*, in the scene frame itself, when some instance
places it with the identity transform, or (``world_space=True``, the default) when
exactly one instance places it: its triangles are then moved to world space first, as
:meth:`Mesh.triangles` moves them, so its boxes are exactly the boxes a single BVH over
the scene uses, its map is the identity and its world boxes need no margin. (The paper
builds the objects of non-instanced scenes in world space too; an object-space tree of a
rotated object would only reach the top level through inflated boxes.) Any other object,
one that several instances share, is built once in its own frame (``Frame.fit`` of its
boxes), which keeps float32 precise whatever the transforms; the map ``to_scene =
scene^-1 * transform * object`` is composed in float64 and then cast.

Placed nodes' world boxes
=========================
The top level and the flattened tree see an object node under an instance through its
*world box* (:func:`bref_boxes`; the BRef box of :mod:`jaxbvh.twolevel.brefs`), one per
(instance, node), computed once by :func:`pack` into ``Instances.world_lo`` /
``world_hi`` (row ``f + box_shift[i]``): under the identity, the node's own box; under
any other map, the box of the node's triangles as the instance places them -- every
object-frame vertex ``v`` of the node's leaves mapped to ``t + M v`` in float64 (the
products of float32 inputs are exact), each coordinate widened by ``margin * (|t_i| +
sum_j |M_ij v_j|) + tiny`` with ``margin = 8 eps`` of the boxes' dtype (16 units of
rounding: the casts of the vertex, the map and the world triangle add about 2) and one
``eps`` more (rounding the result to the dtype), the leaves' boxes refit bottom-up. So it contains the
exactly transformed triangles and their float32 world boxes of
:meth:`Mesh.local_boxes` (``jaxbvh.validate`` of the flattened tree checks it), and a
child's box lies inside its parent's. It is the tightest axis-aligned box of the node's
geometry up to that margin: under a rotation the box of a node's 8 transformed corners
is much looser (a pile of 6 rotated cows: the roots' corner boxes have 1.4-2.0x the
half-area of their geometry's box, the union of the corner boxes three levels down, the
rule before, still 1.1-1.4x), and rotated instances reach the top level only through
these boxes. O(triangles) per instance and one row per placed node: the size of the flattened
tree, built once per :func:`pack`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders.configs import BinnedConfig, BuilderConfig, make_config
from jaxbvh.builders.dispatch import build
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.layout import BVH, capacity_bucket, concat_ranges, depth, to_numpy
from jaxbvh.tree.validate import validate
from jaxbvh.tree.walks import levels


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Forest:
    """Object BVHs as one set of arrays (layout: module docstring).

    ``left``, ``right``, ``parent``, ``prim_start``, ``prim_count``, ``axis``,
    ``subtree_prims`` [N] int32; ``lo``, ``hi`` [N, 3] float (object frames);
    ``prim_index`` [P] int32 object-triangle ids; ``root`` [O] int32;
    ``triangles`` [T, 3, 3] float, object frames.
    """

    left: Any
    right: Any
    parent: Any
    lo: Any
    hi: Any
    prim_start: Any
    prim_count: Any
    axis: Any
    prim_index: Any
    subtree_prims: Any
    root: Any
    triangles: Any

    @property
    def capacity(self) -> int:
        return int(self.left.shape[0])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Instances:
    """Placed objects (layout: module docstring); padded entries are identity maps of object 0.

    ``object`` [I] int32; ``to_scene``, ``to_object`` [I, 3, 4] float;
    ``margin`` [I] float; ``prim_shift`` [I] int32; ``box_shift`` [I] int32 and
    ``world_lo``, ``world_hi`` [W, 3] float: the world box of forest node ``f`` under
    instance ``i`` is row ``f + box_shift[i]`` (:func:`bref_boxes`).
    """

    object: Any
    to_scene: Any
    to_object: Any
    margin: Any
    prim_shift: Any
    box_shift: Any
    world_lo: Any
    world_hi: Any


# ----------------------------------------------------------------------------------
# Placed nodes' world boxes
# ----------------------------------------------------------------------------------


def bref_boxes(instances, node, inst):
    """Scene-frame boxes of forest nodes ``node`` under instances ``inst`` (module
    docstring, "Placed nodes' world boxes"), for JAX or NumPy arrays: a look-up in
    ``instances.world_lo`` / ``world_hi``.

    ``instances``: :class:`Instances`; ``node``, ``inst`` [...] int (node -1: none, the
    empty box). Returns ``(lo, hi)`` [..., 3]: each box contains every triangle below the
    node as the instance places it, and a child's box lies inside its parent's. Exact
    (a gather), so equal in XLA and NumPy.
    """
    xp = jnp if isinstance(node, jax.Array) or isinstance(instances.world_lo, jax.Array) else np
    rows = instances.world_lo.shape[0]
    k = xp.clip(inst, 0, instances.box_shift.shape[0] - 1)
    row = xp.where(node >= 0, node + instances.box_shift[k], -1)
    ok = ((row >= 0) & (row < rows))[..., None]
    safe = xp.clip(row, 0, rows - 1)
    inf = xp.asarray(np.inf, instances.world_lo.dtype)
    return xp.where(ok, instances.world_lo[safe], inf), xp.where(ok, instances.world_hi[safe], -inf)


def _placed_boxes(forest: Forest, node_off, obj_of, to_scene, margin, n_inst: int, *, pad: bool,
                  want: dict):
    """The world boxes of every node of every instance (module docstring): ``(box_shift
    [len(obj_of)] int32, world_lo, world_hi [W, 3])``, NumPy in ``forest.lo``'s dtype.

    Instance ``i``'s rows are its object's nodes in forest order; under the identity they
    are the forest's own boxes. Under any other map every vertex ``v`` of a leaf maps to
    ``t + M v`` in float64, widened by ``(margin + eps) * (|t| + |M| |v|) + tiny`` (the
    extra ``eps`` of the dtype: rounding the result to the dtype cannot move it inward);
    a leaf takes the box of its vertices, an interior node the union of its children's,
    bottom-up (O(triangles) per instance). Rows are padded to a capacity bucket
    (``pad``; at least ``want["boxes"]``) with empty boxes.
    """
    dtype = forest.lo.dtype
    obj = obj_of[:n_inst].astype(np.int64)
    sizes = (node_off[obj + 1] - node_off[obj]).astype(np.int64)
    base = np.cumsum(sizes) - sizes
    shift = np.zeros(obj_of.shape[0], np.int64)
    shift[:n_inst] = base - node_off[obj]
    cap = max(capacity_bucket(int(sizes.sum())) if pad else int(sizes.sum()), want.get("boxes", 0))
    lo = np.full((cap, 3), np.inf, dtype)
    hi = np.full((cap, 3), -np.inf, dtype)
    f = concat_ranges(node_off[obj], sizes)  # forest node of every row
    lo[:f.size], hi[:f.size] = forest.lo[f], forest.hi[f]  # final under the identity
    leaves: dict[int, tuple] = {}  # per object: its leaves, their first vertex rows, the vertices
    tiny, eps = np.finfo(dtype).tiny, np.finfo(dtype).eps
    moved = np.flatnonzero(margin[:n_inst] > 0)
    for i in moved:
        o = int(obj[i])
        if o not in leaves:
            nodes = np.arange(node_off[o], node_off[o + 1])
            leaf = nodes[forest.prim_count[nodes] > 0]
            counts = forest.prim_count[leaf].astype(np.int64)
            v = forest.triangles[forest.prim_index[concat_ranges(forest.prim_start[leaf], counts)]]
            v = v.reshape(-1, 3).astype(np.float64)  # 3 vertices a slot, the leaves' slots in order
            leaves[o] = (leaf, np.cumsum(counts) - counts, v, np.abs(v), bool(np.all(counts == 1)))
        leaf, first, v, size, single = leaves[o]
        linear, t = to_scene[i, :, :3].astype(np.float64), to_scene[i, :, 3].astype(np.float64)
        point = v @ linear.T + t  # products of float32 inputs are exact in float64
        widen = (float(margin[i]) + eps) * (size @ np.abs(linear).T + np.abs(t)) + tiny
        tri_lo = (point - widen).reshape(-1, 3, 3).min(axis=1)  # per slot
        tri_hi = (point + widen).reshape(-1, 3, 3).max(axis=1)
        rows = leaf + shift[i]
        lo[rows] = tri_lo if single else np.minimum.reduceat(tri_lo, first, axis=0)
        hi[rows] = tri_hi if single else np.maximum.reduceat(tri_hi, first, axis=0)
    # refit the interior rows of those instances bottom-up, a level at a time (in the
    # dtype: rounding is monotone, so it commutes with min and max)
    rows = concat_ranges(base[moved], sizes[moved])
    inner = rows[forest.left[f[rows]] >= 0]
    level = forest_depths(forest)[f[inner]]
    inner = inner[np.argsort(-level, kind="stable")]
    ends = np.cumsum(np.bincount(level.max(initial=0) - level))
    for a, b in zip(np.concatenate([[0], ends[:-1]]), ends):
        rows = inner[a:b]
        kid_l = forest.left[f[rows]] + shift[np.searchsorted(base, rows, "right") - 1]
        kid_r = kid_l - forest.left[f[rows]] + forest.right[f[rows]]
        lo[rows] = np.minimum(lo[kid_l], lo[kid_r])
        hi[rows] = np.maximum(hi[kid_l], hi[kid_r])
    return shift.astype(np.int32), lo, hi


def forest_depths(forest) -> np.ndarray:
    """Depth of every forest node below its object's root [N] int64 (-1: padding).

    ``forest``: a :class:`Forest` (any object with ``left``, ``right`` [N] and ``root``
    int arrays). Raises ``ValueError`` if the links hold a cycle (the walk is bounded).
    """
    child = np.stack([forest.left, forest.right], axis=1)
    by_depth = levels(child, forest.root[forest.root >= 0])
    if len(by_depth) > child.shape[0]:  # deeper than its node count: a cycle
        raise ValueError("forest links do not end in leaves (a cycle): refusing to compute node depths")
    out = np.full(child.shape[0], -1, np.int64)
    for d, ids in enumerate(by_depth):
        out[ids] = d
    return out


def margin_for(dtype) -> float:
    """The relative widening of world boxes under a non-identity map: ``8 eps``."""
    return float(8 * np.finfo(dtype).eps)


# ----------------------------------------------------------------------------------
# Building and packing
# ----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Placement:
    """Where an object is built: in ``frame``, after moving it by ``baked`` (None: as it is)."""

    frame: Frame
    baked: np.ndarray | None = None

    def same(self, other: "Placement") -> bool:
        """Whether ``other`` places an object identically (same frame, same baked transform
        or none)."""
        return (np.array_equal(self.frame.origin, other.frame.origin) and self.frame.scale == other.frame.scale
                and (self.baked is None) == (other.baked is None)
                and (self.baked is None or np.array_equal(self.baked, other.baked)))


@dataclasses.dataclass(frozen=True)
class ObjectTree:
    """One object's BVH (NumPy, padding stripped), built as ``placement`` says, with its triangles."""

    tree: Any
    placement: Placement
    triangles: np.ndarray  # [f, 3, 3] in the placement's frame, the tree's dtype


def placements(mesh, world_space: bool = True) -> list[Placement]:
    """Where every object of ``mesh`` is built (module docstring, "Frames")."""
    users: dict[int, list] = {}
    for obj, transform in mesh.instances:
        users.setdefault(obj, []).append(np.asarray(transform, np.float64))
    out = []
    for obj, (vertices, faces) in enumerate(mesh.objects):
        placed = users.get(obj, [])
        if any(np.array_equal(t, np.eye(4)) for t in placed) or faces.shape[0] == 0:
            out.append(Placement(mesh.frame))
        elif world_space and len(placed) == 1:
            out.append(Placement(mesh.frame, baked=placed[0]))
        else:
            tri = vertices[faces]
            out.append(Placement(Frame.fit(tri.min(axis=1), tri.max(axis=1))))
    return out


#: the object BVHs' largest leaf: 4, below the builders' :data:`jaxbvh.configs.DEFAULT_MAX_LEAF`
#: (16). Re-braiding opens object *nodes*; a small object that the SAH packs into one leaf
#: of up to 16 leaves nothing to open (piles of 22-triangle trees then kept the plain top
#: level, tests/twolevel), and the leaves study below measured 4.
OBJECT_MAX_LEAF = 4

#: the object BVHs' builder unless told otherwise: binned SAH with leaves of up to
#: :data:`OBJECT_MAX_LEAF` primitives where the SAH says a leaf costs less (the command
#: line's ``jaxbvh rebraid`` reads its defaults from it). Against the paper's one primitive
#: per leaf, on 7 bench scenes (by-material fandisk and cow, a pile of 12 cows, a room of
#: 254 objects, drone, legocar, a forest of 64 instanced trees; re-braided at the default
#: threshold): flattened SAH 2.4-12.2% lower, box tests per random ray 3.5-14% fewer, stored
#: nodes 42-58% fewer, every hit the same (2026-12-04, bench/results/rebraid_leaves.md).
DEFAULT_BUILDER = BinnedConfig(max_leaf=OBJECT_MAX_LEAF)


def object_builder(builder: BuilderConfig | None = None, **options) -> BuilderConfig:
    """The builder Config of the object BVHs: ``builder`` (None: :data:`DEFAULT_BUILDER`),
    or in the older keyword form the Config of ``method`` (default: the default's) made
    from ``options`` (``max_leaf``, default :data:`OBJECT_MAX_LEAF`, ``bins``, ``ct``,
    ``ci``, ...; knobs of other builders are ignored,
    :func:`jaxbvh.builders.configs.make_config`). Not both at once."""
    if options:
        if builder is not None:
            raise TypeError("give a builder Config or keyword builder options, not both "
                            "(builder.replace(...) changes a Config)")
        options.setdefault("max_leaf", OBJECT_MAX_LEAF)
        return make_config(options.pop("method", DEFAULT_BUILDER.method), **options)
    if builder is None:
        return DEFAULT_BUILDER
    if not isinstance(builder, BuilderConfig):
        raise TypeError(f"builder must be a builder Config (jaxbvh.builders.configs), got {type(builder).__name__}")
    return builder


def _dtype(builder: BuilderConfig, dtype) -> np.dtype:
    """The object BVHs' float type: ``dtype``, else the builder's (float32 when it names none)."""
    return np.dtype(dtype if dtype is not None else builder.dtype if builder.dtype is not None else np.float32)


def build_object(vertices, faces, placement: Placement, builder: BuilderConfig | None = None, *,
                 dtype=None, capacity: int | None = None, **options) -> ObjectTree:
    """BVH of one object's triangles where ``placement`` says (validated, padding stripped).

    ``builder``: the builder Config (None: :data:`DEFAULT_BUILDER`; or the keyword form,
    :func:`object_builder`);
    ``dtype``: float32 or float64 (needs x64) for the triangles and boxes (None: the
    builder's, float32 unless it says float64); ``capacity``: primitive slots the
    builder pads to (``jaxbvh.build``'s; None: its capacity bucket). The tree does not
    depend on it (padding is stripped), only which compiled program builds it.
    """
    builder = object_builder(builder, **options)
    dtype = _dtype(builder, dtype)
    vertices = np.asarray(vertices, np.float64)
    if placement.baked is not None:  # the same arithmetic as Mesh.triangles
        t = placement.baked
        vertices = vertices @ t[:3, :3].T + t[:3, 3]
    tri = placement.frame.to_local(vertices[faces]).astype(dtype)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    tree = to_numpy(build(lo, hi, builder.replace(dtype=dtype), capacity=capacity))
    # the builder numbers nodes level by level from 0: real nodes are a prefix
    real = int(np.count_nonzero((tree.left >= 0) | (tree.prim_count > 0)))
    n = lo.shape[0]
    tree = BVH(left=tree.left[:real], right=tree.right[:real], parent=tree.parent[:real],
                      lo=tree.lo[:real], hi=tree.hi[:real], prim_start=tree.prim_start[:real],
                      prim_count=tree.prim_count[:real], axis=tree.axis[:real],
                      prim_index=tree.prim_index[:n], root=np.int32(0))
    validate(tree, lo, hi)
    return ObjectTree(tree=tree, placement=placement, triangles=tri)


def build_objects(mesh, builder: BuilderConfig | None = None, *, dtype=None, world_space=True, only=None,
                  **options) -> dict[int, ObjectTree]:
    """:func:`build_object` for every object of ``mesh`` (or the ids in ``only``), with
    ``builder`` (or the keyword form, :func:`object_builder`) and ``dtype``, all padded to
    one capacity where :func:`shared_capacity` allows (one compiled builder program)."""
    builder = object_builder(builder, **options)
    where = placements(mesh, world_space)
    ids = list(range(len(mesh.objects)) if only is None else only)
    for obj in ids:
        if mesh.objects[obj][1].shape[0] == 0:
            raise ValueError(f"object {obj} of {mesh.name} has no triangles")
    capacity = shared_capacity([mesh.objects[obj][1].shape[0] for obj in ids], builder)
    return {obj: build_object(*mesh.objects[obj], where[obj], builder, dtype=dtype, capacity=capacity)
            for obj in ids}


#: objects share one builder program when padding them all to the largest one's bucket
#: at most doubles their slots in all (:func:`shared_capacity`)
SHARED_PADDING = 2.0


def shared_capacity(sizes, builder: BuilderConfig) -> int | None:
    """The primitive slots the objects of ``sizes`` (triangles per object) are built
    with: the capacity bucket of the largest, so that one compiled builder program
    builds them all (issue 38: a by-material spot's eight objects of 615-949 triangles
    fell in two buckets, two programs of ~860 StableHLO ops, ~9 CPU-s of XLA each), as
    long as that at most doubles their slots in all (:data:`SHARED_PADDING`: a scene of
    one large object and many small ones would pay in run time, a build per object at
    the large size, more than the compiles it saves). None (each object its own bucket)
    otherwise, or when the builder does not pad (``pad=False``). The trees do not depend
    on it."""
    if not sizes or not builder.pad:
        return None
    shared = capacity_bucket(max(sizes))
    own = sum(capacity_bucket(n) for n in sizes)
    return shared if shared * len(sizes) <= SHARED_PADDING * own else None


def subtree_prims(tree) -> np.ndarray:
    """Primitives under every node [N] int32 (0 for padding), bottom-up by depth."""
    t = to_numpy(tree)
    out = np.asarray(t.prim_count, np.int64).copy()
    d = depth(t)
    parent = np.asarray(t.parent)
    for level in range(int(d.max()), 0, -1):
        nodes = np.flatnonzero(d == level)
        np.add.at(out, parent[nodes], out[nodes])
    return out.astype(np.int32)


def _affine(frame: Frame) -> np.ndarray:
    """4x4 float64 matrix of ``frame``'s map from local to world."""
    m = np.eye(4)
    m[:3, :3] *= frame.scale
    m[:3, 3] = frame.origin
    return m


def pack(mesh, trees: dict[int, ObjectTree], *, pad: bool = True,
         capacity: dict | None = None) -> tuple[Forest, Instances]:
    """Pack the object trees of ``mesh`` into one :class:`Forest` and its :class:`Instances`.

    ``trees`` must hold every object some instance uses, each built where
    :func:`placements` says (checked). Returns NumPy arrays padded to capacity
    buckets (``pad=False``: exact sizes; ``capacity``: at least ``{"nodes": N, "prims":
    P, "instances": I, "boxes": W}``, e.g. to give many scenes one shape). Raises ``ValueError``
    for a singular instance transform.
    """
    where = _check_placements(mesh, trees)
    used = sorted({obj for obj, _ in mesh.instances})
    dtype = np.asarray(trees[used[0]].tree.lo).dtype
    want = capacity or {}
    forest, node_off, prim_off = _pack_forest(trees, len(mesh.objects), dtype, pad=pad, want=want)
    obj_of, to_scene, to_object, margin, prim_shift = _pack_instances(mesh, where, prim_off, dtype, pad=pad,
                                                                      want=want)
    box_shift, world_lo, world_hi = _placed_boxes(forest, node_off, obj_of, to_scene, margin,
                                                  len(mesh.instances), pad=pad, want=want)
    return forest, Instances(object=obj_of, to_scene=to_scene, to_object=to_object, margin=margin,
                             prim_shift=prim_shift, box_shift=box_shift, world_lo=world_lo, world_hi=world_hi)


def _check_placements(mesh, trees: dict[int, ObjectTree]) -> list[Placement]:
    """Every object an instance uses has a tree built where :func:`placements` says;
    returns those placements (``ValueError`` otherwise)."""
    used = sorted({obj for obj, _ in mesh.instances})
    missing = [o for o in used if o not in trees]
    if missing:
        raise ValueError(f"no object tree for object(s) {missing}")
    world_space = any(trees[o].placement.baked is not None for o in used)
    where = placements(mesh, world_space)
    for o in used:
        if not trees[o].placement.same(where[o]):
            raise ValueError(f"object {o}'s tree was built in another frame or placement than the "
                             "scene needs (the scene box or its instances changed); rebuild it")
    return where


def _pack_forest(trees: dict[int, ObjectTree], n_obj: int, dtype, *, pad: bool, want: dict):
    """The object trees one after the other in object order: ``(Forest, node_off,
    prim_off)``, ``node_off``, ``prim_off`` [O + 1] int64 the first node and primitive
    slot of every object."""
    node_off = np.zeros(n_obj + 1, np.int64)
    prim_off = np.zeros(n_obj + 1, np.int64)
    for o in range(n_obj):
        t = trees.get(o)
        node_off[o + 1] = node_off[o] + (t.tree.left.shape[0] if t is not None else 0)
        prim_off[o + 1] = prim_off[o] + (t.tree.prim_index.shape[0] if t is not None else 0)
    n_nodes, n_prims = int(node_off[-1]), int(prim_off[-1])
    cap_n = max(capacity_bucket(n_nodes) if pad else n_nodes, want.get("nodes", 0))
    cap_p = max(capacity_bucket(n_prims) if pad else n_prims, want.get("prims", 0))

    def ints(fill, size):
        return np.full(size, fill, np.int32)

    left, right, parent, axis = ints(-1, cap_n), ints(-1, cap_n), ints(-1, cap_n), ints(-1, cap_n)
    start, count, sub = ints(0, cap_n), ints(0, cap_n), ints(0, cap_n)
    lo = np.full((cap_n, 3), np.inf, dtype)
    hi = np.full((cap_n, 3), -np.inf, dtype)
    prim_index = ints(-1, cap_p)
    triangles = np.zeros((cap_p, 3, 3), dtype)
    root = ints(-1, n_obj)
    for o in range(n_obj):
        if o not in trees:
            continue
        t = trees[o].tree
        a, b = int(node_off[o]), int(node_off[o + 1])
        pa, pb = int(prim_off[o]), int(prim_off[o + 1])
        shift = lambda x, off: np.where(x >= 0, x + off, -1)  # noqa: E731
        left[a:b], right[a:b] = shift(t.left, a), shift(t.right, a)
        parent[a:b], axis[a:b] = shift(t.parent, a), t.axis
        leaf = t.prim_count > 0
        start[a:b] = np.where(leaf, t.prim_start + pa, 0)
        count[a:b] = t.prim_count
        sub[a:b] = subtree_prims(t)
        lo[a:b], hi[a:b] = t.lo, t.hi
        prim_index[pa:pb] = t.prim_index + pa
        triangles[pa:pb] = trees[o].triangles
        root[o] = a + int(t.root)
    forest = Forest(left=left, right=right, parent=parent, lo=lo, hi=hi, prim_start=start,
                    prim_count=count, axis=axis, prim_index=prim_index, subtree_prims=sub,
                    root=root, triangles=triangles)
    return forest, node_off, prim_off


def _pack_instances(mesh, where: list[Placement], prim_off, dtype, *, pad: bool, want: dict):
    """The instances' maps between their object's frame and the scene frame: the arrays
    ``object``, ``to_scene``, ``to_object``, ``margin``, ``prim_shift`` of
    :class:`Instances` (``ValueError`` for a singular map, or one that does not fit
    ``dtype``)."""
    n_inst = len(mesh.instances)
    cap_i = max(capacity_bucket(n_inst) if pad else n_inst, want.get("instances", 0))
    scene_inverse = np.linalg.inv(_affine(mesh.frame))
    obj_of = np.zeros(cap_i, np.int32)
    to_scene = np.zeros((cap_i, 3, 4), dtype)
    to_scene[:, :, :3] = np.eye(3, dtype=dtype)
    to_object = to_scene.copy()
    margin = np.zeros(cap_i, dtype)
    prim_shift = np.zeros(cap_i, np.int32)
    offset = 0
    for i, (obj, transform) in enumerate(mesh.instances):
        if where[obj].baked is not None:
            transform = np.eye(4)  # the object was moved to world space before building
        m = scene_inverse @ np.asarray(transform, np.float64) @ _affine(where[obj].frame)
        if not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) == 0:
            raise ValueError(f"instance {i} (object {obj}) has a singular transform; it cannot "
                             "be traced in object space")
        inverse = np.linalg.inv(m)
        if not (np.isfinite(m[:3].astype(dtype)).all() and np.isfinite(inverse[:3].astype(dtype)).all()):
            raise ValueError(f"instance {i} (object {obj}): its map to the scene frame does not fit "
                             f"{np.dtype(dtype).name} (object and scene sizes differ by ~1e38 or more)")
        obj_of[i] = obj
        to_scene[i] = m[:3].astype(dtype)
        to_object[i] = inverse[:3].astype(dtype)
        margin[i] = 0 if np.array_equal(m, np.eye(4)) else margin_for(dtype)
        prim_shift[i] = offset - prim_off[obj]
        offset += mesh.objects[obj][1].shape[0]
    return obj_of, to_scene, to_object, margin, prim_shift
