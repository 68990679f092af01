"""Synthetic multi-object scenes for two-level BVHs: instanced crowds and dynamic-in-static.

Both return :class:`jaxbvh.io.meshes.Mesh` objects, exactly as :func:`jaxbvh.io.meshes.load_mesh`
returns a scene file: distinct ``objects`` in object space, ``instances`` (object id,
4x4 transform) and the world-space triangles in instance order.

* :func:`instanced_scene` -- many overlapping, randomly rotated and scaled instances of
  a few objects (the shape of the paper's *Trees*: a few objects, thousands of
  instances whose boxes overlap heavily); :func:`tree_mesh` makes such objects, sparse
  branching trees whose boxes are mostly empty, so that neighbouring trees interleave.
* :func:`dynamic_scene` -- a static scene (a room, and instances of an object scattered
  in it) plus one object that moves and deforms every frame and is rebuilt in world
  space (the paper's *San Miguel* + robot). The room bounds everything, so the scene
  frame, and with it every static object's BVH, stays the same from frame to frame.

Random draws take an explicit ``jax.random`` key as the first argument.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from jaxbvh.io.meshes import Mesh


def assemble(objects, instances, name: str = "scene") -> Mesh:
    """A :class:`Mesh` from ``objects`` [(vertices float64 [v, 3], faces int [f, 3])] and
    ``instances`` [(object id, transform float64 [4, 4])], world triangles in instance order.

    A mirroring transform reverses its faces' winding, as :func:`jaxbvh.io.meshes.load_mesh` does.
    """
    objects = [(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in objects]
    instances = [(int(o), np.asarray(t, np.float64)) for o, t in instances]
    if not instances:
        raise ValueError("a scene needs at least one instance")
    world_v, world_f = [], []
    offset = 0
    for obj, transform in instances:
        if not 0 <= obj < len(objects):
            raise ValueError(f"instance of object {obj}, but there are {len(objects)} objects")
        vertices, faces = objects[obj]
        moved = vertices @ transform[:3, :3].T + transform[:3, 3]
        if np.linalg.det(transform[:3, :3]) < 0:
            faces = np.ascontiguousarray(faces[:, ::-1])
        world_v.append(moved)
        world_f.append(faces + offset)
        offset += vertices.shape[0]
    vertices = np.concatenate(world_v)
    faces = np.concatenate(world_f).astype(np.int32)
    if faces.shape[0] == 0:
        raise ValueError("the scene has no triangles")
    tri = vertices[faces]
    degenerate = int(np.sum(~np.any(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) != 0, axis=1)))
    return Mesh(vertices=vertices, faces=faces, name=name, degenerate=degenerate,
                objects=objects, instances=instances)


def random_rotations(key, n: int) -> np.ndarray:
    """``n`` uniformly random rotations float64 [n, 3, 3] (unit quaternions from normals)."""
    q = np.array(jax.random.normal(key, (n, 4)), np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def _centred(vertices) -> tuple[np.ndarray, float]:
    """Vertices moved so their box is centred on 0, and the largest extent."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    return v - 0.5 * (lo + hi), float(np.max(hi - lo))


def _transform(rotation, scale, position) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation * scale
    m[:3, 3] = position
    return m


def upright_rotations(key, n: int) -> np.ndarray:
    """``n`` uniformly random rotations about the y (up) axis, float64 [n, 3, 3]."""
    angle = np.asarray(jax.random.uniform(key, (n,)), np.float64) * 2 * np.pi
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros(n), np.ones(n)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1),
                     np.stack([-s, zero, c], -1)], axis=1)


def instanced_scene(key, objects, n_instances: int = 64, *, spread: float = 0.5, upright: bool = False,
                    scale: tuple[float, float] = (0.7, 1.3), name: str = "instanced") -> Mesh:
    """Many overlapping, randomly rotated instances of ``objects``.

    ``objects``: [(vertices [v, 3], faces [f, 3])], each moved to be centred on its box;
    each instance picks an object uniformly, a random rotation, a uniform scale in
    ``scale`` and a random position. Default: uniform rotations, positions uniform in a
    cube of side ``spread * size * n_instances ** (1/3)`` (``size``: the largest object
    extent). ``upright=True`` (a forest): rotations about the y axis only, positions on
    the ground (y = 0) in a square of side ``spread * size * n_instances ** (1/2)``.
    Either way neighbours sit about ``spread`` object sizes apart, and their boxes
    overlap when ``spread < 1``.
    """
    if n_instances < 1:
        raise ValueError(f"n_instances must be >= 1, got {n_instances}")
    if not spread > 0 or not 0 < scale[0] <= scale[1]:
        raise ValueError(f"spread must be > 0 and 0 < scale[0] <= scale[1], got {spread}, {scale}")
    centred = [_centred(v) for v, _ in objects]
    size = max(s for _, s in centred)
    k_obj, k_rot, k_scale, k_pos = jax.random.split(key, 4)
    which = np.asarray(jax.random.randint(k_obj, (n_instances,), 0, len(objects)))
    scales = np.asarray(jax.random.uniform(k_scale, (n_instances,), minval=scale[0], maxval=scale[1]),
                        np.float64)
    unit = np.asarray(jax.random.uniform(k_pos, (n_instances, 3)), np.float64) - 0.5
    if upright:
        rotations = upright_rotations(k_rot, n_instances)
        positions = unit * spread * size * n_instances ** 0.5
        positions[:, 1] = 0.0
    else:
        rotations = random_rotations(k_rot, n_instances)
        positions = unit * spread * size * n_instances ** (1 / 3)
    instances = [(int(o), _transform(r, s, p)) for o, r, s, p in zip(which, rotations, scales, positions)]
    return assemble([(v, f) for (v, _), (_, f) in zip(centred, objects)], instances, name=name)


def tree_mesh(key, *, levels: int = 4, branches: int = 3, sides: int = 6, leaves: int = 3):
    """A procedural tree (trunk, recursive branches, leaf quads): ``(vertices, faces)``.

    Every branch is an open ``sides``-gon tube (``2 * sides`` triangles) that ends in
    ``branches`` children, each tilted 25-65 degrees away from it and turned at random
    about it, 0.55-0.8 times as long and 0.6 times as thick, for ``levels`` levels; every
    tip carries ``leaves`` small quads. About 2,000 triangles with the defaults, most
    of its box empty. The same ``key`` gives the same tree.
    """
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    vertices: list = []
    faces: list = []

    def frame_of(direction):
        d = direction / np.linalg.norm(direction)
        helper = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 0, 1.0])
        u = np.cross(d, helper)
        u /= np.linalg.norm(u)
        return d, u, np.cross(d, u)

    def tube(a, b, radius):
        _, u, w = frame_of(b - a)
        base = len(vertices)
        for k in range(sides):
            angle = 2 * np.pi * k / sides
            ring = radius * (np.cos(angle) * u + np.sin(angle) * w)
            vertices.extend([a + ring, b + 0.7 * ring])
        for k in range(sides):
            i0, i1 = base + 2 * k, base + 2 * ((k + 1) % sides)
            faces.extend([(i0, i1, i0 + 1), (i1, i1 + 1, i0 + 1)])

    def leaf(at, direction, size):
        d, u, w = frame_of(direction + rng.normal(0, 0.5, 3))
        base = len(vertices)
        vertices.extend([at, at + size * (u + d), at + 2 * size * d, at + size * (d - u)])
        faces.extend([(base, base + 1, base + 2), (base, base + 2, base + 3)])
        del w

    def grow(a, direction, length, radius, level):
        b = a + direction * length
        tube(a, b, radius)
        if level == levels:
            for _ in range(leaves):
                leaf(b, direction, 0.35 * length)
            return
        d, u, w = frame_of(direction)
        for k in range(branches):
            tilt = np.radians(rng.uniform(25, 65))
            turn = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / branches
            child = np.cos(tilt) * d + np.sin(tilt) * (np.cos(turn) * u + np.sin(turn) * w)
            grow(b, child, length * rng.uniform(0.55, 0.8), radius * 0.6, level + 1)

    grow(np.zeros(3), np.array([0.0, 1.0, 0.0]), 1.0, 0.06, 0)
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int32)


def room(half: float, height: float):
    """A closed box room [-half, half] x [0, height] x [-half, half]: 12 triangles."""
    x = np.array([-half, half])
    corners = np.array([[x[i], (0.0, height)[j], x[k]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
    return corners, np.asarray(faces, np.int32)


@dataclasses.dataclass(frozen=True)
class DynamicScene:
    """A static scene plus one moving, deforming object (:func:`dynamic_scene`).

    ``static``: objects and instances that never change (object 0 is the room);
    ``moving``: the moving object's rest vertices [v, 3] (centred) and faces;
    ``frames``: number of frames; ``radius``, ``height``: its circular path.
    """

    static_objects: list
    static_instances: list
    moving_vertices: np.ndarray
    moving_faces: np.ndarray
    frames: int
    radius: float
    height: float
    wobble: float

    @property
    def moving_object(self) -> int:
        """Object id of the moving object in every frame's :class:`Mesh` (the last one)."""
        return len(self.static_objects)

    def moving_at(self, frame: int) -> np.ndarray:
        """World vertices [v, 3] of the moving object at ``frame``: on its path, deformed."""
        phase = 2 * np.pi * frame / max(self.frames, 1)
        v = self.moving_vertices
        size = float(np.max(np.ptp(v, axis=0)))
        bend = self.wobble * size * np.sin(2 * np.pi * v[:, 1] / size + 3 * phase)
        out = v.copy()
        out[:, 0] += bend
        out[:, 2] -= 0.5 * bend
        c, s = np.cos(phase), np.sin(phase)
        turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        return out @ turn.T + np.array([self.radius * c, self.height, self.radius * s])

    def frame(self, frame: int) -> Mesh:
        """The whole scene at ``frame``: static instances, then the moving object (identity)."""
        objects = list(self.static_objects) + [(self.moving_at(frame), self.moving_faces)]
        instances = list(self.static_instances) + [(self.moving_object, np.eye(4))]
        return assemble(objects, instances, name=f"dynamic-{frame}")


def dynamic_scene(key, vertices, faces, *, n_static: int = 32, frames: int = 8,
                  wobble: float = 0.05) -> DynamicScene:
    """A room with ``n_static`` randomly rotated instances of a mesh, and a moving copy of it.

    The room is 8 mesh sizes wide and 3 high; static instances (scale 0.6-1.2) stand at
    random places inside it, the moving object (scale 1) circles through them at
    mid-height, bending by ``wobble`` of its size (so its BVH must be rebuilt each frame).
    """
    if n_static < 0 or frames < 1:
        raise ValueError(f"need n_static >= 0 and frames >= 1, got {n_static}, {frames}")
    v, size = _centred(vertices)
    v = v / size  # unit size
    half, height = 4.0, 3.0
    k_rot, k_scale, k_pos = jax.random.split(key, 3)
    rotations = random_rotations(k_rot, n_static)
    scales = np.asarray(jax.random.uniform(k_scale, (n_static,), minval=0.6, maxval=1.2), np.float64)
    # an instance of scale s fits in a ball of radius s * sqrt(3) / 2 around its position
    reach = scales * np.sqrt(3) / 2
    unit = np.asarray(jax.random.uniform(k_pos, (n_static, 3)), np.float64)
    low = np.stack([-half + reach, reach, -half + reach], 1)
    high = np.stack([half - reach, height - reach, half - reach], 1)
    positions = low + unit * (high - low)
    static_objects = [room(half, height), (v, np.asarray(faces, np.int32))]
    static_instances = [(0, np.eye(4))] + [(1, _transform(r, s, p))
                                           for r, s, p in zip(rotations, scales, positions)]
    return DynamicScene(static_objects=static_objects, static_instances=static_instances,
                        moving_vertices=v, moving_faces=np.asarray(faces, np.int32), frames=frames,
                        radius=half - 1.5, height=height / 2, wobble=wobble)
