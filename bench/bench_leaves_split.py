"""Leaves split before the pipeline (issue 40): final SAH with and without, beside tinybvh.

    python bench/bench_leaves_split.py                          # every mesh + the interior
    python bench/bench_leaves_split.py --inputs interior spot

Per input (the shared meshes of :data:`bench.bench_quality.INPUTS` and the procedural
interior of :mod:`bench.scenes`), each in its own child process, for the default builder
(sweep) and the SBVH builder at their default leaf limit:

* ``plain``: the default optimizer (``pipeline`` to convergence, its final exact leaf merge);
* ``split``: the same with the primitives' boxes given (``pipeline(tree, prims=...)``): every
  leaf first split into one-primitive leaves (:mod:`jaxbvh.optimize.split`);
* ``rebuilt``: the builder at ``max_leaf`` 1, then the plain pipeline (the final merge at
  the default limit): the alternative that needs no split;
* tinybvh (``../shared/peer/``, one thread): ``Build``, ``Optimize(200)``, ``BuildHQ``.

The three runs of ours alternate their order between the builders (each input's first run
pays the compiles its shapes need; the cache is as found: CPU seconds of this process).
SAH: Ct = Ci = 1, normalised by the root's area. Every tree is checked (references mode for
SBVH). Writes ``bench/results/leaves_split.json``; ``--markdown`` prints its table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_leaves import DEFAULT_INPUTS, cpu, mesh_path, peer_rows  # noqa: E402
from bench.bench_quality import INPUTS  # noqa: E402
from bench.scenes import PROCEDURAL  # noqa: E402

RESULTS = ROOT / "bench" / "results"
RUNS = ("plain", "split", "rebuilt")


def load() -> float:
    return round(os.getloadavg()[0], 1)


def one_input(name: str, work: Path) -> dict:
    import jaxbvh
    from jaxbvh.builders import SBVHConfig, SweepConfig, build_sbvh
    from jaxbvh.optimize import optimize, pipeline

    path = mesh_path(name, work)
    mesh = jaxbvh.load_mesh(path)
    tri = mesh.local_triangles()
    lo, hi = mesh.local_boxes()
    row = {"input": name, "triangles": mesh.n_triangles, "ours": {}}
    for order, builder in enumerate(("sweep", "sbvh")):
        sbvh = builder == "sbvh"

        def build(**leaf):
            if sbvh:
                return build_sbvh(tri, SBVHConfig(**leaf)).tree
            return jaxbvh.build(lo, hi, SweepConfig(**leaf))

        tree = build()
        # an SBVH leaf holds clipped references: their whole triangles' boxes, clipped by the split
        prims = (tri.min(1), tri.max(1)) if sbvh else (lo, hi)
        got = {"build_sah": float(jaxbvh.sah(tree))}
        runs = {
            "plain": lambda: optimize(tree, "pipeline"),
            "split": lambda: pipeline.pipeline(tree, prims=prims),
            "rebuilt": lambda: optimize(build(max_leaf=1), "pipeline"),
        }
        for run in (RUNS if order == 0 else RUNS[::-1]):
            t0, l0 = cpu(), load()
            result = runs[run]()
            seconds = cpu() - t0
            problems = jaxbvh.check(result.tree, tri.min(1), tri.max(1), references=sbvh,
                                    triangles=tri if sbvh else None)
            got[run] = {"sah": float(result.sah), "cpu_s": seconds, "steps": int(result.steps),
                        "load": [l0, load()], "valid": not problems, "problems": problems[:3]}
            print(name, builder, run, got[run], file=sys.stderr, flush=True)
        row["ours"][builder] = got
    row["tinybvh"] = peer_rows(path)
    return row


def in_child(name: str) -> dict:
    """``one_input`` in a fresh process."""
    done = subprocess.run([sys.executable, __file__, "--row", name], stdout=subprocess.PIPE, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith('{"input"')]
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"bench_leaves_split on {name} failed (exit {done.returncode})")
    print(lines[-1], flush=True)
    return json.loads(lines[-1])


def markdown(meta: dict) -> str:
    lines = ["| input | tris | sweep+opt | sweep split+opt | sweep L=1+opt | sbvh+opt | sbvh split+opt | "
             "sbvh L=1+opt | tinybvh Build | BuildHQ | Optimize(200) | default split / Opt(200) | "
             "best split / min(HQ, Opt) | CPU s sweep plain / split | CPU s sbvh plain / split |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in meta["rows"]:
        s, b, t = r["ours"]["sweep"], r["ours"]["sbvh"], r["tinybvh"]
        peer = min(t["hq"]["sah"], t["optimize"]["sah"])
        best = min(s["split"]["sah"], b["split"]["sah"])
        def pair(x):  # the lower of plain and split in bold
            p, q = x["plain"]["sah"], x["split"]["sah"]
            return (f"**{p:.3f}**" if p < q else f"{p:.3f}") + " | " + (f"**{q:.3f}**" if q < p else f"{q:.3f}")

        lines.append(f"| {r['input']} | {r['triangles']:,} | {pair(s)} | "
                     f"{s['rebuilt']['sah']:.3f} | {pair(b)} | "
                     f"{b['rebuilt']['sah']:.3f} | {t['binned']['sah']:.3f} | {t['hq']['sah']:.3f} | "
                     f"{t['optimize']['sah']:.3f} | {s['split']['sah'] / t['optimize']['sah']:.4f} | "
                     f"{best / peer:.4f} | {s['plain']['cpu_s']:.0f} / {s['split']['cpu_s']:.0f} | "
                     f"{b['plain']['cpu_s']:.0f} / {b['split']['cpu_s']:.0f} |")
    bad = [(r["input"], k, run, v[run]["problems"]) for r in meta["rows"] for k, v in r["ours"].items()
           for run in RUNS if not v[run]["valid"]]
    if bad:
        lines += ["", "Invalid trees:"] + [f"- {i} {k} {run}: {p}" for i, k, run, p in bad]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", nargs="*", choices=list(INPUTS) + list(PROCEDURAL), default=DEFAULT_INPUTS)
    parser.add_argument("--row", help=argparse.SUPPRESS)
    parser.add_argument("--markdown", action="store_true", help="run nothing: print the table of the JSON")
    args = parser.parse_args(argv)
    out = RESULTS / "leaves_split.json"
    if args.markdown:
        print(markdown(json.loads(out.read_text())))
        return 0
    if args.row:
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(one_input(args.row, Path(tmp))), flush=True)
        return 0
    started = time.time()
    meta = {"date": datetime.now(timezone.utc).isoformat(timespec="minutes"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores", "load_start": os.getloadavg(),
            "rows": []}
    from jaxbvh.files import atomic_write

    for name in args.inputs:
        meta["rows"].append(in_child(name))
        meta["wall_s"] = time.time() - started
        with atomic_write(out, "w") as f:  # what has run, if the run is cut
            f.write(json.dumps(meta, indent=1) + "\n")
    print(markdown(meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
