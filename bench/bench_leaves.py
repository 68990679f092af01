"""Leaves of several primitives (issue 40): SAH per leaf limit, ours beside tinybvh.

    python bench/bench_leaves.py                                   # every mesh + the interior
    python bench/bench_leaves.py --inputs interior spot --limits 1 4 8 --pipeline-limits 1 4

Per input (the shared meshes of :data:`bench.bench_quality.INPUTS` and the procedural
interior of :mod:`bench.scenes`), each in its own child process:

* ours, for every ``--limits`` value L: the default builder (sweep) and the SBVH builder with
  ``max_leaf = L`` (SAH leaf test), the SAH of each build; for every ``--pipeline-limits``
  value, the default optimizer (``pipeline``, to convergence) on each of those builds, and
  its CPU seconds (this process, compiling included: the cache is whatever it is);
* tinybvh (``../shared/peer/``, one thread): ``Build`` (binned, its SAH leaf termination),
  ``Optimize(200)`` on it, ``BuildHQ`` (SBVH).

SAH: Ct = Ci = 1, normalised by the root's area (the harness's figure). Writes
``bench/results/leaves.json`` and ``leaves.md`` (``--tag`` adds a suffix).

``--combine BEFORE AFTER``: no run; ``leaves.md`` from two tagged runs, the code before a
change (``PYTHONPATH`` at the old checkout) and after it: the defaults' SAH before and after,
beside tinybvh, and the leaf-limit study of the run before.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_quality import INPUTS  # noqa: E402
from bench.scenes import PROCEDURAL, bench_mesh_path  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
PEER = ROOT.parent / "shared" / "peer"
RESULTS = ROOT / "bench" / "results"
DEFAULT_INPUTS = [n for n in INPUTS if INPUTS[n].startswith("meshes/")] + list(PROCEDURAL)


def mesh_path(name: str, work: Path) -> Path:
    return bench_mesh_path(name, work) if name in PROCEDURAL else DATA / INPUTS[name]


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def peer_rows(path: Path) -> dict:
    env = {**os.environ, "PY": sys.executable}
    done = subprocess.run([str(PEER / "compare.sh"), str(path), "1", "--methods", "binned,optimize,hq"],
                          capture_output=True, text=True, env=env, check=True)
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    return {r["method"]: {"sah": r["sah"], "ms": r["ms"], "max_leaf": r["max_leaf"]} for r in rows}


def one_input(name: str, args, work: Path) -> dict:
    import jaxbvh
    from jaxbvh.builders import SBVHConfig, SweepConfig, build_sbvh
    from jaxbvh.optimize import optimize

    path = mesh_path(name, work)
    mesh = jaxbvh.load_mesh(path)
    tri = mesh.local_triangles()
    lo, hi = mesh.local_boxes()
    row = {"input": name, "triangles": mesh.n_triangles, "ours": {}}
    for limit in args.limits:
        for builder in ("sweep", "sbvh"):
            t0 = cpu()
            if builder == "sbvh":
                tree = build_sbvh(tri, SBVHConfig(max_leaf=limit)).tree
            else:
                tree = jaxbvh.build(lo, hi, SweepConfig(max_leaf=limit))
            got = {"build_sah": float(jaxbvh.sah(tree)), "build_cpu_s": cpu() - t0}
            if limit in args.pipeline_limits:
                t0 = cpu()
                result = optimize(tree, "pipeline")
                got.update(pipeline_sah=float(result.sah), pipeline_cpu_s=cpu() - t0)
                # references mode for SBVH trees: a triangle may sit in several leaves
                problems = jaxbvh.check(result.tree, tri.min(1), tri.max(1), references=builder == "sbvh",
                                        triangles=tri if builder == "sbvh" else None)
                got.update(valid=not problems, problems=problems[:3])
            row["ours"][f"{builder}:{limit}"] = got
            print(name, builder, limit, got, file=sys.stderr, flush=True)
    row["tinybvh"] = peer_rows(path)
    return row


def markdown(rows: list[dict], meta: dict) -> str:
    limits, plimits = meta["args"]["limits"], meta["args"]["pipeline_limits"]
    lines = [f"# Leaves of several primitives: SAH per leaf limit ({meta['machine']}; load {meta['load']})", "",
             "SAH with Ct = Ci = 1, normalised by the root's area (`bench/bench_leaves.py`). L: `max_leaf`, "
             "SAH leaf test. `sweep` is the default builder; `+opt`: the default optimizer (`pipeline`, "
             "to convergence) on that build. tinybvh v1.6.7, one thread: Build (binned, SAH leaf "
             "termination), Optimize(200) on it, BuildHQ (SBVH).", "",
             "## Builds", "",
             "| input | tris | " + " | ".join(f"sweep L={L}" for L in limits) + " | "
             + " | ".join(f"sbvh L={L}" for L in limits) + " | tinybvh Build |",
             "|---|---|" + "---|" * (2 * len(limits) + 1)]
    for r in rows:
        o = r["ours"]
        lines.append(f"| {r['input']} | {r['triangles']:,} | "
                     + " | ".join(f"{o[f'sweep:{L}']['build_sah']:.3f}" for L in limits) + " | "
                     + " | ".join(f"{o[f'sbvh:{L}']['build_sah']:.3f}" for L in limits)
                     + f" | {r['tinybvh']['binned']['sah']:.3f} |")
    lines += ["", "## Optimized", "",
              "| input | " + " | ".join(f"sweep L={L} +opt" for L in plimits) + " | "
              + " | ".join(f"sbvh L={L} +opt" for L in plimits)
              + " | tinybvh Optimize(200) | tinybvh BuildHQ |",
              "|---|" + "---|" * (2 * len(plimits) + 2)]
    for r in rows:
        o = r["ours"]
        lines.append(f"| {r['input']} | "
                     + " | ".join(f"{o[f'sweep:{L}']['pipeline_sah']:.3f}" for L in plimits) + " | "
                     + " | ".join(f"{o[f'sbvh:{L}']['pipeline_sah']:.3f}" for L in plimits)
                     + f" | {r['tinybvh']['optimize']['sah']:.3f} | {r['tinybvh']['hq']['sah']:.3f} |")
    lines += ["", "## CPU seconds of our pipeline runs (compiling included, cache as found)", "",
              "| input | " + " | ".join(f"{b} L={L}" for b in ("sweep", "sbvh") for L in plimits) + " |",
              "|---|" + "---|" * (2 * len(plimits))]
    for r in rows:
        o = r["ours"]
        lines.append(f"| {r['input']} | " + " | ".join(f"{o[f'{b}:{L}']['pipeline_cpu_s']:.0f}"
                                                     for b in ("sweep", "sbvh") for L in plimits) + " |")
    return "\n".join(lines) + "\n"


def combined(before: dict, after: dict) -> str:
    """The before/after table of two runs (``--combine``): each run's default leaf limit is
    the smallest of its ``--pipeline-limits`` in the before run (the old default, 1) and
    the largest in the after run."""
    lb, la = min(before["args"]["pipeline_limits"]), max(after["args"]["pipeline_limits"])
    rows_a = {r["input"]: r for r in after["rows"]}
    lines = [f"# Leaves of several primitives (issue 40): the defaults before and after", "",
             f"Before: `max_leaf` {lb} (every builder's old default), the pipeline as it was. After: "
             f"`max_leaf` {la} (`jaxbvh.configs.DEFAULT_MAX_LEAF`) in the builders and the pipeline's "
             "final exact leaf merge. SAH with Ct = Ci = 1, normalised by the root's area; default = "
             "`build` (sweep) -> `optimize` (pipeline, to convergence); sbvh = `--builder sbvh` -> "
             "`optimize`. tinybvh v1.6.7, one thread, same triangles. Ratios < 1: ours lower. "
             f"Machine: {after['machine']}; load {before['load']} (before run), {after['load']} (after run): "
             "shared, busy (CPU seconds in the JSON files).", "",
             "| input | tris | default before | default after | sbvh before | sbvh after | tinybvh Build | "
             "tinybvh BuildHQ | tinybvh Optimize(200) | default after / Opt(200) | best after / min(HQ, Opt) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in before["rows"]:
        a = rows_a.get(r["input"])
        if a is None:
            continue
        o, n, t = r["ours"], a["ours"], a["tinybvh"]
        db, sb = o[f"sweep:{lb}"]["pipeline_sah"], o[f"sbvh:{lb}"]["pipeline_sah"]
        da, sa = n[f"sweep:{la}"]["pipeline_sah"], n[f"sbvh:{la}"]["pipeline_sah"]
        peer = min(t["hq"]["sah"], t["optimize"]["sah"])
        lines.append(f"| {r['input']} | {r['triangles']:,} | {db:.3f} | **{da:.3f}** | {sb:.3f} | **{sa:.3f}** | "
                     f"{t['binned']['sah']:.3f} | {t['hq']['sah']:.3f} | {t['optimize']['sah']:.3f} | "
                     f"{da / t['optimize']['sah']:.4f} | {min(da, sa) / peer:.4f} |")
    invalid = [(r["input"], k, v["problems"]) for run in (before, after) for r in run["rows"]
               for k, v in r["ours"].items() if v.get("problems")]
    if invalid:
        lines += ["", "Problems the check found:"] + [f"- {i}, {k}: {p}" for i, k, p in invalid]
    for run in (before, after):
        if run.get("note"):
            lines += ["", f"Note ({'before' if run is before else 'after'} run): {run['note']}"]
    study = markdown(before["rows"], before).split("\n", 1)[1]
    return "\n".join(lines) + "\n\n## The leaf-limit study (code before the change)\n" + study


def in_child(name: str, args) -> dict:
    """``one_input`` in a fresh process (each input compiles its own programs)."""
    cmd = [sys.executable, __file__, "--row", "--inputs", name, "--limits", *map(str, args.limits),
           "--pipeline-limits", *map(str, args.pipeline_limits)]
    done = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)  # progress on stderr
    lines = [line for line in done.stdout.splitlines() if line.startswith('{"input"')]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"bench_leaves on {name} failed (exit {done.returncode})")
    print(lines[-1], flush=True)
    return json.loads(lines[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", nargs="*", choices=list(INPUTS) + list(PROCEDURAL), default=DEFAULT_INPUTS)
    parser.add_argument("--limits", nargs="*", type=int, default=[1, 2, 4, 8, 16])
    parser.add_argument("--pipeline-limits", nargs="*", type=int, default=[1, 4, 8])
    parser.add_argument("--tag", default="")
    parser.add_argument("--rewrite", action="store_true", help="run nothing: rewrite the .md from the .json")
    parser.add_argument("--row", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--combine", nargs=2, metavar=("BEFORE", "AFTER"),
                        help="run nothing: leaves.md from leaves_BEFORE.json and leaves_AFTER.json")
    args = parser.parse_args(argv)
    if args.combine:
        runs = [json.loads((RESULTS / f"leaves_{tag}.json").read_text()) for tag in args.combine]
        (RESULTS / "leaves.md").write_text(combined(*runs))
        return 0
    if not set(args.pipeline_limits) <= set(args.limits):
        parser.error("--pipeline-limits must be among --limits")
    stem = RESULTS / ("leaves" + (f"_{args.tag}" if args.tag else ""))
    if args.rewrite:
        saved = json.loads(stem.with_suffix(".json").read_text())
        stem.with_suffix(".md").write_text(markdown(saved["rows"], saved))
        return 0
    if args.row:
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(one_input(args.inputs[0], args, Path(tmp))), flush=True)
        return 0
    started = time.time()
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    rows = [in_child(name, args) for name in args.inputs]
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "load": load + " at start",
            "args": {k: v for k, v in vars(args).items() if k not in ("row", "rewrite")},
            "wall_s": time.time() - started, "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown(rows, meta))
    print(markdown(rows, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
