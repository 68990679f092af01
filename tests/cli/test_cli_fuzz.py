"""Hostile input to the command line: bad frames and float widths in tree files, options
out of range, seeds of any size, degenerate trees and time budgets (issue 23).

Every case gets one line ``jaxbvh: error: ...`` (exit status 2), an honest ``valid: no``
(exit status 1), or a correct result; never a traceback, a false ``valid``, or a run
that does not end.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import assert_one_line_error, grid_obj, run_cli, run_json, three_triangle_files

import jaxbvh
from jaxbvh.cli import command_kit

#: tree files whose frame is broken: (extra arrays, the array the error names)
BAD_FRAMES = {
    "scale-array": (dict(origin=np.zeros(3), scale=np.ones(1)), "'scale'"),
    "origin-short": (dict(origin=np.zeros(2), scale=np.float64(1)), "'origin'"),
    "nan-origin": (dict(origin=np.array([np.nan, 0, 0]), scale=np.float64(1)), "'origin'"),
    "zero-scale": (dict(origin=np.zeros(3), scale=np.float64(0)), "'scale'"),
    "nan-scale": (dict(origin=np.zeros(3), scale=np.float64(np.nan)), "'scale'"),
    "inf-scale": (dict(origin=np.zeros(3), scale=np.float64(np.inf)), "'scale'"),
    "negative-scale": (dict(origin=np.zeros(3), scale=np.float64(-1)), "'scale'"),
}

#: every command that reads a tree, as argv after the tree file
READERS = {
    "stats": lambda tree, mesh: ["stats", tree],
    "stats --mesh": lambda tree, mesh: ["stats", tree, "--mesh", mesh],
    "optimize": lambda tree, mesh: ["optimize", tree],
    "optimize treelet": lambda tree, mesh: ["optimize", tree, "--method", "treelet"],
    "optimize sa": lambda tree, mesh: ["optimize", tree, "--method", "sa", "--steps", 4],
    "trace": lambda tree, mesh: ["trace", tree, mesh, "--rays", 20],
    "collapse": lambda tree, mesh: ["collapse", tree],
}


@pytest.mark.parametrize("kind", sorted(BAD_FRAMES))
@pytest.mark.parametrize("command", sorted(READERS))
def test_every_reader_refuses_a_bad_frame_in_one_line(capsys, tmp_path, command, kind):
    mesh, arrays = three_triangle_files(tmp_path)
    extra, named = BAD_FRAMES[kind]
    path = tmp_path / f"{kind}.npz"
    np.savez(path, **arrays, **extra)
    assert_one_line_error(*run_cli(capsys, *READERS[command](path, mesh)), path.name, named)


def _with_boxes(tmp_path, arrays, dtype, name):
    path = tmp_path / name
    np.savez(path, **{**arrays, "lo": arrays["lo"].astype(dtype), "hi": arrays["hi"].astype(dtype)})
    return path


def test_boxes_are_checked_in_the_precision_they_are_stored_in(capsys, tmp_path):
    """float16 boxes rounded to nearest miss their triangles: invalid, and said why; the
    same float32 boxes stored as float64 hold the triangles as float32 rounds them: valid,
    checked in float32, and traced against those triangles."""
    mesh = grid_obj(tmp_path / "grid.obj", n=3)
    built = tmp_path / "grid.npz"
    run_json(capsys, "build", mesh, "-o", built)
    arrays = dict(np.load(built))
    half = _with_boxes(tmp_path, arrays, np.float16, "half.npz")
    status, out, err = run_cli(capsys, "stats", half, "--mesh", mesh, "--json")
    assert status == 1 and '"valid": false' in out and "do not contain" in out
    assert "jaxbvh: warning:" in err and "float16: widened to float32 (exact)" in err
    assert "Traceback" not in err
    wide = _with_boxes(tmp_path, arrays, np.float64, "wide.npz")
    result = run_json(capsys, "stats", wide, "--mesh", mesh)
    assert result["valid"] is True and result["dtype"] == "float64" and result["checked_in"] in ("float32", "float64")
    traced = run_json(capsys, "trace", wide, mesh, "--rays", 200)
    single = run_json(capsys, "trace", built, mesh, "--rays", 200)
    assert traced["checked_in"] == result["checked_in"]
    assert traced["hit_fraction"] == single["hit_fraction"]


def test_a_leaf_box_shrunk_below_its_float64_triangle_is_invalid_in_float64(capsys, tmp_path):
    """The float32 fallback never hides a box that misses its triangle by more."""
    mesh, arrays = three_triangle_files(tmp_path)
    wide = {**arrays, "lo": arrays["lo"].astype(np.float64), "hi": arrays["hi"].astype(np.float64)}
    wide["hi"][3, 0] -= 1e-3  # leaf 3 (triangle 0) now misses its triangle by 1e-3
    path = tmp_path / "shrunk.npz"
    np.savez(path, **wide)
    result = run_json(capsys, "stats", path, "--mesh", mesh, status=1)
    assert result["valid"] is False and result["checked_in"] == "float64"


@pytest.mark.parametrize("argv, fragment", [
    (["build", "--max-leaf", "2147483648"], "--max-leaf must be an integer in [1, 2147483647]"),
    (["build", "--ct", "nan"], "--ct must be a finite number >= 0"),
    (["build", "--ci", "inf"], "--ci must be a finite number >= 0"),
    (["build", "--ct", "-1"], "--ct must be a finite number >= 0"),
    (["trace", "t.npz", "m.obj", "--rays", "10000000000000"], "--rays: expected an integer in [1, 2147483647]"),
    (["trace", "t.npz", "m.obj", "--batch", "0"], "--batch: expected an integer in [1, 2147483647]"),
    (["grasp", "m.obj", "--trials", "1e9"], "--trials: expected int"),
    (["grasp", "m.obj", "--trials", "1000000000"], "--trials 1,000,000,000 is more than this command runs"),
    (["evolve", "m.obj", "--generations", "1000000000"], "--generations 1,000,000,000 is more than"),
    (["optimize", "t.npz", "--time-budget", "nan"], "--time-budget must be > 0"),
    (["frobnicate"], "invalid choice"),
])
def test_options_out_of_range_are_one_line_errors_before_any_work(capsys, argv, fragment):
    status, out, err = run_cli(capsys, *argv)
    assert_one_line_error(status, out, err, fragment)
    assert "usage:" not in err


def test_memory_bounds_are_checked_before_any_work(capsys, tmp_path, monkeypatch):
    mesh, arrays = three_triangle_files(tmp_path)
    tree = tmp_path / "three.npz"
    np.savez(tree, **arrays)
    monkeypatch.setattr(command_kit, "memory_bytes", lambda: 2 ** 30)  # a 1 GiB machine
    for argv, fragment in ([["trace", tree, mesh, "--rays", 2_000_000_000], "--rays 2,000,000,000 needs about"],
                           [["optimize", tree, "--method", "sa", "--chains", 1_000_000], "--chains 1,000,000 needs"],
                           [["evolve", mesh, "--population", 100_000_000], "--population 100,000,000 needs"]):
        assert_one_line_error(*run_cli(capsys, *argv), fragment, "1.0 GB available")


def test_any_integer_seed_maps_to_its_own_key():
    import jax

    seeds = [0, 1, 2 ** 32 - 1, 2 ** 32, -1, 2 ** 64 + 1, -(2 ** 64 + 1), 18446744073709551617, 10 ** 40]
    keys = [tuple(np.asarray(jax.random.key_data(command_kit.seed_key(s))).tolist()) for s in seeds]
    assert len(set(keys)) == len(set(seeds))  # distinct seeds, distinct keys (2^64 + 1 is listed twice)
    # seeds a 32-bit key holds give the library's key
    assert keys[1] == tuple(np.asarray(jax.random.key_data(jax.random.key(1))).tolist())


def test_a_huge_seed_traces(capsys, tmp_path):
    mesh, arrays = three_triangle_files(tmp_path)
    tree = tmp_path / "three.npz"
    np.savez(tree, **arrays)
    result = run_json(capsys, "trace", tree, mesh, "--rays", 10, "--seed", 18446744073709551617)
    assert result["seed"] == 18446744073709551617 and result["rays"] == 10


def _chain(n: int) -> dict:
    """Interchange arrays of a chain over leaves 0..n-1 (boxes filled in by the caller):
    interior node i (0 <= i < n-1) has leaf n-1+i and interior i+1 (the last: two leaves)."""
    interior, leaves = n - 1, n
    child = np.full((interior + leaves, 2), -1, np.int32)
    for i in range(interior):
        child[i] = (interior + i, i + 1 if i + 1 < interior else interior + n - 1)
    count = np.r_[np.zeros(interior, np.int32), np.ones(leaves, np.int32)]
    start = np.r_[np.zeros(interior, np.int32), np.arange(leaves, dtype=np.int32)]
    return {"child": child, "prim_start": start, "prim_count": count,
            "prim_index": np.arange(n, dtype=np.int32), "root": np.int32(0)}


def test_trace_warns_when_depth_makes_traversal_explode(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", n=6)  # 72 triangles: a chain 71 deep
    tri = jaxbvh.load_mesh(mesh).triangles.astype(np.float32)
    arrays = _chain(tri.shape[0])
    interior = tri.shape[0] - 1
    lo = np.zeros((2 * tri.shape[0] - 1, 3), np.float32)
    hi = np.zeros_like(lo)
    lo[interior:], hi[interior:] = tri.min(1), tri.max(1)
    for i in reversed(range(interior)):  # unions, bottom up
        a, b = arrays["child"][i]
        lo[i], hi[i] = np.minimum(lo[a], lo[b]), np.maximum(hi[a], hi[b])
    path = tmp_path / "chain.npz"
    np.savez(path, **arrays, lo=lo, hi=hi)
    status, out, err = run_cli(capsys, "trace", path, mesh, "--rays", 64, "--json")
    assert status == 0, err
    warning = [line for line in err.splitlines() if line.startswith("jaxbvh: warning:")]
    assert len(warning) == 1 and "tree depth 71" in warning[0] and "~142 steps" in warning[0]
    # a balanced tree of the same mesh says nothing
    built = tmp_path / "grid.npz"
    run_json(capsys, "build", mesh, "-o", built)
    status, _, err = run_cli(capsys, "trace", built, mesh, "--rays", 64, "--json")
    assert status == 0 and "warning" not in err


def test_a_time_budget_shorter_than_compiling_still_makes_a_pass(capsys, tmp_path):
    mesh, arrays = three_triangle_files(tmp_path)
    tree = tmp_path / "three.npz"
    np.savez(tree, **arrays)
    status, out, err = run_cli(capsys, "optimize", tree, "--method", "reinsert", "--time-budget", "1e-6", "--json")
    assert status == 0, err
    assert "warning" not in err
    result = json.loads(out)
    assert result["passes"] == 1 and result["valid"] is True
    assert 0 <= result["compile_seconds"] <= result["seconds"]
