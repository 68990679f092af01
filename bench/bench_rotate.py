"""Tree rotations: time vs SAH for hill climbing and annealing (Kensler 2008).

    python bench/bench_rotate.py                 # tinybvh trees, HC, SA N in {50, 250}, K in {1, 4}
    python bench/bench_rotate.py --full          # + N = 1250, K = 16, our own builds, 1M-triangle input
    python bench/bench_rotate.py --trees legocar --steps 50 --chains 1

Writes bench/results/rotate.json, rotate.md and rotate.png. Times are wall seconds on
this machine, compile excluded (the first call is timed apart as "compile"), median of
``--repeat`` warm runs. The NumPy reference is timed once on the smallest input.
"""

from __future__ import annotations

import argparse
import json
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
from jaxbvh import rotate  # noqa: E402
from jaxbvh.reference import rotate as ref  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
TINYBVH = {  # start SAH -> after its reinsertion optimizer, time (README of the data)
    "drone": (15.397, 12.763, 0.350),
    "legocar": (30.212, 26.733, 0.119),
    "bunny": (31.880, 31.942, 1.219),
}


def timed(fn, repeat):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    warm = statistics.median(times) if times else first
    return out, warm, max(first - warm, 0.0)


def inputs(args):
    for name in args.trees:
        path = DATA / "trees" / f"{name}_binned_ref.npz"
        if path.exists():
            yield f"{name} (tinybvh)", jaxbvh.load(path)[0], name
    if args.full:
        try:
            from jaxbvh.io import load_mesh
            for mesh_name in ("spot.obj", "stanford-bunny.obj"):
                mesh = load_mesh(DATA / "meshes" / mesh_name)
                lo, hi = mesh.local_boxes()
                yield f"{mesh_name} (jaxbvh sweep)", jaxbvh.to_numpy(jaxbvh.build(lo, hi)), None
        except NotImplementedError as exc:
            print(f"skipping our own builds: {exc}", file=sys.stderr)


def run(args):
    rows = []
    for label, tree, tiny in inputs(args):
        nodes = jaxbvh.tree.node_count(tree)
        print(f"== {label}: {nodes} nodes, capacity {tree.capacity}", file=sys.stderr)
        tj = jaxbvh.to_jax(tree)
        start_sah = float(jaxbvh.sah(tj))
        base = {"input": label, "nodes": nodes, "capacity": tree.capacity, "start_sah": start_sah}
        if tiny:
            base["tinybvh_sah"], base["tinybvh_seconds"] = TINYBVH[tiny][1], TINYBVH[tiny][2]
        res, warm, compile_s = timed(lambda: rotate.hill_climb(tj), args.repeat)
        rows.append({**base, "method": "hc", "steps": 0, "chains": 1, "sah": float(res.sah),
                     "passes": int(res.passes), "moves": int(res.moves), "seconds": warm,
                     "compile_seconds": compile_s})
        print(rows[-1], file=sys.stderr)
        for steps in args.steps:
            for chains in args.chains:
                if chains > 1 and steps != args.chain_steps:
                    continue
                key = jax.random.key(args.seed)
                res, warm, compile_s = timed(
                    lambda: rotate.anneal(key, tj, steps=steps, chains=chains), args.repeat)
                rows.append({**base, "method": "sa", "steps": steps, "chains": chains,
                             "sah": float(res.sah), "passes": int(res.passes),
                             "moves": int(res.moves), "seconds": warm, "compile_seconds": compile_s})
                print(rows[-1], file=sys.stderr)
    reference = None
    if args.reference:
        path = DATA / "trees" / "legocar_binned_ref.npz"
        if path.exists():
            tree = jaxbvh.load(path)[0]
            start = time.perf_counter()
            expected, info = ref.hill_climb(tree)
            ref_s = time.perf_counter() - start
            res, warm, _ = timed(lambda: rotate.hill_climb(tree, split_axes=False), args.repeat)
            same = all(np.array_equal(np.asarray(getattr(res.tree, f)), getattr(expected, f))
                       for f in ("left", "right", "parent", "lo", "hi"))
            reference = {"input": "legocar (tinybvh)", "numpy_seconds": ref_s, "jax_seconds": warm,
                         "speedup": ref_s / warm, "identical": bool(same), "passes": info["passes"]}
            print(reference, file=sys.stderr)
    return rows, reference


def write(rows, reference, args):
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.machine(), "cpus": __import__("os").cpu_count(),
            "jax": jax.__version__, "platform": platform.platform(), "args": vars(args)}
    (RESULTS / "rotate.json").write_text(json.dumps({"meta": meta, "rows": rows,
                                                     "reference": reference}, indent=1))
    lines = ["# Tree rotations: time vs SAH", "",
             f"Machine: {meta['platform']}, {meta['cpus']} CPUs, JAX {meta['jax']}. Seconds are "
             "warm (compile excluded, reported apart), median of "
             f"{args.repeat}; SAH with Ct = Ci = 1.", "",
             "| input | nodes | start SAH | method | N | K | SAH | change | passes | seconds | compile s | tinybvh SAH (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        tiny = f"{r['tinybvh_sah']:.3f} ({r['tinybvh_seconds']:.2f})" if "tinybvh_sah" in r else "-"
        change = 100 * (r["sah"] / r["start_sah"] - 1)
        lines.append(f"| {r['input']} | {r['nodes']:,} | {r['start_sah']:.3f} | {r['method']} | "
                     f"{r['steps'] or '-'} | {r['chains']} | {r['sah']:.3f} | {change:+.1f}% | "
                     f"{r['passes']} | {r['seconds']:.3f} | {r['compile_seconds']:.1f} | {tiny} |")
    if reference:
        lines += ["", f"NumPy reference hill climbing on {reference['input']}: "
                      f"{reference['numpy_seconds']:.2f} s vs JAX {reference['jax_seconds']:.3f} s "
                      f"({reference['speedup']:.0f}x), identical tree: {reference['identical']}."]
    (RESULTS / "rotate.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        inputs_ = sorted({r["input"] for r in rows})
        fig, axes = plt.subplots(1, len(inputs_), figsize=(5 * len(inputs_), 4), squeeze=False)
        for ax, name in zip(axes[0], inputs_):
            for r in (r for r in rows if r["input"] == name):
                label = "HC" if r["method"] == "hc" else f"SA N={r['steps']} K={r['chains']}"
                ax.scatter(r["seconds"], r["sah"], label=label)
            if any("tinybvh_sah" in r for r in rows if r["input"] == name):
                r = next(r for r in rows if r["input"] == name)
                ax.scatter(r["tinybvh_seconds"], r["tinybvh_sah"], marker="x", c="k",
                           label="tinybvh reinsertion")
            ax.set_xscale("log")
            ax.set_title(name)
            ax.set_xlabel("seconds (warm)")
            ax.set_ylabel("SAH")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(RESULTS / "rotate.png", dpi=100)
    except Exception as exc:  # the plot is a convenience; the table is the result
        print(f"no plot: {exc}", file=sys.stderr)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true")
    parser.add_argument("--trees", nargs="*", default=["legocar", "drone", "bunny"])
    parser.add_argument("--steps", nargs="*", type=int, default=None)
    parser.add_argument("--chains", nargs="*", type=int, default=None)
    parser.add_argument("--chain-steps", type=int, default=50,
                        help="schedule length used for the K > 1 runs")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-reference", dest="reference", action="store_false")
    args = parser.parse_args(argv)
    if args.steps is None:
        args.steps = [50, 250, 1250] if args.full else [50, 250]
    if args.chains is None:
        args.chains = [1, 4, 16] if args.full else [1, 4]
    rows, reference = run(args)
    write(rows, reference, args)
    print((RESULTS / "rotate.md").read_text())


if __name__ == "__main__":
    main()
