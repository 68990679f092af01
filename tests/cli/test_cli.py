"""The jaxbvh command line tool, run in-process through ``jaxbvh.cli``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import (
    BROKEN,
    COUNT_COMPILES,
    REPO,
    SHARED_DATA,
    assert_one_line_error,
    broken_arrays,
    broken_tree_file,
    grid_obj,
    run_cli,
    run_json,
    three_triangle_files,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh import cli
from jaxbvh.cli import command_kit
from jaxbvh.configs import DEFAULT_MAX_LEAF
from jaxbvh.testing.plugin import examples

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


def test_compilation_cache_dir(cache_dir, monkeypatch, capsys):
    """A command uses the library's compilation cache (the suite's run folder here) and the
    mesh cache beside it; the mesh cache is put back after the command."""
    import jax

    from jaxbvh import io

    meshes_before = io.mesh_cache_folder()
    assert cli.cache_dir() == cache_dir
    with cli.compilation_cache_on() as path:
        assert path == cache_dir
        assert jax.config.jax_compilation_cache_dir == str(cache_dir)
        assert io.mesh_cache_folder() == cache_dir / "meshes"
    assert io.mesh_cache_folder() == meshes_before
    assert cli.main(["build", "--json"]) == 0
    assert io.mesh_cache_folder() == meshes_before
    assert jax.config.jax_compilation_cache_dir == str(cache_dir)
    assert any((cache_dir / "meshes").iterdir())  # the command did use the caches
    monkeypatch.delenv("JAXBVH_CACHE_DIR")
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert cli.cache_dir() == Path.home() / ".cache" / "jaxbvh" / "jax"


def test_table_and_json_formatting():
    result = {"triangles": 5856, "sah": np.float32(25.5), "valid": True, "output": None,
              "origin": np.zeros(3), "nested": {"a": 1}, "big": float("inf")}
    table = command_kit.format_table(result)
    assert "triangles  5,856" in table and "nested.a" in table and "valid      yes" in table
    plain = command_kit.json_ready(result)
    assert json.loads(json.dumps(plain, allow_nan=False))["big"] == "inf"


def test_progress_is_off_without_a_terminal(capsys):
    class Args:
        json = False

    assert not command_kit.show_progress(Args())  # capsys: stderr is not a TTY
    Args.json = True
    assert not command_kit.show_progress(Args())


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
    result = run_json(capsys, "stats", tree, "--mesh", mesh, status=1)
    assert result["valid"] is False and result["sah"] > 0  # costs still reported
    assert any("do not contain" in p for p in result["problems"])


def test_stats_with_the_wrong_mesh(capsys, tmp_path):
    _, tree = two_triangle_files(tmp_path)
    result = run_json(capsys, "stats", tree, "--mesh", grid_obj(tmp_path / "grid.obj", 2), status=1)
    assert result["valid"] is False
    assert "8 triangles" in result["problems"][0]


def test_stats_table_output(capsys, tmp_path):
    _, tree = two_triangle_files(tmp_path)
    status, out, _ = run_cli(capsys, "stats", tree)
    assert status == 0
    rows = dict(line.split(None, 1) for line in out.strip().splitlines())
    assert rows["nodes"] == "3" and rows["valid"] == "yes" and "sah" in rows


@pytest.mark.skipif(not (SHARED_DATA / "trees").is_dir(), reason=f"shared data not found at {SHARED_DATA}")
def test_stats_of_a_foreign_tree_against_its_mesh(capsys):
    result = run_json(capsys, "stats", SHARED_DATA / "trees" / "legocar_binned_ref.npz",
                      "--mesh", SHARED_DATA / "meshes" / "legocar.obj")
    assert result["valid"] is True
    assert result["sah"] == pytest.approx(30.212, abs=1e-3)  # the value tinybvh reports


# ----------------------------------------------------------------------------------
# build (and stats of a mesh), once jaxbvh.build works
# ----------------------------------------------------------------------------------


def test_build_bundled_mesh(capsys, tmp_path):
    out = tmp_path / "spot.npz"
    result = run_json(capsys, "build", "-o", out)
    assert result["triangles"] == 5856 and result["degenerate"] == 0
    assert result["valid"] is True
    # the default leaves (SAH leaf test up to DEFAULT_MAX_LEAF primitives): a binary tree of them
    assert result["nodes"] == 2 * result["leaves"] - 1 and result["primitives"] == 5856
    assert 1 <= result["leaf_size_min"] and result["leaf_size_max"] <= DEFAULT_MAX_LEAF == result["max_leaf"]
    assert result["depth"] >= 13  # log2(5856) ~ 12.5
    assert result["seconds"] > 0 and result["sah"] > 0
    tree, frame = jaxbvh.load(out)
    assert not frame.is_identity and frame.scale == result["frame_scale"]
    stats = run_json(capsys, "stats", out, "--mesh", jaxbvh.io.bundled_mesh_path())
    assert stats["valid"] is True
    assert stats["sah"] == pytest.approx(result["sah"], rel=1e-6)
    assert stats["nodes"] == result["nodes"] and stats["depth"] == result["depth"]


@pytest.mark.parametrize("builder", ["sweep", "binned", "median"])
def test_build_options(capsys, tmp_path, builder):
    mesh = grid_obj(tmp_path / "grid.obj", 3)
    result = run_json(capsys, "build", mesh, "--builder", builder, "--max-leaf", 2, "--bins", 4)
    assert result["builder"] == builder and result["triangles"] == 18
    assert result["valid"] is True and result["primitives"] == 18
    assert result["leaf_size_max"] <= 2
    assert ("bins" in result) == (builder == "binned")


def test_build_table_and_saved_tree(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 2)
    out = tmp_path / "grid.npz"
    status, text, _ = run_cli(capsys, "build", mesh, "-o", out)
    assert status == 0 and out.is_file()
    for key in ("triangles", "nodes", "depth", "leaf_size_mean", "sah", "ng_trifonov", "seconds"):
        assert f"\n{key} " in "\n" + text
    assert run_json(capsys, "stats", out, "--mesh", mesh)["valid"] is True


def test_stats_of_a_mesh(capsys, tmp_path):
    result = run_json(capsys, "stats", grid_obj(tmp_path / "grid.obj", 2))
    assert result["kind"] == "mesh" and result["valid"] is True and result["triangles"] == 8


@settings(max_examples=examples(8), suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(1, 3), seed=st.integers(0, 2**16), max_leaf=st.sampled_from([1, 3]))
def test_build_then_stats_agree(capsys, tmp_path, n, seed, max_leaf):
    mesh = grid_obj(tmp_path / f"grid{n}_{seed}.obj", n, seed)
    out = tmp_path / f"grid{n}_{seed}.npz"
    built = run_json(capsys, "build", mesh, "--max-leaf", max_leaf, "-o", out)
    stats = run_json(capsys, "stats", out, "--mesh", mesh)
    assert built["valid"] and stats["valid"]
    assert stats["sah"] == pytest.approx(built["sah"], rel=1e-6)
    assert built["leaf_size_max"] <= max_leaf


# ----------------------------------------------------------------------------------
# Broken tree files: every command that reads a tree checks it before any jitted loop
# ----------------------------------------------------------------------------------


def test_the_unbroken_tree_is_valid(capsys, tmp_path):
    mesh, arrays = three_triangle_files(tmp_path)
    path = tmp_path / "good.npz"
    np.savez(path, **arrays)
    assert run_json(capsys, "stats", path, "--mesh", mesh)["valid"] is True
    result = run_json(capsys, "trace", path, mesh, "--rays", 50, "--image", tmp_path / "view.png")
    assert result["rays"] == 50
    # the picture is a separate camera pass, and the result says so
    assert "separate" in result["image_rays"] and "random" in result["image_rays"]
    assert (tmp_path / "view.png").stat().st_size > 0
    assert run_json(capsys, "optimize", path)["valid"] is True


# (command, argv after the tree file); commands that read a tree must refuse broken ones
TREE_READERS = {
    "optimize": lambda tree, mesh: ["optimize", tree],  # the default method: the pipeline
    "optimize hc": lambda tree, mesh: ["optimize", tree, "--method", "hc"],
    "optimize sa": lambda tree, mesh: ["optimize", tree, "--method", "sa", "--steps", 4],
    "trace": lambda tree, mesh: ["trace", tree, mesh, "--rays", 20],
    "collapse dp": lambda tree, mesh: ["collapse", tree],
    "collapse greedy": lambda tree, mesh: ["collapse", tree, "--method", "greedy"],
}


@pytest.mark.parametrize("kind", sorted(BROKEN))
@pytest.mark.parametrize("command", sorted(TREE_READERS))
def test_tree_readers_refuse_broken_trees(capsys, tmp_path, command, kind):
    mesh, path = broken_tree_file(tmp_path, kind)
    assert_one_line_error(*run_cli(capsys, *TREE_READERS[command](path, mesh)), "invalid BVH", path.name)


@pytest.mark.parametrize("kind", sorted(BROKEN))
def test_stats_reports_broken_trees_with_status_1(capsys, tmp_path, kind):
    mesh, path = broken_tree_file(tmp_path, kind)
    for extra in ([], ["--mesh", mesh]):
        result = run_json(capsys, "stats", path, *extra, status=1)
        assert result["valid"] is False and result["problems"]
        assert "sah" not in result  # the costs of a broken structure mean nothing
    status, out, _ = run_cli(capsys, "stats", path)
    assert status == 1 and "valid" in out and "no" in out


def test_traversal_is_bounded_on_a_broken_tree(tmp_path):
    """Bypassing every check, a cycle still cannot hang a ray: the step bound stops it."""
    from jaxbvh import rays

    mesh, arrays = three_triangle_files(tmp_path)
    tri = jaxbvh.load_mesh(mesh).triangles.astype(np.float32)
    origin = np.array([[0.3, 0.3, -1.0], [3.0, 0.5, -1.0]], np.float32)
    direction = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], np.float32)
    good = jaxbvh.from_interchange(arrays)
    assert rays.closest_hit(good, tri, origin, direction).prim.tolist() == [0, 2]
    for kind in ("self-loop", "cycle"):
        tree = jaxbvh.from_interchange(broken_arrays(arrays, **BROKEN[kind]))
        with pytest.raises(jaxbvh.InvalidTreeError, match="did not end"):
            rays.closest_hit(tree, tri, origin, direction)


def test_not_a_tree_file(capsys, tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("a text file, renamed\n")
    array = tmp_path / "array.npz"
    with open(array, "wb") as f:
        np.save(f, np.zeros(3))
    for path in (text, array):
        status, out, err = run_cli(capsys, "stats", path)
        assert_one_line_error(status, out, err, "not a tree file", path.name)
        assert "pickle" not in err


def test_line_segments_are_not_called_a_point_cloud(capsys, tmp_path):
    path = tmp_path / "lines.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\nl 2 3\n")
    assert_one_line_error(*run_cli(capsys, "build", path), "2 line element", "no faces")


def test_build_and_stats_report_the_same_capacity(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 4)
    out = tmp_path / "grid.npz"
    built = run_json(capsys, "build", mesh, "--max-leaf", 4, "-o", out)
    assert built["nodes"] < built["triangles"]  # leaves of several triangles: fewer nodes
    stats = run_json(capsys, "stats", out, "--mesh", mesh)
    assert built["capacity"] == stats["capacity"] == jaxbvh.capacity_bucket(built["nodes"])


def test_image_without_matplotlib_is_a_one_line_error(capsys, tmp_path, monkeypatch):
    import importlib.util

    mesh, arrays = three_triangle_files(tmp_path)
    path = tmp_path / "good.npz"
    np.savez(path, **arrays)
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "matplotlib" else find_spec(name, *a))
    assert_one_line_error(*run_cli(capsys, "trace", path, mesh, "--image", tmp_path / "x.png"),
                          "matplotlib", "jaxbvh[plot]")
    assert not (tmp_path / "x.png").exists()


# ----------------------------------------------------------------------------------
# The persistent compilation cache: a second run compiles nothing
# ----------------------------------------------------------------------------------

_COUNT_COMPILES = """
import json, sys
import jax.monitoring
""" + COUNT_COMPILES + """from jaxbvh import cli
for argv in json.loads(sys.argv[1]):
    assert cli.main(argv) == 0, argv
print("COMPILES", len(compiles) - len(hits), "HITS", len(hits) + len(stored))
"""


def _instanced_scene(path: Path) -> Path:
    """A glTF scene: one small mesh placed by three overlapping, shifted instances."""
    import trimesh

    grid = trimesh.load(grid_obj(path.with_suffix(".obj"), n=3), process=False)
    scene = trimesh.Scene()
    scene.add_geometry(grid, geom_name="grid", node_name="n0")
    for i in (1, 2):
        matrix = np.eye(4)
        matrix[:3, 3] = [0.3 * i, 0.2 * i, 0.1 * i]
        scene.graph.update(frame_to=f"m{i}", frame_from=scene.graph.base_frame, matrix=matrix, geometry="grid")
    scene.export(path)
    return path


def test_second_run_compiles_nothing(tmp_path, cache_dir):
    """Every command, run again in a fresh process, takes every program from the cache.

    The first run shares the suite's cache (``cache_dir``), so it compiles only what the
    tests before it did not; the second must compile nothing and load every program. Each
    command runs once (``optimize`` twice: the pipeline, whose stages are reinsertion and
    treelets, and annealing, whose keys must not reach a program's cache key); its other
    methods and builders compile more programs of the same kind."""
    import subprocess
    import sys

    mesh, arrays = three_triangle_files(tmp_path)
    tree = tmp_path / "tree.npz"
    np.savez(tree, **arrays)
    commands = [["build", str(mesh), "--json"],
                ["optimize", str(tree), "--json"],
                ["optimize", str(tree), "--method", "sa", "--steps", "6", "--chains", "2", "--json"],
                ["trace", str(tree), str(mesh), "--rays", "64", "--json"],
                ["evolve", str(mesh), "--population", "4", "--generations", "2", "--json"],
                ["collapse", str(tree), "--json"],
                ["grasp", str(mesh), "--trials", "4", "--json"],
                ["rebraid", str(_instanced_scene(tmp_path / "scene.glb")), "--rays", "16", "--json"]]
    # only the CLI may turn the cache on: not JAX's own variables, which the suite sets
    env = {name: value for name, value in __import__("os").environ.items() if not name.startswith("JAX_")}
    env.update(JAXBVH_CACHE_DIR=str(cache_dir), PYTHONPATH=str(REPO))

    def run():
        proc = subprocess.run([sys.executable, "-c", _COUNT_COMPILES, json.dumps(commands)], env=env,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        words = proc.stdout.split("COMPILES")[-1].split()
        return int(words[0]), int(words[2])

    first_compiles, first_hits = run()
    second_compiles, second_hits = run()
    assert second_compiles == 0
    assert second_hits >= first_compiles + first_hits > 10  # every program, from the cache


_INTERRUPTED = """
import atexit, sys
from jaxbvh import cli
from jaxbvh.cli.commands import build

def interrupted(args):
    raise KeyboardInterrupt

build.run = interrupted
atexit.register(lambda: print("interpreter shut down", flush=True))
sys.argv = ["jaxbvh", "build"]
sys.exit(cli.main())
"""


def test_ctrl_c_exits_130_at_once_in_the_console_script(capsys, monkeypatch):
    """Ctrl-C (KeyboardInterrupt) in a command: one line, exit 130; run as the console
    script (``main()`` reads the process's arguments) the process ends at once, without
    the interpreter's shutdown that crashed under XLA's running threads (issue 39:
    SIGSEGV after the line); called with arguments (in-process, as here) it returns 130."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _INTERRUPTED], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert proc.stderr.strip() == "jaxbvh: interrupted"
    assert "interpreter shut down" not in proc.stdout  # atexit never ran: no finalization
    from jaxbvh.cli.commands import build

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(build, "run", interrupted)
    assert run_cli(capsys, "build") == (130, "", "jaxbvh: interrupted\n")
