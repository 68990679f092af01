"""Time every builder on the shared meshes: compile (cold and warm) apart from build time.

    python bench/bench_build.py [--meshes bunny,spot] [--repeat 3] [--out bench/results]

Each (mesh, builder) runs in two fresh child processes sharing a new, empty JAX
persistent compilation cache: the first compiles cold, the second finds the compiled
builder in the cache (warm). Build time is the median of ``--repeat`` runs after
compilation. Writes ``build.json`` and ``build.md`` to ``--out``.
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
]


def child(mesh_path: str, options: dict, repeat: int) -> dict:
    """Runs inside a fresh process: compile, then time the build."""
    import jax
    import numpy as np

    import jaxbvh
    from jaxbvh.build import _build, scene_scale
    from jaxbvh.io import load_mesh

    mesh = load_mesh(mesh_path)
    lo, hi = mesh.local_boxes()
    n = lo.shape[0]
    cap = jaxbvh.capacity_bucket(n)
    lo_p = np.full((cap, 3), np.inf, np.float32)
    hi_p = np.full((cap, 3), -np.inf, np.float32)
    lo_p[:n], hi_p[:n] = lo, hi
    args = (jax.numpy.asarray(lo_p), jax.numpy.asarray(hi_p), np.int32(n), np.int32(options.get("max_leaf", 1)),
            np.float32(1), np.float32(1), np.float32(scene_scale(lo, hi)))
    static = dict(method=options["method"], bins=options.get("bins", 16) if options["method"] == "binned" else 0)
    t0 = time.perf_counter()
    _build.lower(*args, **static).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        tree = jaxbvh.build(lo, hi, **options)
        jax.block_until_ready(tree)
        times.append(time.perf_counter() - t0)
    jaxbvh.validate(tree, lo, hi)
    t = jaxbvh.to_numpy(tree)
    costs = jaxbvh.all_costs(tree)
    return dict(triangles=int(n), capacity=cap, compile_s=compile_s, build_s=statistics.median(times),
                nodes=jaxbvh.tree.node_count(t), depth=int(jaxbvh.tree.depth(t).max()),
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", default=",".join(MESHES), help="comma-separated names from: " + ", ".join(MESHES))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = parser.parse_args(argv)
    if not SHARED.exists():
        sys.exit(f"bench needs the shared data at {SHARED}")
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
