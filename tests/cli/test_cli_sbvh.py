"""``--builder sbvh`` on the command line: build, stats, optimize and trace take trees with
references (a triangle in several leaves) and check them in references mode."""

from __future__ import annotations

from helpers import grid_obj, run_json


def test_sbvh_through_build_stats_optimize_and_trace(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", n=4)
    tree = tmp_path / "sbvh.npz"
    # alpha 0: spatial splits tried at every node, so the tree has references
    built = run_json(capsys, "build", mesh, "--builder", "sbvh", "--alpha", "0", "--reference-capacity", "3",
                     "--bins", "4", "-o", tree)
    assert built["builder"] == "sbvh" and built["valid"]
    assert built["references_per_triangle"] >= 1.0
    assert built["primitives"] >= built["triangles"]
    stats = run_json(capsys, "stats", tree, "--mesh", mesh)
    assert stats["valid"] and stats["references_per_triangle"] == built["references_per_triangle"]
    optimized = run_json(capsys, "optimize", mesh, "--builder", "sbvh", "--alpha", "0", "--bins", "4",
                         "--method", "reinsert")
    assert optimized["sah"] <= optimized["sah_start"] * (1 + 1e-6) if "sah_start" in optimized else True
    traced = run_json(capsys, "trace", tree, mesh, "--rays", "64")
    assert traced["box_tests"] > 0
