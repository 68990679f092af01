"""Time to quality: SAH against time for every optimizer beside tinybvh's ``Optimize(K)``.

    python bench/bench_quality.py                         # every shared mesh and scene
    python bench/bench_quality.py --inputs legocar drone bunny --methods pipeline reinsert
    python bench/bench_quality.py --merge --inputs teapot  # redo some inputs, keep the rest
    python bench/bench_quality.py --rewrite               # md/png from quality.json

For each input, the peer harness (``../shared/peer/compare.sh``: tinybvh v1.6.7, one
thread) builds tinybvh's binned tree and times its reinsertion optimizer
``Optimize(K, extreme)`` for K = :data:`SERIES` (a fresh binned tree per K, the min over
``--repeats``); its binned tree is dumped and is the start tree of every jaxbvh method,
so both libraries optimize the same tree. The peer runs before and after our methods on
each input (the machine is shared: the two runs bracket the noise; ratios use the faster
one). Each of our methods is run cold (first call in the process: compiling, init and one
step, under a time budget as the warm run: :func:`bench.curves.warm_up`), then warm with
an ``on_step`` callback: the curve is the SAH after
every pass or iteration against wall seconds since the warm call began (the driver
reports in chunks, so points can come in bursts). ``--budget`` bounds every warm run
(annealing and hill climbing would run for minutes on the big inputs).

Writes ``bench/results/quality.json``, ``quality.md`` and ``quality.png``. The figure of
issue 19: seconds until the pipeline's curve reaches tinybvh's ``Optimize(200)`` SAH,
divided by tinybvh's time for it, in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from bench.bench_optimize import dump, meta, thin_curve  # noqa: E402
from bench.curves import draw_curves, panels, pyplot, save, timed_curve, warm_up  # noqa: E402
from jaxbvh.optimize import OPTIMIZERS  # noqa: E402

METHODS = tuple(OPTIMIZERS)
DATA = ROOT.parent / "shared" / "data"
PEER = ROOT.parent / "shared" / "peer"
RESULTS = ROOT / "bench" / "results"
SERIES = (5, 10, 25, 50, 100, 200)  # tinybvh Optimize(K) iteration counts
INPUTS = {  # name -> mesh or scene file; the first three are the targets of issue 19
    "legocar": "meshes/legocar.obj",
    "drone": "scenes/drone/scene.gltf",
    "bunny": "meshes/stanford-bunny.obj",
    "spot": "meshes/spot.obj",
    "teapot": "meshes/teapot.obj",
    "cow": "meshes/cow.obj",
    "fandisk": "meshes/fandisk.obj",
    "rocker-arm": "meshes/rocker-arm.obj",
}
TARGET_RATIO = 5.0  # issue 19: the pipeline within 5x tinybvh's time on legocar, drone, bunny


def peer(path: Path, repeats: int, out: str | None = None) -> list[dict]:
    """tinybvh's binned tree and its Optimize(K) series on ``path``: the harness's JSON rows."""
    cmd = [str(PEER / "compare.sh"), str(path), str(repeats), "--methods", "binned,series",
           "--series", ",".join(map(str, SERIES))]
    if out:
        cmd += ["--out", out]
    env = {**os.environ, "PY": sys.executable}
    env.setdefault("PEER_BUILD", str(Path(tempfile.gettempdir()) / "jaxbvh-peer-quality"))
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def start_tree(path: Path, workdir: Path):
    """tinybvh's binned tree of ``path`` (dumped by the harness) and the first peer run."""
    prefix = str(workdir / path.stem)
    rows = peer(path, 1, out=prefix)
    npz = workdir / f"{path.stem}_binned.npz"
    subprocess.run([sys.executable, str(PEER / "to_npz.py"), f"{prefix}.binned.bin", str(npz)],
                   check=True, capture_output=True)
    return jaxbvh.load(npz)[0], rows


def series_of(rows: list[dict]) -> list[list[float]]:
    """``[[K, ms, sah], ...]`` of the harness's optimizer series."""
    out = [[r["iterations"], r["ms"], r["sah"]] for r in rows if r["method"].startswith("optimize")]
    return sorted({k: [k, ms, sah] for k, ms, sah in out}.values())


def faster(a: list, b: list) -> list:
    """The per-K minimum time of two series runs (the SAH is deterministic)."""
    by_k = {k: [k, ms, sah] for k, ms, sah in a}
    for k, ms, sah in b:
        by_k[k] = [k, min(ms, by_k.get(k, [k, ms])[1]), sah]
    return sorted(by_k.values())


def run_method(tree, method: str, budget: float):
    """A cold call (:func:`bench.curves.warm_up`: compiling, init and one step), then a
    warm curve cut at ``budget`` seconds: ``(result, cold s, warm s, curve)``."""
    cold = warm_up(tree, method)
    result, warm, curve = timed_curve(tree, method, budget)
    return result, cold, warm, curve


def first_at_or_below(curve, target):
    return next((t for t, sah, _ in curve if sah <= target), None)


def run(args) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.inputs:
            path = DATA / INPUTS[name]
            tree, before = start_tree(path, Path(tmp))
            tiny_binned = next(r for r in before if r["method"] == "binned")
            nodes = jaxbvh.tree.node_count(tree)
            start_sah = float(jaxbvh.sah(jaxbvh.to_jax(tree)))
            print(f"== {name}: {tiny_binned['tris']:,} triangles, {nodes:,} nodes, SAH {start_sah:.3f} "
                  f"(tinybvh {tiny_binned['sah']:.3f})", file=sys.stderr, flush=True)
            mine = []
            for method in args.methods:
                result, cold, warm, curve = run_method(tree, method, args.budget)
                jaxbvh.validate(result.tree)
                mine.append({"input": name, "method": method, "sah": float(result.sah), "cold_seconds": cold,
                             "seconds": warm, "steps": int(result.steps), "converged": bool(result.converged),
                             "curve": curve})
                print({k: v for k, v in mine[-1].items() if k != "curve"}, file=sys.stderr, flush=True)
            after = series_of(peer(path, args.repeats))
            series = faster(series_of(before), after)
            k200 = series[-1]
            for row in mine:
                beat = first_at_or_below(row["curve"], k200[2])
                row.update(triangles=tiny_binned["tris"], nodes=nodes, start_sah=start_sah,
                           tinybvh_binned_sah=tiny_binned["sah"], tinybvh_series=series,
                           tinybvh_series_before=series_of(before), tinybvh_series_after=after,
                           tinybvh_sah=k200[2], tinybvh_seconds=k200[1] / 1e3,
                           seconds_to_tinybvh=beat,
                           ratio_to_tinybvh=None if beat is None else beat / (k200[1] / 1e3))
            rows += mine
    return rows


def plot(rows, path):
    plt = pyplot()
    if plt is None:
        return
    names = list(dict.fromkeys(r["input"] for r in rows))
    fig, axes = panels(plt, len(names), 4, (4.6, 3.8))
    for ax, name in zip(axes, names):
        mine = [r for r in rows if r["input"] == name]
        low = draw_curves(ax, mine, f"{name} ({mine[0]['triangles']:,} triangles)")
        series = mine[-1]["tinybvh_series"]  # the latest run's (--merge puts it last)
        ax.plot([ms / 1e3 for _, ms, _ in series], [sah for _, _, sah in series], "kx--", zorder=5,
                label=f"tinybvh Optimize(K) ({series[-1][2]:.3f})")
        low = min(low, min(sah for _, _, sah in series))
        high = max(mine[0]["start_sah"], max(sah for _, _, sah in series))
        ax.set_ylim(low - 0.01 * abs(low), high * 1.005)
        ax.legend(fontsize=6)
    save(fig, path, 90)


def write(rows, args, m=None):
    RESULTS.mkdir(parents=True, exist_ok=True)
    m = m or meta(args)
    rows = [{**r, "curve": thin_curve(r["curve"])} for r in rows]
    (RESULTS / "quality.json").write_text(dump({"meta": m, "rows": rows}))
    lines = ["# Time to quality: SAH against time beside tinybvh", "",
             f"Machine: {m['platform']}, {m['cpus']} CPUs, shared with other jobs while it ran (timings "
             f"noisy: compare within a row), JAX {m['jax']}. Start: tinybvh's binned tree (the harness's "
             "dump) for every method; SAH with Ct = Ci = 1. tinybvh: `Optimize(K, extreme)` on one thread, "
             "the faster of two runs bracketing ours. Warm: compiled before; cold: the first call "
             "in the process, compiling and one step. Curves: quality.png.", "",
             "| input | method | SAH | warm s | cold s | steps | tinybvh Optimize(200) SAH (s) | "
             "s to reach it | ratio |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        beat, ratio = r.get("seconds_to_tinybvh"), r.get("ratio_to_tinybvh")
        lines.append(f"| {r['input']} | {r['method']} | {r['sah']:.3f} | {r['seconds']:.2f} | "
                     f"{r['cold_seconds']:.1f} | {r['steps']} | {r['tinybvh_sah']:.3f} "
                     f"({r['tinybvh_seconds']:.3f}) | {'-' if beat is None else format(beat, '.2f')} | "
                     f"{'-' if ratio is None else format(ratio, '.1f') + 'x'} |")
    lines += ["", "tinybvh's series (K: ms, SAH):", ""]
    for name in dict.fromkeys(r["input"] for r in rows):
        r = [r for r in rows if r["input"] == name][-1]  # the latest run's (--merge puts it last)
        lines.append(f"- {name}: start {r['tinybvh_binned_sah']:.3f}; " + ", ".join(
            f"{k}: {ms:.1f} ms, {sah:.3f}" for k, ms, sah in r["tinybvh_series"]))
    (RESULTS / "quality.md").write_text("\n".join(lines) + "\n")
    plot(rows, RESULTS / "quality.png")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", nargs="*", default=list(INPUTS), choices=list(INPUTS))
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    parser.add_argument("--budget", type=float, default=20.0, help="seconds per warm run")
    parser.add_argument("--repeats", type=int, default=3, help="tinybvh: min over this many runs")
    parser.add_argument("--merge", action="store_true", help="keep the rows of quality.json this run does not redo")
    parser.add_argument("--rewrite", action="store_true", help="run nothing: rewrite quality.md/.png")
    args = parser.parse_args(argv)
    if args.rewrite:
        old = json.loads((RESULTS / "quality.json").read_text())
        write(old["rows"], args, old["meta"])
        print((RESULTS / "quality.md").read_text())
        return
    rows = run(args)
    if args.merge and (RESULTS / "quality.json").exists():
        new = {(r["input"], r["method"]) for r in rows}
        old = json.loads((RESULTS / "quality.json").read_text())["rows"]
        rows = [r for r in old if (r["input"], r["method"]) not in new] + rows
    write(rows, args)
    print((RESULTS / "quality.md").read_text())


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    jax.config.update("jax_enable_x64", False)
    main()
