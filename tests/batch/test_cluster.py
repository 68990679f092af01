"""Batches on a Dask cluster (:mod:`jaxbvh.batch.runs`): a LocalCluster of 2 worker processes
gives the single-process trees node for node, a bad mesh fails alone, a worker killed mid-run
loses nothing and delivers nothing twice, and ``--resume`` redoes only what is missing or stale."""

from __future__ import annotations

import json
import os
import signal

import jax
import numpy as np
import pytest
from helpers import assert_same_costs, grid_obj, run_cli, run_json

import jaxbvh
from jaxbvh.batch import runs

distributed = pytest.importorskip("distributed")

GOOD = 18  # tiny meshes (8..32 triangles: two capacity buckets)
BAD = ("nan.obj", "junk.obj")


@pytest.fixture(scope="module")
def client():
    """One LocalCluster of 2 worker processes for the module (starting one costs seconds)."""
    with runs.connect("local:2") as made:  # as `--scheduler local:2` starts it
        yield made


def mesh_folder(folder, good: int = GOOD):
    folder.mkdir(parents=True)
    for i in range(good):
        grid_obj(folder / f"m{i:02d}.obj", 2 + i % 3, i)
    (folder / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    (folder / "junk.obj").write_text("hello\n")
    return folder


def tree_arrays(path) -> dict:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def assert_same_files(a, b, names):
    for name in names:
        x, y = tree_arrays(a / name), tree_arrays(b / name)
        assert x.keys() == y.keys(), name
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=f"{name}: {k}")


def test_cluster_trees_equal_the_single_process_run_and_bad_meshes_fail_alone(tmp_path, capsys, client):
    folder = mesh_folder(tmp_path / "in")
    single = run_json(capsys, "batch", "build", folder, "-o", tmp_path / "single", status=1)
    report = tmp_path / "report.csv"
    # the scheduler by address, as `jaxbvh batch --scheduler tcp://...` gets it; chunks of 4 files
    result = run_json(capsys, "batch", "build", folder, "-o", tmp_path / "cluster", "--scheduler",
                      client.scheduler.address, "--chunk-files", "4", "--report", report, status=1)
    assert result["failed"] == len(BAD) and result["written"] == GOOD and result["valid"] is False
    rows = {os.path.basename(r["mesh"]): r for r in result["rows"]}
    assert len(result["rows"]) == len(rows) == GOOD + len(BAD)
    assert "NaN" in rows["nan.obj"]["error"] and rows["junk.obj"]["error"].startswith("load:")
    assert {r["worker"] for r in result["rows"] if not r.get("error")} <= set(client.scheduler_info()["workers"])
    names = [f"m{i:02d}.obj.npz" for i in range(GOOD)]
    assert sorted(p.name for p in (tmp_path / "cluster").glob("*.npz")) == names
    assert_same_files(tmp_path / "single", tmp_path / "cluster", names)  # node for node
    single_rows = {os.path.basename(r["mesh"]): r for r in single["rows"]}
    for name, row in rows.items():
        if not row.get("error"):
            # the same tree priced by another program (a worker's single device, not the
            # batch's two): equal but for the last bits of a float sum
            assert_same_costs(np.float32([row["sah"], row["sah_built"]]), np.float32([single_rows[name]["sah"]] * 2))
            assert row["triangles"] == jaxbvh.load_mesh(folder / name).n_triangles
    text = report.read_text().splitlines()
    assert text[0].split(",") == list(runs.REPORT_FIELDS) and len(text) == 1 + GOOD + len(BAD)


class Keys(Exception):
    """Raised by the spy in place of optimizing: the keys were all the test wanted."""


def test_annealing_keys_come_from_the_file_name_not_its_place(tmp_path, capsys, monkeypatch):
    folder = mesh_folder(tmp_path / "in", good=4)  # with the 2 bad: 6 files
    seen = []  # the keys of every optimize call

    def spy(trees, method, config=None, *, keys=None, **_):
        seen.append([np.asarray(jax.random.key_data(key)).tolist() for key in keys])
        raise Keys

    from jaxbvh.cli.commands import batch as batch_command

    monkeypatch.setattr(batch_command, "optimize", spy)
    monkeypatch.setattr(runs, "optimize", spy)
    # single process: every good mesh in one batch, in folder order
    names = runs.output_names(sorted(folder.iterdir()))
    with pytest.raises(Keys):
        run_cli(capsys, "batch", "optimize", folder, "-o", tmp_path / "a", "--method", "sa", "--seed", "7")
    single = seen.pop(0)
    # chunks of at most 3 files of one capacity bucket: other positions, other chunks
    runs.run_files(sorted(folder.iterdir()), tmp_path / "b", action="optimize", method="sa", seed=7, chunk_files=3)
    chunks = runs.chunk_items(list(zip(map(str, sorted(folder.iterdir())), names)), 3)
    assert len(seen) == sum(any(n.startswith("m") for _, n in c) for c in chunks) > 1  # a call per chunk of good ones
    chunked = [k for part in seen for k in part]
    good = [n for n in names if n.startswith("m")]
    want = {n: np.asarray(jax.random.key_data(runs.mesh_key(7, n))).tolist() for n in good}
    assert sorted(single) == sorted(want.values()) == sorted(chunked)
    assert single == [want[n] for n in good]  # in input order, each mesh its own name's key
    assert len({tuple(k) for k in single}) == len(good)  # distinct meshes, distinct keys


def test_a_worker_killed_mid_run_loses_no_file_and_delivers_none_twice(tmp_path, client):
    folder = mesh_folder(tmp_path / "in")
    pids = client.run(os.getpid)  # worker address -> process id
    killed = []

    def kill_a_busy_worker(done, failed, left, seconds):
        if killed or done + failed == 0:
            return
        busy = [w for w, tasks in client.processing().items() if tasks and w in pids]
        if busy:
            os.kill(pids[busy[0]], signal.SIGKILL)  # no goodbye: its chunk goes to the other worker
            killed.append(busy[0])

    made = runs.run_files(sorted(folder.iterdir()), tmp_path / "out", client=client, chunk_files=4,
                          on_progress=kill_a_busy_worker)
    assert killed, "no worker was busy to kill"
    names = sorted(os.path.basename(r["mesh"]) for r in made.rows)
    assert names == sorted(p.name for p in folder.iterdir())  # every file once
    assert made.failed == len(BAD) and made.done == GOOD
    manifest = json.loads((tmp_path / "out" / runs.MANIFEST).read_text())
    assert sorted(manifest["files"]) == sorted(f"{n}.npz" for n in names)
    for row in made.rows:
        if row.get("error"):
            assert not (tmp_path / "out" / f"{os.path.basename(row['mesh'])}.npz").exists()
            continue
        assert runs.file_sha256(row["output"]) == row["output_sha256"]
        tree, _ = jaxbvh.load(row["output"])
        jaxbvh.validate(tree, *jaxbvh.load_mesh(row["mesh"]).local_boxes())
    left = [p.name for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]
    assert not left  # no temporary file of the killed worker's writes is left


def test_resume_redoes_only_what_is_missing_or_stale(tmp_path, capsys):
    folder = mesh_folder(tmp_path / "in")
    out = tmp_path / "out"
    first = []

    def stop_after_two_chunks(done, failed, left, seconds):
        first.append(done + failed)
        if len(first) == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # here, in this process: chunks of 4 files
        runs.run_files(sorted(folder.iterdir()), out, chunk_files=4, on_progress=stop_after_two_chunks)
    recorded = json.loads((out / runs.MANIFEST).read_text())["files"]
    assert len(recorded) == 8  # two chunks, the manifest written on the way out
    kept = sorted(n for n, r in recorded.items() if not r.get("error"))
    stale_input, lost_output, bad_output = kept[:3]
    grid_obj(folder / stale_input[:-4], 4, 99)      # the mesh changed since its tree was made
    (out / lost_output).unlink()                     # its tree is gone
    (out / bad_output).write_bytes(b"not the tree")  # its tree was changed
    result = run_json(capsys, "batch", "build", folder, "-o", out, "--resume", "--chunk-files", "4", status=1)
    skipped = sorted(f"{os.path.basename(r['mesh'])}.npz" for r in result["rows"] if r.get("skipped"))
    assert skipped == sorted(set(kept) - {stale_input, lost_output, bad_output})
    assert result["skipped"] == len(skipped) and result["written"] == GOOD - len(skipped)
    assert result["failed"] == len(BAD)  # a failed file is tried again, and fails again
    for row in result["rows"]:
        if not row.get("error"):
            tree, _ = jaxbvh.load(row["output"])
            jaxbvh.validate(tree, *jaxbvh.load_mesh(row["mesh"]).local_boxes())
    # a second resume has nothing left but the bad meshes
    again = run_json(capsys, "batch", "build", folder, "-o", out, "--resume", status=1)
    assert again["skipped"] == GOOD and again["written"] == 0 and again["failed"] == len(BAD)
    # other options make every tree stale
    median = run_json(capsys, "batch", "build", folder, "-o", out, "--resume", "--builder", "median", status=1)
    assert median["skipped"] == 0 and median["written"] == GOOD


def hashes_read(monkeypatch) -> list:
    """The files whose bytes run_files hashes from now on (a spy on ``runs.file_sha256``)."""
    read = []
    real = runs.file_sha256

    def spy(path):
        read.append(os.path.basename(path))
        return real(path)

    monkeypatch.setattr(runs, "file_sha256", spy)
    return read


def test_resume_reads_no_file_whose_stamps_are_unchanged_and_redoes_a_changed_one(tmp_path, monkeypatch):
    monkeypatch.setattr(runs, "RACY_S", 0.0)  # files written a moment ago count as settled
    folder = mesh_folder(tmp_path / "in", good=2)
    out = tmp_path / "out"
    paths = sorted(folder.iterdir())
    runs.run_files(paths, out, chunk_files=3)
    recorded = json.loads((out / runs.MANIFEST).read_text())["files"]
    assert recorded["m00.obj.npz"]["input_stamp"] == runs.file_stamp(folder / "m00.obj")
    read = hashes_read(monkeypatch)
    again = runs.run_files(paths, out, chunk_files=3, resume=True)
    assert again.skipped == 2 and again.done == 0 and again.failed == len(BAD)
    assert not [n for n in read if n.startswith("m")]  # nothing of the up-to-date files was read
    # the same size and modification time, other bytes (two vertex lines swapped): redone
    changed = folder / "m01.obj"
    lines = changed.read_text().splitlines(keepends=True)
    before = os.stat(changed)
    assert lines[0] != lines[1] and lines[0].startswith("v") and lines[1].startswith("v")
    changed.write_text("".join([lines[1], lines[0]] + lines[2:]))
    os.utime(changed, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert os.stat(changed).st_size == before.st_size and os.stat(changed).st_mtime_ns == before.st_mtime_ns
    read.clear()
    third = runs.run_files(paths, out, chunk_files=3, resume=True)
    redone = [os.path.basename(r["mesh"]) for r in third.rows if not r.get("skipped") and not r.get("error")]
    assert redone == ["m01.obj"] and third.skipped == 1
    row = next(r for r in third.rows if r["mesh"].endswith("m01.obj"))
    assert row["input_sha256"] == runs.file_sha256(changed)
    tree, _ = jaxbvh.load(row["output"])
    jaxbvh.validate(tree, *jaxbvh.load_mesh(changed).local_boxes())


def test_an_input_changed_just_before_it_was_read_is_hashed_again_on_resume(tmp_path, monkeypatch):
    monkeypatch.setattr(runs, "RACY_S", 1e9)  # every file counts as just changed: no stamp is trusted
    folder = mesh_folder(tmp_path / "in", good=3)
    out = tmp_path / "out"
    paths = sorted(folder.iterdir())
    first = runs.run_files(paths, out)
    assert all(r.get("input_stamp") is None for r in first.rows if not r.get("error"))
    read = hashes_read(monkeypatch)
    again = runs.run_files(paths, out, resume=True)
    assert again.skipped == 3
    assert sorted(n for n in read if n.startswith("m") and n.endswith(".obj")) == ["m00.obj", "m01.obj", "m02.obj"]
