"""``jaxbvh batch`` on Dask workers against the single-process batch (issue 41).

    python bench/bench_cluster.py                      # 1,000 meshes of 200-5,000 triangles
    python bench/bench_cluster.py --meshes 200 --max-tris 2000   # a loaded machine

Meshes: ``bench/bench_batch.py``'s set (pieces of the shared meshes and procedural trees),
written as OBJ files to a temporary folder. Every run is the console script in a fresh
process, over the whole folder, to a fresh output folder, with a warm compile cache
(each configuration is run once first, untimed, to fill it: what a second batch pays):

* ``single``: today's ``jaxbvh batch build`` (JAX's CPU split into one device per core);
* ``local:1``, ``local:2``: ``--scheduler local:N`` (a LocalCluster of N worker processes,
  started and stopped inside the timed run).

Wall seconds, and CPU seconds of the process and every process under it (polled). The
engine's own cost per file is measured on empty work: :func:`jaxbvh.batch.runs.run_files`
over the same files with a task that does nothing but return each file's row
(``local:2``, and in-process; ``--empty-files`` names, no files needed), so what is left is the driver (names, chunks, manifest,
progress) and Dask's round trips. Writes ``bench/results/bench_cluster.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "bench" / "results"


def write_obj(path: Path, tri) -> None:
    import numpy as np

    v = np.asarray(tri, np.float64).reshape(-1, 3)
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v.tolist()]
    lines += [f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}" for i in range(v.shape[0] // 3)]
    path.write_text("\n".join(lines) + "\n")


def timed_cli(argv, env) -> dict:
    """Wall and CPU seconds of a command and every process under it. The CPU is polled
    (psutil, every 0.1 s) rather than read from ``RUSAGE_CHILDREN``: ``local:N`` workers are
    forked by multiprocessing's fork server, so they are not children the command waits
    for, and their CPU would not be counted."""
    import psutil

    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(argv, env=env, stdout=out, stderr=err, text=True)
        root, cpu = psutil.Process(proc.pid), {}
        while proc.poll() is None:
            try:
                tree = [root] + root.children(recursive=True)
            except psutil.Error:
                tree = []
            for p in tree:
                try:
                    times = p.cpu_times()
                    cpu[p.pid] = times.user + times.system
                except psutil.Error:
                    pass
            time.sleep(0.1)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(map(str, argv))}: exit {proc.returncode}\n{stderr[-3000:]}")
    result = json.loads(stdout.strip().splitlines()[-1])
    return {"wall_s": wall, "cpu_s": sum(cpu.values()), "processes": len(cpu), "written": result["written"],
            "failed": result["failed"]}


def empty_chunk(items, settings, out_dir, mesh_cache=None):
    """A task with no work: the row of every file, as a worker would return it."""
    return [{"mesh": path, "output": None, "worker": "empty", "seconds": 0.0} for path, _ in items]


def engine_overhead(paths, out: Path, address: str | None, chunk_files: int) -> dict:
    """Seconds per file of run_files whose task does nothing (module docstring)."""
    from jaxbvh.batch import runs

    real = runs.process_chunk
    runs.process_chunk = empty_chunk  # run_on_client looks the task up at call time
    try:
        if address is None:
            t0 = time.perf_counter()
            runs.run_files(paths, out, client=None, chunk_files=chunk_files)
            wall = time.perf_counter() - t0
            return {"engine": "in-process", "files": len(paths), "wall_s": wall, "ms_per_file": 1e3 * wall / len(paths)}
        with runs.connect(address) as client:
            client.run(lambda: __import__("jaxbvh.batch.runs"))  # the workers' imports, once, untimed
            runs.run_files(paths[:2], out / "warm", client=client, chunk_files=1)
            t0 = time.perf_counter()
            runs.run_files(paths, out, client=client, chunk_files=chunk_files)
            wall = time.perf_counter() - t0
        return {"engine": address, "files": len(paths), "wall_s": wall, "ms_per_file": 1e3 * wall / len(paths),
                "ms_per_chunk": 1e3 * wall / -(-len(paths) // chunk_files)}
    finally:
        runs.process_chunk = real


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=int, default=1000)
    parser.add_argument("--min-tris", type=int, default=200)
    parser.add_argument("--max-tris", type=int, default=5000)
    parser.add_argument("--chunk-files", type=int, default=None, help="default: the library's")
    parser.add_argument("--runs", nargs="*", default=["single", "local:1", "local:2"])
    parser.add_argument("--empty-files", type=int, default=1000, help="files of the empty-work runs")
    args = parser.parse_args(argv)

    from bench.bench_batch import mesh_set
    from jaxbvh.batch import runs

    chunk = args.chunk_files or runs.DEFAULT_CHUNK_FILES
    work = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    try:
        folder = work / "in"
        folder.mkdir()
        named = mesh_set(args.meshes, args.min_tris, args.max_tris)
        for name, tri in named:
            write_obj(folder / f"{name}.obj", tri)
        tris = sum(int(t.shape[0]) for _, t in named)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + os.environ.get("PYTHONPATH", "").split(
            os.pathsep)).rstrip(os.pathsep), JAXBVH_CACHE_DIR=str(work / "cache"))
        env.pop("XLA_FLAGS", None)  # the product's settings, not the test suite's
        out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "load_before": os.getloadavg(),
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "meshes": len(named), "triangles": tris, "chunk_files": chunk, "runs": {}}
        print(f"{len(named)} meshes, {tris:,} triangles; load {os.getloadavg()}", flush=True)
        for run in args.runs:
            argv = [sys.executable, "-m", "jaxbvh.cli.app", "batch", "build", str(folder), "--json"]
            if run != "single":
                argv += ["--scheduler", run, "--chunk-files", str(chunk)]
            for attempt in ("warm-up", "timed"):
                target = work / f"out-{run.replace(':', '')}-{attempt}"
                figures = timed_cli(argv + ["-o", str(target)], env)
                figures["load"] = os.getloadavg()[0]
                print(run, attempt, figures, flush=True)
                shutil.rmtree(target, ignore_errors=True)
            figures["files_per_s"] = len(named) / figures["wall_s"]
            out["runs"][run] = figures
        # empty work needs no files: names are enough (the task reads nothing)
        paths = [str(folder / "empty" / f"m{i:05d}.obj") for i in range(args.empty_files)]
        out["engine"] = [engine_overhead(paths, work / "empty-here", None, chunk),
                         engine_overhead(paths, work / "empty-local2", "local:2", chunk)]
        print(out["engine"], flush=True)
        out["load_after"] = os.getloadavg()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_cluster.json").write_text(json.dumps(out, indent=1))
    lines = [f"# jaxbvh batch build on Dask workers ({out['meshes']} meshes, {out['triangles']:,} triangles)", "",
             f"Machine: {out['machine']}; {out['date']}; load average before {out['load_before'][0]:.1f}, "
             f"after {out['load_after'][0]:.1f} (shared machine). Warm compile cache; "
             f"chunks of {chunk} files.", "",
             "| run | wall s | CPU s (all processes) | files/s | vs single | load |", "|---|---|---|---|---|---|"]
    base = out["runs"].get("single", {}).get("wall_s")
    for run, f in out["runs"].items():
        ratio = f"{f['wall_s'] / base:.2f}x" if base else "-"
        lines.append(f"| {run} | {f['wall_s']:.1f} | {f['cpu_s']:.1f} | {f['files_per_s']:.1f} | {ratio} | "
                     f"{f['load']:.1f} |")
    lines += ["", "Engine overhead on empty work (the task returns each file's row, nothing else):", "",
              "| engine | files | wall s | ms per file |", "|---|---|---|---|"]
    for e in out["engine"]:
        lines.append(f"| {e['engine']} | {e['files']} | {e['wall_s']:.2f} | {e['ms_per_file']:.2f} |")
    (RESULTS / "bench_cluster.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
