"""``jaxbvh batch build|optimize``: one validated tree per mesh, a row per mesh, bad
entries fail alone with their own error, options checked before any work."""

from __future__ import annotations

import importlib
import jax
import numpy as np
from helpers import assert_one_line_error, grid_obj, run_cli, run_json

import jaxbvh
from jaxbvh.cli.commands import batch as batch_command


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
        tree, frame = jaxbvh.load(out / f"{name}.obj.npz")
        mesh = jaxbvh.load_mesh(folder / f"{name}.obj")
        jaxbvh.validate(tree, *mesh.local_boxes())
        assert rows[f"{name}.obj"]["triangles"] == mesh.n_triangles
        assert rows[f"{name}.obj"]["sah"] == rows[f"{name}.obj"]["sah_built"] > 0
        # the tree of the single build of that mesh
        single = jaxbvh.to_numpy(jaxbvh.build(*mesh.local_boxes()))
        np.testing.assert_array_equal(np.asarray(tree.lo)[np.asarray(tree.prim_count) > 0].min(0),
                                      single.lo[single.prim_count > 0].min(0))
    assert sorted(p.name for p in out.iterdir()) == ["a.obj.npz", "b.obj.npz"]  # no file of a failed mesh


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
    assert (tmp_path / "out" / "a.obj.npz").exists() and (tmp_path / "out" / "b.obj.npz").exists()


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


def test_output_names_are_the_inputs_paths_with_their_suffixes(tmp_path):
    """The issue's case: a-2.obj, a.obj and a.ply were a-2, a and a-2 again by stem; by path
    every input has its own name, in its own subfolder when it is below one."""
    (tmp_path / "sub").mkdir()
    paths = [tmp_path / "a-2.obj", tmp_path / "a.obj", tmp_path / "a.ply", tmp_path / "sub" / "a.obj"]
    names = batch_command.output_names(paths)
    assert names == ["a-2.obj.npz", "a.obj.npz", "a.ply.npz", "sub/a.obj.npz"]
    assert batch_command.output_names([tmp_path / "sub" / "a.obj"]) == ["a.obj.npz"]


def test_a_batch_of_inputs_sharing_a_stem_writes_every_tree(tmp_path, capsys):
    src = tmp_path / "in"
    (src / "sub").mkdir(parents=True)
    grid_obj(src / "a-2.obj", 2, 0)
    grid_obj(src / "a.obj", 2, 1)
    grid_obj(src / "sub" / "a.obj", 3, 2)
    _ply(src / "a.ply", src / "a-2.obj")
    out = tmp_path / "out"
    inputs = [src / "a-2.obj", src / "a.obj", src / "a.ply", src / "sub" / "a.obj"]
    result = run_json(capsys, "batch", "build", *inputs, "-o", out)
    assert result["written"] == 4 and result["valid"] is True
    for path in inputs:
        written = out / (str(path.relative_to(src)) + ".npz")
        assert {r["output"] for r in result["rows"] if r["mesh"] == str(path)} == {str(written)}
        tree, _ = jaxbvh.load(written)
        jaxbvh.validate(tree, *jaxbvh.load_mesh(path).local_boxes())  # each tree is its own mesh's


def _ply(path, obj):
    """An ASCII PLY of the OBJ's triangles (another suffix, the same stem)."""
    mesh = jaxbvh.load_mesh(obj)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    path.write_text(head + "".join(f"{x} {y} {z}\n" for x, y, z in v.tolist())
                    + "".join(f"3 {a} {b} {c}\n" for a, b, c in f.tolist()))


def test_an_output_already_there_is_an_error_before_any_work_unless_overwrite(tmp_path, capsys):
    grid_obj(tmp_path / "a.obj", 2, 0)
    grid_obj(tmp_path / "b.obj", 2, 1)
    out = tmp_path / "out"
    out.mkdir()
    (out / "b.obj.npz").write_bytes(b"someone's tree")
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path / "*.obj", "-o", out),
                          str(out / "b.obj.npz"), "--overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["b.obj.npz"]  # nothing was written
    assert (out / "b.obj.npz").read_bytes() == b"someone's tree"
    (out / "a.obj.npz").mkdir()  # a folder in the way: an error even with --overwrite
    assert_one_line_error(*run_cli(capsys, "batch", "build", tmp_path / "*.obj", "-o", out, "--overwrite"),
                          str(out / "a.obj.npz"), "folder")
    (out / "a.obj.npz").rmdir()
    result = run_json(capsys, "batch", "build", tmp_path / "*.obj", "-o", out, "--overwrite")
    assert result["written"] == 2
    jaxbvh.load(out / "b.obj.npz")  # replaced by the tree


def test_one_file_named_twice_is_built_once(tmp_path, capsys, monkeypatch):
    grid_obj(tmp_path / "a.obj", 2, 0)
    monkeypatch.chdir(tmp_path)
    result = run_json(capsys, "batch", "build", "a.obj", "./a.obj", tmp_path / "a.obj", "-o", "out")
    assert result["meshes"] == 1 and result["written"] == 1


def test_batch_build_and_optimize_with_sbvh_write_valid_trees_with_references(tmp_path, capsys):
    grid_obj(tmp_path / "a.obj", 3, 0)
    grid_obj(tmp_path / "b.obj", 3, 1)
    for action, extra in (("build", []), ("optimize", ["--method", "hc"])):
        out = tmp_path / action
        result = run_json(capsys, "batch", action, tmp_path / "*.obj", "-o", out, "--builder", "sbvh",
                          "--alpha", "0", "--bins", "4", *extra)
        assert result["builder"] == "sbvh" and result["written"] == 2 and result["valid"] is True, result
        for name in ("a", "b"):
            tree, _ = jaxbvh.load(out / f"{name}.obj.npz")
            mesh = jaxbvh.load_mesh(tmp_path / f"{name}.obj")
            tri = mesh.local_triangles()
            jaxbvh.validate(tree, tri.min(1), tri.max(1), references=True, triangles=tri)


def test_an_interrupted_batch_exits_130_and_leaves_no_output(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the trees are written (the second one here): exit 130, one line, none
    of the batch's outputs, and an output it would have replaced (--overwrite) as it was."""
    grid_obj(tmp_path / "a.obj", 2, 0)
    grid_obj(tmp_path / "b.obj", 2, 1)
    out = tmp_path / "out"
    out.mkdir()
    (out / "b.obj.npz").write_bytes(b"yesterday's tree")
    real_save, calls = jaxbvh.save, []

    def save(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_save(*args, **kwargs)

    monkeypatch.setattr(jaxbvh, "save", save)
    status, stdout, err = run_cli(capsys, "batch", "build", tmp_path / "*.obj", "-o", out, "--overwrite")
    assert status == 130 and err.strip() == "jaxbvh: interrupted" and stdout == ""
    assert len(calls) == 2  # the first tree was written (staged) before the interrupt
    assert sorted(p.name for p in out.iterdir()) == ["b.obj.npz"]
    assert (out / "b.obj.npz").read_bytes() == b"yesterday's tree"


def test_batch_optimize_writes_every_tree_but_the_one_whose_optimizer_fails(tmp_path, capsys, monkeypatch):
    batch_optimize = importlib.import_module("jaxbvh.batch.optimize")  # the module, not the function
    grid_obj(tmp_path / "a.obj", 3, 0)
    grid_obj(tmp_path / "b.obj", 2, 1)
    bad = jaxbvh.load_mesh(tmp_path / "b.obj").n_triangles
    run_chunk = batch_optimize._run_chunk

    def failing(optimizer, states, *args):  # the compiled call fails for b's tree alone
        if any(int(np.sum(np.asarray(s.tree.prim_count))) == bad for s in states):
            raise RuntimeError("a call that fails")
        return run_chunk(optimizer, states, *args)

    monkeypatch.setattr(batch_optimize, "_run_chunk", failing)
    result = run_json(capsys, "batch", "optimize", str(tmp_path / "*.obj"), "-o", tmp_path / "out",
                      "--method", "hc", status=1)
    rows = {r["mesh"].rsplit("/", 1)[-1]: r for r in result["rows"]}
    assert rows["b.obj"]["error"].startswith("optimize: ") and "a call that fails" in rows["b.obj"]["error"]
    assert "error" not in rows["a.obj"] or not rows["a.obj"]["error"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.obj.npz"]
    tree, _ = jaxbvh.load(tmp_path / "out" / "a.obj.npz")
    jaxbvh.validate(tree, *jaxbvh.load_mesh(tmp_path / "a.obj").local_boxes())
