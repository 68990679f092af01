"""GRASP (Ng & Trifonov 2003, §3.4): time vs objective, and the noise sweep.

    python bench/bench_stochastic.py                  # all shared meshes, everything below
    python bench/bench_stochastic.py --meshes spot --trials 10 100 --noises 0.001 0.01
    python bench/bench_stochastic.py --quick          # spot and teapot, few settings
    python bench/bench_stochastic.py --meshes bunny --trials 10 100 --noises 0.001 0.01 \
        --rcls axes --deviations 10 --more-seeds --merge  # add bunny to the saved results

Per mesh (the shared meshes and the drone scene; triangles' boxes in the scene frame):

* the greedy sweep build (``jaxbvh.build(method="sweep")``, one triangle per leaf): warm
  seconds (median of 3) and objective ``nt`` (Ng & Trifonov's interior area / root area);
* GRASP at the default noise (``jaxbvh.grasp.DEFAULT_DEVIATIONS`` per tree, rcl "axes")
  for ``--trials`` trials: warm seconds (the run after a first, compiling run), best
  objective, improvement over greedy;
* the sweep: every ``--noises`` x ``--rcls`` with 100 trials (the paper's Tables 3-4:
  Base, best of 10, best of 100), plus the scale-free ``--deviations`` with rcl "axes";
  seconds of a single run (forest shapes new to the process compile inside it).

``--noises``, ``--rcls``, ``--deviations`` and ``--more-seeds`` given with no value skip
that part. Writes bench/results/stochastic.json and stochastic.md; with ``--merge`` the
meshes run replace (or join) those already in stochastic.json, the others are kept. The machine is shared, so the
load average is recorded beside the times.
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
from jaxbvh.io import load_mesh  # noqa: E402
from jaxbvh.stochastic import grasp  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
MESHES = {
    "spot": DATA / "meshes" / "spot.obj",
    "cow": DATA / "meshes" / "cow.obj",
    "teapot": DATA / "meshes" / "teapot.obj",
    "legocar": DATA / "meshes" / "legocar.obj",
    "fandisk": DATA / "meshes" / "fandisk.obj",
    "rocker-arm": DATA / "meshes" / "rocker-arm.obj",
    "drone": DATA / "scenes" / "drone" / "scene.gltf",
    "bunny": DATA / "meshes" / "stanford-bunny.obj",
}
NOISES = [0.001, 0.003, 0.01, 0.03, 0.1, 0.33, 1.0]
RCLS = ["axes", "1", "5", "20"]
DEVIATIONS = [1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 30.0]


def timed(fn):
    start = time.perf_counter()
    out = fn()
    jax.block_until_ready(getattr(out, "tree", out))
    return out, time.perf_counter() - start


def row_of(result, seconds, n):
    best10 = result.best_of(10) if result.objectives.size >= 10 else None
    return {
        "noise": result.noise, "deviations": result.noise * (n - 1), "rcl": result.rcl,
        "trials": int(result.objectives.size), "base": result.base, "best": result.objective,
        "best_of_10": best10, "median": float(np.median(result.objectives)),
        "better": int(np.sum(result.objectives < result.base)),
        "improvement_percent": 100.0 * (1.0 - result.objective / result.base),
        "rebuilt_per_trial": float(result.rebuilt.mean()), "seconds": seconds,
    }


def run_mesh(name, path, args):
    mesh = load_mesh(path)
    lo, hi = mesh.local_boxes()
    n = lo.shape[0]
    out = {"mesh": name, "triangles": n, "load_before": os.getloadavg()[0]}
    key = jax.random.key(args.seed)

    tree, first = timed(lambda: jaxbvh.build(lo, hi, method="sweep"))
    times = [timed(lambda: jaxbvh.build(lo, hi, method="sweep"))[1] for _ in range(3)]
    out["greedy"] = {"seconds": statistics.median(times), "compile_seconds": max(first - min(times), 0.0),
                     "nt": float(jaxbvh.ng_trifonov_cost(tree)), "sah": float(jaxbvh.sah(tree))}
    print(f"{name}: {n} triangles, greedy {out['greedy']['seconds']:.3f} s, nt {out['greedy']['nt']:.5f}",
          flush=True)

    out["trials"] = []
    for trials in args.trials:
        run = lambda: grasp.grasp(key, lo, hi, trials=trials)  # noqa: E731
        _, first = timed(run)
        result, seconds = timed(run)
        row = row_of(result, seconds, n)
        row["first_seconds"] = first
        jaxbvh.validate(result.tree, lo, hi)
        row["tree_nt"] = float(jaxbvh.ng_trifonov_cost(result.tree))
        out["trials"].append(row)
        print(f"  default noise, {trials} trials: {seconds:.2f} s warm, best {row['best']:.5f} "
              f"({row['improvement_percent']:+.4f}%)", flush=True)

    out["sweep"] = []
    for rcl in args.rcls:
        for noise in args.noises:
            result, seconds = timed(lambda: grasp.grasp(key, lo, hi, trials=100, noise=noise, rcl=rcl))
            out["sweep"].append(row_of(result, seconds, n))
            r = out["sweep"][-1]
            print(f"  rcl {rcl} noise {noise}: best10 {r['best_of_10']:.5f} best {r['best']:.5f} "
                  f"({r['improvement_percent']:+.4f}%), {r['better']} better, {seconds:.1f} s", flush=True)
    for seed in [args.seed] + args.more_seeds:
        for deviations in args.deviations:
            result, seconds = timed(lambda: grasp.grasp(jax.random.key(seed), lo, hi, trials=100,
                                                        deviations=deviations))
            out["sweep"].append({**row_of(result, seconds, n), "by_deviations": True, "seed": seed})
            r = out["sweep"][-1]
            print(f"  seed {seed} deviations {deviations}: best {r['best']:.5f} ({r['improvement_percent']:+.4f}%), "
                  f"{r['better']} better, {seconds:.1f} s", flush=True)
    out["load_after"] = os.getloadavg()[0]
    return out


def fmt(x, digits=5):
    return "-" if x is None else f"{x:.{digits}f}"


def merged(rows):
    """``rows`` joined to the meshes saved in stochastic.json (a mesh run now replaces its old row)."""
    path = RESULTS / "stochastic.json"
    old = json.loads(path.read_text())["meshes"] if path.exists() else []
    new = {m["mesh"]: m for m in rows}
    out = [new.pop(m["mesh"], m) for m in old]
    return out + [m for m in rows if m["mesh"] in new]


def write(rows, args):
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.merge:
        rows = merged(rows)
    meta = {"machine": platform.machine(), "cpus": os.cpu_count(), "jax": jax.__version__,
            "platform": platform.platform(), "default_deviations": grasp.DEFAULT_DEVIATIONS,
            "args": {k: v for k, v in vars(args).items()}}
    (RESULTS / "stochastic.json").write_text(json.dumps({"meta": meta, "meshes": rows}, indent=1))
    lines = [
        "# GRASP (Ng & Trifonov 2003): time vs objective, noise sweep", "",
        f"Machine: {meta['platform']}, {meta['cpus']} CPUs (shared with other jobs: the load "
        f"average is listed per mesh), JAX {meta['jax']}. Objective nt = total interior box area / "
        "root area, one triangle per leaf; lower is better. Default noise: "
        f"{grasp.DEFAULT_DEVIATIONS:g} expected deviations per tree (rcl axes).", "",
        "## Greedy build and GRASP at the default noise (time vs objective)", "",
        "Change = best vs greedy; better trials = trials below greedy. Warm: the second run in the "
        "process (the first compiles).", "",
        "| mesh | triangles | load | greedy s | greedy nt | trials | GRASP s (warm) | first run s | best of 10 | "
        "best nt | change | better trials |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in rows:
        for r in m["trials"]:
            lines.append(f"| {m['mesh']} | {m['triangles']:,} | {m['load_before']:.1f} | {m['greedy']['seconds']:.3f} | "
                         f"{m['greedy']['nt']:.5f} | {r['trials']} | {r['seconds']:.2f} | {r['first_seconds']:.1f} | "
                         f"{fmt(r['best_of_10'])} | {r['best']:.5f} | {-r['improvement_percent']:+.4f}% | {r['better']} |")
    lines += ["", "## Noise sweep, 100 trials (Tables 3-4 shape)", "",
              "Change = best of 100 vs Base; better = trials below Base. Seconds: one run, compile "
              "of new forest shapes included.", "",
              "| mesh | rcl | noise | deviations/tree | Base | best of 10 | best of 100 | median | change | "
              "better | rebuilt/trial | s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in rows:
        for r in (r for r in m["sweep"] if not r.get("by_deviations")):
            lines.append(f"| {m['mesh']} | {r['rcl']} | {r['noise']:.3g} | {r['deviations']:.3g} | {r['base']:.5f} | "
                         f"{fmt(r['best_of_10'])} | {r['best']:.5f} | {r['median']:.5f} | "
                         f"{-r['improvement_percent']:+.4f}% | {r['better']} | {r['rebuilt_per_trial']:.0f} | "
                         f"{r['seconds']:.1f} |")
    lines += deviation_table(rows)
    (RESULTS / "stochastic.md").write_text("\n".join(lines) + "\n")


def deviation_table(rows):
    """Best of 100 vs greedy per mesh, seed and deviations per tree (rcl axes)."""
    runs = [(m["mesh"], r) for m in rows for r in m["sweep"] if r.get("by_deviations")]
    if not runs:
        return []
    ds = sorted({round(r["deviations"], 6) for _, r in runs})
    keys = sorted({(mesh, r["seed"]) for mesh, r in runs}, key=lambda k: ([m["mesh"] for m in rows].index(k[0]), k[1]))
    cell = {(mesh, r["seed"], round(r["deviations"], 6)): r for mesh, r in runs}
    lines = ["", "## Deviations per tree (rcl axes, 100 trials): best of 100 vs greedy (trials below greedy)", "",
             "| mesh | seed | " + " | ".join(f"D = {d:g}" for d in ds) + " |", "|---|---|" + "---|" * len(ds)]
    for mesh, seed in keys:
        cells = []
        for d in ds:
            r = cell.get((mesh, seed, d))
            cells.append("-" if r is None else f"{-r['improvement_percent']:+.4f}% ({r['better']})")
        lines.append(f"| {mesh} | {seed} | " + " | ".join(cells) + " |")
    below = []
    for d in ds:
        found = [cell[k + (d,)] for k in keys if k + (d,) in cell]
        below.append(f"{sum(r['best'] < r['base'] for r in found)}/{len(found)}, "
                     f"mean {np.mean([r['better'] for r in found]):.1f} trials below")
    lines += ["| runs with best < greedy | | " + " | ".join(below) + " |"]
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    parser.add_argument("--trials", nargs="+", type=int, default=[10, 100, 1000])
    parser.add_argument("--noises", nargs="*", type=float, default=NOISES)
    parser.add_argument("--rcls", nargs="*", default=RCLS)
    parser.add_argument("--deviations", nargs="*", type=float, default=DEVIATIONS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--more-seeds", nargs="*", type=int, default=[1, 2],
                        help="extra seeds for the deviations sweep (how robust the default is)")
    parser.add_argument("--quick", action="store_true", help="spot and teapot, 10/100 trials, three noises")
    parser.add_argument("--merge", action="store_true",
                        help="keep the other meshes already in bench/results/stochastic.json")
    parser.add_argument("--out", default=None, help="write results here instead (JSON only)")
    args = parser.parse_args(argv)
    if args.quick:
        args.meshes, args.trials, args.noises = ["spot", "teapot"], [10, 100], [0.001, 0.01, 0.1]
        args.rcls, args.deviations = ["axes", "5"], [3.0, 30.0]
    missing = [m for m in args.meshes if not MESHES[m].exists()]
    if missing:
        sys.exit(f"shared data not found for {', '.join(missing)} (looked in {DATA})")
    rows = []
    for name in args.meshes:
        rows.append(run_mesh(name, MESHES[name], args))
        if args.out:
            Path(args.out).write_text(json.dumps(rows, indent=1))
        else:
            write(rows, args)
    if not args.out:
        print((RESULTS / "stochastic.md").read_text())


if __name__ == "__main__":
    main()
