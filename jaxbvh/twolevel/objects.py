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

Conservative world boxes
========================
:func:`world_boxes` maps an object-frame box to the scene frame: the box of its 8
transformed corners, computed per output axis as ``t_i + sum_j min(M_ij lo_j, M_ij hi_j)``
(Arvo 1990; the same box as the corners, without enumerating them). Rounding moves that
box by at most a few units in the last place of ``S_i = |t_i| + sum_j max(|M_ij lo_j|,
|M_ij hi_j|)``, and the cast matrix and the cast object boxes add one more each, so the
box is widened by ``margin * S_i + tiny`` with ``margin = 8 eps`` (16 units of rounding):
it always contains the exactly transformed triangles, hence their float32 boxes in
:meth:`Mesh.local_boxes`. Two properties make the JAX builder and its NumPy twin agree
bit for bit and keep flattened trees valid: no product feeds an addition directly (a
``min``/``max``/``abs`` sits between them, and ``margin`` is a power of two), so fused
multiply-adds cannot change a result; and every step is monotone in the box, so a child
box never pokes out of its parent's world box.
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
from jaxbvh.tree.layout import BVH, capacity_bucket, depth, to_numpy
from jaxbvh.tree.validate import validate


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
    ``margin`` [I] float; ``prim_shift`` [I] int32.
    """

    object: Any
    to_scene: Any
    to_object: Any
    margin: Any
    prim_shift: Any


# ----------------------------------------------------------------------------------
# Conservative world boxes
# ----------------------------------------------------------------------------------


def world_boxes(lo, hi, to_scene, margin):
    """Scene-frame boxes of object-frame boxes (module docstring), for JAX or NumPy arrays.

    ``lo``, ``hi`` [..., 3] object-frame boxes (finite); ``to_scene`` [..., 3, 4];
    ``margin`` [...] (0: exact map, no widening). Returns ``(lo, hi)`` [..., 3] in the
    boxes' dtype.
    """
    xp = jnp if isinstance(lo, jax.Array) or isinstance(to_scene, jax.Array) else np
    linear = to_scene[..., :, :3]
    a = linear * lo[..., None, :]  # [..., out, in]
    b = linear * hi[..., None, :]
    low = xp.minimum(a, b)
    high = xp.maximum(a, b)
    size = xp.maximum(xp.abs(a), xp.abs(b))
    t = to_scene[..., :, 3]
    # fixed order of additions, no product feeding an addition (module docstring)
    out_lo = ((t + low[..., 0]) + low[..., 1]) + low[..., 2]
    out_hi = ((t + high[..., 0]) + high[..., 1]) + high[..., 2]
    scale = ((xp.abs(t) + size[..., 0]) + size[..., 1]) + size[..., 2]
    dtype = lo.dtype
    tiny = xp.asarray(np.finfo(dtype).tiny, dtype)
    m = margin[..., None]
    widen = xp.where(m > 0, m * scale + tiny, xp.zeros((), dtype))
    return out_lo - widen, out_hi + widen


def frontier(left, right, node, depth: int):
    """The nodes ``depth`` levels below ``node`` (leaves above that level stand for
    themselves), for JAX or NumPy arrays.

    ``left``, ``right`` [N] int: a forest's children (-1: a leaf); ``node`` [...] int
    (-1: none). Returns int [..., 2^depth], -1 where no node: the *frontier* whose world
    boxes bound a node's under a rotation more tightly than its own (``bref_boxes``).
    """
    xp = jnp if isinstance(node, jax.Array) or isinstance(left, jax.Array) else np
    nodes = node[..., None]
    n = left.shape[0]
    for _ in range(depth):
        safe = xp.clip(nodes, 0, n - 1)
        kid_l = xp.where(nodes >= 0, left[safe], -1)
        kid_r = xp.where(nodes >= 0, right[safe], -1)
        inner = kid_l >= 0
        pair = xp.stack([xp.where(inner, kid_l, nodes), xp.where(inner, kid_r, -1)], axis=-1)
        nodes = pair.reshape(pair.shape[:-2] + (2 * pair.shape[-2],))
    return nodes


def bref_boxes(forest, to_scene, margin, node, depth: int):
    """Scene-frame boxes of forest nodes under their instances' maps, tighter than their
    own world boxes under a rotation (:mod:`jaxbvh.twolevel.brefs`, "BRef boxes"), for
    JAX or NumPy arrays.

    The union of the world boxes (:func:`world_boxes`) of the node's :func:`frontier`
    ``depth`` levels down. ``forest``: :class:`Forest`; ``to_scene`` [..., 3, 4],
    ``margin`` [...]: each node's instance map; ``node`` [...] int (-1: none, the empty
    box). It contains every triangle below the node, and the box of a child is inside
    its parent's (each frontier node of the child lies below one of the parent's, and
    world boxes are monotone), so a flattened tree with these boxes is valid. Under the
    identity it is the node's own box. Returns ``(lo, hi)`` [..., 3]; min/max only, so
    exact and equal in XLA and NumPy.
    """
    xp = jnp if isinstance(node, jax.Array) or isinstance(forest.lo, jax.Array) else np
    front = frontier(forest.left, forest.right, node, depth)  # [..., K]
    ok = front >= 0
    safe = xp.clip(front, 0, forest.lo.shape[0] - 1)
    lo, hi = world_boxes(forest.lo[safe], forest.hi[safe], to_scene[..., None, :, :], margin[..., None])
    inf = xp.asarray(np.inf, forest.lo.dtype)
    lo = xp.where(ok[..., None], lo, inf).min(axis=-2)
    hi = xp.where(ok[..., None], hi, -inf).max(axis=-2)
    return lo, hi


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


#: the object BVHs' builder unless told otherwise: binned SAH, one primitive per leaf (the
#: paper's choice; the command line's ``jaxbvh rebraid`` reads its defaults from it)
DEFAULT_BUILDER = BinnedConfig()


def object_builder(builder: BuilderConfig | None = None, **options) -> BuilderConfig:
    """The builder Config of the object BVHs: ``builder`` (None: :data:`DEFAULT_BUILDER`),
    or in the older keyword form the Config of ``method`` (default: the default's) made
    from ``options`` (``max_leaf``, ``bins``, ``ct``, ``ci``, ...; knobs of other builders
    are ignored, :func:`jaxbvh.builders.configs.make_config`). Not both at once."""
    if options:
        if builder is not None:
            raise TypeError("give a builder Config or keyword builder options, not both "
                            "(builder.replace(...) changes a Config)")
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
                 dtype=None, **options) -> ObjectTree:
    """BVH of one object's triangles where ``placement`` says (validated, padding stripped).

    ``builder``: the builder Config (None: :data:`DEFAULT_BUILDER`; or the keyword form,
    :func:`object_builder`);
    ``dtype``: float32 or float64 (needs x64) for the triangles and boxes (None: the
    builder's, float32 unless it says float64).
    """
    builder = object_builder(builder, **options)
    dtype = _dtype(builder, dtype)
    vertices = np.asarray(vertices, np.float64)
    if placement.baked is not None:  # the same arithmetic as Mesh.triangles
        t = placement.baked
        vertices = vertices @ t[:3, :3].T + t[:3, 3]
    tri = placement.frame.to_local(vertices[faces]).astype(dtype)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    tree = to_numpy(build(lo, hi, builder.replace(dtype=dtype)))
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
    ``builder`` (or the keyword form, :func:`object_builder`) and ``dtype``."""
    builder = object_builder(builder, **options)
    where = placements(mesh, world_space)
    ids = range(len(mesh.objects)) if only is None else only
    out = {}
    for obj in ids:
        vertices, faces = mesh.objects[obj]
        if faces.shape[0] == 0:
            raise ValueError(f"object {obj} of {mesh.name} has no triangles")
        out[obj] = build_object(vertices, faces, where[obj], builder, dtype=dtype)
    return out


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
    P, "instances": I}``, e.g. to give many scenes one shape). Raises ``ValueError``
    for a singular instance transform.
    """
    where = _check_placements(mesh, trees)
    used = sorted({obj for obj, _ in mesh.instances})
    dtype = np.asarray(trees[used[0]].tree.lo).dtype
    want = capacity or {}
    forest, prim_off = _pack_forest(trees, len(mesh.objects), dtype, pad=pad, want=want)
    return forest, _pack_instances(mesh, where, prim_off, dtype, pad=pad, want=want)


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
    """The object trees one after the other in object order: ``(Forest, prim_off)``,
    ``prim_off`` [O + 1] int64 the first primitive slot of every object."""
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
    return forest, prim_off


def _pack_instances(mesh, where: list[Placement], prim_off, dtype, *, pad: bool, want: dict) -> Instances:
    """The instances' maps between their object's frame and the scene frame (``ValueError``
    for a singular one, or one that does not fit ``dtype``)."""
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
    return Instances(object=obj_of, to_scene=to_scene, to_object=to_object, margin=margin,
                     prim_shift=prim_shift)
