"""``jaxbvh rebraid``: the three-way table, its JSON, the flattened output and bad input."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import assert_one_line_error, grid_obj, run_cli, run_json

import jaxbvh
from jaxbvh import scenes
from jaxbvh.io import boxes_in_frame, load_mesh


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A glTF scene: two small trees, each placed by one identity and two rotated instances."""
    import trimesh

    path = tmp_path_factory.mktemp("scene") / "trees.glb"
    sc = trimesh.Scene()
    for k in range(2):
        v, f = scenes.tree_mesh(jax.random.key(k), levels=1, branches=2, sides=3, leaves=1)
        sc.add_geometry(trimesh.Trimesh(v, f, process=False), geom_name=f"tree{k}", node_name=f"n{k}")
    rng = np.random.default_rng(0)
    for i in range(4):
        m = np.eye(4)
        m[:3, :3] = scenes.upright_rotations(jax.random.key(i), 1)[0]
        m[:3, 3] = rng.normal(size=3) * 0.5
        sc.graph.update(frame_to=f"m{i}", frame_from=sc.graph.base_frame, matrix=m, geometry=f"tree{i % 2}")
    sc.export(path)
    return path


def test_json_has_the_three_way_table(capsys, scene, tmp_path):
    out = tmp_path / "flat.npz"
    result = run_json(capsys, "rebraid", scene, "--threshold", "0.05", "--rays", "300", "-o", out)
    mesh = load_mesh(scene)
    assert result["instances"] == len(mesh.instances) == 6 and result["objects"] == 2
    for name in ("two_level", "rebraid", "single"):
        entry = result[name]
        for key in ("sah", "nodes", "seconds", "box_tests", "prim_tests"):
            assert isinstance(entry[key], (int, float)) and entry[key] >= 0, (name, key)
        assert entry["hits_agree"] == 1.0
        if name != "single":  # object-frame costs never exceed the conservative world boxes'
            assert 0 < entry["sah_object"] <= entry["sah"] * (1 + 1e-6)
    for name in ("two_level", "rebraid"):
        assert result[name]["top_seconds"] <= result[name]["seconds"]
    assert result["two_level"]["brefs"] == 6  # the plain top level: one BRef per instance
    assert 6 <= result["rebraid"]["brefs"] <= result["slots"] == 24  # 4 x instances (all shared)
    assert result["kept"] in ("rebraided", "two-level")
    assert result["rebraid"]["sah"] <= result["two_level"]["sah"] * (1 + 1e-6)
    assert result["rebraid_vs_two_level"] == pytest.approx(result["rebraid"]["sah"] / result["two_level"]["sah"])
    # -o: the re-braided tree flattened to world space, valid against the scene's triangles
    tree, frame = jaxbvh.load(out)
    lo, hi = boxes_in_frame(*mesh.prim_boxes(), frame)
    jaxbvh.validate(tree, lo, hi)
    assert jaxbvh.tree.node_count(tree) == result["rebraid"]["flat_nodes"]


def test_text_output_prints_the_table(capsys, scene):
    status, out, err = run_cli(capsys, "rebraid", scene, "--threshold", "inf", "--builder", "sweep")
    assert status == 0, err
    lines = out.splitlines()
    assert lines[0].split()[:2] == ["SAH", "vs"]
    assert [line.split()[0] for line in lines[1:4]] == ["two-level", "rebraid", "single"]
    # threshold inf never opens: the re-braided row is the two-level row
    assert lines[1].split()[1:6] == lines[2].split()[1:6]


def test_plain_mesh_has_no_top_level(capsys, tmp_path, monkeypatch):
    # a plain mesh takes the plain-build path: one build, no object trees, no top level
    # (issue 23: a million copies of one triangle ran past 120 s where `build` takes 11-28 s)
    def refuse(*args, **kwargs):
        raise AssertionError("a plain mesh must not build object trees or a top level")

    monkeypatch.setattr(jaxbvh.twolevel, "build_from", refuse)
    monkeypatch.setattr(jaxbvh.twolevel, "flatten", refuse)
    result = run_json(capsys, "rebraid", grid_obj(tmp_path / "grid.obj", n=3))
    assert result["objects"] == result["instances"] == 1
    assert result["path"] == result["kept"] == "single object"
    for name in ("two_level", "rebraid"):
        assert result[name]["brefs"] == 1 and result[name]["top_seconds"] < 0.05
        assert result[name]["sah"] == result["single"]["sah"]  # the same tree


@pytest.mark.parametrize("argv, fragment", [
    (["--threshold", "0"], "threshold must be a number > 0"),
    (["--threshold", "-0.1"], "threshold must be a number > 0"),
    (["--threshold", "nan"], "threshold must be a number > 0"),
    (["--budget", "0.5"], "budget must be a finite number in [1"),
    (["--budget", "1e9"], "budget must be a finite number in [1"),
    (["--overlap", "-1"], "overlap must be a finite number >= 0"),
    (["--rounds", "0"], "--rounds must be an integer >= 1"),
    (["--top-bins", "1"], "--top-bins must be an integer >= 2"),
])
def test_bad_options_are_one_line_errors(capsys, scene, argv, fragment):
    assert_one_line_error(*run_cli(capsys, "rebraid", scene, *argv), fragment)


def test_bad_scenes_are_one_line_errors(capsys, tmp_path):
    empty = tmp_path / "points.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    assert_one_line_error(*run_cli(capsys, "rebraid", empty), "no faces")
    assert_one_line_error(*run_cli(capsys, "rebraid", tmp_path / "missing.gltf"), "missing.gltf")


def test_sbvh_is_not_offered_and_refused_in_one_line(capsys, tmp_path):
    """Two-level BVHs are built from boxes: --builder sbvh (and its knobs) is not a choice,
    a usage error before any work rather than the library's refusal after loading."""
    status, out, _ = run_cli(capsys, "rebraid", "--help")
    assert status == 0 and "sbvh" not in out and "--alpha" not in out
    mesh = grid_obj(tmp_path / "g.obj", 2, 0)
    assert_one_line_error(*run_cli(capsys, "rebraid", mesh, "--builder", "sbvh"), "--builder", "sbvh")
    assert_one_line_error(*run_cli(capsys, "rebraid", mesh, "--alpha", "0"), "--alpha")


def test_object_bvhs_keep_the_object_leaf_limit_whichever_builder():
    """The object BVHs' leaves stop at OBJECT_MAX_LEAF (re-braiding opens nodes), below the
    builders' own default, for every builder: in the library's keyword form and in
    `jaxbvh rebraid --builder NAME`."""
    from jaxbvh.builders.configs import BOX_BUILDERS
    from jaxbvh.cli import app, command_kit
    from jaxbvh.configs import DEFAULT_MAX_LEAF
    from jaxbvh.twolevel import objects as fm

    assert fm.OBJECT_MAX_LEAF < DEFAULT_MAX_LEAF
    assert fm.object_builder().max_leaf == fm.OBJECT_MAX_LEAF
    parser, _ = app.make_parser()
    for method in BOX_BUILDERS:
        assert fm.object_builder(method=method).max_leaf == fm.OBJECT_MAX_LEAF, method
        assert fm.object_builder(method=method, max_leaf=2).max_leaf == 2, method
        args = parser.parse_args(["rebraid", "scene.glb", "--builder", method])
        assert command_kit.builder_config(args).max_leaf == fm.OBJECT_MAX_LEAF, method
        args = parser.parse_args(["rebraid", "scene.glb", "--builder", method, "--max-leaf", "7"])
        assert command_kit.builder_config(args).max_leaf == 7, method
