"""The optimizer entry point and the treelet + reinsertion pipeline (jaxbvh.optimize)."""

from __future__ import annotations

import numpy as np
import pytest
from test_reinsert import assert_same_tree, random_tree

import jaxbvh
from jaxbvh.optimize import METHODS, PIPELINE_TREELET_PASSES, optimize, reinsert, treelet


def check(tree, result, prim_lo, prim_hi):
    jaxbvh.validate(result.tree, prim_lo, prim_hi)
    t = jaxbvh.to_numpy(tree)
    leaf = t.prim_count > 0
    np.testing.assert_array_equal(result.tree.lo[leaf], t.lo[leaf])
    assert result.sah == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(result.tree))), rel=1e-6)
    assert result.sah <= result.sah_start * (1 + 1e-6)


def test_every_method_gives_a_valid_tree_and_reports_every_step():
    tree, plo, phi = random_tree(21, 50, 2)
    for method in METHODS:
        steps = []
        result = optimize(tree, method, on_step=lambda *a: steps.append(a),
                          **(dict(steps=12) if method == "sa" else {}))
        check(tree, result, plo, phi)
        assert steps and len(steps) == len(result.trace) >= result.steps > 0
        assert {stage for stage, *_ in steps} <= {method, "treelet", "reinsert"}


def test_pipeline_is_its_stages_in_rounds():
    """The pipeline's tree is the one the stages give when chained by hand."""
    tree, plo, phi = random_tree(22, 60, 1)
    result = optimize(tree, "pipeline", split_axes=False)
    t, sah = tree, float(jaxbvh.sah(jaxbvh.to_jax(tree)))
    for round_ in range(8):
        before = sah
        t = treelet.restructure(t, max_passes=PIPELINE_TREELET_PASSES, split_axes=False).tree
        r = reinsert.reinsert(t, split_axes=False, first_fraction=1 / 32 if round_ == 0 else 1.0)
        t, sah = r.tree, float(r.sah)
        if before - sah < 1e-3 * before:
            break
    assert_same_tree(result.tree, t)
    check(tree, result, plo, phi)
    axes = optimize(tree, "pipeline")  # with Kensler's split-axis pass: the same SAH
    assert axes.sah == pytest.approx(result.sah, rel=1e-6)
    assert_same_tree(axes.tree, jaxbvh.tree.assign_split_axes(result.tree), fields=("axis", "lo", "hi"))


def test_time_budget_and_bad_arguments():
    tree, plo, phi = random_tree(23, 60, 1)
    short = optimize(tree, "pipeline", time_budget=1e-9)
    check(tree, short, plo, phi)
    assert [stage for stage, *_ in short.trace] == ["treelet", "treelet"][: len(short.trace)]
    with pytest.raises(ValueError, match="method"):
        optimize(tree, "magic")
    with pytest.raises(ValueError, match="pipeline options"):
        optimize(tree, "pipeline", steps=3)
    with pytest.raises(ValueError, match="time_budget"):
        optimize(tree, "reinsert", time_budget=-1)


# ----------------------------------------------------------------------------------
# jaxbvh optimize --method reinsert|treelet|pipeline (the command line)
# ----------------------------------------------------------------------------------


def test_cli_methods_give_valid_saved_trees(capsys, tmp_path):
    from test_cli import grid_obj, run_json

    mesh = grid_obj(tmp_path / "grid.obj", n=5)
    results = {}
    for method in ("pipeline", "reinsert", "treelet"):
        out = tmp_path / f"{method}.npz"
        argv = ["optimize", mesh, "-o", out] + ([] if method == "pipeline" else ["--method", method])
        results[method] = result = run_json(capsys, *argv)  # the default is the pipeline
        assert result["method"] == method and result["valid"] is True
        assert result["after"]["sah"] <= result["before"]["sah"] * (1 + 1e-6)
        saved = run_json(capsys, "stats", out, "--mesh", mesh)  # the tree written is valid
        assert saved["valid"] is True
        assert saved["sah"] == pytest.approx(result["after"]["sah"], rel=1e-5)
    stages = results["pipeline"]["stages"]
    assert stages[0]["stage"] == "treelet"
    assert sum(s["steps"] for s in stages) == results["pipeline"]["passes"]
    assert all(a["stage"] != b["stage"] for a, b in zip(stages, stages[1:]))
    assert results["pipeline"]["treelet_leaves"] == 7 and "first_fraction" in results["reinsert"]
    assert "first_fraction" not in results["treelet"]


@pytest.mark.parametrize("argv, fragment", [
    (["--method", "reinsert", "--first-fraction", "0"], "--first-fraction"),
    (["--first-fraction", "1.5"], "--first-fraction"),
    (["--method", "treelet", "--treelet-leaves", "11"], "--treelet-leaves"),
    (["--method", "reinsert", "--time-budget", "0"], "--time-budget"),
    (["--method", "treelet", "--time-budget", "-1"], "--time-budget"),
])
def test_cli_bad_options_are_one_line_errors(capsys, tmp_path, argv, fragment):
    from test_cli import assert_one_line_error, grid_obj, run_cli

    mesh = grid_obj(tmp_path / "grid.obj")
    assert_one_line_error(*run_cli(capsys, "optimize", mesh, *argv), fragment)


@pytest.mark.parametrize("method", ["reinsert", "treelet"])
@pytest.mark.parametrize("kind", ["cycle", "nan-box"])
def test_cli_methods_refuse_broken_trees(capsys, tmp_path, method, kind):
    from test_cli import assert_one_line_error, broken_tree_file, run_cli

    mesh, path = broken_tree_file(tmp_path, kind)
    assert_one_line_error(*run_cli(capsys, "optimize", path, "--method", method), "invalid BVH", path.name)


def test_time_budget_clock_starts_after_the_first_step():
    import time

    from jaxbvh.optimize.budget import TimeBudget

    none = TimeBudget(None)
    assert not any(none.spent() for _ in range(3))
    tiny = TimeBudget(1e-9)
    time.sleep(0.01)  # the first step (compiling) is not counted
    assert not tiny.spent()
    time.sleep(0.01)
    assert tiny.spent()
    long = TimeBudget(3600.0)
    assert not long.spent() and not long.spent()
