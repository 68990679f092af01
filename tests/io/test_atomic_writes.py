"""Every file the library and the tool write is replaced atomically (:mod:`jaxbvh.files`):
a write that fails part-way leaves the old file byte-for-byte and no temporary file."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from helpers import assert_one_line_error, grid_obj, run_cli, run_json, three_triangle_files

import jaxbvh
from jaxbvh.files import atomic_write, remove_abandoned_temporaries, trim_least_recent

OLD = b"the user's old file: it must survive a failed write\n" * 3


def _old_file(path: Path) -> Path:
    path.write_bytes(OLD)
    return path


def _leftovers(folder: Path, *keep: str) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def _savez_failing_part_way(monkeypatch, nbytes: int = 100):
    """``np.savez`` that writes ``nbytes`` of its archive, then fails as a full file system
    would (the bytes are real: an in-place write would have destroyed the old file)."""
    real = np.savez

    def savez(file, *args, **kwargs):
        import io
        buffer = io.BytesIO()
        real(buffer, *args, **kwargs)
        data = buffer.getvalue()
        assert len(data) > nbytes
        if hasattr(file, "write"):
            file.write(data[:nbytes])
            file.flush()
        else:
            with open(file if str(file).endswith(".npz") else f"{file}.npz", "wb") as f:
                f.write(data[:nbytes])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "savez", savez)


# ----------------------------------------------------------------------------------
# The helper
# ----------------------------------------------------------------------------------


def test_a_complete_write_replaces_the_file_and_keeps_its_mode(tmp_path):
    target = _old_file(tmp_path / "t.bin")
    target.chmod(0o640)
    with atomic_write(target) as f:
        f.write(b"new")
    assert target.read_bytes() == b"new"
    assert oct(target.stat().st_mode & 0o777) == oct(0o640)
    assert _leftovers(tmp_path, "t.bin") == []


def test_a_new_file_is_made(tmp_path):
    with atomic_write(tmp_path / "new.txt", "w") as f:
        f.write("text")
    assert (tmp_path / "new.txt").read_text() == "text"
    assert _leftovers(tmp_path, "new.txt") == []


@pytest.mark.parametrize("failure", [OSError(errno.EFBIG, "File too large"), ValueError("bad bytes"),
                                     KeyboardInterrupt()])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, failure):
    target = _old_file(tmp_path / "t.npz")
    with pytest.raises(type(failure)) as caught:
        with atomic_write(target) as f:
            f.write(b"x" * 10_000)  # part of the new contents, already on disk
            raise failure
    assert target.read_bytes() == OLD
    assert _leftovers(tmp_path, "t.npz") == []
    if isinstance(failure, OSError):  # raised again naming the target
        assert caught.value.filename == str(target) and caught.value.errno == errno.EFBIG


def test_a_link_keeps_pointing_at_the_replaced_file(tmp_path):
    real = _old_file(tmp_path / "real.npz")
    link = tmp_path / "link.npz"
    link.symlink_to(real.name)
    with atomic_write(link) as f:
        f.write(b"new")
    assert link.is_symlink() and real.read_bytes() == b"new"


def test_a_missing_folder_is_an_error_naming_the_target(tmp_path):
    target = tmp_path / "no" / "t.npz"
    with pytest.raises(FileNotFoundError) as caught:
        with atomic_write(target) as f:
            f.write(b"x")
    assert caught.value.filename == str(target)


# ----------------------------------------------------------------------------------
# jaxbvh.save under a real file size limit (the issue's ``ulimit -f 8``)
# ----------------------------------------------------------------------------------

_SAVE_UNDER_A_LIMIT = """
import json, resource, sys
import numpy as np
import jaxbvh
arrays = json.loads(sys.argv[2])
tree = jaxbvh.from_interchange({k: np.asarray(v, dtype=np.float32 if k in ("lo", "hi") else np.int32)
                                for k, v in arrays.items()})
resource.setrlimit(resource.RLIMIT_FSIZE, (600, resource.RLIM_INFINITY))
try:
    jaxbvh.save(sys.argv[1], tree)
except OSError as exc:
    print(json.dumps({"errno": exc.errno, "filename": exc.filename}))
"""


def test_save_past_a_file_size_limit_leaves_the_old_tree(tmp_path):
    """A real part-way failure: the kernel refuses bytes past 600 (EFBIG; Python ignores
    SIGXFSZ); in place, the tree file would be left truncated."""
    _, arrays = three_triangle_files(tmp_path)
    target = tmp_path / "t.npz"
    jaxbvh.save(target, jaxbvh.from_interchange(arrays))
    old = target.read_bytes()
    assert len(old) > 600  # the limit falls inside the archive
    as_lists = {k: np.asarray(v).tolist() for k, v in arrays.items()}
    proc = subprocess.run([sys.executable, "-c", _SAVE_UNDER_A_LIMIT, str(target), json.dumps(as_lists)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {"errno": errno.EFBIG, "filename": str(target)}
    assert target.read_bytes() == old
    assert _leftovers(tmp_path, "t.npz", "three.obj") == []


# ----------------------------------------------------------------------------------
# The tool: one error line naming the file, exit 2, the old file intact
# ----------------------------------------------------------------------------------


def test_optimize_over_its_own_input_keeps_the_tree_when_the_write_fails(tmp_path, capsys, monkeypatch):
    mesh, arrays = three_triangle_files(tmp_path)
    tree_file = tmp_path / "t.npz"
    np.savez(tree_file, **arrays)
    old = tree_file.read_bytes()
    _savez_failing_part_way(monkeypatch)
    status, out, err = run_cli(capsys, "optimize", tree_file, "--method", "hc", "-o", tree_file)
    assert_one_line_error(status, out, err, str(tree_file), os.strerror(errno.ENOSPC))
    assert tree_file.read_bytes() == old
    assert _leftovers(tmp_path, "t.npz", "three.obj") == []


def test_trace_keeps_old_hits_and_image_when_their_writes_fail(tmp_path, capsys, monkeypatch):
    mesh, arrays = three_triangle_files(tmp_path)
    tree_file = tmp_path / "t.npz"
    np.savez(tree_file, **arrays)
    hits, image = _old_file(tmp_path / "hits.npz"), _old_file(tmp_path / "view.png")
    keep = ("t.npz", "three.obj", "hits.npz", "view.png")
    with monkeypatch.context() as patch:
        _savez_failing_part_way(patch)
        status, out, err = run_cli(capsys, "trace", tree_file, mesh, "--rays", 20, "--save", hits)
    assert_one_line_error(status, out, err, str(hits))
    assert hits.read_bytes() == OLD and _leftovers(tmp_path, *keep) == []

    import matplotlib.figure

    def savefig(self, fname, **kwargs):
        fname.write(b"\x89PNG part")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    status, out, err = run_cli(capsys, "trace", tree_file, mesh, "--rays", 20, "--image", image)
    assert_one_line_error(status, out, err, str(image))
    assert image.read_bytes() == OLD and _leftovers(tmp_path, *keep) == []


def test_trace_writes_hits_where_numpy_would(tmp_path, capsys):
    """--save HITS without the suffix writes HITS.npz (np.savez's rule) and says so."""
    mesh, arrays = three_triangle_files(tmp_path)
    tree_file = tmp_path / "t.npz"
    np.savez(tree_file, **arrays)
    result = run_json(capsys, "trace", tree_file, mesh, "--rays", 20, "--save", tmp_path / "hits")
    assert result["saved"] == str(tmp_path / "hits.npz")
    with np.load(tmp_path / "hits.npz") as data:
        assert data["prim"].shape == (20,)


def test_a_batch_output_that_fails_to_write_is_its_rows_error_and_leaves_no_file(tmp_path, capsys, monkeypatch):
    grid_obj(tmp_path / "a.obj", 2, 0)
    out = tmp_path / "out"
    _savez_failing_part_way(monkeypatch)
    result = run_json(capsys, "batch", "build", tmp_path / "a.obj", "-o", out, status=1)
    (row,) = result["rows"]
    assert row["error"].startswith("write: ") and os.strerror(errno.ENOSPC) in row["error"], row
    assert "a.obj.npz" in row["error"] or "a.npz" in row["error"]
    assert list(out.iterdir()) == []


def test_a_writer_killed_mid_write_leaves_a_temporary_that_only_its_cleanup_removes(tmp_path):
    """A SIGKILL runs no ``except``: the temporary stays until whoever knows the write is
    over (a batch run, for its delivered outputs) removes it; nothing else is touched."""
    target = tmp_path / "t.npz"
    writer = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom jaxbvh.files import atomic_write\n"
        f"with atomic_write({str(target)!r}) as f:\n"
        "    f.write(b'part'); f.flush(); print('writing', flush=True); time.sleep(60)\n")],
        stdout=subprocess.PIPE)
    assert writer.stdout.readline().strip() == b"writing"
    writer.kill()
    writer.wait()
    (left,) = _leftovers(tmp_path)
    assert left.startswith(".t.npz.") and left.endswith(".tmp")
    others = [".t.npz.tmp", ".t.npz.1.notahex0.tmp", ".u.npz.1.0badbeef.tmp", ".t.npz.1.0badbeef.tmp.keep", "t.npz"]
    for name in others:
        (tmp_path / name).write_bytes(OLD)
    assert remove_abandoned_temporaries(tmp_path, ["t.npz"]) == [left]
    assert _leftovers(tmp_path) == sorted(others)
    assert all((tmp_path / name).read_bytes() == OLD for name in others)


def test_a_batch_run_removes_the_temporaries_of_its_outputs_and_no_others(tmp_path):
    from jaxbvh.batch import runs
    (tmp_path / "in").mkdir()
    grid_obj(tmp_path / "in" / "a.obj", 2, 0)
    out = tmp_path / "out"
    out.mkdir()
    dead = out / ".a.obj.npz.99999.0badbeef.tmp"  # as a writer killed mid-write left it
    foreign = out / ".b.obj.npz.99999.0badbeef.tmp"  # not this run's output: not its to remove
    dead.write_bytes(OLD)
    foreign.write_bytes(OLD)
    made = runs.run_files([tmp_path / "in" / "a.obj"], out)
    assert made.done == 1 and not dead.exists() and foreign.read_bytes() == OLD


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 50), st.integers(0, 10 ** 6)), min_size=1, max_size=8,
                unique_by=lambda entry: entry[1]),
       st.integers(0, 200), st.data())
def test_trim_least_recent_removes_the_oldest_until_under_size(tmp_path_factory, files, max_bytes, data):
    """jaxbvh's one cache rule: entries used longest ago go first until the rest fit; the
    entry just written stays; nothing newer goes while something older stays."""
    folder = tmp_path_factory.mktemp("cache")
    paths = []
    for i, (size, age) in enumerate(files):
        p = folder / f"e{i}.bin"
        p.write_bytes(b"x" * size)
        os.utime(p, ns=(10 ** 18 - age * 10 ** 6, 10 ** 18 - age * 10 ** 6))
        paths.append(p)
    keep = data.draw(st.sampled_from(paths + [None]))
    total = trim_least_recent(folder.glob("*.bin"), max_bytes, keep=keep)
    left = [p for p in paths if p.exists()]
    gone = [p for p in paths if not p.exists()]
    assert total == sum(p.stat().st_size for p in left)
    if keep is not None:
        assert keep.exists()
    others = [p for p in left if p != keep]
    assert total <= max_bytes or not others  # under the size, or only the kept entry is left
    if gone and others:  # oldest first: every removed entry is at least as old as every kept one
        assert max(p_mtime for p_mtime in (files[paths.index(p)][1] for p in others)) <= min(
            files[paths.index(p)][1] for p in gone)
    if total <= max_bytes and gone:  # no more than needed: the newest removed one would not have fit
        newest_gone = min(gone, key=lambda p: files[paths.index(p)][1])
        assert total + files[paths.index(newest_gone)][0] > max_bytes
