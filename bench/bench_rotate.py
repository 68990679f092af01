"""Tree rotations: time vs SAH for hill climbing and annealing (Kensler 2008).

    python bench/bench_rotate.py                 # tinybvh trees, HC, SA N in {50, 250}, K in {1, 4}
    python bench/bench_rotate.py --full          # + N = 1250, K = 16, our own builds, 1M-triangle input
    python bench/bench_rotate.py --trees legocar --steps 50 --chains 1
    python bench/bench_rotate.py --big           # only hill climbing on the >= 1M-triangle input,
                                                 # appended to the existing results

The ``--big`` input (:func:`big_scene`): ``--big-copies`` (15) overlapping copies of the
Stanford bunny with random rotations and offsets, plus large wall / floor triangles of
mixed sizes (log-uniform over two orders of magnitude) crossing the whole scene. The
NumPy reference runs in a separate process and is abandoned after ``--ref-timeout``
seconds (reported as skipped, with the reason).

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
from jaxbvh.optimize import rotate  # noqa: E402
from jaxbvh.optimize import rotate_reference as ref  # noqa: E402

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


def big_scene(copies=15, walls=4000, seed=0):
    """World-space triangle boxes ``(lo, hi)`` float64 [F, 3] of the >= 1M-triangle input."""
    from jaxbvh.io import load_mesh
    rng = np.random.default_rng(seed)
    tri = load_mesh(DATA / "meshes" / "stanford-bunny.obj").triangles      # [F, 3, 3]
    tri = tri - tri.reshape(-1, 3).mean(axis=0)
    size = float(np.ptp(tri.reshape(-1, 3), axis=0).max())
    parts = []
    for _ in range(copies):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        rot = q * np.sign(np.diag(r))                                       # random orthogonal
        offset = rng.uniform(-1.0, 1.0, 3) * size                           # copies overlap
        parts.append(tri @ rot.T + offset)
    extent = 2.5 * size
    # walls and floors: axis-aligned-ish large triangles, sizes log-uniform in [0.02, 2] x extent
    sizes = np.exp(rng.uniform(np.log(0.02), np.log(2.0), walls)) * extent
    normal_axis = rng.integers(0, 3, walls)
    corner = rng.uniform(-extent, extent, (walls, 3))
    wall = np.repeat(corner[:, None, :], 3, axis=1)
    for k in range(walls):
        a, b = [ax for ax in range(3) if ax != normal_axis[k]]
        wall[k, 1, a] += sizes[k]
        wall[k, 2, b] += sizes[k] * rng.uniform(0.3, 1.0)
        wall[k, :, normal_axis[k]] += rng.normal(0, 1e-3 * extent, 3)       # not exactly flat
    tris = np.concatenate(parts + [wall])
    return tris.min(axis=1), tris.max(axis=1)


def _reference_child(tree, max_passes, queue):
    import hashlib
    start = time.perf_counter()
    out, info = ref.hill_climb(tree, max_passes=max_passes)
    seconds = time.perf_counter() - start
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(getattr(out, f)).tobytes()
                                     for f in ("left", "right", "parent", "lo", "hi"))).hexdigest()
    queue.put({"seconds": seconds, "passes": info["passes"], "sah": info["sah"], "digest": digest})


def run_big(args):
    """Hill climbing only, on the >= 1M-triangle input; NumPy reference with a time limit."""
    import hashlib
    import multiprocessing as mp
    start = time.perf_counter()
    lo, hi = big_scene(args.big_copies, args.big_walls, args.seed)
    frame = jaxbvh.Frame.fit(lo, hi)
    lo, hi = frame.to_local(lo).astype(np.float32), frame.to_local(hi).astype(np.float32)
    scene_s = time.perf_counter() - start
    print(f"== big scene: {len(lo):,} triangles ({scene_s:.1f} s to generate)", file=sys.stderr)
    start = time.perf_counter()
    tree = jax.block_until_ready(jaxbvh.build(lo, hi))
    build_cold = time.perf_counter() - start
    start = time.perf_counter()
    tree = jax.block_until_ready(jaxbvh.build(lo, hi))
    build_warm = time.perf_counter() - start
    tree = jaxbvh.to_numpy(tree)
    nodes = jaxbvh.tree.node_count(tree)
    print(f"build (default method): cold {build_cold:.2f} s, warm {build_warm:.2f} s, "
          f"{nodes:,} nodes, capacity {tree.capacity}", file=sys.stderr)
    tj = jaxbvh.to_jax(tree)
    start_sah = float(jaxbvh.sah(tj))
    res, warm, compile_s = timed(lambda: rotate.hill_climb(tj, split_axes=False), args.repeat)
    row = {"input": f"big: {args.big_copies} bunnies + {args.big_walls} walls (jaxbvh sweep)",
           "triangles": int(len(lo)), "nodes": nodes, "capacity": tree.capacity,
           "start_sah": start_sah, "method": "hc", "steps": 0, "chains": 1,
           "sah": float(res.sah), "passes": int(res.steps), "moves": int(res.moves),
           "seconds": warm, "compile_seconds": compile_s, "split_axes": False,
           "build_seconds_cold": build_cold, "build_seconds_warm": build_warm}
    print(row, file=sys.stderr)
    res_axes, warm_axes, _ = timed(lambda: rotate.hill_climb(tj), args.repeat)
    row["seconds_with_split_axes"] = warm_axes
    print(f"with split axes (Kensler's final pass): {warm_axes:.3f} s", file=sys.stderr)
    reference = {"input": row["input"], "timeout_seconds": args.ref_timeout}
    if args.ref_timeout > 0:
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        proc = ctx.Process(target=_reference_child, args=(tree, 1000, queue))
        start = time.perf_counter()
        proc.start()
        try:
            got = queue.get(timeout=args.ref_timeout)
        except Exception:
            got = None
        wall = time.perf_counter() - start
        if got is None:
            proc.terminate()
            proc.join()
            reference["skipped"] = (f"NumPy reference not finished after {wall:.0f} s "
                                    f"(limit {args.ref_timeout} s); abandoned")
        else:
            proc.join()
            digest = hashlib.sha256(b"".join(np.ascontiguousarray(np.asarray(getattr(res.tree, f))).tobytes()
                                             for f in ("left", "right", "parent", "lo", "hi"))).hexdigest()
            reference.update(numpy_seconds=got["seconds"], jax_seconds=warm,
                             speedup=got["seconds"] / warm, identical=got["digest"] == digest,
                             passes=got["passes"], numpy_sah=got["sah"])
    else:
        reference["skipped"] = "not run (--ref-timeout 0)"
    print(reference, file=sys.stderr)
    return row, reference


def write_big(row, reference, args):
    """Append the big-input row to rotate.json / rotate.md, keeping what is there."""
    path = RESULTS / "rotate.json"
    data = json.loads(path.read_text()) if path.exists() else {"rows": []}
    data.setdefault("big", []).append({"row": row, "reference": reference,
                                       "args": vars(args), "cpus": __import__("os").cpu_count(),
                                       "jax": jax.__version__})
    path.write_text(json.dumps(data, indent=1))
    r = row
    lines = ["", "## Hill climbing on the >= 1M-triangle input (`--big`)", "",
             f"{r['input']}: {r['triangles']:,} triangles, {r['nodes']:,} nodes (capacity "
             f"{r['capacity']:,}). Build (default sweep builder): {r['build_seconds_warm']:.2f} s warm, "
             f"{r['build_seconds_cold']:.2f} s cold. Seconds are warm, median of {args.repeat}; compile "
             "apart.", "",
             "| input | triangles | start SAH | HC SAH | change | passes | moves | HC seconds | HC + split axes s | compile s |",
             "|---|---|---|---|---|---|---|---|---|---|",
             f"| {r['input']} | {r['triangles']:,} | {r['start_sah']:.3f} | {r['sah']:.3f} | "
             f"{100 * (r['sah'] / r['start_sah'] - 1):+.2f}% | {r['passes']} | {r['moves']:,} | "
             f"{r['seconds']:.3f} | {r['seconds_with_split_axes']:.3f} | {r['compile_seconds']:.1f} |", ""]
    if "skipped" in reference:
        lines.append(f"NumPy reference on this input: skipped: {reference['skipped']}.")
    else:
        lines.append(f"NumPy reference hill climbing on this input: {reference['numpy_seconds']:.1f} s "
                     f"vs JAX {reference['jax_seconds']:.3f} s ({reference['speedup']:.0f}x), "
                     f"identical tree: {reference['identical']}.")
    with open(RESULTS / "rotate.md", "a") as fh:
        fh.write("\n".join(lines) + "\n")


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
                     "passes": int(res.steps), "moves": int(res.moves), "seconds": warm,
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
                             "hottest": rotate.DEFAULT_HOTTEST,
                             "sah": float(res.sah), "passes": int(res.steps),
                             "moves": int(res.moves), "seconds": warm, "compile_seconds": compile_s})
                print(rows[-1], file=sys.stderr)
        for hottest in args.sweep_hottest:
            key = jax.random.key(args.seed)
            res = jax.block_until_ready(rotate.anneal(key, tj, steps=args.sweep_steps,
                                                      hottest=hottest))
            rows.append({**base, "method": "sa", "steps": args.sweep_steps, "chains": 1,
                         "hottest": hottest, "sweep": True, "sah": float(res.sah),
                         "passes": int(res.steps), "moves": int(res.moves)})
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
    sweep = [r for r in rows if r.get("sweep")]
    rows = [r for r in rows if not r.get("sweep")]
    for r in rows:
        tiny = f"{r['tinybvh_sah']:.3f} ({r['tinybvh_seconds']:.2f})" if "tinybvh_sah" in r else "-"
        change = 100 * (r["sah"] / r["start_sah"] - 1)
        lines.append(f"| {r['input']} | {r['nodes']:,} | {r['start_sah']:.3f} | {r['method']} | "
                     f"{r['steps'] or '-'} | {r['chains']} | {r['sah']:.3f} | {change:+.1f}% | "
                     f"{r['passes']} | {r['seconds']:.3f} | {r['compile_seconds']:.1f} | {tiny} |")
    lines += ["", "Equal time against tinybvh's reinsertion optimizer (its seconds are from its "
              "README, same kind of machine): the lowest SAH any run here reached within that time.",
              "", "| input | tinybvh SAH (s) | best here within that time | run |", "|---|---|---|---|"]
    for name in dict.fromkeys(r["input"] for r in rows if "tinybvh_sah" in r):
        mine = [r for r in rows if r["input"] == name]
        ok = [r for r in mine if r["seconds"] <= mine[0]["tinybvh_seconds"]]
        best = min(ok, key=lambda r: r["sah"]) if ok else None
        run_ = ("-" if best is None else "HC" if best["method"] == "hc"
                else f"SA N={best['steps']} K={best['chains']}")
        lines.append(f"| {name} | {mine[0]['tinybvh_sah']:.3f} ({mine[0]['tinybvh_seconds']:.2f}) | "
                     f"{'-' if best is None else format(best['sah'], '.3f')} | {run_} |")
    if sweep:
        hs = sorted({r["hottest"] for r in sweep})
        lines += ["", f"Peak temperature h (annealing, N = {sweep[0]['steps']}, one chain, seed "
                      f"{args.seed}): SAH reached. The default is h = {rotate.DEFAULT_HOTTEST}; "
                      "Kensler's 1.5 is in the last column.", "",
                  "| input | HC | " + " | ".join(f"h = {h:g}" for h in hs) + " |",
                  "|---|---|" + "---|" * len(hs)]
        for name in dict.fromkeys(r["input"] for r in sweep):
            hc = next(r["sah"] for r in rows if r["input"] == name and r["method"] == "hc")
            by_h = {r["hottest"]: r["sah"] for r in sweep if r["input"] == name}
            lines.append(f"| {name} | {hc:.3f} | " + " | ".join(f"{by_h[h]:.3f}" for h in hs) + " |")
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
    parser.add_argument("--sweep-hottest", nargs="*", type=float, default=None,
                        help="peak temperatures h to compare (default with --full: "
                             "0.05 0.1 0.15 0.3 1.5)")
    parser.add_argument("--sweep-steps", type=int, default=250,
                        help="schedule length of the h comparison")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-reference", dest="reference", action="store_false")
    parser.add_argument("--big", action="store_true",
                        help="only hill climbing on the >= 1M-triangle input; appends to results")
    parser.add_argument("--big-copies", type=int, default=15)
    parser.add_argument("--big-walls", type=int, default=4000)
    parser.add_argument("--ref-timeout", type=float, default=180.0,
                        help="seconds the NumPy reference may take on --big (0: skip it)")
    args = parser.parse_args(argv)
    if args.big:
        row, reference = run_big(args)
        write_big(row, reference, args)
        print((RESULTS / "rotate.md").read_text())
        return
    if args.steps is None:
        args.steps = [50, 250, 1250] if args.full else [50, 250]
    if args.chains is None:
        args.chains = [1, 4, 16] if args.full else [1, 4]
    if args.sweep_hottest is None:
        args.sweep_hottest = [0.05, 0.1, 0.15, 0.3, 1.5] if args.full else []
    rows, reference = run(args)
    write(rows, reference, args)
    print((RESULTS / "rotate.md").read_text())


if __name__ == "__main__":
    main()
