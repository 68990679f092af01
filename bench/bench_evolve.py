"""Goldsmith–Salmon insertion and the genetic algorithm over insertion orders: time vs cost.

    python bench/bench_evolve.py            # insertion times, one GA generation, GA runs P in {10, 25, 50} x 100
    python bench/bench_evolve.py --full     # + P in {100, 200} and 200 generations
    python bench/bench_evolve.py --quick    # smoke run: small pieces, few generations

Inputs are shared meshes and *pieces* of them: the ``count`` triangles whose centres are
nearest to the centre of triangle 0 (a connected patch; the 2k piece of the bunny is the
GA's test input, as the paper's "subsets of around 1000 objects").

Writes bench/results/evolve.json, evolve.md and evolve.png. Seconds are wall time on this
machine, warm (the first call, which compiles, is timed apart), median of ``--repeat``
runs; CPU seconds of the process beside them, since the machine may be shared. Costs are
Goldsmith–Salmon costs (:func:`jaxbvh.goldsmith_salmon_cost`); the sweep SAH builder's
binary tree is priced the same way for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from jaxbvh.builders import insertion
from jaxbvh.builders import insertion_reference as ref_insertion  # noqa: E402
from jaxbvh.stochastic import evolve  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
MESHES = ("spot.obj", "teapot.obj", "legocar.obj", "fandisk.obj", "rocker-arm.obj", "stanford-bunny.obj")


def piece(lo, hi, count):
    """The ``count`` boxes whose centres are nearest the centre of box 0, in their order."""
    centre = (lo + hi) / 2
    keep = np.sort(np.argsort(((centre - centre[0]) ** 2).sum(1), kind="stable")[:count])
    return lo[keep], hi[keep]


def timed(fn, repeat):
    """``(result, warm wall s, warm CPU s, compile s)``: median of ``repeat`` warm calls."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = jax.block_until_ready(fn())
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    wall = statistics.median(walls)
    return out, wall, statistics.median(cpus), max(first - wall, 0.0)


def load(name):
    from jaxbvh.io import load_mesh

    return load_mesh(DATA / "meshes" / name).local_boxes()


def insertion_rows(args):
    bunny = load("stanford-bunny.obj")
    inputs = [(f"bunny piece {args.piece_small:,}", *piece(*bunny, args.piece_small)),
              (f"bunny piece {args.piece_big:,}", *piece(*bunny, args.piece_big))]
    if not args.quick:
        inputs += [(name, *load(name)) for name in MESHES]
    rows = []
    for name, lo, hi in inputs:
        n = lo.shape[0]
        order = np.random.default_rng(0).permutation(n)
        tree, wall, cpu, compile_s = timed(lambda: insertion.build(lo, hi, order), args.repeat)
        jaxbvh.validate(tree, lo, hi)
        sweep, sweep_wall, _, _ = timed(lambda: jaxbvh.build(lo, hi), 1)
        row = {"input": name, "n": n, "seconds": wall, "cpu_seconds": cpu, "compile_seconds": compile_s,
               "gs_cost": float(jaxbvh.goldsmith_salmon_cost(tree)),
               "sweep_gs_cost": float(jaxbvh.goldsmith_salmon_cost(sweep)), "sweep_seconds": sweep_wall}
        if n <= args.piece_big:
            start = time.perf_counter()
            ref_insertion.build(lo, hi, order, max_children=insertion.DEFAULT_MAX_CHILDREN)
            row["reference_seconds"] = time.perf_counter() - start
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def generation_seconds(count, population, generations):
    """``(wall, CPU)`` median seconds per warm GA generation on the bunny piece of ``count``."""
    lo, hi = piece(*load("stanford-bunny.obj"), count)
    ticks = []
    evolve.evolve(jax.random.key(0), lo, hi, population=population, generations=generations + 2,
                  on_step=lambda info: ticks.append((time.perf_counter(), time.process_time())))
    walls = np.diff([w for w, _ in ticks])[2:]  # generations 3 .. : compiled, warm
    cpus = np.diff([c for _, c in ticks])[2:]
    return float(np.median(walls)), float(np.median(cpus))


_PINNED = """
import os, sys, json
os.sched_setaffinity(0, {{min(os.sched_getaffinity(0))}})  # before JAX starts its threads
sys.path.insert(0, {bench!r})
import bench_evolve
print("RESULT" + json.dumps(bench_evolve.generation_seconds({count}, {population}, {generations})))
"""


def generation_row(args):
    """Seconds per GA generation (selection + operators + pricing P orders), warm; also in a
    process confined to one core, where XLA's second thread does not compete with others."""
    import subprocess

    wall, cpu = generation_seconds(args.piece_small, args.population, args.repeat)
    row = {"input": f"bunny piece {args.piece_small:,}", "population": args.population,
           "seconds_per_generation": wall, "cpu_seconds_per_generation": cpu}
    if hasattr(os, "sched_setaffinity"):
        code = _PINNED.format(bench=str(ROOT / "bench"), count=args.piece_small, population=args.population,
                              generations=args.repeat)
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=1200)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
        if proc.returncode == 0 and lines:
            row["one_core_seconds_per_generation"], row["one_core_cpu_seconds_per_generation"] = \
                json.loads(lines[-1][6:])
    print(json.dumps(row), flush=True)
    return row


def ga_rows(args):
    """Best cost vs generation and time for several population sizes (the speed/quality trade)."""
    lo, hi = piece(*load("stanford-bunny.obj"), args.piece_small)
    sweep = float(jaxbvh.goldsmith_salmon_cost(jaxbvh.build(lo, hi)))
    rows = []
    for population in args.populations:
        ticks = []
        result = evolve.evolve(jax.random.key(1), lo, hi, population=population, generations=args.generations,
                               on_step=lambda info: ticks.append(time.perf_counter()))
        # time from the priced first generation; generation 1 also compiles the operators,
        # so its time is replaced by the median generation's
        durations = np.diff(ticks)
        if len(durations) > 1:
            durations[0] = np.median(durations[1:])
        elapsed = np.concatenate([[0.0], np.cumsum(durations)])
        row = {"input": f"bunny piece {lo.shape[0]:,}", "population": population, "generations": args.generations,
               "random_median": result.random_median, "initial_best": result.initial_best, "best": result.best,
               "best_vs_median_percent": 100 * (result.best / result.random_median - 1),
               "sweep_gs_cost": sweep, "history": result.history.tolist(), "seconds": elapsed.tolist(),
               "seconds_per_generation": float(np.median(durations)) if len(durations) else None}
        print(json.dumps({k: v for k, v in row.items() if k not in ("history", "seconds")}), flush=True)
        rows.append(row)
    return rows


def write(meta, inserts, generation, runs):
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "evolve.json").write_text(json.dumps({"meta": meta, "insertion": inserts, "generation": generation,
                                                     "ga": runs}, indent=1))
    lines = ["# Goldsmith–Salmon insertion and the genetic algorithm over insertion orders", "",
             f"Machine: {meta['platform']}, {meta['cpus']} CPUs, JAX {meta['jax']}; {meta['note']}",
             "Seconds are warm wall time (compile apart), median of "
             f"{meta['args']['repeat']}; CPU s is the process's CPU time over the same calls. "
             f"max_children = {insertion.DEFAULT_MAX_CHILDREN}.", "",
             "## Insertion build (one random order)", "",
             "| input | triangles | seconds | CPU s | compile s | NumPy reference s | G&S cost "
             "| sweep builder G&S cost |",
             "|---|---|---|---|---|---|---|---|"]
    for r in inserts:
        ref = f"{r['reference_seconds']:.1f}" if "reference_seconds" in r else "-"
        lines.append(f"| {r['input']} | {r['n']:,} | {r['seconds']:.3f} | {r['cpu_seconds']:.3f} | "
                     f"{r['compile_seconds']:.1f} | {ref} | {r['gs_cost']:.3f} | {r['sweep_gs_cost']:.3f} |")
    g = generation
    lines += ["", "## One GA generation", "",
              f"{g['input']}, population {g['population']}: {g['seconds_per_generation']:.3f} s per generation "
              f"({g['cpu_seconds_per_generation']:.3f} CPU s)"
              + (f"; in a process confined to one core: {g['one_core_seconds_per_generation']:.3f} s "
                 f"({g['one_core_cpu_seconds_per_generation']:.3f} CPU s)" if "one_core_seconds_per_generation" in g
                 else "") + ".", "",
              "## GA: best cost vs generations x population", "",
              "Seconds from the priced first generation; the sweep builder's binary tree is priced by the same "
              "G&S cost.", "",
              "| input | population | s / generation | random median | gen 0 best | best @10 | @25 | @50 | "
              "@100 | last | vs median | sweep builder |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        h = r["history"]
        at = [f"{h[g]:.3f}" if g < len(h) else "-" for g in (10, 25, 50, 100)]
        lines.append(f"| {r['input']} | {r['population']} | {r['seconds_per_generation'] or 0:.3f} | "
                     f"{r['random_median']:.3f} | {r['initial_best']:.3f} | {' | '.join(at)} | {r['best']:.3f} "
                     f"({len(h) - 1} gens, {r['seconds'][-1]:.0f} s) | {r['best_vs_median_percent']:+.1f}% | "
                     f"{r['sweep_gs_cost']:.3f} |")
    (RESULTS / "evolve.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
        for r in runs:
            left.plot(r["history"], label=f"P = {r['population']}")
            right.plot(r["seconds"], r["history"], label=f"P = {r['population']}")
        for ax, xlabel in ((left, "generation"), (right, "seconds (warm)")):
            ax.axhline(runs[0]["random_median"], color="gray", ls="--", label="median of random orders")
            ax.axhline(runs[0]["sweep_gs_cost"], color="black", ls=":", label="sweep SAH builder")
            ax.set_xlabel(xlabel)
            ax.set_ylabel("best G&S cost")
        left.legend(fontsize=8)
        fig.suptitle(f"GA over insertion orders, {runs[0]['input']}")
        fig.tight_layout()
        fig.savefig(RESULTS / "evolve.png", dpi=100)
    except ImportError:
        pass


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="larger populations, 200 generations")
    parser.add_argument("--quick", action="store_true", help="smoke run")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--population", type=int, default=50, help="population of the one-generation timing")
    parser.add_argument("--note", default="", help="free text for the header (e.g. 'CPU shared')")
    args = parser.parse_args(argv)
    args.piece_small, args.piece_big = (500, 2000) if args.quick else (2000, 10000)
    args.populations = [10, 25, 50] + ([100, 200] if args.full else [])
    args.generations = 200 if args.full else (5 if args.quick else 100)
    if args.quick:
        args.populations = [10]
    meta = {"machine": platform.machine(), "cpus": os.cpu_count(), "jax": jax.__version__,
            "platform": platform.platform(), "args": vars(args), "note": args.note or "-"}
    inserts = insertion_rows(args)
    generation = generation_row(args)
    runs = ga_rows(args)
    write(meta, inserts, generation, runs)
    print((RESULTS / "evolve.md").read_text())


if __name__ == "__main__":
    main()
