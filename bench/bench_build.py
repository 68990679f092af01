"""Time every builder on the shared meshes: compile (cold and warm) apart from build time.

    python bench/bench_build.py [--meshes bunny,spot] [--repeat 3] [--out bench/results]
    python bench/bench_build.py --trade [--inputs spot,bunny,big] [--repeat 3]

Each (mesh, builder) runs in two fresh child processes sharing a new, empty JAX
persistent compilation cache: the first compiles cold, the second finds the compiled
builder in the cache (warm). Build time is the median of ``--repeat`` runs after
compilation; compile time is the first call's time less that. Writes ``build.json``
and ``build.md`` to ``--out``.

``--trade`` measures the speed/quality trade of all builders in one process (programs
compiled once per capacity bucket, the first call timed apart): SAH and warm build time
of median, LBVH (30- and 63-bit codes), PLOC (r = 4, 8, 16, 25), binned and sweep, and
of the pipelines LBVH + hill climbing and PLOC (r = 16) + hill climbing
(:func:`jaxbvh.optimize.rotate.hill_climb`; pipeline time = warm build + warm climb) and LBVH +
treelet restructuring (:func:`jaxbvh.optimize.treelet.restructure`, one warm run; not on ``big``,
where it takes minutes), on the shared
meshes, two overlapping bunnies (``bunny2``, 138,902 triangles: the 120k class of the
issue's tinybvh timing) and the 1.05M-triangle ``big`` input of
``bench/bench_rotate.py``. Wall time and process CPU time are both recorded: on a shared
machine CPU time is the steadier measure of the work. Writes ``build_trade.json``,
``build_trade.md`` and the Pareto plot ``build_trade.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
MESHES = {
    "spot": "meshes/spot.obj", "cow": "meshes/cow.obj", "teapot": "meshes/teapot.obj",
    "fandisk": "meshes/fandisk.obj", "legocar": "meshes/legocar.obj", "rocker-arm": "meshes/rocker-arm.obj",
    "drone": "scenes/drone/scene.gltf", "bunny": "meshes/stanford-bunny.obj",
}
CONFIGS = [  # (label, builder options)
    ("sweep", dict(method="sweep")),
    ("binned-16", dict(method="binned", bins=16)),
    ("binned-8 leaf<=8", dict(method="binned", bins=8, max_leaf=8)),
    ("median", dict(method="median")),
    ("lbvh", dict(method="lbvh")),
    ("ploc r=16", dict(method="ploc", radius=16)),
]
TRADE = [  # (label, builder options, optimizer after it: None, "hc" or "treelet")
    ("median", dict(method="median"), None),
    ("lbvh", dict(method="lbvh"), None),
    ("lbvh 63-bit", dict(method="lbvh", morton_bits=63), None),
    ("ploc r=4", dict(method="ploc", radius=4), None),
    ("ploc r=8", dict(method="ploc", radius=8), None),
    ("ploc r=16", dict(method="ploc", radius=16), None),
    ("ploc r=25", dict(method="ploc", radius=25), None),
    ("binned-16", dict(method="binned", bins=16), None),
    ("sweep", dict(method="sweep"), None),
    ("lbvh + HC", dict(method="lbvh"), "hc"),
    ("ploc r=16 + HC", dict(method="ploc", radius=16), "hc"),
    ("lbvh + treelet", dict(method="lbvh"), "treelet"),
]
TINYBVH_BINNED_S = (0.088, 0.099)  # the issue: tinybvh's binned build, one C++ thread, 120-150k triangles


def child(mesh_path: str, options: dict, repeat: int) -> dict:
    """Runs inside a fresh process: the first call (compile + build), then the warm builds."""
    import jax

    import jaxbvh
    from jaxbvh.io import load_mesh

    mesh = load_mesh(mesh_path)
    lo, hi = mesh.local_boxes()
    n = lo.shape[0]
    t0 = time.perf_counter()
    jax.block_until_ready(jaxbvh.build(lo, hi, **options))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        tree = jaxbvh.build(lo, hi, **options)
        jax.block_until_ready(tree)
        times.append(time.perf_counter() - t0)
    build_s = statistics.median(times)
    jaxbvh.validate(tree, lo, hi)
    t = jaxbvh.to_numpy(tree)
    costs = jaxbvh.all_costs(tree)
    return dict(triangles=int(n), capacity=jaxbvh.capacity_bucket(n), compile_s=max(first - build_s, 0.0),
                build_s=build_s, nodes=jaxbvh.tree.node_count(t), depth=int(jaxbvh.tree.depth(t).max()),
                max_leaf_size=int(t.prim_count.max()), **costs)


def run_child(mesh_path, options, repeat, cache_dir):
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(cache_dir),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    code = ("import json, sys; sys.path.insert(0, %r); from bench.bench_build import child; "
            "print('RESULT' + json.dumps(child(%r, %r, %d)))" % (str(ROOT), str(mesh_path), options, repeat))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    line = [l for l in out.stdout.splitlines() if l.startswith("RESULT")][-1]
    return json.loads(line[len("RESULT"):])


def trade_inputs(names):
    """``(name, lo, hi)`` scene-frame float32 boxes of each named input."""
    import numpy as np

    from bench.bench_rotate import big_scene
    from jaxbvh.io import load_mesh
    from jaxbvh.tree.frame import Frame

    for name in names:
        if name in MESHES:
            lo, hi = load_mesh(SHARED / MESHES[name]).local_boxes()
        else:
            copies, walls = {"bunny2": (2, 0), "big": (15, 4000)}[name]
            lo, hi = big_scene(copies, walls)
            frame = Frame.fit(lo, hi)
            lo, hi = frame.to_local(lo).astype(np.float32), frame.to_local(hi).astype(np.float32)
        yield name, lo, hi


def timed(fn, repeat):
    """``(result, first call s, warm wall s (median), warm CPU s (median))``."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    walls, cpus = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = jax.block_until_ready(fn())
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return out, first, statistics.median(walls), statistics.median(cpus)


def run_trade(args):
    import jax

    import jaxbvh
    from jaxbvh.optimize import rotate, treelet

    rows = []
    for name, lo, hi in trade_inputs(args.inputs.split(",")):
        big = lo.shape[0] > 500_000
        for label, options, after in TRADE:
            if after == "treelet" and big:
                continue  # minutes per run at 1M triangles (bench/results/optimize.md: 9 s on 69k)
            repeat = 1 if big and options["method"] in ("sweep", "binned") else args.repeat
            tree, first, wall, cpu = timed(lambda: jaxbvh.build(lo, hi, **options), repeat)
            jaxbvh.validate(tree, lo, hi)
            row = dict(input=name, triangles=int(lo.shape[0]), config=label, first_s=first, build_s=wall,
                       build_cpu_s=cpu, build_sah=float(jaxbvh.sah(tree)))
            if after:
                def optimized(tree=tree, after=after):
                    if after == "hc":
                        return rotate.hill_climb(tree, split_axes=False)
                    result = treelet.restructure(tree, split_axes=False)
                    jax.block_until_ready(result.tree)
                    return result

                result, climb_first, climb_wall, climb_cpu = timed(
                    optimized, args.repeat if after == "hc" else 1)
                jaxbvh.validate(result.tree, lo, hi)
                tree = result.tree
                row.update(climb_s=climb_wall, climb_cpu_s=climb_cpu, climb_first_s=climb_first,
                           passes=int(result.steps))
            row.update(seconds=row["build_s"] + row.get("climb_s", 0.0),
                       cpu_seconds=row["build_cpu_s"] + row.get("climb_cpu_s", 0.0),
                       sah=float(jaxbvh.sah(tree)), nodes=jaxbvh.tree.node_count(tree),
                       depth=int(jaxbvh.tree.depth(tree).max()))
            rows.append(row)
            print(f"{name:10s} {label:16s} n={row['triangles']:8d} first {first:6.2f}s  warm {row['seconds']:7.3f}s "
                  f"(cpu {row['cpu_seconds']:6.3f}s)  SAH {row['sah']:.3f}", flush=True)
    return rows


def pareto(points):
    """Indices of the points no other point beats in both time and SAH."""
    return [i for i, (t, s) in enumerate(points)
            if not any((t2 <= t and s2 <= s) and (t2 < t or s2 < s) for t2, s2 in points)]


def write_trade(rows, args):
    import jax

    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, JAX {jax.__version__}"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "build_trade.json").write_text(json.dumps(dict(machine=machine, repeat=args.repeat, rows=rows), indent=1))
    lines = [f"# Builders: time against SAH ({machine}; float32; Ct = Ci = 1; max_leaf = 1)", "",
             "Warm seconds, median of the repeats (1 for sweep and binned on `big`); CPU = process CPU "
             "seconds (all threads), steadier than wall time on a shared machine. Pipelines: warm build "
             "+ warm hill climbing (`jaxbvh.rotate.hill_climb`, split axes off) or + one warm treelet "
             "restructuring (`jaxbvh.treelet.restructure`, to convergence; not on `big`). `vs sweep`: SAH change "
             "and time ratio against the sweep build of the same input. First call = compile + build.", ""]
    for name in dict.fromkeys(r["input"] for r in rows):
        mine = [r for r in rows if r["input"] == name]
        sweep = next((r for r in mine if r["config"] == "sweep"), None)
        lines += [f"## {name} ({mine[0]['triangles']:,} triangles)", "",
                  "| config | SAH | vs sweep | seconds | CPU s | time / sweep | first call s | depth |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in mine:
            rel = f"{100 * (r['sah'] / sweep['sah'] - 1):+.1f}%" if sweep else "-"
            ratio = f"{r['seconds'] / sweep['seconds']:.3f}" if sweep else "-"
            lines.append(f"| {r['config']} | {r['sah']:.3f} | {rel} | {r['seconds']:.3f} | {r['cpu_seconds']:.3f} | "
                         f"{ratio} | {r['first_s']:.1f} | {r['depth']} |")
        lines.append("")
    lines.append(f"tinybvh's binned builder (one C++ thread) on 120-150k triangles, from the issue: "
                 f"{TINYBVH_BINNED_S[0] * 1e3:.0f}-{TINYBVH_BINNED_S[1] * 1e3:.0f} ms.")
    (out / "build_trade.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    names = list(dict.fromkeys(r["input"] for r in rows))
    shown = [n for n in ("legocar", "bunny", "bunny2", "big") if n in names] or names[:4]
    fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 3.8), squeeze=False)
    colors = dict(zip([c for c, _, _ in TRADE], plt.cm.tab20.colors))
    for ax, name in zip(axes[0], shown):
        mine = [r for r in rows if r["input"] == name]
        front = pareto([(r["seconds"], r["sah"]) for r in mine])
        for i, r in enumerate(mine):
            ax.scatter(r["seconds"], r["sah"], color=colors[r["config"]], s=50 if i in front else 25,
                       edgecolor="k" if i in front else "none", label=r["config"], zorder=3)
        pts = sorted((mine[i]["seconds"], mine[i]["sah"]) for i in front)
        ax.step([p[0] for p in pts], [p[1] for p in pts], where="post", color="gray", lw=0.8, zorder=1)
        ax.set_xscale("log")
        ax.set_title(f"{name} ({mine[0]['triangles']:,} tris)", fontsize=9)
        ax.set_xlabel("warm seconds (log)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("SAH")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=7, frameon=False)
    fig.suptitle("time vs SAH (Pareto front outlined)", fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 0.95))
    fig.savefig(out / "build_trade.png", dpi=100)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", default=",".join(MESHES), help="comma-separated names from: " + ", ".join(MESHES))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "bench" / "results"))
    parser.add_argument("--trade", action="store_true", help="time vs SAH of every builder and pipeline")
    parser.add_argument("--inputs", default=",".join(list(MESHES) + ["bunny2", "big"]),
                        help="for --trade: names from the meshes, bunny2, big")
    args = parser.parse_args(argv)
    if not SHARED.exists():
        sys.exit(f"bench needs the shared data at {SHARED}")
    if args.trade:
        sys.path.insert(0, str(ROOT))
        write_trade(run_trade(args), args)
        return
    rows = []
    for name in args.meshes.split(","):
        for label, options in CONFIGS:
            with tempfile.TemporaryDirectory() as cache:
                cold = run_child(SHARED / MESHES[name], options, args.repeat, cache)
                warm = run_child(SHARED / MESHES[name], options, 1, cache)
            row = dict(mesh=name, builder=label, **cold, warm_compile_s=warm["compile_s"])
            rows.append(row)
            print(f"{name:11s} {label:17s} n={row['triangles']:6d} compile cold {row['compile_s']:5.2f}s "
                  f"warm {row['warm_compile_s']:5.2f}s build {row['build_s']:6.3f}s SAH {row['sah']:.3f}", flush=True)
    machine = f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "build.json").write_text(json.dumps(dict(machine=machine, rows=rows), indent=1))
    lines = [f"# Builders ({machine}; JAX CPU; float32; Ct = Ci = 1)", "",
             "| mesh | builder | triangles | compile cold (s) | compile warm (s) | build (s) | SAH | Ng-Trifonov | nodes | depth |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['builder']} | {r['triangles']} | {r['compile_s']:.2f} | {r['warm_compile_s']:.2f} "
                     f"| {r['build_s']:.3f} | {r['sah']:.3f} | {r['ng_trifonov']:.2f} | {r['nodes']} | {r['depth']} |")
    (out / "build.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
