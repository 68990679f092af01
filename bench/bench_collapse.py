"""Adaptive collapsing (Susano Pinto 2010): DP time vs K and vs nodes, and the paper's comparison.

    python bench/bench_collapse.py            # every shared mesh, K sweep, node sweep, NumPy reference
    python bench/bench_collapse.py --big      # the DP on the 1.05M-triangle input (appended)
    python bench/bench_collapse.py --meshes legocar bunny --rays 5000

Sections (all on binary trees built with ``jaxbvh.build`` sweep SAH, one primitive per
leaf as in the paper, unless said otherwise):

* **comparison** — for every shared mesh: tree size, R_cost with T(k) = k and with
  T(k) = ceil(k / 4), and box tests per ray (all-hits and closest-hit queries over
  ``--rays`` bounce rays, the paper's secondary rays, and all-hits over as many random
  lines through the root box, the cost model's rays; :mod:`jaxbvh.rays`) for the binary
  tree, greedy pushup (no width limit), QBVH and the DP with K = 8 and K = 16.
* **K sweep** — DP time (warm, compile apart) and R_cost for K = 2 ... 16 on the bunny.
* **node sweep** — DP time with K = 8 against the number of nodes (linear growth).
* **reference** — the NumPy twin (:mod:`jaxbvh.wide.collapse_reference`) against the JAX DP
  on the tinybvh legocar tree (and the bunny): time and whether the trees are identical.
* **leaves** (beyond the paper) — the DP allowed to merge subtrees into leaves of up to
  P primitives: R_cost + leaf cost against the binary tree.
* ``--big`` — the 1.05M-triangle input of ``bench_rotate.py --big`` (15 bunnies + walls):
  DP (K = 8) time, compile time, greedy and QBVH times, and the NumPy reference in a
  separate process abandoned after ``--ref-timeout`` seconds; and the DP time on the same
  scene with 1, 2, 4 and 8 bunnies (node sweep).

Times are wall seconds on this machine, median of ``--repeat`` warm runs; the first call
is timed apart as compile (+ one run). Writes ``bench/results/collapse.json`` and ``.md``.
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
from jaxbvh import rays
from jaxbvh.wide import collapse  # noqa: E402
from jaxbvh.wide import collapse_reference as ref  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
MESHES = {"spot": "meshes/spot.obj", "teapot": "meshes/teapot.obj", "cow": "meshes/cow.obj",
          "fandisk": "meshes/fandisk.obj", "rocker-arm": "meshes/rocker-arm.obj",
          "legocar": "meshes/legocar.obj", "drone": "scenes/drone/scene.gltf",
          "bunny": "meshes/stanford-bunny.obj"}
SIMD4 = collapse.node_test_cost(4)


FASTEST = {}  # id(result) -> fastest warm run of the last timed() call that made it


def timed(fn, repeat):
    """``(result, warm seconds (median), compile seconds (first call minus warm))``.

    The fastest warm run is kept in ``FASTEST[id(result)]``: on a shared CPU the
    median carries the other jobs' load, the fastest run less of it.
    """
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    warm = statistics.median(times) if times else first
    FASTEST[id(out)] = min(times) if times else first
    return out, warm, max(first - warm, 0.0)


def load(name):
    from jaxbvh.io import load_mesh

    mesh = load_mesh(DATA / MESHES[name])
    lo, hi = mesh.local_boxes()
    tree = jaxbvh.to_numpy(jax.block_until_ready(jaxbvh.build(lo, hi)))
    return tree, mesh.local_triangles()


def methods():
    return {"binary": None,
            "greedy": lambda t: collapse.greedy(t),
            "qbvh": lambda t: collapse.qbvh(t),
            "dp K=8": lambda t: collapse.optimal(t, max_children=8),
            "dp K=16": lambda t: collapse.optimal(t, max_children=16)}


def comparison(args):
    rows = []
    for name in args.meshes:
        tree, tri = load(name)
        origin, direction = rays.make_rays(jax.random.key(0), "bounce", tree, tri, args.rays)
        # lines through the root box, as the cost model assumes (all hits)
        r_origin, r_direction = rays.make_rays(jax.random.key(1), "random", tree, tri, args.rays)
        nodes = jaxbvh.tree.node_count(tree)
        print(f"== {name}: {tri.shape[0]:,} triangles, {nodes:,} nodes", file=sys.stderr, flush=True)
        for label, fn in methods().items():
            if fn is None:
                wide, seconds, compile_s = tree, 0.0, 0.0
                r_k, r_4 = collapse.rcost(tree), collapse.rcost(tree, SIMD4)
            else:
                result, seconds, compile_s = timed(lambda: fn(tree), args.repeat)
                wide = jaxbvh.to_numpy(result.tree)
                r_k, r_4 = result.rcost, collapse.rcost(wide, SIMD4)
            jaxbvh.validate(wide, *[np.asarray(a) for a in (tri.min(axis=1), tri.max(axis=1))])
            width = np.sum(np.asarray(wide.child) >= 0, axis=1)
            row = {"mesh": name, "triangles": int(tri.shape[0]), "tree": label,
                   "nodes": jaxbvh.tree.node_count(wide), "widest": int(width.max()),
                   "rcost": float(r_k), "rcost_simd4": float(r_4),
                   "seconds": seconds, "fastest_seconds": FASTEST.get(id(result), 0.0) if fn else 0.0,
                   "compile_seconds": compile_s}
            for mode in ("all", "closest"):
                hits = rays.trace(wide, tri, origin, direction, mode=mode, max_hits=1)
                row[f"box_tests_{mode}"] = float(np.mean(hits.box_tests))
                row[f"prim_tests_{mode}"] = float(np.mean(hits.prim_tests))
            hits = rays.trace(wide, tri, r_origin, r_direction, mode="all", max_hits=1)
            row["box_tests_random_all"] = float(np.mean(hits.box_tests))
            rows.append(row)
            print(f"   {label:8s} nodes {row['nodes']:>9,}  R {row['rcost']:8.3f}  R(ceil k/4) "
                  f"{row['rcost_simd4']:8.3f}  box/ray all {row['box_tests_all']:7.2f} closest "
                  f"{row['box_tests_closest']:6.2f} random-all {row['box_tests_random_all']:6.2f}  "
                  f"{seconds * 1e3:8.1f} ms (compile {compile_s:.1f} s)",
                  file=sys.stderr, flush=True)
    return rows


def k_sweep(args, tree):
    rows = []
    for k in (2, 3, 4, 6, 8, 12, 16):
        for cost_name, cost in (("k", None), ("ceil(k/4)", SIMD4)):
            result, seconds, compile_s = timed(lambda: collapse.optimal(tree, max_children=k, test_cost=cost),
                                               args.repeat)
            rows.append({"k": k, "cost": cost_name, "rcost": float(result.rcost),
                         "rcost_before": float(result.rcost_before),
                         "nodes": int(np.asarray(result.kept).sum()), "seconds": seconds,
                         "fastest_seconds": FASTEST[id(result)], "compile_seconds": compile_s})
            print(f"   K={k:2d} T={cost_name:9s} R {rows[-1]['rcost']:8.3f}  {seconds * 1e3:7.1f} ms "
                  f"(compile {compile_s:.1f} s)", file=sys.stderr, flush=True)
    return rows


def _reference_child(tree, queue):
    start = time.perf_counter()
    total, children, _ = ref.optimal(tree, max_children=8)
    queue.put({"seconds": time.perf_counter() - start, "cost": float(total), "children": children})


def reference_run(tree, timeout):
    """The NumPy twin in a separate process (abandoned after ``timeout`` s): its dict or None."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_reference_child, args=(jaxbvh.to_numpy(tree), queue))
    start = time.perf_counter()
    proc.start()
    try:
        got = queue.get(timeout=timeout)
    except Exception:
        got = None
    wall = time.perf_counter() - start
    if got is None:
        proc.terminate()
    proc.join()
    return got, wall


def compare_reference(label, tree, args):
    result, seconds, compile_s = timed(lambda: collapse.optimal(tree, max_children=8), args.repeat)
    row = {"input": label, "nodes": jaxbvh.tree.node_count(tree), "jax_seconds": seconds,
           "jax_fastest_seconds": FASTEST[id(result)], "compile_seconds": compile_s,
           "jax_rcost": float(result.rcost)}
    if args.ref_timeout <= 0:
        row["skipped"] = "not run (--ref-timeout 0)"
        return row
    got, wall = reference_run(tree, args.ref_timeout)
    if got is None:
        row["skipped"] = f"NumPy reference not finished after {wall:.0f} s (limit {args.ref_timeout} s)"
    else:
        w = jaxbvh.to_numpy(result.tree)
        mine = {i: [int(c) for c in r if c >= 0] for i, r in enumerate(w.child) if (r >= 0).any()}
        row.update(numpy_seconds=got["seconds"], speedup=got["seconds"] / seconds,
                   speedup_fastest=got["seconds"] / row["jax_fastest_seconds"],
                   numpy_cost=got["cost"], identical=mine == got["children"])
    print(f"   reference {row}", file=sys.stderr, flush=True)
    return row


def leaf_merging(args, inputs):
    rows = []
    for label, tree in inputs:
        before = collapse.optimal(tree, max_children=8)
        for p in (1, 4, 8):
            result, seconds, _ = timed(lambda: collapse.optimal(tree, max_children=8, max_leaf=p), args.repeat)
            wide = jaxbvh.to_numpy(result.tree)
            rows.append({"input": label, "max_leaf": p,
                         "binary_total": float(before.rcost_before + before.leaf_cost_before),
                         "rcost": float(result.rcost), "leaf_cost": float(result.leaf_cost),
                         "total": float(result.rcost + result.leaf_cost),
                         "binary_sah": float(jaxbvh.sah(jaxbvh.to_jax(tree))),
                         "sah": float(jaxbvh.sah(jaxbvh.to_jax(wide))),
                         "leaves": int(np.sum(np.asarray(wide.prim_count) > 0)), "seconds": seconds})
            print(f"   leaves {rows[-1]}", file=sys.stderr, flush=True)
    return rows


def big_tree(copies, walls, seed):
    """Binary tree (jaxbvh sweep) of the ``bench_rotate.py --big`` scene with ``copies`` bunnies."""
    from bench.bench_rotate import big_scene

    lo, hi = big_scene(copies, walls, seed)
    frame = jaxbvh.Frame.fit(lo, hi)
    lo, hi = frame.to_local(lo).astype(np.float32), frame.to_local(hi).astype(np.float32)
    return jaxbvh.to_numpy(jax.block_until_ready(jaxbvh.build(lo, hi))), len(lo)


def node_sweep(args):
    """DP (K = 8) time on the big scene with 1, 2, 4, 8 bunnies (walls in proportion)."""
    rows = []
    for copies in (1, 2, 4, 8):
        tree, triangles = big_tree(copies, round(args.big_walls * copies / args.big_copies), args.seed)
        result, seconds, compile_s = timed(lambda: collapse.optimal(tree, max_children=8), args.repeat)
        rows.append({"input": f"{copies} bunnies + walls", "triangles": triangles,
                     "nodes": jaxbvh.tree.node_count(tree), "capacity": tree.capacity, "seconds": seconds,
                     "fastest_seconds": FASTEST[id(result)], "compile_seconds": compile_s})
        print(f"   sweep {rows[-1]}", file=sys.stderr, flush=True)
    return rows


def big(args):
    tree, triangles = big_tree(args.big_copies, args.big_walls, args.seed)
    nodes = jaxbvh.tree.node_count(tree)
    print(f"== big: {triangles:,} triangles, {nodes:,} nodes, capacity {tree.capacity}", file=sys.stderr)
    row = {"input": f"big: {args.big_copies} bunnies + {args.big_walls} walls (jaxbvh sweep)",
           "triangles": int(triangles), "nodes": nodes, "capacity": tree.capacity}
    for label, fn in methods().items():
        if fn is None:
            row["binary"] = {"rcost": float(collapse.rcost(tree))}
            continue
        result, seconds, compile_s = timed(lambda: fn(tree), args.repeat)
        row[label] = {"rcost": float(result.rcost), "nodes": int(np.asarray(result.kept).sum()),
                      "seconds": seconds, "fastest_seconds": FASTEST[id(result)], "compile_seconds": compile_s}
        print(f"   {label}: {row[label]}", file=sys.stderr, flush=True)
    row["reference"] = compare_reference(row["input"], tree, args)
    return row


def write(data):
    data["meta"]["load_average_at_end"] = os.getloadavg()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "collapse.json").write_text(json.dumps(data, indent=1))
    meta = data["meta"]
    lines = ["# Adaptive collapsing (Susano Pinto 2010)", "",
             f"{meta['machine']}, {meta['cpus']} CPUs, JAX {meta['jax']} ({meta['backend']}), float32. "
             "Binary trees: `jaxbvh.build` sweep SAH, one primitive per leaf. R_cost in "
             "root-normalised areas (box tests of a ray that hits the root box and finds every hit). "
             f"Box tests per ray: {meta.get('rays', '?')} bounce rays per mesh (the paper's secondary rays), "
             "all-hits and closest-hit. Times: median warm seconds; compile apart. "
             "The CPU was shared with other jobs while these ran (load average "
             f"{meta['load_average_at_start'][0]:.1f} at the start, {meta['load_average_at_end'][0]:.1f} "
             "at the end, on 2 cores).", ""]
    if data.get("comparison"):
        lines += ["## The paper's comparison (T(k) = k unless said)", "",
                  "| mesh | tree | nodes | widest | R_cost | R_cost, T = ceil(k/4) | box tests/ray all-hits | "
                  "box tests/ray closest | prim tests/ray closest | box tests/ray all-hits, random lines | time |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in data["comparison"]:
            lines.append(f"| {r['mesh']} | {r['tree']} | {r['nodes']:,} | {r['widest']} | {r['rcost']:.3f} | "
                         f"{r['rcost_simd4']:.3f} | {r['box_tests_all']:.2f} | {r['box_tests_closest']:.2f} | "
                         f"{r['prim_tests_closest']:.2f} | {r['box_tests_random_all']:.2f} | "
                         f"{r['seconds'] * 1e3:.1f} ms |")
        lines.append("")
    if data.get("k_sweep"):
        lines += [f"## DP time and R_cost vs K ({data.get('k_sweep_input', 'bunny')})", "",
                  "| K | T | R_cost (binary: R before) | nodes | DP time | compile |", "|---:|---|---:|---:|---:|---:|"]
        for r in data["k_sweep"]:
            lines.append(f"| {r['k']} | {r['cost']} | {r['rcost']:.3f} ({r['rcost_before']:.3f}) | {r['nodes']:,} | "
                         f"{r['seconds'] * 1e3:.1f} ms | {r['compile_seconds']:.1f} s |")
        lines.append("")
    sweep = [r for r in data.get("comparison", []) if r["tree"] == "dp K=8"]
    binary = {r["mesh"]: r["nodes"] for r in data.get("comparison", []) if r["tree"] == "binary"}
    if sweep or data.get("big"):
        lines += ["## DP time (K = 8) vs nodes", "",
                  "The whole `collapse.optimal` call: schedule, tables, back-tracking, emitting the "
                  "WideBVH and both R_cost. Median warm run, and the fastest (less of the other jobs' load).", "",
                  "| input | nodes | DP time, median (fastest) | per node, fastest | compile |",
                  "|---|---:|---:|---:|---:|"]
        entries = [(r["mesh"], binary[r["mesh"]], r) for r in sweep]
        entries += [(r["input"], r["nodes"], r) for r in data.get("node_sweep", [])]
        entries += [(b["input"], b["nodes"], b["dp K=8"]) for b in data.get("big", [])]
        for label, n, r in sorted(entries, key=lambda e: e[1]):
            fast = r.get("fastest_seconds", r["seconds"])
            lines.append(f"| {label} | {n:,} | {r['seconds'] * 1e3:.1f} ms ({fast * 1e3:.1f} ms) | "
                         f"{fast / n * 1e9:.0f} ns | {r['compile_seconds']:.1f} s |")
        lines.append("")
    refs = data.get("reference", []) + [b["reference"] for b in data.get("big", [])]
    if refs:
        lines += ["## JAX DP against the NumPy reference (K = 8)", "",
                  "| input | nodes | JAX warm, median (fastest) | NumPy | speed-up, median (fastest) "
                  "| identical tree |",
                  "|---|---:|---:|---:|---:|---|"]
        for r in refs:
            if "skipped" in r:
                lines.append(f"| {r['input']} | {r['nodes']:,} | {r['jax_seconds'] * 1e3:.1f} ms | "
                             f"{r['skipped']} | | |")
            else:
                fast = r.get("jax_fastest_seconds", r["jax_seconds"])
                lines.append(f"| {r['input']} | {r['nodes']:,} | {r['jax_seconds'] * 1e3:.1f} ms "
                             f"({fast * 1e3:.1f} ms) | "
                             f"{r['numpy_seconds']:.1f} s | {r['speedup']:.0f}x ({r['numpy_seconds'] / fast:.0f}x) | "
                             f"{r['identical']} |")
        lines.append("")
    if data.get("big"):
        lines += ["## The 1.05M-triangle input (`--big`)", "",
                  "| input | method | R_cost | nodes | time, median (fastest) | compile |",
                  "|---|---|---:|---:|---:|---:|"]
        for b in data["big"]:
            lines.append(f"| {b['input']} | binary | {b['binary']['rcost']:.3f} | {b['nodes']:,} | | |")
            for m in ("greedy", "qbvh", "dp K=8", "dp K=16"):
                d = b[m]
                fast = d.get("fastest_seconds", d["seconds"])
                lines.append(f"| | {m} | {d['rcost']:.3f} | {d['nodes']:,} | {d['seconds'] * 1e3:.0f} ms "
                             f"({fast * 1e3:.0f} ms) | {d['compile_seconds']:.1f} s |")
        lines.append("")
    if data.get("leaves"):
        lines += ["## Beyond the paper: the DP also merges leaves (`max_leaf` P, K = 8, Ci = 1)", "",
                  "R_cost + Ci sum a(leaf) count (box tests + primitive tests per ray, the cost the DP then "
                  "minimises) against the binary tree's; and `jaxbvh.sah` (Ct per node) of both.", "",
                  "| input | P | leaves | R_cost | leaf cost | total | binary total | SAH | binary SAH |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in data["leaves"]:
            lines.append(f"| {r['input']} | {r['max_leaf']} | {r['leaves']:,} | {r['rcost']:.3f} | "
                         f"{r['leaf_cost']:.3f} | "
                         f"{r['total']:.3f} | {r['binary_total']:.3f} | {r['sah']:.3f} | {r['binary_sah']:.3f} |")
        lines.append("")
    (RESULTS / "collapse.md").write_text("\n".join(lines))
    print(f"wrote {RESULTS / 'collapse.json'} and .md", file=sys.stderr)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    parser.add_argument("--rays", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--ref-timeout", type=float, default=3600.0,
                        help="seconds the NumPy reference may take per input (0: skip it)")
    parser.add_argument("--big", action="store_true", help="only the 1.05M-triangle input, appended")
    parser.add_argument("--big-copies", type=int, default=15)
    parser.add_argument("--big-walls", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not DATA.exists():
        raise SystemExit(f"shared data not found at {DATA}")
    path = RESULTS / "collapse.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data["meta"] = {"machine": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "jax": jax.__version__, "backend": jax.default_backend(), "rays": args.rays,
                    "repeat": args.repeat, "load_average_at_start": os.getloadavg()}
    if args.big:
        data["big"] = [big(args)]
        data["node_sweep"] = node_sweep(args)
        write(data)
        return
    data["comparison"] = comparison(args)
    bunny, _ = load("bunny")
    data["k_sweep_input"] = f"bunny, {jaxbvh.tree.node_count(bunny):,} nodes"
    data["k_sweep"] = k_sweep(args, bunny)
    legocar, _ = jaxbvh.load(DATA / "trees" / "legocar_binned_ref.npz")
    data["reference"] = [compare_reference("legocar (tinybvh tree)", legocar, args),
                         compare_reference("bunny (jaxbvh sweep)", bunny, args)]
    drone, _ = jaxbvh.load(DATA / "trees" / "drone_binned_ref.npz")
    lego_ours, _ = load("legocar")
    data["leaves"] = leaf_merging(args, [("legocar (jaxbvh sweep)", lego_ours), ("bunny (jaxbvh sweep)", bunny),
                                         ("drone (tinybvh tree)", drone)])
    write(data)


if __name__ == "__main__":
    main()
