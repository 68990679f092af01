"""Loading triangle meshes and scenes into world-space triangles and their boxes.

Anything trimesh reads (OBJ, PLY, STL, glTF/GLB, OFF, ...) loads through
:func:`load_mesh` into a :class:`Mesh`: float64 world-space vertices, int32 faces, and
for scenes the distinct objects and their instances. The triangle order of a scene is
trimesh's ``Scene.to_geometry()`` order: instances in ``scene.graph.nodes_geometry``
order, each instance's faces in their stored order, vertices moved to world space (a
mirroring transform reverses the winding of its faces, as trimesh does).

Nothing is dropped silently. Files without triangles, non-finite coordinates, face
indices that name no vertex (an OBJ's index 0 included: OBJ counts from 1) and binary STL
files cut short raise :class:`MeshError` naming the file and the problem. Text that is
not UTF-8 is read as Latin-1 (:func:`_lenient_text`): the geometry of these formats is
ASCII, and trimesh would otherwise need an optional dependency to read a stray byte.
Zero-area triangles are kept (a BVH handles them fine) and counted in
:attr:`Mesh.degenerate`. Scene geometry that is not a triangle mesh (lines, points next
to meshes) is listed in :attr:`Mesh.skipped` and reported with a warning.

Trees are built in the scene :class:`~jaxbvh.tree.frame.Frame` (:meth:`Mesh.local_boxes`):
the float64 world boxes are moved into the frame on the host, then cast (round to
nearest) to the device dtype. Rounding is monotone, so the box of a cast triangle is
exactly the cast box, and :func:`jaxbvh.tree.validate` holds with no tolerance.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import re
import urllib.parse
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from jaxbvh import compile_cache
from jaxbvh.files import atomic_write, trim_least_recent
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.interchange import load
from jaxbvh.tree.validate import few_ids

__all__ = ["Mesh", "MeshError", "TreeFile", "load_mesh", "load_any", "bundled_mesh_path",
           "boxes_in_frame", "use_mesh_cache", "mesh_cache_folder"]

TREE_SUFFIXES = (".npz",)


class MeshError(ValueError):
    """A mesh file cannot be used: unreadable, no triangles, bad coordinates or indices."""


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in world space.

    ``vertices`` float64 [V, 3]; ``faces`` int32 [F, 3] (indices into ``vertices``);
    ``name``: the file's stem; ``degenerate``: number of zero-area triangles (kept);
    ``objects``: distinct geometries in object space, each ``(vertices float64 [v, 3],
    faces int32 [f, 3])``; ``instances``: ``(object_id, transform float64 [4, 4])`` in
    triangle order (a plain mesh is one object with one identity instance);
    ``skipped``: names of scene geometry that holds no triangles and was left out;
    ``path``: the file it came from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str
    degenerate: int
    objects: list = dataclasses.field(default_factory=list)
    instances: list = dataclasses.field(default_factory=list)
    skipped: tuple = ()
    path: str = ""

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    @functools.cached_property
    def triangles(self) -> np.ndarray:
        """Corner positions float64 [F, 3 corners, 3 coords], world space."""
        return self.vertices[self.faces]

    def prim_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """World boxes of the triangles: ``(lo, hi)`` float64 [F, 3]."""
        tri = self.triangles
        return tri.min(axis=1), tri.max(axis=1)

    @functools.cached_property
    def frame(self) -> Frame:
        """The scene frame: ``Frame.fit`` of the world triangle boxes."""
        return Frame.fit(*self.prim_boxes())

    def local_boxes(self, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
        """Triangle boxes in :attr:`frame`, cast to ``dtype``: ``(lo, hi)`` [F, 3]."""
        lo, hi = self.prim_boxes()
        return boxes_in_frame(lo, hi, self.frame, dtype)

    def local_triangles(self, dtype=np.float32) -> np.ndarray:
        """Triangles [F, 3, 3] in :attr:`frame`, cast to ``dtype``.

        Their per-triangle min/max equals :meth:`local_boxes` exactly (same rounding).
        """
        return self.frame.to_local(self.triangles).astype(dtype)


@dataclasses.dataclass(frozen=True, eq=False)
class TreeFile:
    """A tree read from an interchange ``.npz`` (:func:`jaxbvh.load`)."""

    tree: object
    frame: Frame
    path: str


def boxes_in_frame(world_lo, world_hi, frame: Frame, dtype=np.float32):
    """World boxes float64 [n, 3] -> ``frame`` coordinates cast to ``dtype``.

    The same conversion :meth:`Mesh.local_boxes` uses, for checking a saved tree
    against a mesh in the tree's frame.
    """
    if frame.is_identity:
        return np.asarray(world_lo).astype(dtype), np.asarray(world_hi).astype(dtype)
    return frame.to_local(world_lo).astype(dtype), frame.to_local(world_hi).astype(dtype)


def bundled_mesh_path() -> Path:
    """Path of the mesh shipped with the package (Keenan Crane's "Spot", CC0)."""
    return Path(str(resources.files("jaxbvh") / "data" / "spot.obj"))


# ----------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------


def _read(path: str):
    """``trimesh.load`` with every failure turned into a :class:`MeshError`.

    Before trimesh reads them: a binary STL whose size disagrees with its triangle count
    and an OBJ face that names vertex 0 are refused (:func:`_check_stl`,
    :func:`_check_obj`). Text is decoded leniently (:func:`_lenient_text`).
    """
    import trimesh

    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix == "stl":
        _check_stl(path)
    if suffix == "obj":
        _check_obj(path)
    try:
        with _lenient_text():
            return trimesh.load(path, process=False)
    except NotImplementedError:
        raise MeshError(f"{path}: unsupported file type '.{suffix}' "
                        "(trimesh reads e.g. obj, ply, stl, off, gltf, glb)") from None
    except IndexError as exc:
        # trimesh's OBJ reader indexes vertices with the face indices as it parses
        raise MeshError(f"{path}: face index out of range: a face names a vertex "
                        f"that does not exist ({exc})") from None
    except FileNotFoundError as exc:
        # a glTF whose buffer is missing, or a glTF that is not JSON (trimesh then
        # looks for a sidecar file)
        raise MeshError(f"{path}: cannot read as .{suffix}: malformed file or missing "
                        f"referenced file ({exc})") from None
    except Exception as exc:  # parser errors of every format: ValueError, KeyError, ...
        detail = str(exc) or type(exc).__name__
        raise MeshError(f"{path}: cannot read as .{suffix}: malformed file ({detail})") from None


@contextlib.contextmanager
def _lenient_text():
    """Text that is not UTF-8 decoded as Latin-1 while trimesh parses.

    trimesh decodes text formats (OBJ, MTL, ASCII STL/PLY, OFF) as UTF-8 and otherwise
    asks ``charset_normalizer``, an optional dependency it does not install, so one
    stray byte (an accented name in a comment) fails the whole file. Latin-1 maps every
    byte to one character, and the numbers and keywords of these formats are ASCII, so
    the geometry is read unchanged; only names and comments may differ.
    """
    import trimesh.util

    original = trimesh.util.decode_text

    def decode(text, initial: str = "utf-8"):
        if isinstance(text, str):
            return text
        try:
            return text.decode(initial)
        except UnicodeDecodeError:
            return text.decode("latin-1")

    trimesh.util.decode_text = decode
    try:
        yield
    finally:
        trimesh.util.decode_text = original


#: a binary STL: an 80-byte header, a uint32 triangle count, 50 bytes per triangle
_STL_HEADER, _STL_TRIANGLE = 84, 50


def _check_stl(path: str) -> None:
    """Refuse a binary STL whose size does not match its triangle count (truncated or
    padded); ASCII STL (``solid`` ...) and binary files that match are left to trimesh."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        head = f.read(_STL_HEADER)
    if size >= _STL_HEADER:
        count = int(np.frombuffer(head[80:84], "<u4")[0])
        if size == _STL_HEADER + _STL_TRIANGLE * count:
            return  # a binary STL whose size matches (its header may start with "solid")
    if head.lstrip().lower().startswith(b"solid"):
        return  # ASCII
    if size < _STL_HEADER:
        raise MeshError(f"{path}: truncated binary STL: {size} bytes, shorter than the "
                        f"{_STL_HEADER}-byte header")
    expected = _STL_HEADER + _STL_TRIANGLE * count
    what = "truncated" if size < expected else "damaged"
    raise MeshError(f"{path}: {what} binary STL: its header announces {count:,} triangles "
                    f"({expected:,} bytes), the file has {size:,} bytes")


#: an OBJ face record with a vertex index 0 (OBJ counts from 1; negative counts back)
_OBJ_ZERO_INDEX = re.compile(rb"(?m)^[ \t]*f[ \t](?:[^\n]*?[ \t])?0+(?=[/ \t\r\n]|$)")


def _check_obj(path: str) -> None:
    """Refuse an OBJ face that names vertex 0: OBJ indices start at 1, and trimesh would
    read 0 as the last vertex, a silent degenerate triangle."""
    with open(path, "rb") as f:
        data = f.read()
    match = _OBJ_ZERO_INDEX.search(data)
    if match:
        line = data.count(b"\n", 0, match.start()) + 1
        raise MeshError(f"{path}: face index 0 on line {line}: OBJ vertex indices start at 1 "
                        "(negative ones count back from the last vertex)")


def _obj_line_records(path: str) -> int:
    """Number of ``l`` (polyline) records in an OBJ file; trimesh drops them."""
    with open(path, "rb") as f:
        return sum(1 for line in f if line.lstrip().startswith(b"l "))


def _describe(geometry, path: str = "") -> str:
    kind = type(geometry).__name__
    if kind == "PointCloud":
        n = len(geometry.vertices)
        lines = _obj_line_records(path) if path.lower().endswith(".obj") else 0
        if lines:
            return f"{lines} line element(s) ('l' records) over {n} vertices"
        return f"a point cloud of {n} points"
    if kind in ("Path3D", "Path2D"):
        return f"a line set ({kind}) of {len(geometry.entities)} lines/curves"
    n = len(getattr(geometry, "vertices", ()))
    return f"a {kind} with {n} vertices and no faces"


def _geometry_arrays(path: str, name: str, geometry) -> tuple[np.ndarray, np.ndarray]:
    """Vertices float64 [v, 3], faces int32 [f, 3] of one trimesh geometry, checked."""
    vertices = np.asarray(geometry.vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(geometry.faces).reshape(-1, 3)
    where = f"{path}" + (f" (object '{name}')" if name else "")
    if faces.size:
        bad = (faces < 0) | (faces >= vertices.shape[0])
        if bad.any():
            rows = np.flatnonzero(bad.any(axis=1))
            raise MeshError(f"{where}: face index out of range: face(s) {few_ids(rows)} name vertex "
                            f"{int(faces[bad][0])}, but there are {vertices.shape[0]} vertices")
    return vertices, faces.astype(np.int32)


def _check_finite(where: str, vertices: np.ndarray, faces: np.ndarray):
    bad = ~np.isfinite(vertices).all(axis=1)
    if not bad.any():
        return
    ids = np.flatnonzero(bad)
    users = np.flatnonzero(bad[faces].any(axis=1)) if faces.size else np.zeros(0, int)
    used = f"used by face(s) {few_ids(users)}" if users.size else "used by no face"
    count = f"{ids.size} vertex" if ids.size == 1 else f"{ids.size} vertices"
    raise MeshError(f"{where}: NaN/inf coordinates in {count} "
                    f"(vertex index {few_ids(ids)}; {used})")


def _flips_winding(transform: np.ndarray) -> bool:
    return bool(np.linalg.det(transform[:3, :3]) < 0)


def _degenerate_count(triangles: np.ndarray) -> int:
    edge1 = triangles[:, 1] - triangles[:, 0]
    edge2 = triangles[:, 2] - triangles[:, 0]
    return int(np.sum(~np.any(np.cross(edge1, edge2) != 0, axis=1)))


# ----------------------------------------------------------------------------------
# Cache of parsed meshes (on beside jaxbvh's compilation cache, library and tool alike)
# ----------------------------------------------------------------------------------


class _FollowCompileCache:
    def __repr__(self) -> str:
        return "FOLLOW_COMPILE_CACHE"


#: :func:`use_mesh_cache`'s default: parsed meshes go beside jaxbvh's compilation cache
FOLLOW_COMPILE_CACHE = _FollowCompileCache()

#: FOLLOW_COMPILE_CACHE, the folder :func:`use_mesh_cache` set, or None (switched off)
_mesh_cache: "Path | _FollowCompileCache | None" = FOLLOW_COMPILE_CACHE
_CACHE_FORMAT = "1"

#: the cache of parsed meshes is kept under this size (bytes); the entries read longest
#: ago go first. A parsed mesh takes ~60 bytes a triangle (spot: 0.3 MB).
MAX_MESH_CACHE_BYTES = 2 * 1024 ** 3


def use_mesh_cache(folder: "str | os.PathLike | _FollowCompileCache | None"):
    """Keep every mesh :func:`load_mesh` parses in ``folder`` (``None``: no cache;
    :data:`FOLLOW_COMPILE_CACHE`: the default, below). Returns the setting before, to
    restore it with.

    Parsing a mesh file costs far more than reading back its arrays (trimesh's import
    alone takes 0.3 to 1.4 s, most of a warm script's start), so by default the cache is
    on wherever jaxbvh's compilation cache is (:func:`mesh_cache_folder`); call this to
    move it or, with ``None``, to switch it off. An entry is keyed by the file's absolute
    path, size, modification and change times and inode (for a glTF, also those of the
    files it names: its buffers), so an edited file is parsed again. Only meshes that
    loaded without error are kept; a damaged entry is ignored and parsed anew; the folder
    is kept under :data:`MAX_MESH_CACHE_BYTES`.
    """
    global _mesh_cache
    before = _mesh_cache
    _mesh_cache = folder if folder is None or folder is FOLLOW_COMPILE_CACHE else Path(folder)
    return before


def mesh_cache_folder() -> Path | None:
    """The folder parsed meshes are kept in (``None``: no cache): the one
    :func:`use_mesh_cache` set, else ``meshes/`` in jaxbvh's compilation cache folder
    while that cache is on (:func:`jaxbvh.compile_cache.mesh_cache_dir`; off with
    ``JAXBVH_CACHE=off`` or when you configured JAX's cache yourself)."""
    if _mesh_cache is not FOLLOW_COMPILE_CACHE:
        return _mesh_cache
    return compile_cache.mesh_cache_dir() if compile_cache.status()["owner"] == "jaxbvh" else None


def _cache_entry(path: str) -> Path | None:
    folder = mesh_cache_folder()
    if folder is None:
        return None
    files = [path] + (_gltf_references(path) if path.lower().endswith(".gltf") else [])
    parts = [_CACHE_FORMAT]
    for f in files:
        try:
            st = os.stat(f)
        except OSError:  # a missing buffer: parsing reports it, and nothing is cached
            parts += [os.path.abspath(f), "missing"]
            continue
        # the change time and inode too: a file rewritten with its old size and its
        # modification time put back (a copy tool, a build step) still gets a new key
        parts += [os.path.abspath(f), str(st.st_size), str(st.st_mtime_ns), str(st.st_ctime_ns), str(st.st_ino)]
    return folder / (hashlib.sha256("\0".join(parts).encode()).hexdigest()[:32] + ".npz")


def _gltf_references(path: str) -> list[str]:
    """The files a ``.gltf`` names (its buffers' and images' ``uri``, not ``data:`` URIs),
    as paths beside it; none when it is not readable JSON (parsing will say so).

    Only these are part of its cache key: other files in the folder (a symlink loop, a
    dangling link, another scene) are not the scene's and are never looked at.
    """
    try:
        with open(path, "rb") as f:
            document = json.loads(f.read().decode("utf-8", errors="replace"))
    except (OSError, ValueError):
        return []
    if not isinstance(document, dict):
        return []
    folder = os.path.dirname(os.path.abspath(path))
    found = []
    for section in ("buffers", "images"):
        entries = document.get(section)
        for entry in entries if isinstance(entries, list) else []:
            uri = entry.get("uri") if isinstance(entry, dict) else None
            if isinstance(uri, str) and uri and not uri.startswith("data:"):
                found.append(os.path.join(folder, urllib.parse.unquote(uri)))
    return sorted(set(found))


def _write_cached(entry: Path, mesh: "Mesh") -> None:
    arrays = {"vertices": mesh.vertices, "faces": mesh.faces, "name": np.str_(mesh.name),
              "degenerate": np.int64(mesh.degenerate), "skipped": np.array(mesh.skipped, dtype=str),
              "instance_object": np.array([i for i, _ in mesh.instances], np.int64),
              "instance_transform": np.array([t for _, t in mesh.instances], np.float64).reshape(-1, 4, 4)}
    for i, (vertices, faces) in enumerate(mesh.objects):
        arrays[f"object{i}_vertices"], arrays[f"object{i}_faces"] = vertices, faces
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(entry) as f:  # a reader in another process sees all or nothing
            np.savez(f, **arrays)
    except OSError:
        return  # a read-only cache folder: parse every time
    trim_least_recent(entry.parent.glob("*.npz"), MAX_MESH_CACHE_BYTES, keep=entry)


def _read_cached(entry: Path, path: str) -> "Mesh | None":
    try:
        with np.load(entry, allow_pickle=False) as data:
            objects, i = [], 0
            while f"object{i}_vertices" in data.files:
                objects.append((data[f"object{i}_vertices"], data[f"object{i}_faces"]))
                i += 1
            instances = [(int(o), t) for o, t in zip(data["instance_object"], data["instance_transform"])]
            skipped = tuple(str(x) for x in data["skipped"])
            mesh = Mesh(vertices=data["vertices"], faces=data["faces"], name=str(data["name"]),
                        degenerate=int(data["degenerate"]), objects=objects, instances=instances,
                        skipped=skipped, path=path)
    except Exception:  # a damaged or foreign entry: parse the file again
        return None
    with contextlib.suppress(OSError):
        os.utime(entry)  # read now: the last to be evicted
    if skipped:
        warnings.warn(f"{path}: left out {len(skipped)} object(s) without triangles: "
                      f"{', '.join(skipped[:5])}", stacklevel=3)
    return mesh


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read any file trimesh reads into a world-space :class:`Mesh` (module docstring).

    Raises ``FileNotFoundError`` for a missing file and :class:`MeshError` for a file
    that cannot be read or has no usable triangles. A file parsed before is read back
    from the cache of parsed meshes (:func:`mesh_cache_folder`; on by default).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    if os.path.isdir(path):
        raise MeshError(f"{path}: is a directory, expected a mesh file")
    entry = _cache_entry(path)
    if entry is not None and entry.exists():
        mesh = _read_cached(entry, path)
        if mesh is not None:
            return mesh
    mesh = _parse(path)
    if entry is not None:
        _write_cached(entry, mesh)
    return mesh


def _parse(path: str) -> Mesh:
    import trimesh

    loaded = _read(path)
    stem = Path(path).stem

    if isinstance(loaded, trimesh.Scene):
        names = list(loaded.geometry.keys())
        nodes = list(loaded.graph.nodes_geometry)
        placed = []
        for node in nodes:
            transform, geometry_name = loaded.graph[node]
            placed.append((np.asarray(transform, np.float64), geometry_name))
        geometries = loaded.geometry
    else:
        names = [stem]
        placed = [(np.eye(4), stem)]
        geometries = {stem: loaded}

    if not geometries:
        raise MeshError(f"{path}: no faces: the file holds no geometry (empty or unrecognised "
                        "content)")
    has_faces = {name: hasattr(g, "faces") and len(np.asarray(g.faces)) > 0
                 for name, g in geometries.items()}
    if not any(has_faces.values()):
        found = "; ".join(f"'{n}': {_describe(g)}" if len(geometries) > 1 else _describe(g, path)
                          for n, g in geometries.items())
        raise MeshError(f"{path}: no faces: found {found}; a BVH needs triangles")
    skipped = tuple(n for n in names if not hasattr(geometries[n], "faces"))
    if skipped:
        warnings.warn(f"{path}: left out {len(skipped)} object(s) without triangles: "
                      f"{', '.join(map(str, skipped[:5]))}", stacklevel=2)

    object_id = {}
    objects = []
    for name in names:
        if name in skipped:
            continue
        vertices, faces = _geometry_arrays(path, name if len(names) > 1 else "", geometries[name])
        _check_finite(path + (f" (object '{name}')" if len(names) > 1 else ""), vertices, faces)
        object_id[name] = len(objects)
        objects.append((vertices, faces))

    instances = []
    world_vertices, world_faces = [], []
    offset = 0
    for transform, name in placed:
        if name not in object_id:
            continue
        if not np.isfinite(transform).all():
            raise MeshError(f"{path}: instance of '{name}' has a NaN/inf transform")
        obj = object_id[name]
        vertices, faces = objects[obj]
        instances.append((obj, transform))
        moved = vertices @ transform[:3, :3].T + transform[:3, 3]
        if _flips_winding(transform):
            faces = np.ascontiguousarray(faces[:, ::-1])
        world_vertices.append(moved)
        world_faces.append(faces + offset)
        offset += vertices.shape[0]
    if not world_faces:
        raise MeshError(f"{path}: no faces: the scene places none of its meshes")
    vertices = np.concatenate(world_vertices).astype(np.float64)
    faces = np.concatenate(world_faces).astype(np.int32)
    if faces.shape[0] == 0:
        raise MeshError(f"{path}: no faces: its meshes hold 0 triangles")
    # a finite object can still overflow to inf under a huge transform
    _check_finite(f"{path} (world space)", vertices, faces)
    return Mesh(vertices=vertices, faces=faces, name=stem,
                degenerate=_degenerate_count(vertices[faces]), objects=objects,
                instances=instances, skipped=skipped, path=path)


def load_any(path: str | os.PathLike) -> Mesh | TreeFile:
    """A ``.npz`` path loads as a tree (:class:`TreeFile`), anything else as a :class:`Mesh`."""
    path = os.fspath(path)
    if Path(path).suffix.lower() in TREE_SUFFIXES:

        tree, frame = load(path)
        return TreeFile(tree=tree, frame=frame, path=path)
    return load_mesh(path)
