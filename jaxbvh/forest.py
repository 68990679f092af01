"""Object BVHs packed into one forest, and the instances that place them in a scene.

A scene (:class:`jaxbvh.io.Mesh`) holds distinct *objects* (vertices, faces in object
space) and *instances* (object id, 4x4 transform), in the world triangle order of
:attr:`Mesh.triangles`: instance ``i`` owns the triangles ``prim_offset[i] ..
prim_offset[i] + faces of its object``, in the object's face order. This module builds
one BVH per object, once, in the object's own frame, and packs all of them into one
:class:`Forest` of fixed-shape arrays so that one jitted function reaches any object node.

Layout
======
:class:`Forest` is the :class:`~jaxbvh.tree.BVH` layout (:mod:`jaxbvh.tree`) for many
trees at once: object ``o``'s nodes keep the order its builder gave them and are offset
by the nodes of the objects before it; ``root`` [O] names each object's root.
``prim_index`` holds *object-triangle ids*: indices into ``triangles`` [T, 3, 3], the
triangles of all objects in their object frames, concatenated in object order.
``subtree_prims`` [N] counts the primitives under every node (exact; a BRef's primitive
count, :mod:`jaxbvh.brefs`). Arrays are padded to capacity buckets with inert entries.

:class:`Instances` [I] hold, per instance, its ``object``, the affine map ``to_scene``
[I, 3, 4] from the object's frame to the scene frame (:attr:`Mesh.frame`, where all
world-space boxes live), its inverse ``to_object`` (rays go this way), the relative
``margin`` its world boxes are widened by (0 for an exact, identity map) and
``prim_shift``: the world triangle id of object-triangle ``g`` under instance ``i`` is
``g + prim_shift[i]``.

Frames
======
An object that some instance places with the identity transform is built in the scene
frame itself (it is "built in world space", as the paper's dynamic objects are): its
boxes are then exactly the boxes a single BVH over the scene uses, its map is the
identity and its world boxes need no margin. Any other object is built in its own frame
(``Frame.fit`` of its boxes), which keeps float32 precise whatever the transforms; the
map ``to_scene = scene^-1 * transform * object`` is composed in float64 and then cast.

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

from jaxbvh.frame import Frame
from jaxbvh.tree import capacity_bucket, depth, to_numpy


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


def margin_for(dtype) -> float:
    """The relative widening of world boxes under a non-identity map: ``8 eps``."""
    return float(8 * np.finfo(dtype).eps)


# ----------------------------------------------------------------------------------
# Building and packing
# ----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ObjectTree:
    """One object's BVH (NumPy, padding stripped) in ``frame``, with its triangles."""

    tree: Any
    frame: Frame
    triangles: np.ndarray  # [f, 3, 3] in ``frame``, the tree's dtype


def object_frames(mesh) -> list[Frame]:
    """The frame every object of ``mesh`` is built in (module docstring)."""
    in_scene = {obj for obj, transform in mesh.instances if np.array_equal(transform, np.eye(4))}
    frames = []
    for obj, (vertices, faces) in enumerate(mesh.objects):
        if obj in in_scene or faces.shape[0] == 0:
            frames.append(mesh.frame)
        else:
            tri = vertices[faces]
            frames.append(Frame.fit(tri.min(axis=1), tri.max(axis=1)))
    return frames


def build_object(vertices, faces, frame: Frame, *, method="binned", max_leaf=1, bins=16,
                 ct=1.0, ci=1.0, dtype=np.float32) -> ObjectTree:
    """BVH of one object's triangles in ``frame`` (validated, padding stripped)."""
    import jaxbvh

    tri = frame.to_local(np.asarray(vertices, np.float64)[faces]).astype(dtype)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    tree = to_numpy(jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=bins, ct=ct,
                                 ci=ci, dtype=dtype))
    # the builder numbers nodes level by level from 0: real nodes are a prefix
    real = int(np.count_nonzero((tree.left >= 0) | (tree.prim_count > 0)))
    n = lo.shape[0]
    tree = jaxbvh.BVH(left=tree.left[:real], right=tree.right[:real], parent=tree.parent[:real],
                      lo=tree.lo[:real], hi=tree.hi[:real], prim_start=tree.prim_start[:real],
                      prim_count=tree.prim_count[:real], axis=tree.axis[:real],
                      prim_index=tree.prim_index[:n], root=np.int32(0))
    jaxbvh.validate(tree, lo, hi)
    return ObjectTree(tree=tree, frame=frame, triangles=tri)


def build_objects(mesh, *, method="binned", max_leaf=1, bins=16, ct=1.0, ci=1.0,
                  dtype=np.float32, only=None) -> dict[int, ObjectTree]:
    """:func:`build_object` for every object of ``mesh`` (or the ids in ``only``)."""
    frames = object_frames(mesh)
    ids = range(len(mesh.objects)) if only is None else only
    out = {}
    for obj in ids:
        vertices, faces = mesh.objects[obj]
        if faces.shape[0] == 0:
            raise ValueError(f"object {obj} of {mesh.name} has no triangles")
        out[obj] = build_object(vertices, faces, frames[obj], method=method, max_leaf=max_leaf,
                                bins=bins, ct=ct, ci=ci, dtype=dtype)
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


def pack(mesh, trees: dict[int, ObjectTree], *, pad: bool = True) -> tuple[Forest, Instances]:
    """Pack the object trees of ``mesh`` into one :class:`Forest` and its :class:`Instances`.

    ``trees`` must hold every object some instance uses, built in
    :func:`object_frames`' frames (checked). Returns NumPy arrays padded to capacity
    buckets (``pad=False``: exact sizes). Raises ``ValueError`` for a singular
    instance transform.
    """
    frames = object_frames(mesh)
    n_obj = len(mesh.objects)
    used = sorted({obj for obj, _ in mesh.instances})
    missing = [o for o in used if o not in trees]
    if missing:
        raise ValueError(f"no object tree for object(s) {missing}")
    for o in used:
        f = trees[o].frame
        if not (np.array_equal(f.origin, frames[o].origin) and f.scale == frames[o].scale):
            raise ValueError(f"object {o}'s tree was built in another frame than the scene needs "
                             "(the scene box changed); rebuild it")
    dtype = np.asarray(trees[used[0]].tree.lo).dtype
    node_off = np.zeros(n_obj + 1, np.int64)
    prim_off = np.zeros(n_obj + 1, np.int64)
    for o in range(n_obj):
        t = trees.get(o)
        node_off[o + 1] = node_off[o] + (t.tree.left.shape[0] if t is not None else 0)
        prim_off[o + 1] = prim_off[o] + (t.tree.prim_index.shape[0] if t is not None else 0)
    n_nodes, n_prims = int(node_off[-1]), int(prim_off[-1])
    cap_n = capacity_bucket(n_nodes) if pad else n_nodes
    cap_p = capacity_bucket(n_prims) if pad else n_prims

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

    n_inst = len(mesh.instances)
    cap_i = capacity_bucket(n_inst) if pad else n_inst
    scene_inverse = np.linalg.inv(_affine(mesh.frame))
    obj_of = np.zeros(cap_i, np.int32)
    to_scene = np.zeros((cap_i, 3, 4), dtype)
    to_scene[:, :, :3] = np.eye(3, dtype=dtype)
    to_object = to_scene.copy()
    margin = np.zeros(cap_i, dtype)
    prim_shift = np.zeros(cap_i, np.int32)
    offset = 0
    for i, (obj, transform) in enumerate(mesh.instances):
        m = scene_inverse @ np.asarray(transform, np.float64) @ _affine(frames[obj])
        if not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) == 0:
            raise ValueError(f"instance {i} (object {obj}) has a singular transform; it cannot "
                             "be traced in object space")
        inverse = np.linalg.inv(m)
        obj_of[i] = obj
        to_scene[i] = m[:3].astype(dtype)
        to_object[i] = inverse[:3].astype(dtype)
        margin[i] = 0 if np.array_equal(m, np.eye(4)) else margin_for(dtype)
        prim_shift[i] = offset - prim_off[obj]
        offset += mesh.objects[obj][1].shape[0]
    instances = Instances(object=obj_of, to_scene=to_scene, to_object=to_object, margin=margin,
                          prim_shift=prim_shift)
    return forest, instances
