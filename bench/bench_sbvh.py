"""Spatial splits: our SBVH against our binned builder and tinybvh's ``BuildHQ``, same triangles.

    python bench/bench_sbvh.py [--meshes legocar,fandisk,rocker-arm] [--repeat 3] [--rays 20000]
                               [--max-leaf 16] [--out bench/results]

Per mesh, in one process (compiled once, the first call timed apart, then binned and
sbvh builds taken in turn, so that their ratio compares builds under the same load;
wall and process CPU time, CPU time being the steadier measure on a shared machine):

* ours: ``binned`` and ``sbvh`` (same ``bins``, ``max_leaf``, SAH leaf test), warm build
  time (min of ``--repeat``), SAH (Ct = Ci = 1, normalised by the root's area),
  references per triangle, spatial splits, whether the reference slots ran out, and
  the references-mode check (every triangle covered by its leaf boxes);
* tinybvh v1.6.7 (``../shared/peer/compare.sh``, one thread, min of ``--repeat``):
  ``binned`` and ``hq`` (SBVH) build time and SAH; its ``hq`` tree dumped, loaded through
  the interchange form and checked by the same references-mode check;
* rays: ``jaxbvh trace`` (closest hit, random and bounce rays) on our sbvh tree and on
  tinybvh's ``hq`` tree: box and primitive tests per ray.

Writes ``sbvh.json`` and ``sbvh.md`` to ``--out``.
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
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
MESHES = {"legocar": "meshes/legocar.obj", "fandisk": "meshes/fandisk.obj", "rocker-arm": "meshes/rocker-arm.obj",
          "bunny": "meshes/stanford-bunny.obj", "drone": "scenes/drone/scene.gltf"}


def timed(calls: dict, repeat: int) -> dict:
    """``{name: (result, first_wall, best_wall, best_cpu)}`` of each call: the first
    calls (they compile) apart, then ``repeat`` rounds that take the calls in turn, so
    that each ratio compares builds run under the same load."""
    import jax

    out, first = {}, {}
    for name, call in calls.items():
        start = time.perf_counter()
        out[name] = jax.block_until_ready(call())
        first[name] = time.perf_counter() - start
    walls, cpus = {name: [] for name in calls}, {name: [] for name in calls}
    for _ in range(repeat):
        for name, call in calls.items():
            w, c = time.perf_counter(), time.process_time()
            out[name] = jax.block_until_ready(call())
            walls[name].append(time.perf_counter() - w)
            cpus[name].append(time.process_time() - c)
    return {name: (out[name], first[name], min(walls[name]), min(cpus[name])) for name in calls}


def peer(mesh_path: Path, repeat: int, prefix: str) -> dict:
    """tinybvh's binned and hq builds (JSON lines of compare.sh) and its hq tree as .npz."""
    run = subprocess.run([str(SHARED / "peer" / "compare.sh"), str(mesh_path), str(repeat), "--methods",
                          "binned,hq", "--out", prefix], capture_output=True, text=True, check=True)
    rows = {}
    for line in run.stdout.splitlines():
        if line.startswith("{"):
            row = json.loads(line)
            rows[row["method"]] = row
    subprocess.run([sys.executable, str(SHARED / "peer" / "to_npz.py"), f"{prefix}.hq.bin", f"{prefix}_hq.npz"],
                   check=True, capture_output=True)
    rows["hq_npz"] = f"{prefix}_hq.npz"
    return rows


def trace(tree_path: str, mesh_path: Path, kind: str, rays: int) -> dict:
    """Box and primitive tests per ray of ``jaxbvh trace`` (closest hit)."""
    code = "import sys; from jaxbvh.cli import main; sys.exit(main())"
    run = subprocess.run([sys.executable, "-c", code, "trace", tree_path, str(mesh_path), "--rays", str(rays),
                          "--kind", kind, "--json"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    if run.returncode:
        return {"error": (run.stderr.strip().splitlines() or ["?"])[-1]}
    out = json.loads(run.stdout.strip().splitlines()[-1])
    return {k: round(out[k], 3) for k in ("box_tests", "prim_tests", "sah") if k in out}


def one_mesh(name: str, args, work: Path) -> dict:
    import jaxbvh
    from jaxbvh.builders import BinnedConfig, SBVHConfig, build_sbvh

    mesh_path = SHARED / "data" / MESHES[name]
    mesh = jaxbvh.load_mesh(mesh_path)
    tri = mesh.local_triangles()
    lo, hi = mesh.local_boxes()
    row = {"mesh": name, "triangles": mesh.n_triangles}
    config = SBVHConfig(max_leaf=args.max_leaf)
    times = timed({"binned": lambda: jaxbvh.build(lo, hi, BinnedConfig(max_leaf=args.max_leaf)),
                   "sbvh": lambda: build_sbvh(tri, config)}, args.repeat)
    binned, first, wall, cpu = times["binned"]
    row["binned"] = {"sah": float(jaxbvh.sah(binned)), "first_s": first, "wall_s": wall, "cpu_s": cpu}
    built, first, wall, cpu = times["sbvh"]
    problems = jaxbvh.check(built.tree, tri.min(1), tri.max(1), references=True, triangles=tri)
    row["sbvh"] = {"sah": float(jaxbvh.sah(built.tree)), "first_s": first, "wall_s": wall, "cpu_s": cpu,
                   "references_per_triangle": int(built.references) / mesh.n_triangles,
                   "spatial_splits": int(built.spatial_splits), "out_of_capacity": bool(built.out_of_capacity),
                   "problems": problems[:3], "valid": not problems}
    row["sbvh_over_binned"] = {"wall": row["sbvh"]["wall_s"] / row["binned"]["wall_s"],
                               "cpu": row["sbvh"]["cpu_s"] / row["binned"]["cpu_s"]}
    ours = str(work / f"{name}_sbvh.npz")
    jaxbvh.save(ours, jaxbvh.tree.interchange.compact(built.tree), frame=mesh.frame)
    if not args.no_peer:
        tiny = peer(mesh_path, args.repeat, str(work / name))
        hq, _ = jaxbvh.load(tiny["hq_npz"])
        world = mesh.triangles.astype(np.float32)
        hq_problems = jaxbvh.check(hq, world.min(1), world.max(1), references=True, triangles=world)
        row["tinybvh"] = {"binned": {k: tiny["binned"][k] for k in ("sah", "ms")},
                          "hq": {"sah": tiny["hq"]["sah"], "ms": tiny["hq"]["ms"],
                                 "references_per_triangle": tiny["hq"]["refs"] / tiny["hq"]["tris"],
                                 "problems": hq_problems[:3], "valid": not hq_problems}}
        row["sbvh_sah_over_hq"] = row["sbvh"]["sah"] / tiny["hq"]["sah"]
        row["rays"] = {kind: {"sbvh": trace(ours, mesh_path, kind, args.rays),
                              "tinybvh_hq": trace(tiny["hq_npz"], mesh_path, kind, args.rays)}
                       for kind in ("random", "bounce")}
    return row


def markdown(rows, args) -> str:
    lines = [f"# SBVH vs binned vs tinybvh BuildHQ ({platform.machine()}, {platform.processor() or 'cpu'}; "
             f"max_leaf {args.max_leaf}; min of {args.repeat} warm runs, binned and sbvh in turn)", "",
             "Shared 2-core machine under load: compare times as ratios taken in the same run; "
             "CPU time (process) is steadier than wall time.", "",
             "| mesh | tris | SAH binned | SAH sbvh | SAH tinybvh hq | sbvh / hq SAH | refs/tri sbvh | refs/tri hq "
             "| sbvh valid | hq valid | build sbvh / binned (wall, cpu) | sbvh s | sbvh first call s (compiles) "
             "| tinybvh hq ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r.get("tinybvh", {}).get("hq", {})
        lines.append(
            f"| {r['mesh']} | {r['triangles']} | {r['binned']['sah']:.3f} | {r['sbvh']['sah']:.3f} | "
            f"{t.get('sah', float('nan')):.3f} | {r.get('sbvh_sah_over_hq', float('nan')):.4f} | "
            f"{r['sbvh']['references_per_triangle']:.3f} | {t.get('references_per_triangle', float('nan')):.3f} | "
            f"{r['sbvh']['valid']} | {t.get('valid', '-')} | {r['sbvh_over_binned']['wall']:.1f}x, "
            f"{r['sbvh_over_binned']['cpu']:.1f}x | {r['sbvh']['wall_s']:.2f} | {r['sbvh']['first_s']:.1f} | "
            f"{t.get('ms', float('nan')):.0f} |")
    lines += ["", "Rays (closest hit, `jaxbvh trace`): box + primitive tests per ray, ours / tinybvh hq", ""]
    for r in rows:
        for kind, pair in r.get("rays", {}).items():
            lines.append(f"- {r['mesh']} {kind}: sbvh {json.dumps(pair['sbvh'])}; hq {json.dumps(pair['tinybvh_hq'])}")
    for r in rows:
        t = r.get("tinybvh", {}).get("hq", {})
        if t.get("problems"):
            lines.append(f"- tinybvh hq on {r['mesh']}: {t['problems']}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="legocar,fandisk,rocker-arm")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--rays", type=int, default=20000)
    parser.add_argument("--max-leaf", type=int, default=16)
    parser.add_argument("--no-peer", action="store_true", help="ours only (no C++ build needed)")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_sbvh_") as work:
        for name in args.meshes.split(","):
            rows.append(one_mesh(name, args, Path(work)))
            print(json.dumps(rows[-1]), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sbvh.json").write_text(json.dumps({"max_leaf": args.max_leaf, "repeat": args.repeat,
                                                "rays": args.rays, "rows": rows}, indent=1))
    (out / "sbvh.md").write_text(markdown(rows, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
