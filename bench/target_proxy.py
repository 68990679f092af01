"""Does the binary SAH a target gives the optimizers track that target's cost? (issue 40)

    python bench/target_proxy.py                         # spot, tinybvh-bvh8
    python bench/target_proxy.py --mesh legocar --target tinybvh-bvh4 --cts 0.5 1 2 3

For a wide target the optimizers lower a *binary* SAH (the target's ``ct``, ``ci``,
``max_leaf``), while the target's cost is the SAH of the wide tree the layout traces
(:func:`jaxbvh.tree.targets.target_cost`). This builds the mesh once per ``ct`` (the
default builder with that ``ct`` and the target's ``ci`` and leaf limit), runs the default
pipeline with the same constants, and reports the target's cost of each result beside its
binary SAH: the ``ct`` whose tree has the lowest target cost is the proxy that serves the
target best. Writes ``bench/results/target_proxy.{json,md}`` (``--name``).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.bench_render import DATA, INPUTS, RESULTS, load  # noqa: E402


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None) -> int:
    import jaxbvh
    from jaxbvh.files import atomic_write
    from jaxbvh.io import load_mesh
    from jaxbvh.optimize import optimize
    from jaxbvh.tree import targets

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mesh", default="spot")
    parser.add_argument("--target", default="tinybvh-bvh8")
    parser.add_argument("--cts", nargs="+", type=float, default=None,
                        help="the optimizers' ct values to try (default: 0.5, 1, the target's ct, 3)")
    parser.add_argument("--name", default="target_proxy")
    args = parser.parse_args(argv)
    target = targets.get(args.target)
    cts = args.cts or sorted({0.5, 1.0, target.ct, 3.0})
    path = Path(INPUTS.get(args.mesh, args.mesh))
    path = path if path.is_absolute() or path.exists() else DATA / path
    lo, hi = load_mesh(path).local_boxes()
    rows = []
    started = load()
    for ct in cts:
        start = cpu()
        costs = targets.costs(target, ct=ct)
        tree = jaxbvh.build(lo, hi, **costs)
        result = optimize(tree, "pipeline", **costs)
        rows.append({"ct": ct, "binary_sah_at_ct": float(result.sah),
                     "sah_1_1": targets.target_cost(result.tree, "sah"),
                     "target_cost": targets.target_cost(result.tree, target),
                     "target_cost_of_build": targets.target_cost(tree, target),
                     "leaves": int((result.tree.prim_count > 0).sum()), "cpu_seconds": cpu() - start, "load": load()})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    best = min(rows, key=lambda r: r["target_cost"])
    report = {"mesh": args.mesh, "target": dataclass_dict(target), "load_start": started, "load_end": load(),
              "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "rows": rows, "best_ct": best["ct"]}
    lines = [f"# Which binary Ct serves `{args.target}`? (`bench/target_proxy.py`)", "",
             f"{args.mesh}; the default build and pipeline with Ct as below and the target's Ci "
             f"{target.ci:g} and leaf limit {target.max_leaf}; the target's cost (the SAH of the {target.width}-wide "
             f"tree after its leaf merge, node price {target.node_ct:g}) of each result. Load {started} → {load()}, "
             f"{report['utc']} UTC.", "",
             "| optimizers' Ct | target cost of the build | **target cost after the pipeline** | SAH (Ct = Ci = 1) "
             "| leaves | CPU s |", "|---|---|---|---|---|---|"]
    for r in rows:
        mark = " (the target's)" if r["ct"] == target.ct else ""
        lines.append(f"| {r['ct']:g}{mark} | {r['target_cost_of_build']:.3f} | **{r['target_cost']:.3f}** "
                     f"| {r['sah_1_1']:.3f} | {r['leaves']:,} | {r['cpu_seconds']:.0f} |")
    lines += ["", f"Lowest target cost at Ct = {best['ct']:g}."]
    RESULTS.mkdir(parents=True, exist_ok=True)
    with atomic_write(RESULTS / f"{args.name}.json", "w") as f:
        json.dump(report, f, indent=1)
    with atomic_write(RESULTS / f"{args.name}.md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines), file=sys.stderr)
    return 0


def dataclass_dict(x) -> dict:
    import dataclasses

    return dataclasses.asdict(x)


if __name__ == "__main__":
    sys.exit(main())
