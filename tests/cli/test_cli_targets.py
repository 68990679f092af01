"""``--target`` on build, optimize and batch: the target's costs, explicit options winning, errors."""

from __future__ import annotations

import pytest
from helpers import grid_obj, run_cli, run_json

import jaxbvh
from jaxbvh.cli import command_kit, make_parser
from jaxbvh.tree import cost_reference, targets


@pytest.mark.parametrize("command", ["build", "optimize", "batch"])
def test_target_sets_the_costs_and_explicit_options_win(command):
    parser, _ = make_parser()
    head = {"build": ["build"], "optimize": ["optimize", "x.obj"], "batch": ["batch", "build", "x.obj"]}[command]
    target = targets.get("tinybvh-bvh8")
    args = parser.parse_args(head + ["--target", "tinybvh-bvh8"])
    builder = command_kit.builder_config(args)
    assert (builder.ct, builder.ci, builder.max_leaf) == (target.ct, target.ci, target.max_leaf)
    args = parser.parse_args(head + ["--target", "tinybvh-bvh8", "--ct", "2.5", "--max-leaf", "2"])
    builder = command_kit.builder_config(args)
    assert (builder.ct, builder.ci, builder.max_leaf) == (2.5, target.ci, 2)
    plain = command_kit.builder_config(parser.parse_args(head))  # no target: the Config's defaults
    assert (plain.ct, plain.ci) == (1.0, 1.0)


def test_unknown_target_is_a_usage_error_naming_the_targets(capsys):
    status, out, err = run_cli(capsys, "build", "--target", "bvh16")
    assert status == 2 and out == ""
    assert "bvh16" in err and all(name in err for name in targets.TARGETS)


def test_build_and_optimize_report_the_target_cost(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 3)
    out = tmp_path / "t.npz"
    built = run_json(capsys, "build", mesh, "--target", "tinybvh-soa", "-o", out)
    tree, _ = jaxbvh.load(out)
    target = targets.get("tinybvh-soa")
    want = float(cost_reference.sah(jaxbvh.to_numpy(tree), target.ct, target.ci))
    assert built["target"] == "tinybvh-soa"
    assert built["target_cost"] == pytest.approx(want, rel=1e-5) and built["sah"] == pytest.approx(want, rel=1e-5)
    result = run_json(capsys, "optimize", mesh, "--target", "tinybvh-bvh8", "--method", "treelet")
    for side in ("before", "after"):
        assert result[side]["target"] == "tinybvh-bvh8" and result[side]["target_cost"] > 0
    assert "target_cost" not in run_json(capsys, "build", mesh)  # no target, no target cost
