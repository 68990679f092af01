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


# ----------------------------------------------------------------------------------
# Scenes whose objects overlap, the kind partial re-braiding is for (issue 22)
# ----------------------------------------------------------------------------------


def by_material(vertices, faces, groups: int = 8, name: str = "by-material") -> Mesh:
    """One mesh split into objects by a material-like attribute, each placed once.

    Triangles are grouped by the direction of their normal (``groups`` in 2 ... 8: the
    octant of the normal for 8, the sign pattern of its first ``log2(groups)``
    components otherwise), the way a scanned or modelled scene's materials scatter: every
    group spans the whole mesh, so the objects' boxes overlap almost completely (the
    paper's San Miguel, Rungholt and Powerplant, whose objects are material groups).
    Empty groups are dropped. Every object keeps the world vertices it uses and is
    placed by the identity.
    """
    if groups not in (2, 4, 8):
        raise ValueError(f"groups must be 2, 4 or 8, got {groups}")
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int32)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    bits = int(round(np.log2(groups)))
    key = sum((normal[:, k] >= 0).astype(np.int64) << k for k in range(bits))
    objects = []
    for g in range(groups):
        mine = f[key == g]
        if mine.shape[0] == 0:
            continue
        used, local = np.unique(mine, return_inverse=True)
        objects.append((v[used], local.reshape(-1, 3).astype(np.int32)))
    return assemble(objects, [(k, np.eye(4)) for k in range(len(objects))], name=name)


def pile(key, vertices, faces, n_instances: int = 12, *, jitter: float = 0.1, name: str = "pile") -> Mesh:
    """``n_instances`` uniformly rotated instances of one mesh piled around one centre.

    Positions are uniform in a cube of side ``jitter`` x the mesh's largest extent around
    the origin, so every instance overlaps every other: rotated instances reach the top
    level only through the loose world boxes of their rotated object boxes.
    """
    if n_instances < 1 or not jitter >= 0:
        raise ValueError(f"need n_instances >= 1 and jitter >= 0, got {n_instances}, {jitter}")
    v, size = _centred(vertices)
    k_rot, k_pos = jax.random.split(key)
    rotations = random_rotations(k_rot, n_instances)
    positions = (np.asarray(jax.random.uniform(k_pos, (n_instances, 3)), np.float64) - 0.5) * jitter * size
    instances = [(0, _transform(r, 1.0, p)) for r, p in zip(rotations, positions)]
    return assemble([(v, np.asarray(faces, np.int32))], instances, name=name)


def rod(length: float, radius: float, sides: int = 6, segments: int = 16):
    """A closed-ended ``sides``-gon tube along x from 0 to ``length``, cut into
    ``segments`` rings: ``(vertices, faces)``, ``2 sides segments`` triangles (open ends)."""
    angle = 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([np.zeros(sides), radius * np.cos(angle), radius * np.sin(angle)], 1)
    xs = np.linspace(0.0, length, segments + 1)
    vertices = np.concatenate([ring + np.array([x, 0.0, 0.0]) for x in xs])
    faces = []
    for s in range(segments):
        for k in range(sides):
            a, b = s * sides + k, s * sides + (k + 1) % sides
            faces += [(a, b, a + sides), (b, b + sides, a + sides)]
    return vertices, np.asarray(faces, np.int32)


def rails(key, vertices, faces, n_compact: int = 24, n_rails: int = 6, name: str = "rails") -> Mesh:
    """Long thin objects across a scene among compact ones (the paper's Powerplant pipes).

    ``n_compact`` instances of the mesh (unit size, scale 0.6-1.2, upright rotations)
    stand on a square ground of side ``2 sqrt(n_compact)``; ``n_rails`` rods (rails,
    kerbs, wires), each its own object placed once, run across the whole square at
    random heights and directions in the ground plane, through the compact objects' boxes.
    """
    if n_compact < 1 or n_rails < 1:
        raise ValueError(f"need n_compact >= 1 and n_rails >= 1, got {n_compact}, {n_rails}")
    v, size = _centred(vertices)
    v = v / size
    side = 2.0 * np.sqrt(n_compact)
    k_rot, k_scale, k_pos, k_rail = jax.random.split(key, 4)
    rotations = upright_rotations(k_rot, n_compact)
    scales = np.asarray(jax.random.uniform(k_scale, (n_compact,), minval=0.6, maxval=1.2), np.float64)
    positions = (np.asarray(jax.random.uniform(k_pos, (n_compact, 3)), np.float64) - 0.5) * side
    positions[:, 1] = 0.5 * scales
    objects = [(v, np.asarray(faces, np.int32))]
    instances = [(0, _transform(r, s, p)) for r, s, p in zip(rotations, scales, positions)]
    draw = np.asarray(jax.random.uniform(k_rail, (n_rails, 3)), np.float64)
    for k in range(n_rails):
        length = side * np.sqrt(2.0)
        rv, rf = rod(length, 0.02, segments=32)
        turn = upright_rotations(jax.random.fold_in(k_rail, k), 1)[0]
        start = np.array([-0.5 * length, 0.2 + 0.8 * draw[k, 1], (draw[k, 2] - 0.5) * side * 0.5])
        moved = (rv + start) @ turn.T
        objects.append((moved, rf))
        instances.append((len(objects) - 1, np.eye(4)))
    return assemble(objects, instances, name=name)


def mixed(key, vertices, faces, n_once: int = 8, n_instanced: int = 16, name: str = "mixed") -> Mesh:
    """Objects placed once beside instanced ones, all in one room, overlapping.

    The room (one object, placed once), ``n_once`` distinct objects placed once (the mesh
    split by material, :func:`by_material`, then each group scaled to the room and
    moved at random, so each spans a large part of it) and ``n_instanced`` randomly
    rotated instances of the mesh at unit size scattered through the room.
    """
    v, size = _centred(vertices)
    v = v / size
    half, height = 4.0, 3.0
    parts = by_material(v, faces, groups=8).objects[:n_once]
    k_once, k_inst = jax.random.split(key)
    shift = (np.asarray(jax.random.uniform(k_once, (len(parts), 3)), np.float64) - 0.5) * np.array([2, 0.5, 2])
    objects = [room(half, height)]
    instances = [(0, np.eye(4))]
    for (pv, pf), d in zip(parts, shift):
        objects.append((pv * 5.0 + np.array([0.0, 1.5, 0.0]) + d, pf))
        instances.append((len(objects) - 1, np.eye(4)))
    shared = len(objects)
    objects.append((v, np.asarray(faces, np.int32)))
    k_rot, k_pos = jax.random.split(k_inst)
    rotations = random_rotations(k_rot, n_instanced)
    unit = np.asarray(jax.random.uniform(k_pos, (n_instanced, 3)), np.float64)
    positions = np.stack([-half + 1, 0.5, -half + 1]) + unit * np.stack([2 * half - 2, height - 1, 2 * half - 2])
    instances += [(shared, _transform(r, 1.0, p)) for r, p in zip(rotations, positions)]
    return assemble(objects, instances, name=name)


def furnished_room(key, n_objects: int = 254, triangles: int = 48, name: str = "room") -> Mesh:
    """A room of ``n_objects`` distinct objects, each placed once (the shape of San Miguel's
    254 objects): object 0 is the room's shell, the others are small random closed blobs
    (``triangles`` each, a perturbed octahedron subdivided) of many sizes standing
    anywhere in it, most compact and a few long (tables, shelves, beams).
    """
    if n_objects < 2:
        raise ValueError(f"n_objects must be >= 2, got {n_objects}")
    half, height = 4.0, 3.0
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    base_v, base_f = _blob(triangles)
    objects = [room(half, height)]
    for _ in range(n_objects - 1):
        extent = np.exp(rng.uniform(np.log(0.05), np.log(0.8), 3))
        if rng.uniform() < 0.1:  # a long one
            extent[rng.integers(3)] = rng.uniform(2.0, 6.0)
        centre = rng.uniform([-half, 0, -half], [half, height, half])
        bumps = 1 + 0.3 * rng.uniform(-1, 1, base_v.shape[0])[:, None]
        objects.append((base_v * bumps * extent + centre, base_f))
    return assemble(objects, [(k, np.eye(4)) for k in range(n_objects)], name=name)


def _blob(triangles: int):
    """An octahedron subdivided until it has at least ``triangles`` faces (unit radius)."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    for _ in range(8):  # bounded: 8 * 4^8 faces at most
        if f.shape[0] >= triangles:
            break
        mids = {}
        vs = list(v)

        def mid(a, b):
            k = (min(a, b), max(a, b))
            if k not in mids:
                m = 0.5 * (vs[a] + vs[b])
                vs.append(m / np.linalg.norm(m))
                mids[k] = len(vs) - 1
            return mids[k]

        new = []
        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        v, f = np.asarray(vs), np.asarray(new)
    return v, np.asarray(f, np.int32)
