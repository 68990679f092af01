"""Many small meshes: batched calls (jaxbvh.batch) against one call per mesh, and tinybvh's loop.

    python bench/bench_batch.py                          # 200 meshes of 200-5,000 triangles
    python bench/bench_batch.py --meshes 1000            # the issue's 1,000 meshes
    python bench/bench_batch.py --meshes 40 --no-pipeline --sizes 1 8 40   # a quick look

Meshes: the shared meshes (``../shared/data/meshes``) cut into spatial pieces (recursive
median splits of the triangle centres along the longest axis, each piece stopping at
a size drawn log-uniformly in [2 * min, max], so pieces hold min .. max triangles) plus
procedural trees (:func:`jaxbvh.scenes.tree_mesh`, 3 to 4 levels); each in its own
scene frame (``Frame.fit``), as the command line builds a mesh.

Measured, warm (every program compiled by a first run of the same calls; timings are the
second run): the batched build (:func:`jaxbvh.batch.build`) against the loop of
:func:`jaxbvh.build` over the same meshes, and the batched pipeline
(:func:`jaxbvh.batch.optimize`) against the loop of :func:`jaxbvh.optimize.optimize`;
every batched tree is checked equal, array for array, to the loop's. Throughput of the
batched build against the batch size (the first k meshes). Peak memory: the process's
peak resident set (``ru_maxrss``) after each phase, beside the plan's estimate. tinybvh:
``bench/peer_many.cpp`` (built with g++ from ``../shared/peer/tiny_bvh.h``) loops over
the same triangles in one process on one thread: ``BVH::Build`` (binned SAH) and
``BVH::Optimize(200, extreme)``.

On a CPU the batch is split over one JAX device per core (``--cpu-devices``; the loop of
single calls runs on one); ``--cpu-devices 1`` gives the one-device figures.

Writes ``bench/results/batch.json``, ``batch.md`` and ``batch.png`` (``--tag`` adds a
suffix, e.g. ``--tag gpu`` from ``bench/gpu.sh``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from jaxbvh import batch  # noqa: E402
from jaxbvh.batch import plan  # noqa: E402
from jaxbvh.batch import rows as batch_rows  # noqa: E402
from jaxbvh.builders import dispatch, inputs  # noqa: E402
from jaxbvh.tree.frame import Frame  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
PEER = ROOT.parent / "shared" / "peer"
RESULTS = ROOT / "bench" / "results"
FIELDS = ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "axis", "prim_index", "root")


def pieces(tri: np.ndarray, rng, low: int, high: int) -> list[np.ndarray]:
    """Spatial pieces of ``tri`` [n, 3, 3] of ``low .. high`` triangles (module docstring)."""
    out, todo = [], [np.arange(tri.shape[0])]
    centre = tri.mean(axis=1)
    while todo:
        ids = todo.pop()
        stop = int(np.exp(rng.uniform(np.log(min(2 * low, high)), np.log(high))))
        if ids.size <= stop:
            if ids.size >= low:
                out.append(tri[ids])
            continue
        c = centre[ids]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = ids[np.argsort(c[:, axis], kind="stable")]
        half = order.size // 2
        todo += [order[:half], order[half:]]
    return out


def mesh_set(count: int, low: int, high: int, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """``count`` named triangle sets [n, 3, 3] (world space), pieces and procedural trees."""
    rng = np.random.default_rng(seed)
    sources = []
    for path in sorted((DATA / "meshes").glob("*.obj")):
        mesh = jaxbvh.load_mesh(path)
        sources.append((path.stem, np.asarray(mesh.triangles, np.float64)))
    out = []
    k = 0
    while len(out) < count:
        for name, tri in sources:
            out += [(f"{name}.{k}.{j}", p) for j, p in enumerate(pieces(tri, rng, low, high))]
        # every fifth mesh a procedural tree (about 500-2,000 triangles)
        for j in range(max(1, count // 25)):
            v, f = jaxbvh.scenes.tree_mesh(jax.random.key(1000 * k + j), levels=int(rng.integers(3, 5)))
            if low <= f.shape[0] <= high:
                out.append((f"tree.{k}.{j}", v[f]))
        k += 1
    order = rng.permutation(len(out))[:count]
    return [out[i] for i in order]


def local_boxes(tri: np.ndarray):
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    frame = Frame.fit(lo, hi)
    return frame.to_local(lo).astype(np.float32), frame.to_local(hi).astype(np.float32)


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def same(a, b) -> bool:
    a, b = jaxbvh.to_numpy(a), jaxbvh.to_numpy(b)
    return all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f))) for f in FIELDS)


def loop_build(meshes, builder):
    return [jax.block_until_ready(jaxbvh.build(lo, hi, method=builder)) for lo, hi in meshes]


def engine_only(meshes, builder):
    """Seconds of the compiled builds alone (inputs prepared beforehand, no host work per
    mesh): the floor of any batching that runs each mesh's build as the single call does."""
    config = jaxbvh.builders.configs.make_config(builder)
    run = dispatch._ON_PREPARED[builder]
    prepared = [inputs.prepare(lo, hi) for lo, hi in meshes]
    jax.block_until_ready([run(*p, config) for p in one_per_capacity(prepared, [lo.shape[0] for lo, _ in meshes])])
    start = time.perf_counter()
    for p in prepared:
        jax.block_until_ready(run(*p, config))
    return time.perf_counter() - start


def loop_optimize(trees, method):
    return [jaxbvh.optimize.optimize(t, method) for t in trees]


def one_per_capacity(items, sizes):
    """The first item of each capacity bucket (a loop's warm-up compiles once per bucket)."""
    seen, out = set(), []
    for item, n in zip(items, sizes):
        cap = jaxbvh.capacity_bucket(n)
        if cap not in seen:
            seen.add(cap)
            out.append(item)
    return out


def run_peer(named) -> dict | None:
    """tinybvh's one-thread loop over the same triangles (``bench/peer_many.cpp``)."""
    compiler = shutil.which(os.environ.get("CXX", "g++"))
    if compiler is None or not (PEER / "tiny_bvh.h").exists():
        return None
    build_dir = Path(os.environ.get("PEER_BUILD", "/tmp/jaxbvh-peer"))
    build_dir.mkdir(parents=True, exist_ok=True)
    exe = build_dir / "peer_many"
    source = ROOT / "bench" / "peer_many.cpp"
    if not exe.exists() or exe.stat().st_mtime < source.stat().st_mtime:
        subprocess.run([compiler, "-O3", "-march=native", "-std=c++17", "-DNDEBUG", f"-I{PEER}", "-o", str(exe),
                        str(source), "-lpthread"], check=True)
    with tempfile.NamedTemporaryFile(suffix=".bin", delete=False) as f:
        f.write(np.uint32(len(named)).astype("<u4").tobytes())
        for _, tri in named:
            f.write(np.uint32(tri.shape[0]).astype("<u4").tobytes())
            f.write(np.ascontiguousarray(tri, "<f4").tobytes())
        path = f.name
    try:
        proc = subprocess.run([str(exe), path], check=True, capture_output=True, text=True)
    finally:
        os.unlink(path)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=int, default=200)
    parser.add_argument("--min-tris", type=int, default=200)
    parser.add_argument("--max-tris", type=int, default=5000)
    parser.add_argument("--builder", default="sweep", choices=list(jaxbvh.BOX_BUILDERS))
    parser.add_argument("--method", default="pipeline", help="optimizer of the batched-vs-loop run")
    parser.add_argument("--no-pipeline", action="store_true", help="skip the optimizer runs")
    parser.add_argument("--sizes", type=int, nargs="*", default=None,
                        help="batch sizes of the throughput curve (default 1 4 16 64 all)")
    parser.add_argument("--memory-mb", type=float, default=batch.BatchConfig().memory_mb)
    parser.add_argument("--vmap-pipeline", action="store_true",
                        help="time the optimizer's batch with rows vmapped too (slow on a CPU)")
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--tag", default="", help="suffix of the result files (batch_<tag>.*)")
    parser.add_argument("--cpu-devices", type=int, default=None,
                        help="JAX CPU devices the batch is split over (default: one per core, as `jaxbvh batch`)")
    args = parser.parse_args(argv)
    batch.use_cpu_cores(args.cpu_devices)  # before JAX's first operation

    config = batch.BatchConfig(memory_mb=args.memory_mb)
    modes = {mode: config.replace(rows=mode) for mode in ("map", "vmap")}
    auto = batch_rows.resolve(config.rows, jax.devices())  # what "auto" runs here
    named = mesh_set(args.meshes, args.min_tris, args.max_tris)
    meshes = [local_boxes(tri) for _, tri in named]
    sizes = [lo.shape[0] for lo, _ in meshes]
    tris = int(sum(sizes))
    out = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, {jax.devices()[0].platform} "
                      f"({jax.device_count()} device(s): {jax.devices()[0].device_kind})",
           "jax": jax.__version__, "meshes": len(meshes), "triangles": tris,
           "triangles_min": int(min(sizes)), "triangles_mean": float(np.mean(sizes)),
           "triangles_max": int(max(sizes)), "builder": args.builder, "memory_mb": args.memory_mb,
           "chunks": [dict(capacity=c.capacity, meshes=int(c.index.size), rows=c.rows,
                           estimate_mb=plan.estimate_mb(c, plan.BYTES_PER_SLOT["build"]))
                      for c in plan.chunks(sizes, config, plan.BYTES_PER_SLOT["build"], jax.device_count())],
           "peak_mb": {"start": peak_mb()}}
    print(f"{len(meshes)} meshes, {tris:,} triangles ({min(sizes)}..{max(sizes)}), {out['machine']}", flush=True)

    # build: compile every way, then time them in one run (rows mapped, rows vmapped, the loop,
    # the loop's compiled builds alone)
    compile_batch = {m: timed(lambda c=c: batch.build(meshes, method=args.builder, batch=c))[1]
                     for m, c in modes.items()}
    _, compile_loop = timed(lambda: loop_build(one_per_capacity(meshes, sizes), args.builder))
    built, t_batch = timed(lambda: batch.build(meshes, method=args.builder, batch=config))
    out["peak_mb"]["after_batched_build"] = peak_mb()
    t_modes = {m: timed(lambda c=c: batch.build(meshes, method=args.builder, batch=c))[1] for m, c in modes.items()}
    singles, t_loop = timed(lambda: loop_build(meshes, args.builder))
    t_engine = engine_only(meshes, args.builder)
    trees = built.trees.unstack()
    identical = all(same(a, b) for a, b in zip(trees, singles))
    out["build"] = dict(batched_s=t_batch, loop_s=t_loop, speedup=t_loop / t_batch, identical=identical,
                        rows=auto, by_rows_s=t_modes, engine_only_s=t_engine,
                        compile_batched_s=compile_batch, compile_loop_s=compile_loop,
                        meshes_per_s=len(meshes) / t_batch, triangles_per_s=tris / t_batch,
                        sah_mean=float(np.mean(batch.costs(built.trees)["sah"])))
    print("build", json.dumps(out["build"]), flush=True)

    # throughput against the batch size (batched build of the first k meshes, warm)
    curve = []
    for k in sorted(set(args.sizes or [1, 4, 16, 64, len(meshes)])):
        k = min(k, len(meshes))
        part = meshes[:k]
        batch.build(part, method=args.builder, batch=config)
        _, t = timed(lambda part=part: batch.build(part, method=args.builder, batch=config))
        curve.append(dict(batch=k, seconds=t, meshes_per_s=k / t, triangles_per_s=sum(sizes[:k]) / t))
        print("throughput", json.dumps(curve[-1]), flush=True)
    out["throughput"] = curve

    if not args.no_pipeline:
        _, compile_batch = timed(lambda: batch.optimize(built.trees, args.method, batch=config))
        _, compile_loop = timed(lambda: loop_optimize(one_per_capacity(singles, sizes), args.method))
        opt, t_batch = timed(lambda: batch.optimize(built.trees, args.method, batch=config))
        out["peak_mb"]["after_batched_optimize"] = peak_mb()
        single_opt, t_loop = timed(lambda: loop_optimize(singles, args.method))
        identical = all(same(a, r.tree) for a, r in zip(opt.trees.unstack(), single_opt))
        by_rows = {}
        if args.vmap_pipeline:
            batch.optimize(built.trees, args.method, batch=modes["vmap"])  # compile
            vmapped, by_rows["vmap"] = timed(lambda: batch.optimize(built.trees, args.method, batch=modes["vmap"]))
            identical &= all(same(a, r.tree) for a, r in zip(vmapped.trees.unstack(), single_opt))
        out["optimize"] = dict(method=args.method, batched_s=t_batch, loop_s=t_loop, speedup=t_loop / t_batch,
                               rows=auto, by_rows_s=by_rows,
                               identical=identical, compile_batched_s=compile_batch, compile_loop_s=compile_loop,
                               meshes_per_s=len(meshes) / t_batch, sah_mean=float(np.mean(opt.sah)),
                               sah_start_mean=float(np.mean(opt.sah_start)))
        print("optimize", json.dumps(out["optimize"]), flush=True)
    out["peak_mb"]["end"] = peak_mb()

    if not args.no_peer:
        peer = run_peer(named)
        out["tinybvh"] = peer
        if peer:
            out["tinybvh_ratio"] = {"build": out["build"]["batched_s"] / (peer["build_ms"] / 1e3)}
            if "optimize" in out:
                out["tinybvh_ratio"]["optimize"] = out["optimize"]["batched_s"] / (peer["optimize_ms"] / 1e3)
        print("tinybvh", json.dumps(peer), flush=True)
    write(out, args.tag)


def write(out: dict, tag: str) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / ("batch" + (f"_{tag}" if tag else ""))
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1) + "\n")
    b = out["build"]
    lines = [f"# Batches of meshes ({out['machine']})", "",
             f"{out['meshes']} meshes, {out['triangles']:,} triangles ({out['triangles_min']}..."
             f"{out['triangles_max']}, mean {out['triangles_mean']:.0f}); builder {out['builder']}; warm; "
             "one run, so ratios are the figures to read.", "",
             "| run | batched s | loop s | loop / batched | identical trees | mean SAH |", "|---|---|---|---|---|---|",
             f"| build | {b['batched_s']:.2f} | {b['loop_s']:.2f} | {b['speedup']:.1f}x | {b['identical']} | "
             f"{b['sah_mean']:.3f} |"]
    if "optimize" in out:
        o = out["optimize"]
        lines.append(f"| {o['method']} | {o['batched_s']:.2f} | {o['loop_s']:.2f} | {o['speedup']:.1f}x | "
                     f"{o['identical']} | {o['sah_mean']:.3f} (from {o['sah_start_mean']:.3f}) |")
    lines += ["", "Build by rows mode (batched, same run): "
              + ", ".join(f"{k} {v:.2f} s" for k, v in b.get("by_rows_s", {}).items())
              + f"; the loop's compiled builds alone (inputs prepared, no host work): {b.get('engine_only_s', 0):.2f} s"
              + f" (the table's batched row: rows = {b.get('rows')})"]
    if "optimize" in out and out["optimize"].get("by_rows_s"):
        lines += [f"{out['optimize']['method']} by rows mode: "
                  + ", ".join(f"{k} {v:.2f} s" for k, v in out["optimize"]["by_rows_s"].items())
                  + f" (the table's row: rows = {out['optimize'].get('rows')})"]
    peer = out.get("tinybvh")
    if peer:
        lines += ["", f"tinybvh, one thread, same triangles: build {peer['build_ms'] / 1e3:.2f} s (mean SAH "
                  f"{peer['sah_built_mean']:.3f}), Optimize({peer['opt_iters']}) {peer['optimize_ms'] / 1e3:.2f} s "
                  f"(mean SAH {peer['sah_optimized_mean']:.3f}); jaxbvh batched / tinybvh: "
                  + ", ".join(f"{k} {v:.1f}x" for k, v in out["tinybvh_ratio"].items())]
    lines += ["", "| batch size | seconds | meshes/s | triangles/s |", "|---|---|---|---|"]
    lines += [f"| {c['batch']} | {c['seconds']:.3f} | {c['meshes_per_s']:.1f} | {c['triangles_per_s']:,.0f} |"
              for c in out["throughput"]]
    lines += ["", "Peak resident memory (MiB): " + ", ".join(f"{k} {v:.0f}" for k, v in out["peak_mb"].items()),
              "", "Chunks (capacity, meshes, rows, estimated MiB): "
              + "; ".join(f"{c['capacity']}, {c['meshes']}, {c['rows']}, {c['estimate_mb']:.0f}" for c in out["chunks"])]
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    c = out["throughput"]
    ax[0].plot([p["batch"] for p in c], [p["meshes_per_s"] for p in c], "o-", label="batched build")
    ax[0].axhline(out["meshes"] / b["loop_s"], color="gray", ls="--", label="loop of jaxbvh.build")
    if peer:
        ax[0].axhline(out["meshes"] / (peer["build_ms"] / 1e3), color="k", ls=":", label="tinybvh loop (1 thread)")
    ax[0].set(xscale="log", yscale="log", xlabel="meshes per batch", ylabel="meshes / s", title="build throughput")
    ax[0].legend(fontsize=8)
    runs = [("build", b["batched_s"], b["loop_s"], peer and peer["build_ms"] / 1e3)]
    if "optimize" in out:
        runs.append((out["optimize"]["method"], out["optimize"]["batched_s"], out["optimize"]["loop_s"],
                     peer and peer["optimize_ms"] / 1e3))
    x = np.arange(len(runs))
    ax[1].bar(x - 0.25, [r[1] for r in runs], 0.25, label="batched")
    ax[1].bar(x, [r[2] for r in runs], 0.25, label="loop")
    if peer:
        ax[1].bar(x + 0.25, [r[3] for r in runs], 0.25, label="tinybvh loop")
    ax[1].set(xticks=x, xticklabels=[r[0] for r in runs], yscale="log", ylabel="seconds (warm)",
              title=f"{out['meshes']} meshes")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
