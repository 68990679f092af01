"""jaxbvh.io: meshes and scenes to world triangles, boxes and the scene frame."""

from __future__ import annotations

import os

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import SHARED_DATA
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.io import Mesh, MeshError, TreeFile, boxes_in_frame, bundled_mesh_path, load_any, load_mesh
from jaxbvh.testing.plugin import examples

needs_shared = pytest.mark.skipif(
    not SHARED_DATA.is_dir(), reason=f"shared test data not found at {SHARED_DATA} (clone without ../shared)")


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def obj_text(vertices, faces) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces).tolist()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------
# The bundled mesh
# ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spot() -> Mesh:
    return load_mesh(bundled_mesh_path())


def test_bundled_mesh_is_shipped_with_its_license():
    path = bundled_mesh_path()
    assert path.is_file() and path.name == "spot.obj"
    license_text = (path.parent / "LICENSE.md").read_text()
    assert "CC0" in license_text and "Keenan Crane" in license_text


def test_bundled_mesh_loads(spot):
    # trimesh splits OBJ vertices along UV seams, so compare triangles, not vertex counts
    assert spot.vertices.dtype == np.float64 and spot.vertices.shape[1] == 3
    assert spot.faces.dtype == np.int32 and spot.faces.shape == (5856, 3)
    assert_matches_trimesh(spot, bundled_mesh_path())
    assert spot.n_triangles == 5856 and spot.degenerate == 0
    assert spot.name == "spot"
    assert len(spot.objects) == 1 and len(spot.instances) == 1
    assert spot.instances[0][0] == 0 and np.array_equal(spot.instances[0][1], np.eye(4))
    assert spot.skipped == ()


def test_boxes_and_frame(spot):
    tri = spot.triangles
    assert tri.shape == (5856, 3, 3) and tri.dtype == np.float64
    lo, hi = spot.prim_boxes()
    assert lo.shape == hi.shape == (5856, 3) and lo.dtype == np.float64
    assert (lo <= tri.min(axis=1)).all() and (hi >= tri.max(axis=1)).all()
    frame = spot.frame
    assert frame == spot.frame  # cached: one object
    local_lo, local_hi = spot.local_boxes()
    assert local_lo.dtype == local_hi.dtype == np.float32
    assert local_lo.min() >= -1 and local_hi.max() <= 1
    assert (local_lo <= local_hi).all()
    # the box of the cast triangles is exactly the cast box (rounding is monotone)
    local_tri = spot.local_triangles()
    assert local_tri.dtype == np.float32
    assert np.array_equal(local_tri.min(axis=1), local_lo)
    assert np.array_equal(local_tri.max(axis=1), local_hi)
    lo64, _ = spot.local_boxes(np.float64)
    assert lo64.dtype == np.float64
    np.testing.assert_allclose(frame.to_world(lo64), lo, rtol=0, atol=1e-12)


def test_boxes_in_frame_identity_is_a_cast():
    lo = np.array([[1e7 + 0.25, -3.0, 0.1]])
    got, _ = boxes_in_frame(lo, lo, jaxbvh.Frame.identity(), np.float32)
    assert np.array_equal(got, lo.astype(np.float32))


# ----------------------------------------------------------------------------------
# Bad inputs: each a clear error naming the problem and the file
# ----------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.obj"
    with pytest.raises(FileNotFoundError, match="nowhere.obj"):
        load_mesh(path)


def test_directory(tmp_path):
    with pytest.raises(MeshError, match="directory"):
        load_mesh(tmp_path)


def test_point_cloud_obj(tmp_path):
    path = write(tmp_path / "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match=r"points\.obj.*no faces.*point cloud of 3 points"):
        load_mesh(path)


def test_line_set_obj(tmp_path):
    path = write(tmp_path / "lines.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\nl 2 3\n")
    with pytest.raises(MeshError, match=r"lines\.obj.*no faces.*2 line element"):
        load_mesh(path)


def test_point_cloud_ply(tmp_path):
    header = ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    path = write(tmp_path / "cloud.ply", header + "0 0 0\n1 1 1\n")
    with pytest.raises(MeshError, match=r"cloud\.ply.*no faces.*point cloud"):
        load_mesh(path)


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_coordinates(tmp_path, bad):
    path = write(tmp_path / "bad.obj",
                 f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 {bad} 1\nf 1 2 3\nf 1 3 4\nf 2 4 3\n")
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    message = str(info.value)
    assert "bad.obj" in message and "NaN/inf" in message
    assert "1 vertex" in message and "vertex index 3" in message
    assert "face(s) 1, 2" in message


def test_non_finite_unused_vertex_is_reported(tmp_path):
    # trimesh's OBJ reader drops unreferenced vertices; PLY keeps them
    header = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    path = write(tmp_path / "unused.ply", header + "0 0 0\n1 0 0\n0 1 0\nnan 0 0\n3 0 1 2\n")
    with pytest.raises(MeshError, match=r"unused\.ply.*vertex index 3; used by no face"):
        load_mesh(path)


def test_face_index_out_of_range_obj(tmp_path):
    path = write(tmp_path / "oor.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")
    with pytest.raises(MeshError, match=r"oor\.obj.*face index out of range"):
        load_mesh(path)


def test_face_index_out_of_range_ply(tmp_path):
    header = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    path = write(tmp_path / "oor.ply", header + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 7\n")
    with pytest.raises(MeshError, match=r"oor\.ply.*face index out of range.*face\(s\) 1 "
                                        r"name vertex 7.*3 vertices"):
        load_mesh(path)


@pytest.mark.parametrize("name", ["garbage.glb", "garbage.ply", "garbage.gltf"])
def test_garbage_bytes(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError, match=name.replace(".", r"\.")):
        load_mesh(path)


def test_malformed_gltf(tmp_path):
    path = write(tmp_path / "broken.gltf", '{"asset": {"version": "2.0"}, "meshes": [')
    with pytest.raises(MeshError, match=r"broken\.gltf.*cannot read"):
        load_mesh(path)


@pytest.mark.parametrize("name,text", [("empty.obj", ""), ("junk.obj", "hello world\n"),
                                       ("empty.stl", "solid x\nendsolid x\n")])
def test_empty_files(tmp_path, name, text):
    with pytest.raises(MeshError, match=name.replace(".", r"\.") + ".*no faces"):
        load_mesh(write(tmp_path / name, text))


def test_unsupported_suffix(tmp_path):
    with pytest.raises(MeshError, match="unsupported file type"):
        load_mesh(write(tmp_path / "mesh.xyz123", "v 0 0 0\n"))


def test_mesh_error_is_a_value_error():
    assert issubclass(MeshError, ValueError)


# ----------------------------------------------------------------------------------
# Nothing dropped: degenerate triangles, random meshes
# ----------------------------------------------------------------------------------


def test_degenerate_triangles_are_kept_and_counted(tmp_path):
    text = obj_text([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]],
                    [[0, 1, 2], [0, 1, 3], [3, 3, 3], [0, 0, 1]])
    mesh = load_mesh(write(tmp_path / "flat.obj", text))
    assert mesh.n_triangles == 4
    assert mesh.degenerate == 3
    lo, hi = mesh.local_boxes()
    assert lo.shape == (4, 3)


coords = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=64)


@st.composite
def meshes(draw):
    n_vertices = draw(st.integers(3, 12))
    vertices = np.array(draw(st.lists(st.tuples(coords, coords, coords),
                                      min_size=n_vertices, max_size=n_vertices)))
    n_faces = draw(st.integers(1, 10))
    index = st.integers(0, n_vertices - 1)
    faces = np.array(draw(st.lists(st.tuples(index, index, index), min_size=n_faces,
                                   max_size=n_faces)))
    return vertices, faces


@settings(max_examples=examples(25), suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=meshes())
def test_random_obj_round_trip(tmp_path, data):
    vertices, faces = data
    mesh = load_mesh(write(tmp_path / "random.obj", obj_text(vertices, faces)))
    # trimesh's OBJ reader drops unused vertices and renumbers: compare triangles
    tri = vertices[faces]
    assert mesh.faces.dtype == np.int32
    assert np.array_equal(mesh.triangles, tri)
    area2 = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert mesh.degenerate == int((area2 == 0).all(axis=1).sum())
    lo, hi = mesh.local_boxes(np.float64)
    assert lo.min() >= -1 and hi.max() <= 1
    lo32, hi32 = mesh.local_boxes()
    assert (lo32 <= hi32).all() and np.isfinite(lo32).all()


# ----------------------------------------------------------------------------------
# Scenes: triangle order of Scene.to_geometry(), objects and instances
# ----------------------------------------------------------------------------------


def assert_matches_trimesh(mesh: Mesh, path):
    reference = trimesh.load(path, process=False)
    if isinstance(reference, trimesh.Scene):
        reference = reference.to_geometry()
    assert np.array_equal(mesh.faces, reference.faces)
    np.testing.assert_allclose(mesh.vertices, reference.vertices, rtol=1e-12, atol=1e-12)


def assert_instances_rebuild_world(mesh: Mesh):
    pieces = []
    for object_id, transform in mesh.instances:
        vertices, _ = mesh.objects[object_id]
        pieces.append(vertices @ transform[:3, :3].T + transform[:3, 3])
    np.testing.assert_allclose(np.concatenate(pieces), mesh.vertices, rtol=0, atol=1e-9)
    sizes = [mesh.objects[i][1].shape[0] for i, _ in mesh.instances]
    assert sum(sizes) == mesh.n_triangles


@needs_shared
def test_drone_scene():
    path = SHARED_DATA / "scenes" / "drone" / "scene.gltf"
    mesh = load_mesh(path)
    assert mesh.n_triangles == 32720
    assert len(mesh.objects) == 39 and len(mesh.instances) == 39
    assert_matches_trimesh(mesh, path)
    assert_instances_rebuild_world(mesh)


@needs_shared
def test_legocar_material_groups():
    path = SHARED_DATA / "meshes" / "legocar.obj"
    mesh = load_mesh(path)
    assert mesh.n_triangles == 10992 and len(mesh.objects) == 8
    assert mesh.degenerate > 0  # it has zero-area triangles; they are kept
    assert_matches_trimesh(mesh, path)
    assert_instances_rebuild_world(mesh)


def test_mirrored_instances_match_trimesh(tmp_path):
    scene = trimesh.Scene()
    box = trimesh.creation.box()
    scene.add_geometry(box, node_name="plain", geom_name="box")
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[:3, 3] = [5.0, 0.0, 0.0]
    scene.add_geometry(box, node_name="mirrored", geom_name="box", transform=mirror)
    turn = trimesh.transformations.rotation_matrix(0.3, [1, 2, 3])
    scene.add_geometry(trimesh.creation.icosphere(1), node_name="ball", geom_name="ball",
                       transform=turn)
    path = tmp_path / "scene.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert mesh.n_triangles == 12 + 12 + 80
    assert_matches_trimesh(mesh, path)
    assert_instances_rebuild_world(mesh)


def test_scene_geometry_without_triangles_is_reported(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), geom_name="box")
    scene.add_geometry(trimesh.PointCloud(np.random.default_rng(1).random((5, 3))), geom_name="dots")
    path = tmp_path / "mixed.glb"
    scene.export(path)
    with pytest.warns(UserWarning, match="dots"):
        mesh = load_mesh(path)
    assert mesh.skipped == ("dots",)
    assert mesh.n_triangles == 12


# ----------------------------------------------------------------------------------
# The cache of parsed meshes
# ----------------------------------------------------------------------------------


@pytest.fixture
def mesh_cache(tmp_path):
    from jaxbvh import io

    folder = tmp_path / "mesh-cache"
    before = io.use_mesh_cache(folder)
    yield folder
    io.use_mesh_cache(before)


def assert_same_mesh(a: Mesh, b: Mesh):
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert (a.name, a.degenerate, a.skipped, a.path) == (b.name, b.degenerate, b.skipped, b.path)
    assert len(a.objects) == len(b.objects) and len(a.instances) == len(b.instances)
    for (va, fa), (vb, fb) in zip(a.objects, b.objects):
        assert np.array_equal(va, vb) and np.array_equal(fa, fb)
    for (oa, ta), (ob, tb) in zip(a.instances, b.instances):
        assert oa == ob and np.array_equal(ta, tb)


def test_cached_mesh_equals_the_parsed_one(tmp_path, mesh_cache, monkeypatch):
    from jaxbvh import io

    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), node_name="a", geom_name="box")
    scene.add_geometry(trimesh.creation.box(), node_name="b", geom_name="box",
                       transform=trimesh.transformations.rotation_matrix(0.4, [0, 1, 1]))
    scene.add_geometry(trimesh.PointCloud(np.ones((3, 3))), geom_name="dots")
    path = tmp_path / "scene.glb"
    scene.export(path)
    with pytest.warns(UserWarning, match="dots"):
        parsed = load_mesh(path)
    assert len(list(mesh_cache.glob("*.npz"))) == 1

    def no_parsing(path):
        raise AssertionError("parsed again")

    monkeypatch.setattr(io.meshes, "_parse", no_parsing)
    with pytest.warns(UserWarning, match="dots"):  # the warning comes back with the entry
        cached = load_mesh(path)
    assert_same_mesh(cached, parsed)
    assert len(cached.instances) == 2 and cached.n_triangles == 24


def test_the_mesh_cache_follows_jaxbvhs_compilation_cache(tmp_path):
    from jaxbvh import compile_cache, io

    before = io.use_mesh_cache(io.meshes.FOLLOW_COMPILE_CACHE)
    try:
        on = compile_cache.status()["owner"] == "jaxbvh"  # the suite's run cache, by the library's rules
        assert on
        assert io.mesh_cache_folder() == compile_cache.mesh_cache_dir()
        compile_cache.disable()
        try:
            assert io.mesh_cache_folder() is None  # off with jaxbvh's cache (JAXBVH_CACHE=off, a user's JAX cache)
            path = write(tmp_path / "tri.obj", obj_text([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
            assert load_mesh(path).n_triangles == 1 and io.meshes._cache_entry(str(path)) is None
        finally:
            compile_cache.enable_default()
        assert io.mesh_cache_folder() == compile_cache.mesh_cache_dir()
        assert io.use_mesh_cache(None) is io.meshes.FOLLOW_COMPILE_CACHE and io.mesh_cache_folder() is None
    finally:
        io.use_mesh_cache(before)


def test_the_mesh_cache_evicts_what_was_read_longest_ago(tmp_path, mesh_cache, monkeypatch):
    from jaxbvh import io

    paths = [write(tmp_path / f"m{i}.obj", obj_text([[0, 0, 0], [1, 0, 0], [0, 1, i + 1]], [[0, 1, 2]]))
             for i in range(3)]
    load_mesh(paths[0])
    entry_size = sum(e.stat().st_size for e in mesh_cache.glob("*.npz"))
    monkeypatch.setattr(io.meshes, "MAX_MESH_CACHE_BYTES", 2 * entry_size + entry_size // 2)  # room for two
    load_mesh(paths[1])
    first, second = (io.meshes._cache_entry(str(p)) for p in paths[:2])
    os.utime(first, ns=(1, 1))
    os.utime(second, ns=(2, 2))
    load_mesh(paths[0])  # read again: now the most recently used
    load_mesh(paths[2])  # a third entry: the one read longest ago (paths[1]) goes
    kept = {e.name for e in mesh_cache.glob("*.npz")}
    assert kept == {io.meshes._cache_entry(str(p)).name for p in (paths[0], paths[2])}
    assert load_mesh(paths[1]).n_triangles == 1  # parsed again, not lost


def test_a_warm_load_neither_parses_nor_imports_trimesh(tmp_path):
    script = (
        "import sys, jaxbvh\n"
        "from jaxbvh.io import bundled_mesh_path, load_mesh\n"
        "n = load_mesh(bundled_mesh_path()).n_triangles\n"
        "print(n, 'trimesh' in sys.modules)\n")
    env = dict(os.environ, JAXBVH_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("JAXBVH_CACHE", None)
    runs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    cold, warm = (r.stdout.split() for r in runs)
    assert cold == [warm[0], "True"] and warm[1] == "False"
    assert list((tmp_path / "cache" / "meshes").glob("*.npz"))


def test_mesh_cache_notices_an_edited_file_and_ignores_damage(tmp_path, mesh_cache):
    path = write(tmp_path / "tri.obj", obj_text([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    first = load_mesh(path)
    write(path, obj_text([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2], [0, 1, 3]]))
    assert load_mesh(path).n_triangles == 2 == first.n_triangles + 1
    for entry in mesh_cache.glob("*.npz"):
        entry.write_bytes(b"damaged")
    assert load_mesh(path).n_triangles == 2
    # the same size and its old modification time put back: still noticed (change time)
    stamp = os.stat(path)
    write(path, obj_text([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2]], [[0, 1, 2], [0, 1, 3]]))
    assert os.stat(path).st_size == stamp.st_size
    os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    assert float(load_mesh(path).triangles.max()) == 2.0
    # bad files are not cached: the error comes every time
    bad = write(tmp_path / "bad.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    for _ in range(2):
        with pytest.raises(MeshError, match="NaN"):
            load_mesh(bad)


# ----------------------------------------------------------------------------------
# load_any
# ----------------------------------------------------------------------------------


def small_tree():
    """Root 0 with two one-triangle leaves, boxes in world space."""
    return jaxbvh.from_interchange({
        "child": np.array([[1, 2], [-1, -1], [-1, -1]], np.int32),
        "prim_start": np.array([0, 0, 1], np.int32),
        "prim_count": np.array([0, 1, 1], np.int32),
        "prim_index": np.array([0, 1], np.int32),
        "lo": np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], np.float32),
        "hi": np.array([[2, 1, 0], [1, 1, 0], [2, 1, 0]], np.float32),
        "root": np.int32(0),
    })


def test_load_any_tree_and_mesh(tmp_path):
    tree_path = tmp_path / "tree.npz"
    jaxbvh.save(tree_path, small_tree())
    loaded = load_any(tree_path)
    assert isinstance(loaded, TreeFile) and loaded.frame.is_identity
    assert loaded.path == str(tree_path)
    assert isinstance(load_any(bundled_mesh_path()), Mesh)
    with pytest.raises(FileNotFoundError):
        load_any(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"junk\.npz"):
        load_any(tmp_path / "junk.npz")


# ----------------------------------------------------------------------------------
# Hostile meshes (issue 23)
# ----------------------------------------------------------------------------------


def test_a_gltf_beside_symlink_loops_and_dangling_links_loads(tmp_path, mesh_cache):
    """The cache key stats only the files the glTF names (its buffer), never the folder."""
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), node_name="a", geom_name="box")
    for name, data in scene.export(file_type="gltf").items():
        (tmp_path / name).write_bytes(data)
    path = next(p for p in tmp_path.iterdir() if p.suffix == ".gltf")
    (tmp_path / "loop_a.obj").symlink_to(tmp_path / "loop_b.obj")
    (tmp_path / "loop_b.obj").symlink_to(tmp_path / "loop_a.obj")
    (tmp_path / "dangling.obj").symlink_to(tmp_path / "nowhere.obj")
    first = load_mesh(path)
    assert first.n_triangles == 12 and len(list(mesh_cache.glob("*.npz"))) == 1
    # the buffer is part of the key: a changed buffer is parsed again
    buffer = next(p for p in tmp_path.iterdir() if p.suffix == ".bin")
    data = buffer.read_bytes()
    buffer.write_bytes(data + b"\0" * 4)
    load_mesh(path)
    assert len(list(mesh_cache.glob("*.npz"))) == 2


@pytest.mark.parametrize("text", [
    b"# caf\xe9 au lait\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",          # Latin-1 in a comment
    b"v 0 0 0\nv 1 0 0\nv 0 1 0\no \xff\xfe\x80name\nf 1 2 3\n",         # bytes no codec reads
])
def test_an_obj_that_is_not_utf8_loads(tmp_path, monkeypatch, text):
    # as on an install without trimesh's optional charset_normalizer (import fails)
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    path = tmp_path / "latin.obj"
    path.write_bytes(text)
    mesh = load_mesh(path)
    assert mesh.n_triangles == 1
    assert np.array_equal(mesh.triangles[0], [[0, 0, 0], [1, 0, 0], [0, 1, 0]])


def test_a_truncated_binary_stl_is_named_so(tmp_path):
    whole = tmp_path / "box.stl"
    trimesh.creation.box().export(whole)
    data = whole.read_bytes()
    assert load_mesh(whole).n_triangles == 12
    cut = tmp_path / "cut.stl"
    cut.write_bytes(data[:-30])
    with pytest.raises(MeshError, match=r"cut\.stl: truncated binary STL: its header announces 12 "
                                        r"triangles \(684 bytes\), the file has 654 bytes"):
        load_mesh(cut)
    stub = tmp_path / "stub.stl"
    stub.write_bytes(data[:40])
    with pytest.raises(MeshError, match=r"stub\.stl: truncated binary STL: 40 bytes"):
        load_mesh(stub)


@pytest.mark.parametrize("face", ["f 0 1 2", "f 1 2 0", "f 1/1 0/1 2/1", "  f 1 2 00"])
def test_obj_face_index_zero_is_refused(tmp_path, face):
    path = write(tmp_path / "zero.obj", f"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\n{face}\n")
    with pytest.raises(MeshError, match=r"zero\.obj: face index 0 on line 5: OBJ vertex indices start at 1"):
        load_mesh(path)


def test_obj_indices_that_merely_contain_a_zero_load(tmp_path):
    vertices = np.arange(33.0).reshape(11, 3) % 7
    path = write(tmp_path / "ten.obj", obj_text(vertices, [[9, 10, 0], [0, 9, 10]]) + "f 10/0 11 1\n")
    assert load_mesh(path).n_triangles == 3  # 10, 11 and a texture index 0 are no vertex 0
