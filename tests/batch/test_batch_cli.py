"""``jaxbvh batch build|optimize``: one validated tree per mesh, a row per mesh, bad
entries fail alone with their own error, options checked before any work."""

from __future__ import annotations

import jax
import numpy as np
from helpers import assert_one_line_error, grid_obj, run_cli, run_json

import jaxbvh


def _folder(tmp_path):
    tmp_path.mkdir()
    grid_obj(tmp_path / "a.obj", 2, 0)
    grid_obj(tmp_path / "b.obj", 3, 1)
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "junk.obj").write_text("hello\n")
    (tmp_path / "notes.txt").write_text("not a mesh suffix: a folder passes it over\n")
    return tmp_path


def test_batch_build_writes_every_good_mesh_and_reports_the_bad_ones(tmp_path, capsys):
    folder = _folder(tmp_path / "in")
    out = tmp_path / "out"
    result = run_json(capsys, "batch", "build", folder, "-o", out, status=1)
    rows = {r["mesh"].rsplit("/", 1)[-1]: r for r in result["rows"]}
    assert set(rows) == {"a.obj", "b.obj", "nan.obj", "junk.obj"}
    assert result["failed"] == 2 and result["written"] == 2 and result["valid"] is False
    assert result["devices"] == jax.device_count()  # JAX had started: its devices are kept
    assert "NaN" in rows["nan.obj"]["error"] and rows["junk.obj"]["error"].startswith("load:")
    for name in ("a", "b"):
        tree, frame = jaxbvh.load(out / f"{name}.npz")
        mesh = jaxbvh.load_mesh(folder / f"{name}.obj")
        jaxbvh.validate(tree, *mesh.local_boxes())
        assert rows[f"{name}.obj"]["triangles"] == mesh.n_triangles
        assert rows[f"{name}.obj"]["sah"] == rows[f"{name}.obj"]["sah_built"] > 0
        # the tree of the single build of that mesh
        single = jaxbvh.to_numpy(jaxbvh.build(*mesh.local_boxes()))
        np.testing.assert_array_equal(np.asarray(tree.lo)[np.asarray(tree.prim_count) > 0].min(0),
                                      single.lo[single.prim_count > 0].min(0))
    assert not (out / "nan.npz").exists() and not (out / "junk.npz").exists()


def test_batch_optimize_lowers_no_sah_and_prints_a_table(tmp_path, capsys):
    grid_obj(tmp_path / "a.obj", 3, 0)
    grid_obj(tmp_path / "b.obj", 2, 1)
    status, out, err = run_cli(capsys, "batch", "optimize", str(tmp_path / "*.obj"), "-o", tmp_path / "out",
                               "--method", "hc", "--builder", "median")
    assert status == 0, err
    lines = out.splitlines()
    assert lines[0].split() == ["mesh", "triangles", "sah_built", "sah_optimized", "seconds"]
    for line in lines[1:3]:
        name, _, built, optimized, _ = line.split()
        assert float(optimized) <= float(built) * (1 + 1e-6), line
    assert (tmp_path / "out" / "a.npz").exists() and (tmp_path / "out" / "b.npz").exists()


def test_options_are_checked_before_any_work(tmp_path, capsys):
    grid_obj(tmp_path / "a.obj", 2, 0)
    out = tmp_path / "out"
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path, "-o", out, "--memory-mb", "0"), "--memory-mb")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path, "-o", out, "--iterations", "5"),
                          "batch optimize")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path), "-o OUTDIR")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path, "-o", out, "--cpu-devices", "0"),
                          "cpu devices")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path, "-o", out, "--cpu-devices",
                                   str(jax.device_count() + 1)), "JAX has started")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path / "none*.obj", "-o", out), "no file matches")
    assert not out.exists()  # nothing was written
