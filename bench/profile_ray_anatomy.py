"""Where a ray-traversal step's time goes (issue 43): per-iteration cost vs lanes, stack
size and batch; XLA CPU's while-loop overhead; gathers and scatters; the program's size.

    python bench/profile_ray_anatomy.py [--rays 16384] [--what all]

Counts the walk's outer ``while_loop`` iterations by wrapping ``jax.lax.while_loop`` in
this process only (a counter in the carry, read back by a callback), so CPU seconds per
iteration and per lane-step are exact. Prints JSON; bench/results/ray_anatomy.md quotes it.
Run WITHOUT the test suite's XLA_FLAGS.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


COUNTS = []


def install_counter():
    import jax
    import jax.numpy as jnp

    orig = jax.lax.while_loop

    def counting(cond, body, init):
        def c2(c):
            return cond(c[0])

        def b2(c):
            return body(c[0]), c[1] + 1

        out, n = orig(c2, b2, (init, jnp.int32(0)))
        jax.debug.callback(lambda n: COUNTS.append(int(n)), n)
        return out

    jax.lax.while_loop = counting


def best_of(fn, repeat=3):
    best = None
    for _ in range(repeat):
        c = cpu()
        out = fn()
        t = cpu() - c
        best = t if best is None else min(best, t)
    return best, out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rays", type=int, default=16384)
    p.add_argument("--what", nargs="+", default=["lanes", "stack", "micro", "program"])
    p.add_argument("--lanes", nargs="+", type=int, default=[128, 512, 2048, 8192])
    args = p.parse_args()
    install_counter()
    import jax
    import jax.numpy as jnp

    import jaxbvh
    from jaxbvh import rays
    from jaxbvh.rays import traversal
    from bench_rays import DATA, chain_tree, load_triangles

    res = {"load": os.getloadavg()}
    tri = load_triangles("bunny")
    tree, _ = jaxbvh.load(DATA / "trees" / "bunny_binned_ref.npz")
    jt = jaxbvh.tree.layout.to_jax(tree) if hasattr(jaxbvh, "tree") else None
    from jaxbvh.tree.layout import to_jax
    jt = to_jax(tree)
    o, d = rays.make_rays(jax.random.key(0), "random", tree, tri, args.rays)
    jo, jd = jnp.asarray(o), jnp.asarray(d)
    jtri = jnp.asarray(tri)
    t0 = jnp.zeros(len(o), jnp.float32)
    t1 = jnp.full(len(o), jnp.inf, jnp.float32)

    def run(lanes=None, capacity=64, tree=jt, tri=jtri, o=jo, d=jd, lo=t0, hi=t1, **kw):
        COUNTS.clear()
        h = traversal.trace_batch(tree, tri, o, d, lo, hi, capacity=capacity, lanes=lanes, **kw)
        jax.block_until_ready(h)
        jax.effects_barrier()
        return h

    rows = []
    if "lanes" in args.what:
        for lanes in args.lanes:
            run(lanes)  # compile
            s, h = best_of(lambda: run(lanes))
            it = COUNTS[-1] * traversal.__dict__.get("REFILL_EVERY", 4) if COUNTS else None
            from jaxbvh.rays import stack_walk
            it = COUNTS[-1] * stack_walk.REFILL_EVERY
            lane_steps = int(np.sum(np.asarray(h.nodes_visited))) + int(np.sum(np.asarray(h.prim_tests)))
            rows.append(dict(section="lanes", lanes=lanes, cpu_s=s, step_iterations=it,
                             us_per_iteration=1e6 * s / it, ns_per_lane_iteration=1e9 * s / (it * lanes),
                             rays_per_cpu_s=args.rays / s, steps_per_ray=lane_steps / args.rays,
                             lane_occupancy=None))
            print(rows[-1], file=sys.stderr, flush=True)
    if "stack" in args.what:
        for cap in (8, 64, 512):
            run(512, cap)
            s, h = best_of(lambda: run(512, cap))
            from jaxbvh.rays import stack_walk
            it = COUNTS[-1] * stack_walk.REFILL_EVERY
            rows.append(dict(section="stack", lanes=512, capacity=cap, cpu_s=s, step_iterations=it,
                             us_per_iteration=1e6 * s / it, rays_per_cpu_s=args.rays / s,
                             box_tests=float(np.mean(h.box_tests))))
            print(rows[-1], file=sys.stderr, flush=True)
    if "chain" in args.what:
        bunny = tri
        rng = np.random.default_rng(0)
        for n in (50, 500, 6320):
            ctri = bunny[np.sort(rng.choice(len(bunny), n, replace=False))]
            ct = chain_tree(ctri)
            co, cd = rays.make_rays(jax.random.key(1), "random", ct, ctri, 2048)
            cjt = to_jax(ct)
            kw = dict(tree=cjt, tri=jnp.asarray(ctri), o=jnp.asarray(co), d=jnp.asarray(cd),
                      lo=jnp.zeros(len(co), jnp.float32), hi=jnp.full(len(co), jnp.inf, jnp.float32))
            for lanes in (512, 2048):
                run(lanes, **kw)
                s, h = best_of(lambda: run(lanes, **kw), 1)
                from jaxbvh.rays import stack_walk
                it = COUNTS[-1] * stack_walk.REFILL_EVERY
                steps = float(np.mean(np.asarray(h.nodes_visited) + np.asarray(h.prim_tests)))
                rows.append(dict(section="chain", n=n, lanes=lanes, rays=len(co), cpu_s=s, step_iterations=it,
                                 us_per_iteration=1e6 * s / it, steps_per_ray=steps,
                                 steps_per_cpu_s=len(co) * steps / s))
                print(rows[-1], file=sys.stderr, flush=True)
    if "micro" in args.what:
        n_it = 20000
        for lanes in (512, 4096):
            x = jnp.zeros(lanes, jnp.int32)

            @jax.jit
            def empty(x):
                return jax.lax.fori_loop(0, n_it, lambda i, x: x + 1, x)

            table = jnp.asarray(np.random.default_rng(0).random((200_000, 16), np.float32))

            @jax.jit
            def gather(x):
                def body(i, c):
                    idx, acc = c
                    row = table[idx]
                    return (idx * 1103515245 + 12345) % 200_000, acc + row[:, 0]
                return jax.lax.fori_loop(0, n_it, body, (x, jnp.zeros(lanes, jnp.float32)))

            stacks = jnp.zeros((lanes, 64), jnp.int32)

            @jax.jit
            def scatter(x, st):
                def body(i, c):
                    idx, st = c
                    st = st.at[jnp.arange(lanes), idx % 64].set(idx, mode="drop")
                    return idx + 1, st
                return jax.lax.fori_loop(0, n_it, body, (x, st))

            for name, fn, a in (("empty loop", empty, (x,)), ("gather 64B rows", gather, (x,)),
                                ("scatter into [L,64]", scatter, (x, stacks))):
                jax.block_until_ready(fn(*a))
                s, _ = best_of(lambda: jax.block_until_ready(fn(*a)))
                rows.append(dict(section="micro", op=name, lanes=lanes, us_per_iteration=1e6 * s / n_it))
                print(rows[-1], file=sys.stderr, flush=True)
    if "program" in args.what:
        from jaxbvh.rays.stack_walk import lanes_for
        fn = traversal.trace_batch
        lowered = jax.jit(fn.fun,
                          static_argnames=("intersect", "mode", "capacity", "max_hits", "lanes", "leaf_width")
                          ).lower(jt, jtri, jo, jd, t0, t1)
        text = lowered.as_text()
        n_ops = sum(1 for line in text.splitlines() if "=" in line and ("stablehlo." in line or "chlo." in line))
        c = cpu()
        compiled = lowered.compile()
        compile_s = cpu() - c
        hlo = compiled.as_text()
        n_fusions = hlo.count(" fusion(")
        rows.append(dict(section="program", stablehlo_ops=n_ops, compile_cpu_s=compile_s,
                         optimized_hlo_lines=len(hlo.splitlines()), fusion_calls=n_fusions))
        Path("/tmp/ray_hlo.txt").write_text(hlo)
        print(rows[-1], file=sys.stderr, flush=True)
    res["rows"] = rows
    res["load_end"] = os.getloadavg()
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
