"""Our best tree beside tinybvh's best, on every shared mesh and scene (issue 19's quality target).

    python bench/bench_best.py                       # every input of bench_quality, 10 s per pipeline
    python bench/bench_best.py --inputs legocar cow --budget 5 --rays 20000

Per input (the meshes and the drone scene of :data:`bench.bench_quality.INPUTS`):

* ours: the SBVH build (``max_leaf`` 16, SAH leaf test, as ``bench_sbvh.py``), the
  pipeline run on it, and the pipeline run on our binned build (same leaf setting), each
  pipeline compiled first, then cut at ``--budget`` seconds; *best* is the lowest SAH of the three. Every
  tree is checked (references mode for the SBVH ones: every triangle covered).
* tinybvh (``../shared/peer/``, one thread): ``BuildHQ`` (SBVH) and ``Optimize(200,
  extreme)`` on its binned tree; their trees are dumped, loaded and checked too.
* rays: ``jaxbvh trace`` (closest hit, random and bounce rays) on our best tree and on
  both of tinybvh's: box and primitive tests per ray.

Each input runs in its own child process (:func:`in_child`). SAH: Ct = Ci = 1,
normalised by the root's area (the harness's figure). Writes
``bench/results/best.json`` and ``best.md``. Times are not the point here (see
``bench_sbvh.py`` and ``bench_quality.py``); the pipeline's budget is.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from bench.bench_quality import INPUTS  # noqa: E402
from bench.bench_sbvh import trace  # noqa: E402
from bench.curves import warm_up  # noqa: E402
from jaxbvh.builders import BinnedConfig, SBVHConfig, build_sbvh  # noqa: E402
from jaxbvh.tree.interchange import compact  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
PEER = ROOT.parent / "shared" / "peer"
RESULTS = ROOT / "bench" / "results"
KINDS = ("random", "bounce")


def peer_trees(mesh_path: Path, prefix: str) -> dict:
    """tinybvh's ``hq`` and ``optimize`` rows (the harness's JSON) with their trees as .npz."""
    env = {**os.environ, "PY": sys.executable}
    done = subprocess.run([str(PEER / "compare.sh"), str(mesh_path), "1", "--methods", "optimize,hq",
                           "--out", prefix], capture_output=True, text=True, env=env, check=True)
    rows = {}
    for line in done.stdout.splitlines():
        if line.startswith("{"):
            row = json.loads(line)
            rows[row["method"]] = row
    for method in ("hq", "optimize"):
        npz = f"{prefix}_{method}.npz"
        subprocess.run([sys.executable, str(PEER / "to_npz.py"), f"{prefix}.{method}.bin", npz],
                       check=True, capture_output=True)
        rows[method]["npz"] = npz
    return rows


def checked(tree, triangles: np.ndarray, references: bool) -> list:
    """The check's problems (empty: valid); references mode also checks every triangle is covered."""
    return jaxbvh.check(tree, triangles.min(1), triangles.max(1), references=references,
                        triangles=triangles if references else None)


def one_input(name: str, args, work: Path) -> dict:
    path = DATA / INPUTS[name]
    mesh = jaxbvh.load_mesh(path)
    tri = mesh.local_triangles()
    lo, hi = mesh.local_boxes()
    row = {"input": name, "triangles": mesh.n_triangles}
    sbvh = build_sbvh(tri, SBVHConfig(max_leaf=args.max_leaf)).tree
    binned = jaxbvh.build(lo, hi, BinnedConfig(max_leaf=args.max_leaf))
    def pipeline(tree):  # compiled first, so the budget is the warm run's
        warm_up(tree, "pipeline")
        return jaxbvh.optimize.optimize(tree, "pipeline", time_budget=args.budget).tree

    ours = {"sbvh": (sbvh, True), "sbvh+pipeline": (pipeline(sbvh), True),
            "binned+pipeline": (pipeline(binned), False)}
    row["ours"] = {}
    for label, (tree, references) in ours.items():
        problems = checked(tree, tri, references)
        row["ours"][label] = {"sah": float(jaxbvh.sah(tree)), "valid": not problems, "problems": problems[:3]}
    best = min(row["ours"], key=lambda k: row["ours"][k]["sah"])
    row["best"] = best
    best_path = str(work / f"{name}_best.npz")
    jaxbvh.save(best_path, compact(ours[best][0]), frame=mesh.frame)

    tiny = peer_trees(path, str(work / name))
    world = mesh.triangles.astype(np.float32)
    row["tinybvh"] = {}
    for method in ("hq", "optimize"):
        tree, _ = jaxbvh.load(tiny[method]["npz"])
        problems = checked(tree, world, method == "hq")
        row["tinybvh"][method] = {"sah": tiny[method]["sah"], "ms": tiny[method]["ms"],
                                  "valid": not problems, "problems": problems[:3]}
    sah = row["ours"][best]["sah"]
    row["best_over"] = {m: sah / row["tinybvh"][m]["sah"] for m in ("hq", "optimize")}
    row["rays"] = {kind: {"ours": trace(best_path, path, kind, args.rays),
                          "tinybvh_hq": trace(tiny["hq"]["npz"], path, kind, args.rays),
                          "tinybvh_optimize": trace(tiny["optimize"]["npz"], path, kind, args.rays)}
                   for kind in KINDS}
    return row


def tests_per_ray(r: dict) -> float | None:
    return None if "error" in r else r["box_tests"] + r["prim_tests"]


def markdown(rows: list[dict], args) -> str:
    lines = [f"# Our best tree beside tinybvh's best ({platform.machine()}; max_leaf {args.max_leaf}; "
             f"pipeline budget {args.budget:g} s; {args.rays:,} rays per kind)", "",
             "SAH with Ct = Ci = 1, normalised by the root's area. Best: the lowest SAH of our SBVH build, "
             "the pipeline on it and the pipeline on our binned build. Tests per ray: box + primitive "
             "tests, closest hit (`jaxbvh trace`).", "",
             "| input | tris | SAH sbvh | sbvh+pipeline | binned+pipeline | best | tinybvh BuildHQ | "
             "tinybvh Optimize(200) | best / HQ | best / Optimize | ours valid | tinybvh's valid |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o, t = r["ours"], r["tinybvh"]
        valid = (all(v["valid"] for v in o.values()), all(v["valid"] for v in t.values()))
        lines.append(f"| {r['input']} | {r['triangles']:,} | {o['sbvh']['sah']:.3f} | {o['sbvh+pipeline']['sah']:.3f} | "
                     f"{o['binned+pipeline']['sah']:.3f} | {r['best']} | {t['hq']['sah']:.3f} | "
                     f"{t['optimize']['sah']:.3f} | {r['best_over']['hq']:.4f} | {r['best_over']['optimize']:.4f} | "
                     f"{valid[0]} | {valid[1]} |")
    lines += ["", "| input | rays | tests per ray: ours (best) | tinybvh BuildHQ | tinybvh Optimize(200) |",
              "|---|---|---|---|---|"]
    for r in rows:
        for kind, got in r["rays"].items():
            cells = [tests_per_ray(got[k]) for k in ("ours", "tinybvh_hq", "tinybvh_optimize")]
            lines.append(f"| {r['input']} | {kind} | "
                         + " | ".join("error" if c is None else f"{c:.2f}" for c in cells) + " |")
    problems = [(r["input"], side, k, v["problems"]) for r in rows for side in ("ours", "tinybvh")
                for k, v in r[side].items() if v["problems"]]
    if problems:
        lines += ["", "Problems the check found:"]
        lines += [f"- {name}, {side} {k}: {p}" for name, side, k, p in problems]
    return "\n".join(lines) + "\n"


def in_child(name: str, args) -> dict:
    """``one_input(name)`` in a child process: one process over all eight inputs ran out of
    LLVM section memory on the eighth (every input compiles its own programs, and the
    process's memory maps run out), so each input gets a fresh process."""
    done = subprocess.run([sys.executable, __file__, "--row", "--inputs", name, "--budget", str(args.budget),
                           "--max-leaf", str(args.max_leaf), "--rays", str(args.rays)],
                          capture_output=True, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith('{"input"')]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"bench_best on {name} failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
    print(lines[-1], flush=True)
    return json.loads(lines[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", nargs="*", choices=list(INPUTS), default=list(INPUTS))
    parser.add_argument("--budget", type=float, default=10.0, help="seconds per pipeline run (warm: compiled first)")
    parser.add_argument("--max-leaf", type=int, default=16)
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument("--tag", default="", help="suffix of the result files (best_<tag>.*)")
    parser.add_argument("--rewrite", action="store_true", help="run nothing: rewrite best.md from best.json")
    parser.add_argument("--row", action="store_true", help=argparse.SUPPRESS)  # in_child's: one input, print its row
    args = parser.parse_args(argv)
    if args.row and len(args.inputs) != 1:
        parser.error("--row takes exactly one input")
    if args.rewrite:
        stem = RESULTS / ("best" + (f"_{args.tag}" if args.tag else ""))
        saved = json.loads(stem.with_suffix(".json").read_text())
        stem.with_suffix(".md").write_text(markdown(saved["rows"], argparse.Namespace(**saved["args"])))
        return 0
    if args.row:  # one input in this process: its row as one JSON line, nothing written
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(one_input(args.inputs[0], args, Path(tmp))), flush=True)
        return 0
    rows = [in_child(name, args) for name in args.inputs]
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / ("best" + (f"_{args.tag}" if args.tag else ""))
    stem.with_suffix(".json").write_text(json.dumps({"machine": platform.machine(), "args": vars(args),
                                                     "rows": rows}, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown(rows, args))
    print(markdown(rows, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
