"""Batches of mesh *files*, in this process or on a Dask cluster, resumable: :func:`run_files`.

:func:`jaxbvh.batch.build` and :func:`jaxbvh.batch.optimize` work on meshes in memory.
This module runs a whole folder of mesh files to tree files, the way ``jaxbvh batch``
does, on many processes or hosts: the files are cut into *chunks* (``chunk_files``
files of one estimated capacity bucket, :mod:`jaxbvh.batch.chunking`), and each chunk is
one task: a worker loads its meshes, builds them with :func:`jaxbvh.batch.build` (one
compiled call per capacity bucket in the chunk: one, unless an estimate was off), optimizes them with
:func:`jaxbvh.batch.optimize`, validates every tree against its mesh and writes it
atomically (:func:`jaxbvh.save`). A worker compiles each program once, then reuses it
for every later chunk of that shape; workers that share a disk share the persistent
compile cache (:mod:`jaxbvh.compile_cache`), so a program compiled by one is loaded by
the others. A worker reads meshes through the driver's parsed-mesh cache
(:func:`jaxbvh.io.use_mesh_cache`; the command line's is on), as the single-process
command does.

Engines (``client``): None runs the chunks here, one after another; a
:class:`distributed.Client`, or an address (``"tcp://host:8786"``, a running Dask
scheduler; ``"local:N"``, a :class:`distributed.LocalCluster` of N worker processes
started for the run), runs them on Dask workers. Dask is an optional extra
(``pip install jaxbvh[cluster]``); nothing here imports it until a client is asked for.

Nothing lost, nothing twice. Every output is written atomically (a temporary file in
the output folder, then a rename). The run keeps a manifest, ``OUT/`` :data:`MANIFEST`:
per file its input path and content hash (SHA-256), the options' hash, its output and
the output's hash, seconds, worker and error, and the *stamps* of the input and output
(:func:`file_stamp`: size, modification and change times in ns, inode); it is rewritten
atomically as chunks finish (at most every :data:`MANIFEST_EVERY_S` seconds, less often
when it is big, and at the end). With ``resume=True`` a file whose manifest row has no
error, the same options, the same input hash and an output whose hash still matches is
skipped; every other file is (re)done. The hashes are read again only where a stamp
changed (:func:`row_still_holds`): a file whose size, times and inode are all what they
were when it was hashed has the same bytes (the rule of ``make``, ``rsync`` and git's
index; any write sets the change time, which no tool can set back). An input changed
less than :data:`RACY_S` before it was hashed gets no stamp (a second write in the same
clock tick would leave the stamp as it was), so it is hashed again on resume.

A worker that dies mid-chunk (killed, out of memory) loses only its chunk:
the scheduler gives the chunk to another worker (Dask's ``allowed-failures``), and the
temporary file of a write it had begun is removed at the end of the run; a
chunk that fails again (a mesh that crashes its worker) is split and each file run
alone, so a bad mesh fails alone. Each file's row is taken once, from the first result
that delivers it; the rows are in input order.

Keys. Annealing (``"sa"``) draws from ``mesh_key(seed, name)``: the seed's key folded
with a hash of the file's output name (its path below the inputs' common folder), so a
tree does not depend on the chunk, the worker or the position it ran in; ``jaxbvh
batch`` without a scheduler uses the same rule, and gives the same trees.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import json
import os
import time
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

import jaxbvh
from jaxbvh.batch.build import build, builder_config
from jaxbvh.batch.chunking import chunk_items
from jaxbvh.batch.measure import costs
from jaxbvh.batch.optimize import one_line, optimize
from jaxbvh.batch.plan import BatchConfig
from jaxbvh.builders.configs import TRIANGLE_BUILDERS
from jaxbvh.cli.command_kit import seed_key  # any integer seed, as the command line takes it
from jaxbvh.files import atomic_write, remove_abandoned_temporaries
from jaxbvh.io import load_mesh, mesh_cache_folder, use_mesh_cache
from jaxbvh.optimize import DEFAULT_METHOD, make_config
from jaxbvh.tree.interchange import compact

#: the manifest's file name in the output folder
MANIFEST = "jaxbvh-manifest.json"
#: the manifest is rewritten at most this often while a run goes on (seconds): a run
#: stopped hard loses at most that much of its record (those files are redone on resume).
#: A big manifest takes long to write; the wait is then at least
#: :data:`MANIFEST_WAIT_RATIO` times the last write, so writing it costs the driver at most
#: about a tenth of its time however many files the run has
MANIFEST_EVERY_S = 1.0
MANIFEST_WAIT_RATIO = 10.0
#: files per chunk (one task): enough for a compiled call to pay for itself, few enough
#: that a lost worker costs little and the workers stay evenly loaded
DEFAULT_CHUNK_FILES = 32
#: prefix of an address that starts a LocalCluster of N worker processes
LOCAL = "local:"
#: Dask settings of the workers a run starts itself (``local:N``): no statistical profiler
#: (it samples the running task's stack every 10 ms, a fifth of a worker's CPU on our
#: chunks, bench/bench_cluster.py) and no GIL monitor; nothing here reads what they gather
QUIET_WORKER = {"distributed.worker.profile.enabled": False, "distributed.admin.system-monitor.gil.enabled": False}
#: the fields of a report row, in the CSV's column order
REPORT_FIELDS = ("mesh", "output", "triangles", "builder", "optimizer", "sah_built", "sah", "seconds", "worker",
                 "input_sha256", "output_sha256", "skipped", "error")


def checked_tree(tree, lo, hi, triangles=None):
    """``tree`` (one of a batch's) validated against its mesh and compacted to NumPy.

    ``lo``, ``hi`` [P, 3]: the mesh's primitive boxes; ``triangles`` [P, 3, 3] for a tree
    with spatial splits (a triangle may sit in several leaves, each leaf box holding a
    piece of it), else None. Raises :class:`jaxbvh.InvalidTreeError` on a broken tree.
    The single-process batch command and the chunked runs check every tree this one way.
    """
    if triangles is None:
        jaxbvh.validate(tree, lo, hi)
    else:
        jaxbvh.validate(tree, lo, hi, references=True, triangles=triangles)
    return compact(tree)

def mesh_key(seed: int, name: str):
    """The ``jax.random`` key of the mesh whose output name is ``name`` (module docstring):
    ``fold_in(seed_key(seed), h)``, ``h`` the first 31 bits of SHA-256 of ``name``."""
    h = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:4], "little") & 0x7FFFFFFF
    return jax.random.fold_in(seed_key(seed), h)


def output_names(paths) -> list[str]:
    """The output name of each path: the path relative to the folder all the inputs share,
    its suffix kept, then ``.npz`` (``a.obj`` -> ``a.obj.npz``, ``sub/a.ply`` ->
    ``sub/a.ply.npz``). Distinct files get distinct names by construction (stems alone
    would not: ``a.obj`` and ``a.ply``); ``ValueError`` if two names still clash."""
    absolute = [os.path.abspath(p) for p in paths]
    root = os.path.commonpath([os.path.dirname(a) for a in absolute]) if absolute else ""
    names = [Path(os.path.relpath(a, root)).as_posix() + ".npz" for a in absolute]
    first: dict[str, Any] = {}
    for path, name in zip(paths, names):
        if name in first:
            raise ValueError(f"{first[name]} and {path} would both be written to {name}")
        first[name] = path
    return names


#: an input whose change time is less than this before it is read (seconds) gets no stamp
#: and is hashed again on resume: a write in the same clock tick as the read would leave
#: its stamp unchanged. Also covers a file server's clock running ahead of the worker's.
RACY_S = 2.0


def file_stamp(path) -> list[int]:
    """``[size, st_mtime_ns, st_ctime_ns, st_ino]`` of a file (module docstring: what makes
    a stamp stand for the bytes). ``OSError`` as :func:`os.stat`."""
    st = os.stat(path)
    return [int(st.st_size), int(st.st_mtime_ns), int(st.st_ctime_ns), int(st.st_ino)]


def hashed_with_stamp(path, settle_s: float | None = None) -> tuple[str, list[int] | None]:
    """``(SHA-256, stamp)`` of ``path``; the stamp None when the file changed while it was
    read or less than ``settle_s`` before (None: :data:`RACY_S`; module docstring)."""
    before = file_stamp(path)
    digest = file_sha256(path)
    after = file_stamp(path)
    racy = time.time_ns() - after[2] < (RACY_S if settle_s is None else settle_s) * 1e9
    return digest, (None if racy or after != before else after)


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclasses.dataclass(frozen=True)
class Settings:
    """What every chunk of a run does: ``action`` (``"build"`` or ``"optimize"``), the
    ``builder`` Config, the optimizer ``method`` and its Config ``optimizer`` (None for
    ``"build"``), the ``seed`` of :func:`mesh_key`, the ``batch`` Config."""
    action: str
    builder: Any
    method: str | None
    optimizer: Any
    seed: int
    batch: Any

    def options(self) -> dict:
        """The settings as plain JSON values (the manifest's ``options``)."""

        def plain(config):
            return None if config is None else {"type": type(config).__name__, **dataclasses.asdict(config)}

        return {"action": self.action, "builder": plain(self.builder), "method": self.method,
                "optimizer": plain(self.optimizer), "seed": self.seed, "batch": plain(self.batch),
                "jaxbvh": getattr(jaxbvh, "__version__", None)}

    def options_sha256(self) -> str:
        """SHA-256 of :meth:`options` (sorted JSON): rows made under other options are stale."""
        text = json.dumps(self.options(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()


def worker_name() -> str:
    """The Dask worker's address when running on one, else ``local:<pid>``."""
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"local:{os.getpid()}"


def trees_of(meshes, names, settings: Settings, on_chunk=None) -> tuple[list, list[dict]]:
    """Build (and optimize) the trees of loaded ``meshes`` (:class:`jaxbvh.io.Mesh`; None
    for one that failed to load), every tree checked against its mesh.

    Returns ``(trees, rows)``, one of each per mesh: a compacted tree (NumPy arrays) or
    None, and a dict with ``sah_built``, ``sah`` or ``error`` (``"build: ..."``,
    ``"optimize: ..."``, ``"validate: ..."``: a mesh that fails, fails alone). ``on_chunk(index)``: as :func:`jaxbvh.batch.build`'s, ``index``
    positions in ``meshes``. Keys: :func:`mesh_key` of ``names``.
    """
    loaded = [i for i, m in enumerate(meshes) if m is not None]
    trees: list = [None] * len(meshes)
    rows: list[dict] = [{} for _ in meshes]
    if not loaded:
        return trees, rows
    builder = settings.builder
    boxes = {i: meshes[i].local_boxes() for i in loaded}
    triangles = [meshes[i].local_triangles() for i in loaded] if builder.method in TRIANGLE_BUILDERS else None
    clock = None if on_chunk is None else (lambda index: on_chunk([loaded[int(k)] for k in index]))
    built = build([boxes[i] for i in loaded], builder, batch=settings.batch, errors="keep", on_chunk=clock,
                  triangles=triangles)
    for k, message in built.errors.items():
        rows[loaded[k]]["error"] = f"build: {message.replace(f'mesh {k}', 'mesh')}"
    batch_trees = built.trees
    sah_built = costs(batch_trees, builder.ct, builder.ci)["sah"]
    figures = None
    if settings.action == "optimize" and batch_trees.groups:
        keys = [mesh_key(settings.seed, names[i]) for i in loaded]
        figures = optimize(batch_trees, settings.method, settings.optimizer, keys=keys, batch=settings.batch,
                           errors="keep", on_chunk=clock)
        for k, message in figures.errors.items():  # that tree alone: the rest are delivered
            rows[loaded[k]]["error"] = f"optimize: {message.replace(f'mesh {k}', 'mesh')}"
        batch_trees = figures.trees
    for k, tree in enumerate(batch_trees.unstack()):
        i = loaded[k]
        if tree is None:
            continue
        try:
            trees[i] = checked_tree(tree, *boxes[i], None if triangles is None else triangles[k])
            rows[i]["sah_built"] = float(sah_built[k])
            rows[i]["sah"] = float(figures.sah[k]) if figures is not None else float(sah_built[k])
        except Exception as exc:  # noqa: BLE001 (a tree that fails its checks is that mesh's row)
            rows[i]["error"] = f"validate: {one_line(exc)}"
    return trees, rows


def process_chunk(items, settings: Settings, out_dir: str, mesh_cache: str | None = None) -> list[dict]:
    """One task: the files ``items`` (``[(path, name), ...]``) to trees in ``out_dir``
    (``out_dir/name``, written atomically); returns a report row per file (module
    docstring). Runs on a worker (or in this process); raises nothing for a bad mesh.
    ``mesh_cache``: the folder of parsed meshes to read and fill (None: parse every file)."""
    before = use_mesh_cache(mesh_cache)
    try:
        return chunk_rows(items, settings, out_dir)
    finally:
        use_mesh_cache(before)


def chunk_rows(items, settings: Settings, out_dir: str) -> list[dict]:
    """:func:`process_chunk` under the mesh cache it set."""
    worker = worker_name()
    rows, meshes, seconds = [], [], np.zeros(len(items))
    for path, name in items:
        row = {"mesh": path, "output": None, "builder": settings.builder.method,
               "optimizer": settings.method if settings.action == "optimize" else None, "worker": worker}
        t = time.perf_counter()
        try:
            row["input_sha256"], row["input_stamp"] = hashed_with_stamp(path)
            mesh = load_mesh(path)
            row["triangles"] = int(mesh.n_triangles)
        except Exception as exc:  # noqa: BLE001 (any load failure is that mesh's row)
            row["error"] = f"load: {one_line(exc)}"
            mesh = None
        seconds[len(rows)] += time.perf_counter() - t
        rows.append(row)
        meshes.append(mesh)
    last = [time.perf_counter()]

    def clock(index):  # a compiled call's seconds shared among the meshes it ran
        now = time.perf_counter()
        seconds[np.asarray(index, np.int64)] += (now - last[0]) / max(len(index), 1)
        last[0] = now

    try:
        trees, made = trees_of(meshes, [n for _, n in items], settings, clock)
    except Exception as exc:  # noqa: BLE001 (a chunk-wide failure: every loaded mesh's row)
        trees, made = [None] * len(items), [{} if m is None else {"error": f"build: {one_line(exc)}"}
                                            for m in meshes]
    for i, ((path, name), row, tree) in enumerate(zip(items, rows, trees)):
        row.update(made[i])
        if tree is None:
            continue
        t = time.perf_counter()
        output = os.path.join(out_dir, name)
        try:
            os.makedirs(os.path.dirname(output), exist_ok=True)
            jaxbvh.save(output, tree, frame=meshes[i].frame)
            row["output"] = output
            # the tree was just written, by us: its stamp stands without the settling
            # time of an input (only a second writer of the same tree could race it)
            row["output_sha256"], row["output_stamp"] = hashed_with_stamp(output, settle_s=0.0)
        except Exception as exc:  # noqa: BLE001
            row["error"] = f"write: {one_line(exc)}"
        seconds[i] += time.perf_counter() - t
    for row, s in zip(rows, seconds):
        row["seconds"] = float(s)
    return rows


def read_manifest(out_dir) -> dict:
    """The manifest of ``out_dir`` (``{"options_sha256": ..., "files": {name: row}}``), or an
    empty one when there is none or it cannot be read."""
    path = Path(out_dir) / MANIFEST
    try:
        data = json.loads(path.read_text())
        if isinstance(data, dict) and isinstance(data.get("files"), dict):
            return data
    except (OSError, ValueError):
        pass
    return {"files": {}}


def row_still_holds(row: dict | None, path, out_dir, options_sha: str, name: str) -> dict | None:
    """The manifest ``row`` of ``path`` if it still stands (``--resume``: made without
    error under the same options, from the same input bytes, its output unchanged), with
    any stamp it lacked or that changed refreshed; None when the file must be redone.

    Cheap where nothing changed: an input and an output whose :func:`file_stamp` equals
    the row's are not read; any other is hashed and compared (module docstring)."""
    if not row or row.get("error") or row.get("options_sha256") != options_sha:
        return None
    output = Path(out_dir) / name
    fresh = dict(row)
    try:
        if row.get("input_stamp") is None or file_stamp(path) != row["input_stamp"]:
            digest, fresh["input_stamp"] = hashed_with_stamp(path)
            if digest != row.get("input_sha256"):
                return None
        if not output.is_file():
            return None
        if row.get("output_stamp") is None or file_stamp(output) != row["output_stamp"]:
            digest, fresh["output_stamp"] = hashed_with_stamp(output, settle_s=0.0)
            if digest != row.get("output_sha256"):
                return None
    except OSError:
        return None
    return fresh


def up_to_date(row: dict | None, path, out_dir, options_sha: str, name: str) -> bool:
    """Whether a manifest ``row`` still stands for ``path`` (:func:`row_still_holds`)."""
    return row_still_holds(row, path, out_dir, options_sha, name) is not None


def write_manifest(out_dir, settings_options: dict, options_sha: str, files: dict) -> None:
    """Write the manifest atomically (:func:`jaxbvh.files.atomic_write`)."""
    text = json.dumps({"options_sha256": options_sha, "options": settings_options, "files": files},
                      indent=1, sort_keys=True, default=str)
    with atomic_write(Path(out_dir) / MANIFEST, "w") as f:
        f.write(text)


def write_report(rows, path) -> None:
    """The per-file report, ``path`` ending ``.csv`` (the columns :data:`REPORT_FIELDS`) or
    anything else (JSON: a list of rows), written atomically."""
    if str(path).lower().endswith(".csv"):
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, REPORT_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in REPORT_FIELDS})
        text = buffer.getvalue()
    else:
        text = json.dumps(list(rows), indent=1, default=str)
    with atomic_write(path, "w") as f:
        f.write(text)


def quick_exit_plugin():
    """A Dask worker plugin that ends its worker's process as soon as the worker closes.

    A worker that has run JAX takes seconds to wind its interpreter down (freeing every
    program and buffer), longer than Dask's nanny waits (it kills the process after 4 s,
    with a warning), and the run's end waits for it. The worker has nothing left to
    write by then (every tree is renamed into place before its task returns, the
    manifest is the driver's), so its process may end at once. Only for the workers a
    run starts itself (``local:N``), never on a cluster someone else runs."""
    from distributed import WorkerPlugin

    class QuickExit(WorkerPlugin):
        name = "jaxbvh-quick-exit"

        def teardown(self, worker):
            import sys

            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)

    return QuickExit()


def warm_start() -> dict:
    """Have Dask start the workers of a ``local:N`` run by forking a server process that
    has imported JAX and this module once (multiprocessing's ``forkserver``, where the
    platform has it), instead of spawning fresh interpreters that each import them.

    Importing JAX and jaxbvh is about 3 s of CPU a process, as much as a worker's share
    of a small batch; a forked worker starts with it done. The server forks before any
    JAX computation (it only imports), so no XLA thread is copied. Dask reads the method
    from its configuration (:data:`QUIET_WORKER` is in force); this sets what the server
    imports before it is started, and returns the Dask setting to start workers with
    (empty where the platform has no forkserver, Windows: workers are spawned as usual)."""
    import multiprocessing

    import dask

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return {}
    from distributed.utils import get_mp_context

    setting = {"distributed.worker.multiprocessing-method": "forkserver"}
    with dask.config.set(setting):
        get_mp_context().set_forkserver_preload(["distributed", __name__])
    return setting


@contextlib.contextmanager
def connect(address: str, **cluster_options):
    """A :class:`distributed.Client` for ``address``: ``"local:N"`` starts a LocalCluster of N
    worker processes (one thread each: JAX uses the cores itself) for the ``with`` block;
    anything else is a running scheduler's address (``"tcp://host:8786"``)."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:  # the optional extra
        raise ImportError("a Dask scheduler needs the 'cluster' extra: pip install 'jaxbvh[cluster]'") from exc
    if address.startswith(LOCAL):
        text = address[len(LOCAL):]
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"--scheduler {address}: local:N needs a worker count N >= 1")
        options = dict(n_workers=int(text), threads_per_worker=1, processes=True, dashboard_address=None)
        options.update(cluster_options)
        # read by the nannies as they start workers (a restarted worker is spawned as usual)
        with dask.config.set({**QUIET_WORKER, **warm_start()}):
            cluster = LocalCluster(**options)
        with cluster, Client(cluster) as client:
            client.register_plugin(quick_exit_plugin())
            yield client
    else:
        with Client(address) as client:
            yield client


@dataclasses.dataclass
class RunResult:
    """What :func:`run_files` returns: ``rows`` (a report row per file, input order),
    ``done`` (written this run), ``skipped`` (up to date, ``resume``), ``failed``,
    ``seconds`` (wall) and ``workers`` (the workers that ran chunks)."""
    rows: list
    done: int
    skipped: int
    failed: int
    seconds: float
    workers: int

    @property
    def ok(self) -> bool:
        """True when no file failed."""
        return self.failed == 0


def run_files(paths, out, *, action: str = "build", builder=None, method: str | None = None, optimizer=None,
              seed: int | None = None, batch=None, client=None, resume: bool = False, overwrite: bool = False,
              chunk_files: int = DEFAULT_CHUNK_FILES, on_progress: Callable | None = None,
              report=None) -> RunResult:
    """Turn mesh files into tree files ``out/<name>`` (:func:`output_names`), in this process
    or on a Dask cluster (module docstring).

    Args:
      paths: mesh files (each once).
      out: the output folder (made if missing).
      action: ``"build"`` or ``"optimize"``.
      builder: a builder Config or method name (None: the default builder).
      method, optimizer: the optimizer's name and Config (``"optimize"``; None: the
        default method, its default Config).
      seed: the seed of :func:`mesh_key` (None: 0, the command line's default).
      batch: :class:`jaxbvh.batch.BatchConfig` of every chunk.
      client: None (here), a :class:`distributed.Client`, or an address for :func:`connect`.
      resume: skip files the manifest says are up to date (:func:`up_to_date`), redo the
        rest (an output in the way is replaced).
      overwrite: replace outputs already there (without it, and without ``resume``, an
        output in the way is a ``ValueError`` before any work).
      chunk_files: files per task (:func:`chunk_items`).
      on_progress: called as ``on_progress(done, failed, left, seconds)`` after each chunk
        (``done`` counts skipped files).
      report: a path for :func:`write_report` (``.csv`` or JSON), or None.

    Returns:
      :class:`RunResult`.
    """
    if action not in ("build", "optimize"):
        raise ValueError(f"action must be 'build' or 'optimize', got {action!r}")
    builder = builder_config(builder)
    if action == "optimize":
        method = DEFAULT_METHOD if method is None else method
        optimizer = make_config(method, optimizer) if optimizer is None or not isinstance(optimizer, dict) \
            else make_config(method, None, **optimizer)
    else:
        method, optimizer = None, None
    settings = Settings(action, builder, method, optimizer, 0 if seed is None else int(seed),
                        BatchConfig() if batch is None else batch)
    paths = [str(p) for p in paths]
    if not paths:
        raise ValueError("run_files: no mesh files")
    names = output_names(paths)
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir} is a file, not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    options, options_sha = settings.options(), settings.options_sha256()
    manifest = read_manifest(out_dir) if resume else {"files": {}}
    files = dict(manifest["files"]) if resume else {}

    started = time.perf_counter()
    rows: dict[str, dict] = {}
    todo = []
    for path, name in zip(paths, names):
        held = row_still_holds(files.get(name), path, out_dir, options_sha, name) if resume else None
        if held is not None:
            files[name] = held  # its stamps refreshed: the next resume reads nothing of it
            rows[name] = dict(held, skipped=True)
        else:
            todo.append((path, name))
    in_the_way = [out_dir / n for _, n in todo if (out_dir / n).exists() or (out_dir / n).is_symlink()]
    if any(p.is_dir() for p in in_the_way):
        raise ValueError(f"{next(p for p in in_the_way if p.is_dir())} is a folder, where a tree would be written")
    if in_the_way and not (overwrite or resume):
        more = f" (and {len(in_the_way) - 1} more)" if len(in_the_way) > 1 else ""
        raise ValueError(f"{in_the_way[0]} exists{more}: pass overwrite (--overwrite) or resume (--resume), "
                         "or choose another output folder")
    skipped = len(rows)
    counts = {"done": skipped, "failed": 0}
    last_write = [time.perf_counter(), 0.0]  # when the manifest was last written, and how long that took

    def take(chunk_rows) -> None:
        for row in chunk_rows:
            name = index_of[row["mesh"]]
            if name in rows and not rows[name].get("skipped"):
                continue  # a chunk delivered twice (a retry raced its first run): the first row stands
            row = dict(row, skipped=False, options_sha256=options_sha)
            rows[name] = row
            files[name] = row
            counts["failed" if row.get("error") else "done"] += 1
        now = time.perf_counter()
        if now - last_write[0] >= max(MANIFEST_EVERY_S, MANIFEST_WAIT_RATIO * last_write[1]):
            write_manifest(out_dir, options, options_sha, files)
            last_write[:] = [time.perf_counter(), time.perf_counter() - now]
        if on_progress is not None:
            on_progress(counts["done"], counts["failed"], len(paths) - len(rows), now - started)

    index_of = dict(zip(paths, names))
    chunks = chunk_items(todo, chunk_files)
    cache = mesh_cache_folder()
    mesh_cache = None if cache is None else str(cache)
    workers = 1
    try:
        if on_progress is not None:
            on_progress(counts["done"], counts["failed"], len(paths) - len(rows), 0.0)
        if client is None:
            for chunk in chunks:
                take(process_chunk(chunk, settings, str(out_dir), mesh_cache))
        elif isinstance(client, str):
            with connect(client) as made:
                workers = run_on_client(made, chunks, settings, str(out_dir), take, mesh_cache)
        else:
            workers = run_on_client(client, chunks, settings, str(out_dir), take, mesh_cache)
    finally:
        write_manifest(out_dir, options, options_sha, files)
        # a worker killed mid-write leaves its temporary file; the output was delivered by another
        delivered: dict[Path, list[str]] = {}
        for name in (n for n in rows if not rows[n].get("skipped")):
            delivered.setdefault((out_dir / name).parent, []).append(Path(name).name)
        for folder, in_folder in delivered.items():
            remove_abandoned_temporaries(folder, in_folder)
    ordered = [rows[n] for n in names]
    failed = sum(1 for r in ordered if r.get("error"))
    if report is not None:
        write_report(ordered, report)
    return RunResult(ordered, len(ordered) - failed - skipped, skipped, failed, time.perf_counter() - started,
                     workers)


def run_on_client(client, chunks, settings: Settings, out_dir: str, take: Callable,
                  mesh_cache: str | None = None) -> int:
    """Run ``chunks`` as Dask tasks, handing each result to ``take`` as it arrives; a chunk
    whose task fails (its worker died past the scheduler's retries, or it raised) is split
    and its files run alone, a file that fails alone gets the failure as its error.
    ``mesh_cache``: as :func:`process_chunk`'s. Returns how many workers ran tasks."""
    from distributed import as_completed

    def submit(chunk):
        return client.submit(process_chunk, chunk, settings, out_dir, mesh_cache, pure=False)

    futures = {}
    for chunk in chunks:
        futures[submit(chunk)] = chunk
    seen = set()
    pending = as_completed(list(futures))
    for future in pending:
        chunk = futures.pop(future)
        try:
            rows = future.result()
            seen.update(r.get("worker") for r in rows)
        except Exception as exc:  # noqa: BLE001 (the task, not a mesh: split it, or fail the file)
            if len(chunk) > 1:
                for item in chunk:
                    one = submit([item])
                    futures[one] = [item]
                    pending.add(one)
                continue
            path, _ = chunk[0]
            rows = [{"mesh": path, "output": None, "builder": settings.builder.method,
                     "optimizer": settings.method, "worker": None, "error": f"worker: {one_line(exc)}"}]
        finally:
            future.release()
        take(rows)
    return len(seen - {None}) or 1


__all__ = ["run_files", "RunResult", "Settings", "connect", "mesh_key", "output_names", "process_chunk",
           "trees_of", "chunk_items", "read_manifest", "write_manifest", "write_report", "up_to_date",
           "row_still_holds", "file_stamp", "hashed_with_stamp", "quick_exit_plugin", "warm_start", "MANIFEST",
           "DEFAULT_CHUNK_FILES", "REPORT_FIELDS", "RACY_S", "QUIET_WORKER"]
