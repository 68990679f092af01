"""A/B: rays per CPU-second of several checkouts, alternated round by round (shared machine).

    python bench/ab_rays.py NAME=PATH [NAME=PATH ...] [--rounds 3]

Each round runs one child per checkout (in turn, ``PYTHONPATH=PATH``) that traces the same
rays: bunny random and bounce rays (20,000, its tinybvh binary tree) and 2,048 random
rays through the 500- and 6,320-deep chains; warm CPU seconds (best of 2 in the child).
Prints the median and the best over rounds per checkout and set as JSON (under load the
best is the steadier estimate: contention only ever slows a run).
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

CHILD = r'''
import json, os, resource, sys
sys.path.insert(0, %(bench)r)
import jax, numpy as np
import jaxbvh
from jaxbvh import rays
from bench_rays import DATA, chain_tree, load_triangles
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
bunny = load_triangles("bunny")
tree, _ = jaxbvh.load(DATA / "trees" / "bunny_binned_ref.npz")
sets = {}
for kind in %(kinds)r:
    sets["bunny " + kind] = (tree, bunny, *rays.make_rays(jax.random.key(0), kind, tree, bunny, 20000))
for n in %(chains)r:
    rng = np.random.default_rng(0)
    tri = bunny[np.sort(rng.choice(len(bunny), n, replace=False))]
    ct = chain_tree(tri)
    sets["chain %%d" %% n] = (ct, tri, *rays.make_rays(jax.random.key(1), "random", ct, tri, 2048))
out = {}
for name, (t, tri, o, d) in sets.items():
    rays.closest_hit(t, tri, o, d)
    best = None
    for _ in range(2):
        c = cpu(); h = rays.closest_hit(t, tri, o, d); s = cpu() - c
        best = s if best is None else min(best, s)
    out[name] = dict(cpu=best, rays=len(o), steps=float(np.mean(h.nodes_visited + h.prim_tests)),
                     prim=h.prim.tolist()[:0])
    out[name]["checksum"] = int(np.sum(h.prim.astype(np.int64))) + int(np.sum(h.box_tests))
out["load"] = os.getloadavg()[0]
print(json.dumps(out))
'''


def main(argv):
    rounds = 3
    kinds = ["random", "bounce"]
    chains = [500, 6320]
    pairs = []
    it = iter(argv)
    for a in it:
        if a == "--rounds":
            rounds = int(next(it))
        elif a == "--chains":
            chains = [int(x) for x in next(it).split(",") if x]
        elif a == "--kinds":
            kinds = [x for x in next(it).split(",") if x]
        else:
            name, path = a.split("=", 1)
            pairs.append((name, path))
    code = CHILD % dict(bench=str(HERE), kinds=kinds, chains=chains)
    results = {name: [] for name, _ in pairs}
    for r in range(rounds):
        for name, path in pairs:
            env = dict(os.environ, PYTHONPATH=path)
            env.pop("XLA_FLAGS", None)
            env.setdefault("JAXBVH_CACHE_DIR", "/tmp/jaxbvh_ab_cache")
            out = subprocess.run([sys.executable, "-c", code], env=env, check=True, stdout=subprocess.PIPE,
                                 text=True).stdout
            results[name].append(json.loads(out.strip().splitlines()[-1]))
            print(name, r, {k: (round(v["rays"] / v["cpu"]) if isinstance(v, dict) else v)
                            for k, v in results[name][-1].items()}, file=sys.stderr, flush=True)
    summary = {}
    for name, runs in results.items():
        summary[name] = {k: dict(rays_per_cpu_s=round(statistics.median(x[k]["rays"] / x[k]["cpu"] for x in runs)),
                                 best_rays_per_cpu_s=round(max(x[k]["rays"] / x[k]["cpu"] for x in runs)),
                                 steps=runs[0][k]["steps"], checksum=runs[0][k]["checksum"])
                         for k in runs[0] if k != "load"}
        summary[name]["load"] = [x["load"] for x in runs]
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
