"""The jaxbvh command line tool, run in-process through ``jaxbvh.cli.main``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh import cli
from jaxbvh.commands import _common

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(autouse=True, scope="module")
def cache_dir(tmp_path_factory):
    """Keep the compilation cache of the tests out of the user's home."""
    path = tmp_path_factory.mktemp("jax-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXBVH_CACHE_DIR", str(path))
        yield path


def _build_works() -> bool:
    try:
        jaxbvh.build(np.zeros((2, 3), np.float32), np.ones((2, 3), np.float32))
    except NotImplementedError:
        return False
    return True


needs_build = pytest.mark.skipif(not _build_works(), reason="jaxbvh.build is not implemented yet")


def run_cli(capsys, *argv):
    """``(exit status, stdout, stderr)`` of ``jaxbvh ARGV``."""
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def run_json(capsys, *argv) -> dict:
    status, out, err = run_cli(capsys, *argv, "--json")
    assert status == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1, out  # one JSON object, nothing else on stdout
    return json.loads(lines[0])


def assert_one_line_error(status, out, err, *fragments):
    assert status == 2
    assert out == ""
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("jaxbvh: error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def grid_obj(path: Path, n: int = 3, seed: int = 0) -> Path:
    """A bumpy n x n grid of 2 n^2 triangles."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij")
    zs = rng.random(xs.shape)
    vertices = np.stack([xs, ys, zs], -1).reshape(-1, 3)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            faces += [(a, b, c), (a, c, d)]
    text = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist())
    text += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------------
# Global behaviour
# ----------------------------------------------------------------------------------


def test_help_and_version(capsys):
    assert cli.main(["--help"]) == 0
    out, _ = capsys.readouterr()
    assert "build" in out and "stats" in out
    assert cli.main(["--version"]) == 0
    assert jaxbvh.__version__ in capsys.readouterr().out


def test_every_command_module_is_a_command(capsys):
    names = cli.command_names()
    assert names[:4] == cli.ORDER  # listed first, in this order
    assert len(set(names)) == len(names)
    parser, modules = cli.make_parser()
    assert list(modules) == names
    for name, module in modules.items():
        assert callable(module.add_parser) and callable(module.run), name
        assert cli.main([name, "--help"]) == 0
        assert "--json" in capsys.readouterr().out, name


def test_usage_errors_exit_2(capsys):
    assert cli.main([]) == 2
    assert cli.main(["build", "--builder", "octree"]) == 2
    assert cli.main(["build", "--max-leaf", "0"]) == 2
    assert cli.main(["build", "--bins", "1"]) == 2
    assert cli.main(["build", "--bins", "many"]) == 2
    assert cli.main(["frobnicate"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_compilation_cache_dir(cache_dir, monkeypatch):
    import jax

    assert cli.cache_dir() == cache_dir
    assert cli.enable_compilation_cache() == cache_dir
    assert jax.config.jax_compilation_cache_dir == str(cache_dir)
    monkeypatch.delenv("JAXBVH_CACHE_DIR")
    assert cli.cache_dir() == Path.home() / ".cache" / "jaxbvh" / "jax"


def test_table_and_json_formatting():
    result = {"triangles": 5856, "sah": np.float32(25.5), "valid": True, "output": None,
              "origin": np.zeros(3), "nested": {"a": 1}, "big": float("inf")}
    table = _common.format_table(result)
    assert "triangles  5,856" in table and "nested.a" in table and "valid      yes" in table
    plain = _common._plain(result)
    assert json.loads(json.dumps(plain, allow_nan=False))["big"] == "inf"


def test_progress_is_off_without_a_terminal(capsys):
    class Args:
        json = False

    assert not _common.show_progress(Args())  # capsys: stderr is not a TTY
    Args.json = True
    assert not _common.show_progress(Args())


# ----------------------------------------------------------------------------------
# Errors: one line on stderr, status 2
# ----------------------------------------------------------------------------------


def test_missing_mesh(capsys, tmp_path):
    missing = tmp_path / "missing.obj"
    assert_one_line_error(*run_cli(capsys, "build", missing, "--json"), "not found", str(missing))


def test_missing_tree(capsys, tmp_path):
    missing = tmp_path / "missing.npz"
    assert_one_line_error(*run_cli(capsys, "stats", missing), "not found", str(missing))


@pytest.mark.parametrize("name,text,fragment", [
    ("cloud.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN/inf"),
    ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "face index out of range"),
    ("broken.gltf", '{"asset": {', "cannot read"),
])
@pytest.mark.parametrize("command", ["build", "stats"])
def test_bad_meshes(capsys, tmp_path, name, text, fragment, command):
    path = tmp_path / name
    path.write_text(text)
    assert_one_line_error(*run_cli(capsys, command, path), fragment, name)


def test_garbage_tree_file(capsys, tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"\x00not a zip archive")
    assert_one_line_error(*run_cli(capsys, "stats", path), "junk.npz")


def test_malformed_tree_arrays(capsys, tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(path, child=np.array([[1, 5], [-1, -1]], np.int32), prim_start=np.zeros(2, np.int32),
             prim_count=np.array([0, 1], np.int32), prim_index=np.zeros(1, np.int32),
             lo=np.zeros((2, 3), np.float32), hi=np.ones((2, 3), np.float32), root=np.int32(0))
    assert_one_line_error(*run_cli(capsys, "stats", path), "bad.npz", "child")


def test_build_refuses_a_tree(capsys, tmp_path):
    _, tree = two_triangle_files(tmp_path)
    assert_one_line_error(*run_cli(capsys, "build", tree), "tree file", "two.npz")


@needs_build
def test_unwritable_output(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 1)
    target = tmp_path / "no" / "such" / "dir" / "tree.npz"
    assert_one_line_error(*run_cli(capsys, "build", mesh, "-o", target), str(target))


def test_mesh_flag_needs_a_tree(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 1)
    assert_one_line_error(*run_cli(capsys, "stats", mesh, "--mesh", mesh), "--mesh")


# ----------------------------------------------------------------------------------
# stats on saved trees (no builder needed)
# ----------------------------------------------------------------------------------


def two_triangle_files(tmp_path, *, box_hi_x=1.0):
    """An OBJ of two triangles and a world-space tree over them (root + 2 leaves)."""
    mesh = tmp_path / "two.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nf 1 2 3\nf 2 4 5\n")
    tree = jaxbvh.from_interchange({
        "child": np.array([[1, 2], [-1, -1], [-1, -1]], np.int32),
        "prim_start": np.array([0, 0, 1], np.int32),
        "prim_count": np.array([0, 1, 1], np.int32),
        "prim_index": np.array([0, 1], np.int32),
        "lo": np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], np.float32),
        "hi": np.array([[2, 1, 0], [box_hi_x, 1, 0], [2, 1, 0]], np.float32),
        "root": np.int32(0),
    })
    path = tmp_path / "two.npz"
    jaxbvh.save(path, tree)
    return mesh, path


def test_stats_of_a_tree(capsys, tmp_path):
    mesh, tree = two_triangle_files(tmp_path)
    result = run_json(capsys, "stats", tree)
    assert result["kind"] == "tree" and result["valid"] is True
    assert result["nodes"] == 3 and result["leaves"] == 2 and result["depth"] == 1
    assert result["leaf_size_min"] == result["leaf_size_max"] == 1
    assert result["sah"] == pytest.approx(1 + (1 + 1) / 2)  # leaves of half the root's area
    assert set(result) >= {"sah", "ng_trifonov", "goldsmith_salmon"}
    checked = run_json(capsys, "stats", tree, "--mesh", mesh)
    assert checked["valid"] is True and checked["validated_against"] == "mesh"
    assert checked["triangles"] == 2


def test_stats_finds_a_box_that_misses_its_triangle(capsys, tmp_path):
    mesh, tree = two_triangle_files(tmp_path, box_hi_x=0.5)
    assert run_json(capsys, "stats", tree)["valid"] is True  # structure alone is fine
    result = run_json(capsys, "stats", tree, "--mesh", mesh)
    assert result["valid"] is False
    assert any("do not contain" in p for p in result["problems"])


def test_stats_with_the_wrong_mesh(capsys, tmp_path):
    _, tree = two_triangle_files(tmp_path)
    result = run_json(capsys, "stats", tree, "--mesh", grid_obj(tmp_path / "grid.obj", 2))
    assert result["valid"] is False
    assert "8 triangles" in result["problems"][0]


def test_stats_table_output(capsys, tmp_path):
    _, tree = two_triangle_files(tmp_path)
    status, out, _ = run_cli(capsys, "stats", tree)
    assert status == 0
    rows = dict(line.split(None, 1) for line in out.strip().splitlines())
    assert rows["nodes"] == "3" and rows["valid"] == "yes" and "sah" in rows


@pytest.mark.skipif(not (SHARED / "trees").is_dir(), reason=f"shared data not found at {SHARED}")
def test_stats_of_a_foreign_tree_against_its_mesh(capsys):
    result = run_json(capsys, "stats", SHARED / "trees" / "legocar_binned_ref.npz",
                      "--mesh", SHARED / "meshes" / "legocar.obj")
    assert result["valid"] is True
    assert result["sah"] == pytest.approx(30.212, abs=1e-3)  # the value tinybvh reports


# ----------------------------------------------------------------------------------
# build (and stats of a mesh), once jaxbvh.build works
# ----------------------------------------------------------------------------------


@needs_build
def test_build_bundled_mesh(capsys, tmp_path):
    out = tmp_path / "spot.npz"
    result = run_json(capsys, "build", "-o", out)
    assert result["triangles"] == 5856 and result["degenerate"] == 0
    assert result["valid"] is True
    assert result["nodes"] == 2 * 5856 - 1 and result["leaves"] == 5856
    assert result["depth"] >= 13  # log2(5856) ~ 12.5
    assert result["seconds"] > 0 and result["sah"] > 0
    tree, frame = jaxbvh.load(out)
    assert not frame.is_identity and frame.scale == result["frame_scale"]
    stats = run_json(capsys, "stats", out, "--mesh", jaxbvh.io.bundled_mesh_path())
    assert stats["valid"] is True
    assert stats["sah"] == pytest.approx(result["sah"], rel=1e-6)
    assert stats["nodes"] == result["nodes"] and stats["depth"] == result["depth"]


@needs_build
@pytest.mark.parametrize("builder", ["sweep", "binned", "median"])
def test_build_options(capsys, tmp_path, builder):
    mesh = grid_obj(tmp_path / "grid.obj", 3)
    result = run_json(capsys, "build", mesh, "--builder", builder, "--max-leaf", 2, "--bins", 4)
    assert result["builder"] == builder and result["triangles"] == 18
    assert result["valid"] is True and result["primitives"] == 18
    assert result["leaf_size_max"] <= 2
    assert ("bins" in result) == (builder == "binned")


@needs_build
def test_build_table_and_saved_tree(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 2)
    out = tmp_path / "grid.npz"
    status, text, _ = run_cli(capsys, "build", mesh, "-o", out)
    assert status == 0 and out.is_file()
    for key in ("triangles", "nodes", "depth", "leaf_size_mean", "sah", "ng_trifonov", "seconds"):
        assert f"\n{key} " in "\n" + text
    assert run_json(capsys, "stats", out, "--mesh", mesh)["valid"] is True


@needs_build
def test_stats_of_a_mesh(capsys, tmp_path):
    result = run_json(capsys, "stats", grid_obj(tmp_path / "grid.obj", 2))
    assert result["kind"] == "mesh" and result["valid"] is True and result["triangles"] == 8


@needs_build
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(1, 3), seed=st.integers(0, 2**16), max_leaf=st.sampled_from([1, 3]))
def test_build_then_stats_agree(capsys, tmp_path, n, seed, max_leaf):
    mesh = grid_obj(tmp_path / f"grid{n}_{seed}.obj", n, seed)
    out = tmp_path / f"grid{n}_{seed}.npz"
    built = run_json(capsys, "build", mesh, "--max-leaf", max_leaf, "-o", out)
    stats = run_json(capsys, "stats", out, "--mesh", mesh)
    assert built["valid"] and stats["valid"]
    assert stats["sah"] == pytest.approx(built["sah"], rel=1e-6)
    assert built["leaf_size_max"] <= max_leaf
