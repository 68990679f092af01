"""Two-level traversal: the native engine (numba) beside the JAX walk, rays per CPU second.

    python bench/bench_twolevel_native.py             # pile of 12 cows and a crowd of 64, random + camera rays
    python bench/bench_twolevel_native.py --quick     # fewer rays and repeats

Scenes (jaxbvh.scenes, the bundled spot mesh): a pile of 12 randomly rotated cows around
one centre (overlapping objects, re-braided: threshold 0.1, the top level opens them) and
a crowd of 64 instances (plain two-level, ``threshold = inf``). Rays: random rays in the
root box and camera rays framing it (jaxbvh.rays.make_rays on the flattened tree).
For each scene and ray set, both engines in one process, alternated (``--repeat``
rounds): CPU seconds (user + system) of :func:`jaxbvh.twolevel.closest_hit` warm (its
first call, which compiles, is not counted), rays per CPU s, and whether hits and
counters agree. Then each engine's first call in a fresh process with an empty cache
(cold: compiles) and again with that cache (warm: loads the compiled code). Runs without
the test suite's XLA flags. Writes bench/results/bench_twolevel_native.json and .md
(``--quick``: bench_twolevel_native_quick.*).
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
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results"


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def scenes_and_rays(n_rays: int):
    import jax
    import numpy as np

    import jaxbvh
    from jaxbvh import scenes, twolevel
    from jaxbvh.io import bundled_mesh_path, load_mesh

    spot = load_mesh(bundled_mesh_path())
    v = np.asarray(spot.local_triangles(), np.float64).reshape(-1, 3)
    f = np.arange(v.shape[0], dtype=np.int32).reshape(-1, 3)
    pile = scenes.pile(jax.random.key(0), v, f, 12)
    crowd = scenes.instanced_scene(jax.random.key(1), [(v, f)], 64, spread=0.5, upright=True)
    out = []
    for name, mesh, threshold in (("pile-12 (re-braided)", pile, 0.1), ("crowd-64 (two-level)", crowd, float("inf"))):
        tl = jaxbvh.to_numpy(twolevel.build(mesh, threshold=threshold))
        flat = twolevel.flatten(tl)
        for kind in ("random", "camera"):
            o, d = jaxbvh.rays.make_rays(jax.random.key(2), kind, flat, None, n_rays)
            out.append((name, mesh.n_triangles, int(tl.bref_count), kind, tl, np.asarray(o), np.asarray(d)))
    return out


def in_process(args):
    import numpy as np

    from jaxbvh import twolevel

    rows = []
    for name, tris, brefs, kind, tl, o, d in scenes_and_rays(args.rays):
        first = {e: twolevel.closest_hit(tl, o, d, engine=e) for e in ("jax", "native")}  # compile
        seconds = {"jax": [], "native": []}
        for _ in range(args.repeat):
            for engine in ("jax", "native"):
                c = cpu()
                twolevel.closest_hit(tl, o, d, engine=engine)
                seconds[engine].append(cpu() - c)
        a, b = first["jax"], first["native"]
        same_t = (a.t == b.t) | (np.isinf(a.t) & np.isinf(b.t))
        row = {"scene": name, "triangles": tris, "brefs": brefs, "kind": kind, "rays": int(o.shape[0]),
               "hits": int(np.sum(b.prim >= 0)), "load": os.getloadavg()[0],
               "jax_cpu_s": min(seconds["jax"]), "native_cpu_s": min(seconds["native"]),
               "prim_equal": float(np.mean(a.prim == b.prim)),
               "counters_equal": float(np.mean((a.box_tests == b.box_tests) & (a.prim_tests == b.prim_tests)
                                               & (a.nodes_visited == b.nodes_visited))),
               "t_bit_equal": float(np.mean(same_t)),
               "box_tests_per_ray": float(np.mean(b.box_tests)), "prim_tests_per_ray": float(np.mean(b.prim_tests))}
        row["jax_rays_per_cpu_s"] = row["rays"] / max(row["jax_cpu_s"], 1e-9)
        row["native_rays_per_cpu_s"] = row["rays"] / max(row["native_cpu_s"], 1e-9)
        rows.append(row)
        print(row, file=sys.stderr, flush=True)
    return rows


FIRST_CALL = """
import resource, sys
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
import jax, numpy as np, jaxbvh
from jaxbvh import scenes, twolevel
from jaxbvh.io import bundled_mesh_path, load_mesh
spot = load_mesh(bundled_mesh_path())
v = np.asarray(spot.local_triangles(), np.float64).reshape(-1, 3)
f = np.arange(v.shape[0], dtype=np.int32).reshape(-1, 3)
tl = jaxbvh.to_numpy(twolevel.build(scenes.pile(jax.random.key(0), v, f, 12), threshold=0.1))
o, d = jaxbvh.rays.make_rays(jax.random.key(2), "random", twolevel.flatten(tl), None, 1000)
ready = cpu()
twolevel.closest_hit(tl, o, d, engine=sys.argv[1])
print(cpu() - ready)
"""


def first_calls():
    """CPU s of a process's first two-level closest-hit call (pile-12, 1,000 rays) per
    engine, with an empty cache (cold) and in a second process (warm: loaded from it)."""
    out = []
    for engine in ("native", "jax"):
        with tempfile.TemporaryDirectory() as tmp:
            env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "NUMBA_CACHE_DIR", "JAXBVH_CACHE")}
            env.update(JAXBVH_CACHE_DIR=tmp, PYTHONPATH=str(REPO))
            for state in ("cold", "warm"):
                done = subprocess.run([sys.executable, "-c", FIRST_CALL, engine], env=env, check=True,
                                      stdout=subprocess.PIPE, text=True)
                out.append({"engine": engine, "cache": state, "first_call_cpu_s": float(done.stdout.split()[-1]),
                            "load": os.getloadavg()[0]})
                print(out[-1], file=sys.stderr, flush=True)
    return out


def write(result, quick: bool):
    sys.path.insert(0, str(REPO))
    from jaxbvh.files import atomic_write

    out = RESULTS / ("bench_twolevel_native_quick" if quick else "bench_twolevel_native")
    lines = ["# Two-level traversal: the native engine beside the JAX walk (closest hit)\n",
             f"{result['meta']['machine']}, {result['meta']['cpus']} CPUs (shared: load given per row); "
             f"`python bench/bench_twolevel_native.py{' --quick' if quick else ''}`. CPU s (user + system) "
             f"of `jaxbvh.twolevel.closest_hit` warm, best of {result['meta']['repeat']} alternated rounds, "
             "both engines in one process; `t` bit-equal: rays whose distance both engines compute to the "
             "same bit (XLA contracts multiply-adds in the instance transform, numba does not; the native "
             "engine equals the NumPy twin on every ray, tests/twolevel/test_twolevel_native.py).\n",
             "| scene | triangles | BRefs | rays | hits | JAX rays/CPU s | native rays/CPU s | native / JAX | "
             "prim equal | counters equal | t bit-equal | box tests/ray | load |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['triangles']:,} | {r['brefs']} | {r['rays']:,} {r['kind']} | "
                     f"{r['hits']:,} | {r['jax_rays_per_cpu_s']:,.0f} | {r['native_rays_per_cpu_s']:,.0f} | "
                     f"{r['native_rays_per_cpu_s'] / r['jax_rays_per_cpu_s']:.1f}x | {r['prim_equal']:.4f} | "
                     f"{r['counters_equal']:.4f} | {r['t_bit_equal']:.3f} | {r['box_tests_per_ray']:.1f} | "
                     f"{r['load']:.1f} |")
    lines += ["", "First call in a fresh process (pile-12, 1,000 random rays; CPU s of the call alone, "
              "after the scene is built): cold = empty cache (numba or XLA compiles), warm = a second "
              "process with that cache.\n", "| engine | cache | first call CPU s | load |", "|---|---|---:|---:|"]
    for r in result["first_calls"]:
        lines.append(f"| {r['engine']} | {r['cache']} | {r['first_call_cpu_s']:.2f} | {r['load']:.1f} |")
    with atomic_write(out.with_suffix(".json"), "w") as f:
        json.dump(result, f, indent=1)
    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(out.with_suffix(".md"))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--rays", type=int, default=None)
    p.add_argument("--repeat", type=int, default=None)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    args.rays = args.rays or (4000 if args.quick else 20000)
    args.repeat = args.repeat or (2 if args.quick else 3)
    if args.child:
        print(json.dumps(in_process(args)))
        return
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("XLA_FLAGS", None)  # the library's own compile settings, not the test suite's
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--rays", str(args.rays),
           "--repeat", str(args.repeat)]
    rows = json.loads(subprocess.run(cmd, env=env, check=True, stdout=subprocess.PIPE, text=True).stdout)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "rays": args.rays, "repeat": args.repeat}
    write({"meta": meta, "rows": rows, "first_calls": first_calls()}, args.quick)


if __name__ == "__main__":
    main()
