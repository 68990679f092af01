"""``jaxbvh batch build|optimize INPUT... -o OUTDIR``: many meshes in a few compiled calls.

INPUT is mesh files, globs (quoted, so the shell leaves them) or folders (their mesh
files, not recursive). Every mesh is loaded, then all are built together
(:func:`jaxbvh.batch.build`) and, for ``optimize``, optimized together
(:func:`jaxbvh.batch.optimize`); each tree is validated against its mesh and written to
``OUTDIR/<name>.npz`` (interchange, with its scene frame), ``<name>`` the input's path below
the folder all inputs share, suffix kept (``a.obj.npz``, ``sub/a.ply.npz``: unique by
construction); an output file already there is an error before any work, unless
``--overwrite``. The summary has one row per
mesh (triangles, SAH after the build and after the optimizer, seconds: the mesh's share
of its compiled calls) and the totals. On a CPU the batch runs on every core: JAX's CPU
is split into one device per core (``--cpu-devices``; :func:`jaxbvh.batch.use_cpu_cores`). A mesh that fails to load, build or validate
gets its own one-line error in its row, the others are still written, and the exit
status is 1. Every option is checked before any mesh is read. The trees are renamed into
place together at the end, so an interrupted batch leaves none of its outputs.

With ``--scheduler ADDRESS`` (a Dask scheduler, or ``local:N`` worker processes) or
``--resume`` the files run in chunks (:func:`jaxbvh.batch.runs.run_files`,
``docs/cluster.md``): each tree is written as soon as its chunk is done, a manifest in
OUTDIR records every file, and ``--resume`` redoes only what is missing or stale.
``--report PATH`` writes a row per file (CSV or JSON) either way. Annealing's key per
mesh comes from its output name (:func:`jaxbvh.batch.runs.mesh_key`), so every engine
gives the same trees.
"""

from __future__ import annotations

import contextlib
import glob
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxbvh
from jaxbvh.batch import BatchConfig, build, costs, optimize, runs, use_cpu_cores
from jaxbvh.builders.configs import TRIANGLE_BUILDERS
from jaxbvh.cli import command_kit
from jaxbvh.cli.commands.optimize import OPTIONS as OPTIMIZER_OPTIONS
from jaxbvh.cli.commands.optimize import leaf_limit
from jaxbvh.cli.options import add_config_options
from jaxbvh.io import load_mesh
from jaxbvh.optimize import DEFAULT_METHOD, OPTIMIZERS

HELP = "build (and optimize) the BVHs of many meshes at once, one tree file per mesh"
ACTIONS = ("build", "optimize")
#: file suffixes a folder INPUT contributes (other files in it are passed over)
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def add_parser(subparsers):
    """Add the ``batch`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("batch", help=HELP, description=HELP + ".")
    parser.add_argument("action", choices=ACTIONS, help="build the trees, or build and optimize them")
    parser.add_argument("inputs", metavar="INPUT", nargs="+", help="mesh files, globs or folders of meshes")
    parser.add_argument("-o", "--output", metavar="OUTDIR", default=None,
                        help="folder for the trees (OUTDIR/<input's path below the inputs' common folder>.npz, "
                             "e.g. OUTDIR/a.obj.npz; made if missing; required)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace tree files already in OUTDIR (default: such a file is an error, "
                             "before any work)")
    parser.add_argument("--method", choices=tuple(OPTIMIZERS), default=DEFAULT_METHOD,
                        help=f"optimizer of 'batch optimize' (default: {DEFAULT_METHOD})")
    parser.add_argument("--cpu-devices", type=int, metavar="N", default=None,
                        help="split the CPU into N JAX devices, the batch over them (default: one per core; "
                             "no effect where JAX runs on a GPU)")
    command_kit.add_seed(parser, "random seed for annealing (each mesh's key: the seed's folded with a hash of "
                                 "its output name, so a tree does not depend on where it ran)")
    cluster = parser.add_argument_group("runs on a Dask cluster, resumable runs (docs/cluster.md)")
    cluster.add_argument("--scheduler", metavar="ADDRESS", default=None,
                         help="run the files in chunks on a Dask scheduler: tcp://host:8786, or local:N for N "
                              "worker processes on this machine (needs jaxbvh[cluster]); writes a manifest")
    cluster.add_argument("--resume", action="store_true",
                         help="skip the files whose output the manifest in OUTDIR says is up to date (same input, "
                              "options and output hash); redo the rest")
    cluster.add_argument("--report", metavar="PATH", default=None,
                         help="write a report row per file to PATH (.csv, else JSON)")
    cluster.add_argument("--chunk-files", type=int, metavar="N", default=runs.DEFAULT_CHUNK_FILES,
                         help=f"files per task with --scheduler or --resume (default: {runs.DEFAULT_CHUNK_FILES})")
    parser.set_defaults(batch_options=add_config_options(parser, BatchConfig, title="batch options"))
    OPTIMIZER_OPTIONS.add_to(parser, "optimizer options of 'batch optimize' (fields of each method's Config)")
    command_kit.add_builder_args(parser)
    command_kit.add_target(parser)
    command_kit.add_json(parser)
    return parser


def expand(inputs) -> list[Path]:
    """Mesh paths of INPUTs: a folder gives its mesh files (sorted), a glob its matches,
    a file itself (even if it is not a mesh: its load fails in its own row).
    ``ValueError`` for an INPUT that names nothing."""
    out = []
    for text in inputs:
        path = Path(text)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
            if not found:
                raise ValueError(f"{text}: a folder with no mesh files ({', '.join(MESH_SUFFIXES)})")
            out += found
        elif glob.has_magic(text):
            found = sorted(Path(p) for p in glob.glob(text) if Path(p).is_file())
            if not found:
                raise ValueError(f"{text}: no file matches")
            out += found
        elif path.is_file():
            out.append(path)
        else:
            raise ValueError(f"{text}: no such file or folder")
    unique: dict[str, Path] = {}
    for p in out:  # each file once, however it was named (a.obj, ./a.obj, its absolute path)
        unique.setdefault(os.path.abspath(p), p)
    return list(unique.values())


output_names = runs.output_names  # the library's rule (jaxbvh.batch.runs)


def check_outputs(out_dir: Path, names, overwrite: bool) -> None:
    """``ValueError`` before any work when an output is in the way: a folder, or (unless
    ``overwrite``) a file a run would replace."""
    in_the_way = [out_dir / n for n in names if (out_dir / n).exists() or (out_dir / n).is_symlink()]
    folders = [p for p in in_the_way if p.is_dir()]
    if folders:
        raise ValueError(f"{folders[0]} is a folder, where the tree of a mesh would be written")
    if in_the_way and not overwrite:
        more = f" (and {len(in_the_way) - 1} more)" if len(in_the_way) > 1 else ""
        raise ValueError(f"{in_the_way[0]} exists{more}: pass --overwrite to replace the trees in "
                         f"{out_dir}, or choose another -o")


def staged_name(output: str) -> str:
    """Where ``output`` is written before the batch renames it into place: beside it, hidden."""
    folder, name = os.path.split(output)
    return os.path.join(folder, f".{name}.{os.getpid()}.staged")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


class Clock:
    """Seconds of compiled calls shared out evenly among the meshes each one ran
    (``on_chunk(index)`` of :func:`jaxbvh.batch.build` and :func:`jaxbvh.batch.optimize`)."""

    def __init__(self, bar, size: int):
        self.bar = bar
        self.seconds = np.zeros(size)
        self.last = time.perf_counter()

    def __call__(self, index) -> None:
        now = time.perf_counter()
        self.seconds[np.asarray(index)] += (now - self.last) / max(len(index), 1)
        self.bar.update(len(index))
        self.last = now


def run(args) -> dict:
    """Run ``jaxbvh batch`` on parsed ``args``; returns the result the command prints (a row per mesh)."""
    # every option first: the devices, the builder's, the optimizer's, the batch's, the folder
    use_cpu_cores(args.cpu_devices)  # before JAX's first operation (it fixes the devices then)
    builder = command_kit.builder_config(args)
    optimizer = None
    given = OPTIMIZER_OPTIONS.given(args)
    if args.action == "optimize":
        optimizer = OPTIMIZER_OPTIONS.config(args.method, args, ct=builder.ct, ci=builder.ci, **leaf_limit(args.method, builder))
    elif given:
        raise ValueError(f"{', '.join(given)}: optimizer options apply to 'batch optimize' only")
    batch_config = args.batch_options.config(None, args)
    if args.output is None:
        raise ValueError("batch needs -o OUTDIR, the folder for the trees")
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--output {out_dir} is a file, not a folder")
    if args.chunk_files < 1:
        raise ValueError(f"--chunk-files must be >= 1, got {args.chunk_files}")
    paths = expand(args.inputs)
    names = output_names(paths)
    if args.scheduler is not None or args.resume:
        return run_chunks(args, paths, builder, optimizer, batch_config, out_dir)
    check_outputs(out_dir, names, args.overwrite)
    for name in dict.fromkeys(os.path.dirname(n) for n in names):
        (out_dir / name).mkdir(parents=True, exist_ok=True)

    started = time.perf_counter()
    rows = [{"mesh": str(p), "output": str(out_dir / n)} for p, n in zip(paths, names)]
    bar = command_kit.progress(args, total=len(paths), desc="load")
    meshes = []
    for row, path in zip(rows, paths):
        try:
            mesh = load_mesh(path)
            row["triangles"] = mesh.n_triangles
            meshes.append(mesh)
        except Exception as exc:  # noqa: BLE001 (any load failure is that mesh's row)
            row["error"] = f"load: {_one_line(exc)}"
            meshes.append(None)
        bar.update(1)
    loaded = [i for i, m in enumerate(meshes) if m is not None]
    boxes = {i: meshes[i].local_boxes() for i in loaded}

    if loaded:
        bar.reset(total=len(loaded))
        bar.set_description("build")
        clock = Clock(bar, len(loaded))
        # a builder that needs the triangles (sbvh) gets them in the boxes' frame
        triangles = [meshes[i].local_triangles() for i in loaded] if builder.method in TRIANGLE_BUILDERS else None
        built = build([boxes[i] for i in loaded], builder, batch=batch_config, errors="keep", on_chunk=clock,
                      triangles=triangles)
        for k, message in built.errors.items():
            rows[loaded[k]]["error"] = f"build: {message.replace(f'mesh {k}', 'mesh')}"
        seconds = clock.seconds
        trees = built.trees
        sah_built = costs(trees, builder.ct, builder.ci)["sah"]
        figures = None
        if optimizer is not None and trees.groups:
            bar.reset(total=sum(len(g) for g in trees.groups))
            bar.set_description(args.method)
            clock.last = time.perf_counter()
            keys = [runs.mesh_key(args.seed, names[i]) for i in loaded]  # the file's identity, not its place
            figures = optimize(trees, args.method, optimizer, keys=keys, batch=batch_config, errors="keep",
                               on_chunk=clock)
            for k, message in figures.errors.items():  # that tree alone: the rest are delivered
                rows[loaded[k]]["error"] = f"optimize: {message.replace(f'mesh {k}', 'mesh')}"
            trees = figures.trees
        bar.reset(total=len(loaded))
        bar.set_description("save")
        # every tree is written beside its output first and all are renamed into place at
        # the end: an interrupted batch (Ctrl-C) leaves none of its outputs, and no
        # output it would have replaced is lost
        staged = []
        try:
            for k, tree in enumerate(trees.unstack()):
                i = loaded[k]
                if tree is None:
                    continue
                row = rows[i]
                stage = "validate"
                try:
                    tree = runs.checked_tree(tree, *boxes[i], None if triangles is None else triangles[k])
                    stage = "write"  # atomic: a failed write leaves no file behind
                    temporary = staged_name(row["output"])
                    try:
                        jaxbvh.save(temporary, tree, frame=meshes[i].frame)
                    except OSError as exc:  # named by its output, not the staging name
                        raise OSError(exc.errno, exc.strerror, row["output"]) from None
                    staged.append((temporary, row["output"]))
                    row["sah_built"] = float(sah_built[k])
                    row["sah"] = float(figures.sah[k]) if figures is not None else float(sah_built[k])
                    row["seconds"] = float(seconds[k])
                    row.update(command_kit.target_report(tree, args, builder))
                except Exception as exc:  # noqa: BLE001 (a tree that fails its checks is that mesh's row)
                    row["error"] = f"{stage}: {_one_line(exc)}"
                bar.update(1)
            for temporary, output in staged:
                os.replace(temporary, output)
        except BaseException:
            for temporary, _ in staged:
                with contextlib.suppress(OSError):
                    os.unlink(temporary)
            raise
    bar.close()
    for row in rows:
        if "error" in row:
            row["output"] = None
    failed = sum("error" in r for r in rows)
    result = {"command": "batch", "action": args.action, "builder": builder.method,
              "method": args.method if optimizer is not None else None, "meshes": len(rows),
              "written": len(rows) - failed, "failed": failed,
              "triangles": int(sum(r.get("triangles", 0) for r in rows)),
              "seconds": time.perf_counter() - started, "devices": jax.device_count(), "output_dir": str(out_dir),
              "valid": failed == 0, "rows": rows}
    if args.report is not None:
        runs.write_report([dict(r, builder=builder.method, optimizer=result["method"]) for r in rows], args.report)
    if not getattr(args, "json", False):
        # people get the rows as a table here, and the totals below it
        print(table(rows, optimizer is not None), file=sys.stdout)
        del result["rows"]
    return result


def run_chunks(args, paths, builder, optimizer, batch_config, out_dir: Path) -> dict:
    """``--scheduler`` / ``--resume``: the files in chunks, on Dask workers or here, with a
    manifest (:func:`jaxbvh.batch.runs.run_files`); one progress bar for the run."""
    bar = command_kit.progress(args, total=len(paths), desc=f"batch {args.action}")

    def on_progress(done, failed, left, seconds):
        bar.n = done + failed
        bar.set_postfix_str(f"done {done}, failed {failed}, left {left}, "
                            f"{(done + failed) / max(seconds, 1e-9):.1f} trees/s", refresh=False)
        bar.refresh()

    try:
        made = runs.run_files(paths, out_dir, action=args.action, builder=builder,
                              method=args.method if optimizer is not None else None, optimizer=optimizer,
                              seed=args.seed, batch=batch_config, client=args.scheduler, resume=args.resume,
                              overwrite=args.overwrite, chunk_files=args.chunk_files, on_progress=on_progress,
                              report=args.report)
    finally:
        bar.close()
    rows = made.rows
    result = {"command": "batch", "action": args.action, "builder": builder.method,
              "method": args.method if optimizer is not None else None, "meshes": len(rows),
              "written": made.done, "skipped": made.skipped, "failed": made.failed,
              "triangles": int(sum(r.get("triangles") or 0 for r in rows)), "seconds": made.seconds,
              "workers": made.workers, "scheduler": args.scheduler, "output_dir": str(out_dir),
              "manifest": str(out_dir / runs.MANIFEST), "valid": made.ok, "rows": rows}
    if not getattr(args, "json", False):
        print(table(rows, optimizer is not None), file=sys.stdout)
        del result["rows"]
    return result


def table(rows, optimized: bool) -> str:
    """The per-mesh summary: name, triangles, SAH built (and optimized), seconds, or the error."""
    head = ["mesh", "triangles", "sah_built"] + (["sah_optimized"] if optimized else []) + ["seconds"]
    lines = []
    for r in rows:
        name = os.path.basename(r["mesh"])
        if "error" in r:
            lines.append([name, str(r.get("triangles", "-")), "error: " + r["error"]])
            continue
        cells = [name, f"{r['triangles']:,}", f"{r['sah_built']:.4f}"]
        cells += [f"{r['sah']:.4f}"] if optimized else []
        lines.append(cells + [f"{r['seconds']:.3f}"])
    widths = [max([len(h)] + [len(line[j]) for line in lines if j < len(line) and (j < 2 or len(line) == len(head))])
              for j, h in enumerate(head)]
    out = ["  ".join(h.ljust(w) for h, w in zip(head, widths)).rstrip()]
    for line in lines:
        if len(line) == len(head):
            out.append("  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip())
        else:  # name, triangles, then the error
            out.append("  ".join(c.ljust(w) for c, w in zip(line[:2], widths)) + "  " + line[2])
    return "\n".join(out)
