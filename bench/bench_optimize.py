"""Every optimizer from the same start trees: SAH against wall time (jaxbvh.optimize).

    python bench/bench_optimize.py                  # tinybvh trees + our builds, all methods
    python bench/bench_optimize.py --trees legocar --no-builds --methods reinsert pipeline
    python bench/bench_optimize.py --methods pipeline --merge   # redo one method, keep the rest
    python bench/bench_optimize.py --rewrite        # md/png/thinned json from optimize.json
    python bench/bench_optimize.py --big            # the 1.05M-triangle input of bench_rotate.py:
                                                    # annealing, then the others in a tenth of its time

Methods: ``hc`` (rotations, hill climbing), ``sa`` (rotations, annealing, Kensler's
N = 1250, one chain), ``reinsert`` (parallel reinsertion), ``treelet`` (treelet
restructuring), ``pipeline`` (rounds of both). Inputs: the three tinybvh trees in
``../shared/data/trees`` (tinybvh's own reinsertion optimizer beside them, from the data
README) and our sweep / binned builds of shared meshes.

Every run is made twice: once to compile (cut short), then timed; the curve is the SAH
after every pass or iteration against the seconds since the timed call began (annealing
and hill climbing report in chunks of passes, so their points come in bursts). Writes
``bench/results/optimize.json``, ``optimize.md`` and ``optimize.png``; ``--big`` writes
``optimize_big.*``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from bench.curves import draw_curves, panels, pyplot, save, timed_curve, warm_up  # noqa: E402
from jaxbvh.optimize import OPTIMIZERS  # noqa: E402

METHODS = tuple(OPTIMIZERS)

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
TINYBVH = {  # start SAH -> after its reinsertion optimizer, seconds (README of the data)
    "legocar": (30.212, 26.733, 0.119),
    "drone": (15.397, 12.763, 0.350),
    "bunny": (31.880, 31.942, 1.219),
}
BUILDS = (("spot.obj", "sweep", 1), ("fandisk.obj", "binned", 1), ("stanford-bunny.obj", "sweep", 1))


def options_for(method, args):
    if method == "sa":
        return dict(steps=args.sa_steps)
    return {}


def run_curve(tree, method, args, time_budget=None):
    """Compile (:func:`bench.curves.warm_up`), then a timed run: ``(result, seconds, curve)``."""
    options = options_for(method, args)
    warm_up(tree, method, **options)
    return timed_curve(tree, method, time_budget, **options)


def inputs(args):
    for name in args.trees:
        path = DATA / "trees" / f"{name}_binned_ref.npz"
        if path.exists():
            yield f"{name} (tinybvh)", jaxbvh.load(path)[0], name
    if args.builds:
        from jaxbvh.io import load_mesh
        from jaxbvh.tree import compact

        for mesh_name, builder, max_leaf in BUILDS:
            path = DATA / "meshes" / mesh_name
            if not path.exists():
                continue
            lo, hi = load_mesh(path).local_boxes()
            tree = compact(jax.block_until_ready(jaxbvh.build(lo, hi, method=builder, max_leaf=max_leaf)))
            yield f"{mesh_name} (jaxbvh {builder})", tree, None


def best_within(curve, seconds):
    ok = [sah for t, sah, _ in curve if t <= seconds]
    return min(ok) if ok else None


def first_below(curve, target):
    return next((t for t, sah, _ in curve if sah < target), None)


def run(args):
    rows = []
    for label, tree, tiny in inputs(args):
        nodes = jaxbvh.tree.node_count(tree)
        start_sah = float(jaxbvh.sah(jaxbvh.to_jax(tree)))
        print(f"== {label}: {nodes:,} nodes, SAH {start_sah:.3f}", file=sys.stderr)
        for method in args.methods:
            result, seconds, curve = run_curve(tree, method, args)
            jaxbvh.validate(result.tree)
            row = {"input": label, "nodes": nodes, "start_sah": start_sah, "method": method,
                   "sah": float(result.sah), "seconds": seconds, "steps": int(result.steps),
                   "moves": int(result.moves), "curve": curve}
            if tiny:
                row["tinybvh_sah"], row["tinybvh_seconds"] = TINYBVH[tiny][1], TINYBVH[tiny][2]
                row["best_in_tinybvh_time"] = best_within(curve, TINYBVH[tiny][2])
                row["seconds_to_beat_tinybvh"] = first_below(curve, TINYBVH[tiny][1])
            rows.append(row)
            print({k: v for k, v in row.items() if k != "curve"}, file=sys.stderr, flush=True)
    return rows


def plot(rows, path, title=""):
    plt = pyplot()
    if plt is None:
        return
    names = list(dict.fromkeys(r["input"] for r in rows))
    fig, axes = panels(plt, len(names), 3, (5.2, 4))
    for ax, name in zip(axes, names):
        mine = [r for r in rows if r["input"] == name]
        low = draw_curves(ax, mine, name)
        if "tinybvh_sah" in mine[0]:
            ax.scatter([mine[0]["tinybvh_seconds"]], [mine[0]["tinybvh_sah"]], marker="x", c="k",
                       zorder=5, label=f"tinybvh reinsertion ({mine[0]['tinybvh_sah']:.3f})")
        ax.set_ylim(low - 0.02 * abs(low), mine[0]["start_sah"] * 1.005)
        ax.legend(fontsize=7)
    save(fig, path, 100, title)


def meta(args):
    return {"machine": platform.machine(), "cpus": os.cpu_count(), "jax": jax.__version__,
            "platform": platform.platform(), "args": vars(args)}


CURVE_POINTS = 200  # points kept per curve in the JSON (log-spaced in time)


def thin_curve(curve, points=CURVE_POINTS):
    """At most about ``points`` of a curve's ``(seconds, sah, stage)`` points: the first, the
    last, the lowest SAH, and the last point at or before each of ``points`` log-spaced
    times; seconds rounded to 4 significant digits and SAH to 6 (float32 holds ~7)."""
    if len(curve) > points:
        t = np.array([p[0] for p in curve])
        edges = np.geomspace(max(t[0], 1e-4), t[-1], points)
        keep = set(np.searchsorted(t, edges, side="right") - 1)
        keep |= {0, len(curve) - 1, int(np.argmin([p[1] for p in curve]))}
        curve = [curve[i] for i in sorted(k for k in keep if k >= 0)]
    return [[float(f"{p[0]:.4g}"), float(f"{p[1]:.6g}"), p[2]] for p in curve]


def dump(obj):
    """JSON with one line per row field and one line per curve (keeps the file small)."""
    rows = obj["rows"]
    head = {k: v for k, v in obj.items() if k != "rows"}
    out = ["{"] + [f" {json.dumps(k)}: {json.dumps(v)}," for k, v in head.items()] + [' "rows": [']
    for i, r in enumerate(rows):
        fields = [f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in r.items()]
        out.append("  {\n" + ",\n".join(fields) + "\n  }" + ("," if i + 1 < len(rows) else ""))
    return "\n".join(out + [" ]", "}"]) + "\n"


def write(rows, args, m=None):
    RESULTS.mkdir(parents=True, exist_ok=True)
    m = m or meta(args)
    rows = [{**r, "curve": thin_curve(r["curve"])} for r in rows]
    (RESULTS / "optimize.json").write_text(dump({"meta": m, "rows": rows}))
    lines = ["# Optimizers: SAH against time", "",
             f"Machine: {m['platform']}, {m['cpus']} CPUs (shared with other jobs while it ran), "
             f"JAX {m['jax']}. Seconds are wall time of a warm call (compiled before), SAH with "
             f"Ct = Ci = 1. Annealing: N = {args.sa_steps}, one chain, h = 0.15. Curves: "
             "optimize.png.", "",
             "| input | nodes | start SAH | method | SAH | change | seconds | passes / iterations | "
             "tinybvh SAH (s) | best in tinybvh's time | s to beat tinybvh |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        tiny = (f"{r['tinybvh_sah']:.3f} ({r['tinybvh_seconds']:.2f})" if "tinybvh_sah" in r else "-")
        within = r.get("best_in_tinybvh_time")
        beat = r.get("seconds_to_beat_tinybvh")
        lines.append(f"| {r['input']} | {r['nodes']:,} | {r['start_sah']:.3f} | {r['method']} | "
                     f"{r['sah']:.3f} | {100 * (r['sah'] / r['start_sah'] - 1):+.1f}% | "
                     f"{r['seconds']:.2f} | {r['steps']} | {tiny} | "
                     f"{'-' if within is None else format(within, '.3f')} | "
                     f"{'-' if beat is None else format(beat, '.2f')} |")
    (RESULTS / "optimize.md").write_text("\n".join(lines) + "\n")
    plot(rows, RESULTS / "optimize.png")


def run_big(args):
    """Annealing (N = ``--sa-steps``) on the big input, then every other method with a
    time budget of a tenth of annealing's time."""
    from bench_rotate import big_scene

    start = time.perf_counter()
    lo, hi = big_scene(args.big_copies, args.big_walls, args.seed)
    frame = jaxbvh.Frame.fit(lo, hi)
    lo, hi = frame.to_local(lo).astype(np.float32), frame.to_local(hi).astype(np.float32)
    tree = jaxbvh.tree.compact(jax.block_until_ready(jaxbvh.build(lo, hi)))
    label = f"big: {args.big_copies} bunnies + {args.big_walls} walls (jaxbvh sweep)"
    print(f"== {label}: {len(lo):,} triangles, built in {time.perf_counter() - start:.0f} s",
          file=sys.stderr, flush=True)
    nodes = jaxbvh.tree.node_count(tree)
    start_sah = float(jaxbvh.sah(jaxbvh.to_jax(tree)))
    rows = []
    sa, sa_seconds, curve = run_curve(tree, "sa", args)
    rows.append({"input": label, "nodes": nodes, "start_sah": start_sah, "method": "sa",
                 "sah": float(sa.sah), "seconds": sa_seconds, "steps": int(sa.steps), "moves": int(sa.moves),
                 "curve": curve})
    print({k: v for k, v in rows[-1].items() if k != "curve"}, file=sys.stderr, flush=True)
    budget = sa_seconds / 10
    for method in [m for m in args.methods if m != "sa"]:
        result, seconds, curve = run_curve(tree, method, args, time_budget=budget)
        jaxbvh.validate(result.tree, lo, hi)
        rows.append({"input": label, "nodes": nodes, "start_sah": start_sah, "method": method,
                     "sah": float(result.sah), "seconds": seconds, "steps": int(result.steps),
                     "moves": int(result.moves), "curve": curve, "time_budget": budget})
        print({k: v for k, v in rows[-1].items() if k != "curve"}, file=sys.stderr, flush=True)
    return rows, len(lo), budget


def write_big(rows, triangles, budget, args, m=None):
    RESULTS.mkdir(parents=True, exist_ok=True)
    m = m or meta(args)
    rows = [{**r, "curve": thin_curve(r["curve"])} for r in rows]
    (RESULTS / "optimize_big.json").write_text(dump({"meta": m, "triangles": triangles,
                                                     "time_budget": budget, "rows": rows}))
    sa = rows[0]
    lines = ["# Optimizers on the >= 1M-triangle input (`--big`)", "",
             f"{sa['input']}: {triangles:,} triangles, {sa['nodes']:,} nodes, start SAH "
             f"{sa['start_sah']:.3f}. Machine: {m['platform']}, {m['cpus']} CPUs (shared with "
             f"other jobs while it ran), JAX {m['jax']}. Annealing (N = {args.sa_steps}, one "
             f"chain) ran to the end; every other method had a time budget of a tenth of its "
             f"time ({budget:.1f} s; a method stops at the end of the pass or iteration that "
             "crosses it, and the budget's clock starts after the first one, so runs overshoot; "
             "the last columns read the curve at the budget). Seconds are warm (compiled "
             "before).", "",
             "| method | SAH | change | seconds | passes / iterations | below annealing's SAH | "
             "SAH at the budget | below annealing's SAH at the budget |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        below = "-" if r is sa else ("yes" if r["sah"] < sa["sah"] else "no")
        at = best_within(r["curve"], budget) if r is not sa else None
        at_below = "-" if at is None else ("yes" if at < sa["sah"] else "no")
        lines.append(f"| {r['method']} | {r['sah']:.3f} | {100 * (r['sah'] / r['start_sah'] - 1):+.1f}% | "
                     f"{r['seconds']:.1f} | {r['steps']} | {below} | "
                     f"{'-' if at is None else format(at, '.3f')} | {at_below} |")
    (RESULTS / "optimize_big.md").write_text("\n".join(lines) + "\n")
    plot(rows, RESULTS / "optimize_big.png", title="big input: annealing vs a tenth of its time")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trees", nargs="*", default=["legocar", "drone", "bunny"])
    parser.add_argument("--no-builds", dest="builds", action="store_false")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    parser.add_argument("--sa-steps", type=int, default=1250)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of optimize.json this run does not redo")
    parser.add_argument("--rewrite", action="store_true",
                        help="run nothing: rewrite optimize.md/.png and a thinned optimize.json "
                             "from the existing optimize.json (with --big: optimize_big.*)")
    parser.add_argument("--big", action="store_true")
    parser.add_argument("--big-copies", type=int, default=15)
    parser.add_argument("--big-walls", type=int, default=4000)
    args = parser.parse_args(argv)
    if args.big and args.rewrite:
        old = json.loads((RESULTS / "optimize_big.json").read_text())
        args.sa_steps = old["meta"]["args"]["sa_steps"]
        write_big(old["rows"], old["triangles"], old["time_budget"], args, old["meta"])
        print((RESULTS / "optimize_big.md").read_text())
        return
    if args.big:
        sys.path.insert(0, str(ROOT / "bench"))
        rows, triangles, budget = run_big(args)
        write_big(rows, triangles, budget, args)
        print((RESULTS / "optimize_big.md").read_text())
        return
    if args.rewrite:
        old = json.loads((RESULTS / "optimize.json").read_text())
        args.sa_steps = old["meta"]["args"]["sa_steps"]
        write(old["rows"], args, old["meta"])
        print((RESULTS / "optimize.md").read_text())
        return
    rows = run(args)
    if args.merge and (RESULTS / "optimize.json").exists():
        new = {(r["input"], r["method"]) for r in rows}
        old = json.loads((RESULTS / "optimize.json").read_text())["rows"]
        rows = [r for r in old if (r["input"], r["method"]) not in new] + rows
        order = list(dict.fromkeys(r["input"] for r in old + rows))
        rows.sort(key=lambda r: (order.index(r["input"]), METHODS.index(r["method"])))
    write(rows, args)
    print((RESULTS / "optimize.md").read_text())


if __name__ == "__main__":
    main()
