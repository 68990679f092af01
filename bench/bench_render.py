"""Rays per second in tinybvh's own kernels: our best trees beside tinybvh's (issue 40).

    python bench/bench_render.py                                  # legocar and the bunny
    python bench/bench_render.py --meshes legocar --res 256 --repeats 3
    python bench/bench_render.py --meshes legocar stanford-bunny drone --reuse
    python bench/bench_render.py --meshes legocar fandisk --targets tinybvh-bvh8 --name bench_render_targets

Per mesh, one run of the shared tracer (``../shared/peer/tinybvh_trace``, TRACE.md there):

* our trees, made as a user makes them, with the command line's defaults:
  ``jaxbvh optimize MESH -o`` (the default build, then the default optimizer) and
  ``jaxbvh optimize MESH --builder sbvh -o`` (spatial splits, then the optimizer), each
  written by ``jaxbvh export --format tinybvh``;
* with ``--targets NAME ...``, also ``jaxbvh optimize MESH --target NAME -o`` for each
  cost target (:mod:`jaxbvh.tree.targets`), reported against ``ours_default``;
* tinybvh's trees, built by the tracer on the same triangles: ``Build`` (binned SAH),
  ``Build`` + ``Optimize(200, extreme)`` and ``BuildHQ`` (SBVH);
* every tree traced in the four layouts (``BVH``, ``BVH_SoA``, ``BVH4_CPU``,
  ``BVH8_CPU``; the wide ones made by tinybvh's ``ConvertFrom``, which first merges every
  subtree of at most 4 triangles into a leaf) on the same primary, random and bounce rays
  (``--res``² each), min over ``--repeats`` rounds of the thread's CPU time (the machine
  is shared: wall time would count other jobs).

Reported: Mrays/s per (tree, layout, ray set); per layout the geometric mean over the
three ray sets; and the ratio of our best tree to tinybvh's best tree per layout (each
side's best by that geometric mean). Every trace's hits are compared ray by ray with
tinybvh's ``Build`` tree (the tracer's reference): disagreements are listed. Writes
``bench/results/bench_render.{json,md,png}`` (``--name`` renames them). The JAX trees are
built in child processes without the test suite's XLA flags.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
PEER = ROOT.parent / "shared" / "peer"
RESULTS = ROOT / "bench" / "results"
#: short names of the shared inputs (a path works too)
INPUTS = {"legocar": "meshes/legocar.obj", "stanford-bunny": "meshes/stanford-bunny.obj",
          "bunny": "meshes/stanford-bunny.obj", "drone": "scenes/drone/scene.gltf",
          "rocker-arm": "meshes/rocker-arm.obj", "fandisk": "meshes/fandisk.obj", "spot": "meshes/spot.obj",
          "teapot": "meshes/teapot.obj", "cow": "meshes/cow.obj"}
#: our trees: name -> the extra options of ``jaxbvh optimize`` (none: the defaults)
OURS = {"ours_default": [], "ours_sbvh": ["--builder", "sbvh"]}
PEERS = ("build", "optimize", "hq")
LAYOUTS = ("bvh", "soa", "bvh4", "bvh8")
LAYOUT_CLASS = {"bvh": "BVH", "soa": "BVH_SoA", "bvh4": "BVH4_CPU", "bvh8": "BVH8_CPU"}
SETS = ("primary", "random", "bounce")


def child_env() -> dict:
    """The environment of the child processes: this checkout first on the path, and no
    XLA flags (the suite's unoptimized compiles would slow the builds, not the traces)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def tracer(build_dir: Path) -> Path:
    exe = build_dir / "tinybvh_trace"
    source = PEER / "tinybvh_trace.cpp"
    if not exe.exists() or exe.stat().st_mtime < source.stat().st_mtime:
        subprocess.run(["bash", str(PEER / "build_trace.sh"), str(exe)], check=True)
    return exe


def our_tree(mesh: Path, name: str, options: list, work: Path, reuse: bool) -> dict:
    """``jaxbvh optimize`` then ``jaxbvh export``; the optimize command's JSON, with the
    CPU seconds of both children."""
    npz, out, report = work / f"{name}.npz", work / f"{name}.bin", work / f"{name}.json"
    if reuse and npz.exists() and report.exists():
        result = json.loads(report.read_text())
    else:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        done = subprocess.run([sys.executable, "-m", "jaxbvh.cli.app", "optimize", str(mesh), *options, "-o", str(npz),
                               "--json"], capture_output=True, text=True, env=child_env(), check=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        result = json.loads(done.stdout)
        result["cpu_seconds"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        report.write_text(json.dumps(result))
    subprocess.run([sys.executable, "-m", "jaxbvh.cli.app", "export", str(npz), str(mesh), "--format", "tinybvh",
                    "-o", str(out), "--overwrite", "--json"], capture_output=True, text=True, env=child_env(),
                   check=True)
    keep = ("builder", "method", "passes", "seconds", "compile_seconds", "cpu_seconds", "sah_change_percent")
    return {"file": str(out), "options": options, **{k: result.get(k) for k in keep},
            "sah_before": result["before"]["sah"], "sah_after": result["after"]["sah"],
            "target_cost_before": result["before"].get("target_cost"),
            "target_cost_after": result["after"].get("target_cost")}


def geomean(values) -> float:
    values = list(values)
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values and all(v > 0 for v in values) else float("nan")


def one_mesh(name: str, args, exe: Path, work: Path) -> dict:
    path = Path(INPUTS.get(name, name))
    path = path if path.is_absolute() or path.exists() else DATA / path
    work = work / Path(name).stem
    work.mkdir(parents=True, exist_ok=True)
    started = {"load": load(), "utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    ours = {}
    trees = dict({k: v for k, v in OURS.items() if k in args.ours}, **{f"ours_{t}": ["--target", t] for t in args.targets})
    for tree, options in trees.items():
        print(f"{name}: {tree} (jaxbvh optimize {' '.join(options)})", file=sys.stderr, flush=True)
        ours[tree] = our_tree(path, tree, options, work, args.reuse)
    tris = work / "tris.bin"
    subprocess.run([sys.executable, str(PEER / "dump_tris.py"), str(path), str(tris)], check=True, capture_output=True)
    cmd = [str(exe), str(tris), "--peer", ",".join(PEERS), "--layouts", ",".join(LAYOUTS),
           "--repeats", str(args.repeats), "--res", str(args.res), "--seed", str(args.seed), "--label", name]
    for tree, info in ours.items():
        cmd += ["--tree", f"{tree}={info['file']}"]
    print(f"{name}: tracing (load {load()})", file=sys.stderr, flush=True)
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    return {"mesh": name, "path": str(path), "started": started, "finished_load": load(), "ours": ours,
            "tracer_command": cmd, "lines": lines, "summary": summarize(lines)}


def summarize(lines: list) -> dict:
    """Per tree: SAH, SAH after the wide layouts' leaf merge, depth and per layout the
    geometric mean of Mrays/s over the ray sets; per layout the best of ours and of
    tinybvh's and their ratio; hit disagreements with the reference."""
    trees = {x["tree"]: x for x in lines if x["kind"] == "tree"}
    traces = [x for x in lines if x["kind"] == "trace"]
    per_tree = {}
    for name, t in trees.items():
        row = {"sah": t["sah"], "depth": t["depth"], "leaves": t["leaves"], "max_leaf": t["max_leaf"],
               "refs_per_tri": t["refs_per_tri"], "references": t["references"],
               "sah_after_combine4": t["layouts"].get("bvh4", {}).get("sah_after_combine4"),
               "skipped": {k: v["skip"] for k, v in t["layouts"].items() if not v["traced"]}}
        for layout in LAYOUTS:
            got = {x["set"]: x["mrays_per_s"] for x in traces if x["tree"] == name and x["layout"] == layout}
            row[layout] = {"geomean": geomean(got.values()) if len(got) == len(SETS) else float("nan"), **got}
        per_tree[name] = row
    best = {}
    for layout in LAYOUTS:
        side = {}
        for who, pick in (("ours", lambda n: not n.startswith("tinybvh")), ("tinybvh", lambda n: n.startswith("tinybvh"))):
            scored = [(per_tree[n][layout]["geomean"], n) for n in per_tree if pick(n)
                      and not math.isnan(per_tree[n][layout]["geomean"])]
            side[who] = max(scored) if scored else (float("nan"), None)
        best[layout] = {"ours": side["ours"][1], "ours_mrays": side["ours"][0], "tinybvh": side["tinybvh"][1],
                        "tinybvh_mrays": side["tinybvh"][0], "ratio": side["ours"][0] / side["tinybvh"][0]}
        for name in per_tree:  # each tree against tinybvh's best
            per_tree[name][layout]["vs_tinybvh_best"] = per_tree[name][layout]["geomean"] / side["tinybvh"][0]
    # a tree against the reference in the same kernel: a hit missed or found at another t
    # would be the tree's fault; the same t on another triangle is a tie (coincident
    # triangles), which the visiting order decides
    disagreements = [{k: x[k] for k in ("tree", "layout", "set", "vs_ref_same_layout")}
                     for x in traces if x["vs_ref_same_layout"]["hit_miss"] or x["vs_ref_same_layout"]["t_diff"]]
    ties = {}
    for x in traces:
        ties[x["tree"]] = ties.get(x["tree"], 0) + x["vs_ref_same_layout"]["prim_diff"]
    # the reference's binary kernel against each layout's kernel (their triangle tests
    # differ), and whether every tree shows the same hit/miss and t differences there
    kernels = {f"{x['layout']}/{x['set']}": x["vs_ref_bvh"] for x in traces
               if x["tree"] == traces[0]["tree"] and any(x["vs_ref_bvh"].values())}
    alike = all((x["vs_ref_bvh"]["hit_miss"], x["vs_ref_bvh"]["t_diff"])
                == (kernels.get(f"{x['layout']}/{x['set']}", {}).get("hit_miss", 0),
                    kernels.get(f"{x['layout']}/{x['set']}", {}).get("t_diff", 0)) for x in traces)
    return {"trees": per_tree, "best": best, "disagreements": disagreements, "ties": ties,
            "kernel_differences": kernels, "kernel_differences_alike": alike,
            "rays": {x["set"]: x["rays"] for x in lines if x["kind"] == "rays"}}


def fmt(x, digits=2) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown(report: dict) -> str:
    m = report["machine"]
    out = [
        "# Rays per second in tinybvh's kernels (`bench/bench_render.py`)",
        "",
        f"{m['cpu']}, {m['cores']} cores, shared (load {report['load_start']} at the start, "
        f"{report['load_end']} at the end); tinybvh v1.6.7 kernels, one thread; "
        f"{report['res']}² rays per set, min of {report['repeats']} rounds of thread CPU time; "
        f"from {report['utc']} UTC, one tracer run per mesh. Ours: `jaxbvh optimize MESH` (the default build, then the default "
        "optimizer) and `jaxbvh optimize MESH --builder sbvh`, written by `jaxbvh export --format "
        "tinybvh`; tinybvh's: `Build`, `Build` + `Optimize(200, extreme)`, `BuildHQ`, built by the tracer. "
        "Mrays/s are geometric means over the primary, random and bounce rays.",
        "",
        "## Our best tree / tinybvh's best tree, per layout",
        "",
        "| mesh | triangles | " + " | ".join(LAYOUT_CLASS[x] for x in LAYOUTS) + " |",
        "|---|---|" + "---|" * len(LAYOUTS),
    ]
    for r in report["meshes"]:
        tris = next(x["tris"] for x in r["lines"] if x["kind"] == "tree")
        cells = []
        for layout in LAYOUTS:
            b = r["summary"]["best"][layout]
            cells.append(f"**{fmt(b['ratio'], 3)}×** ({b['ours'] or '–'} / {b['tinybvh'] or '–'})")
        out.append(f"| {r['mesh']} | {tris:,} | " + " | ".join(cells) + " |")
    for r in report["meshes"]:
        s = r["summary"]
        out += ["", f"## {r['mesh']}", "",
                "| tree | SAH | SAH after CombineLeafs(4) | leaves (max) | depth | refs/tri | "
                + " | ".join(f"{LAYOUT_CLASS[x]} Mrays/s (vs best tinybvh)" for x in LAYOUTS) + " |",
                "|---|---|---|---|---|---|" + "---|" * len(LAYOUTS)]
        for name, t in s["trees"].items():
            cells = [f"{fmt(t[x]['geomean'])} ({fmt(t[x]['vs_tinybvh_best'], 3)})" for x in LAYOUTS]
            out.append(f"| {name} | {fmt(t['sah'], 3)} | {fmt(t['sah_after_combine4'], 3)} | {t['leaves']:,} ({t['max_leaf']}) "
                       f"| {t['depth']} | {fmt(t['refs_per_tri'], 3)} | " + " | ".join(cells) + " |")
        out += target_rows(r)
        ours = "; ".join(f"{k}: {v['builder']} → {v['method']}, SAH {fmt(v['sah_before'], 3)} → {fmt(v['sah_after'], 3)}"
                         + (f", target cost {fmt(v['target_cost_before'], 3)} → {fmt(v['target_cost_after'], 3)}"
                            if v.get("target_cost_after") is not None else "")
                         + " (jaxbvh's figures, tree frame, before rounding to world float32)" for k, v in r["ours"].items())
        out += ["", f"Ours: {ours}. Run at {r['started']['utc']} UTC, load {r['started']['load']} → {r['finished_load']}."]
        skipped = {n: t["skipped"] for n, t in s["trees"].items() if t["skipped"]}
        if skipped:
            out.append(f"Not traced: {json.dumps(skipped)}.")
        if s["disagreements"]:
            out.append(f"Hits that differ from tinybvh's `Build` tree in the same kernel: {len(s['disagreements'])} "
                       f"traces (in the JSON), e.g. {json.dumps(s['disagreements'][0])}.")
        else:
            traced = sum(r["summary"]["rays"].values()) * len(LAYOUTS)
            out.append("In every layout, every ray hit or missed on every tree as on tinybvh's `Build` tree in that "
                       f"layout, at the same t; ties (the same t on another triangle), of {traced:,} rays per tree: "
                       + ", ".join(f"{k} {v}" for k, v in s["ties"].items()) + ".")
        if s["kernel_differences"]:
            diff = s["kernel_differences"]
            parts = ", ".join(f"{k} {v['hit_miss']:,} / {v['t_diff']:,}" for k, v in diff.items()
                              if v["hit_miss"] or v["t_diff"])
            if parts:
                out.append("The kernels themselves disagree: against `BVH::Intersect` on tinybvh's `Build` tree, "
                           f"rays that hit/miss otherwise / hit at another t: {parts}"
                           + ("; the same counts on every tree" if s["kernel_differences_alike"] else
                              "; the counts differ between trees (see the JSON)") + ".")
    return "\n".join(out) + "\n"


def target_rows(r: dict) -> list[str]:
    """Per tree optimized for a target: its rays/s over ``ours_default``'s, per layout and
    ray set (one run: the same process, the same rays)."""
    trees = r["summary"]["trees"]
    named = [n for n in trees if n.startswith("ours_tinybvh") or n.startswith("ours_sah")]
    if not named or "ours_default" not in trees:
        return []
    out = ["", "Trees optimized for a target / `ours_default`, Mrays/s ratio per ray set (geomean):", "",
           "| tree | " + " | ".join(LAYOUT_CLASS[x] for x in LAYOUTS) + " |", "|---|" + "---|" * len(LAYOUTS)]
    for name in named:
        cells = []
        for layout in LAYOUTS:
            mine, base = trees[name][layout], trees["ours_default"][layout]
            sets = " / ".join(fmt(mine.get(x, float("nan")) / base.get(x, float("nan")), 3) for x in SETS)
            cells.append(f"{sets} (**{fmt(mine['geomean'] / base['geomean'], 3)}**)")
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    out.append(f"Ray sets in the order {' / '.join(SETS)}.")
    return out


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = report["meshes"]
    fig, axes = plt.subplots(1, len(meshes), figsize=(6 * len(meshes), 4.2), squeeze=False, constrained_layout=True)
    for ax, r in zip(axes[0], meshes):
        trees = list(r["summary"]["trees"])
        width = 0.8 / len(trees)
        for i, name in enumerate(trees):
            values = [r["summary"]["trees"][name][x]["geomean"] for x in LAYOUTS]
            hatch = None if name.startswith("ours") else "//"
            ax.bar([j + i * width for j in range(len(LAYOUTS))], values, width, label=name, hatch=hatch)
        ax.set_xticks([j + 0.4 - width / 2 for j in range(len(LAYOUTS))], [LAYOUT_CLASS[x] for x in LAYOUTS])
        ax.set_ylabel("Mrays/s (thread CPU time, geomean of 3 ray sets)")
        ax.set_title(r["mesh"])
        ax.legend(fontsize=8)
    fig.suptitle("tinybvh's kernels on our trees and on tinybvh's")
    from jaxbvh.files import atomic_write

    with atomic_write(path) as f:
        fig.savefig(f, dpi=100, format="png")
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", nargs="+", default=["legocar", "stanford-bunny"])
    parser.add_argument("--res", type=int, default=512, help="rays per set: RES^2 (default 512)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--ours", nargs="*", default=list(OURS), choices=list(OURS),
                        help="which of our default trees to make (default: all)")
    parser.add_argument("--targets", nargs="*", default=[],
                        help="also trees optimized for these cost targets (jaxbvh optimize --target NAME)")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "jaxbvh-bench-render")
    parser.add_argument("--reuse", action="store_true", help="reuse our trees already in --work")
    parser.add_argument("--name", default="bench_render")
    parser.add_argument("--append", action="store_true",
                        help="add the meshes to the saved JSON of --name (one run per mesh either way)")
    parser.add_argument("--peer-build", type=Path, default=Path(os.environ.get("PEER_BUILD", "/tmp/jaxbvh-peer")))
    parser.add_argument("--render-only", action="store_true",
                        help="only write the table and plot again from the saved JSON (no runs)")
    args = parser.parse_args(argv)
    if args.render_only:
        report = json.loads((RESULTS / f"{args.name}.json").read_text())
        for r in report["meshes"]:
            r["summary"] = summarize(r["lines"])
        write(report, args.name)
        plot(report, RESULTS / f"{args.name}.png")
        return 0
    if shutil.which("g++") is None and not (args.peer_build / "tinybvh_trace").exists():
        raise SystemExit("needs g++ to build ../shared/peer/tinybvh_trace")
    exe = tracer(args.peer_build)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor())
    report = {"machine": {"cpu": cpu, "cores": os.cpu_count(), "platform": platform.platform()},
              "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "load_start": load(), "res": args.res,
              "repeats": args.repeats, "seed": args.seed, "meshes": []}
    if args.append:
        report = json.loads((RESULTS / f"{args.name}.json").read_text())
        report["meshes"] = [r for r in report["meshes"] if r["mesh"] not in args.meshes]
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name in args.meshes:
        report["meshes"].append(one_mesh(name, args, exe, args.work))
        report["load_end"] = load()
        write(report, args.name)  # after every mesh: a run cut short keeps what it measured
        print(markdown(report), file=sys.stderr)
    plot(report, RESULTS / f"{args.name}.png")
    return 0


def write(report: dict, name: str) -> None:
    from jaxbvh.files import atomic_write

    with atomic_write(RESULTS / f"{name}.json", "w") as f:
        json.dump(report, f, indent=1)
    with atomic_write(RESULTS / f"{name}.md", "w") as f:
        f.write(markdown(report))


if __name__ == "__main__":
    sys.exit(main())
