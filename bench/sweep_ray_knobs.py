"""Sweep the walk's static knobs (lanes, batch, steps between refills) on a few ray sets.

    python bench/sweep_ray_knobs.py [--lanes 512 2048] [--batch 16384 65536] [--refill 4]

Rays per CPU-second (warm, best of 2) for bunny random / bounce rays (its tinybvh binary
tree) and the 6,320-deep chain; prints JSON lines. bench/results/ray_anatomy.md quotes it.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--lanes", nargs="+", type=int, default=[512, 2048])
    p.add_argument("--batch", nargs="+", type=int, default=[16384, 65536])
    p.add_argument("--refill", nargs="+", type=int, default=[4])
    p.add_argument("--rays", type=int, default=20000)
    p.add_argument("--chain-rays", type=int, default=2000)
    p.add_argument("--sets", nargs="+", default=["bunny random", "bunny bounce", "chain 6320"])
    args = p.parse_args()
    import jax

    import jaxbvh
    from jaxbvh import rays
    from jaxbvh.rays import stack_walk
    from bench_rays import DATA, chain_tree, load_triangles

    bunny = load_triangles("bunny")
    tree, _ = jaxbvh.load(DATA / "trees" / "bunny_binned_ref.npz")
    sets = {}
    for name in args.sets:
        if name.startswith("bunny"):
            kind = name.split()[1]
            sets[name] = (tree, bunny, *rays.make_rays(jax.random.key(0), kind, tree, bunny, args.rays))
        else:
            n = int(name.split()[1])
            rng = np.random.default_rng(0)
            tri = bunny[np.sort(rng.choice(len(bunny), n, replace=False))]
            ct = chain_tree(tri)
            sets[name] = (ct, tri, *rays.make_rays(jax.random.key(1), "random", ct, tri, args.chain_rays))
    for refill in args.refill:
        stack_walk.REFILL_EVERY = refill
        jax.clear_caches()
        for lanes in args.lanes:
            for batch in args.batch:
                for name, (t, tri, o, d) in sets.items():
                    def go():
                        return rays.closest_hit(t, tri, o, d, lanes=lanes, batch=batch)
                    c = cpu()
                    go()
                    first = cpu() - c
                    best = None
                    for _ in range(1 if name.startswith("chain") else 2):
                        c = cpu()
                        h = go()
                        s = cpu() - c
                        best = s if best is None else min(best, s)
                    steps = float(np.mean(h.nodes_visited + h.prim_tests))
                    print(json.dumps(dict(set=name, lanes=lanes, batch=batch, refill=refill, rays=len(o),
                                          cpu_s=round(best, 3), rays_per_cpu_s=round(len(o) / best),
                                          steps_per_cpu_s=round(len(o) * steps / best),
                                          first_call_cpu_s=round(first - best, 2),
                                          load=os.getloadavg()[0])), flush=True)


if __name__ == "__main__":
    main()
