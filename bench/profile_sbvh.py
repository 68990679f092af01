"""Where the SBVH engine's time goes: each level timed alone, and its parts.

    python bench/profile_sbvh.py [--meshes legocar,rocker-arm] [--repeat 3] [--max-leaf 16]

Runs the engine's levels one at a time from the host (the program each level runs in is
chosen as :func:`jaxbvh.builders.sbvh.engine` chooses it) and times, per level (min of
``--repeat``, process CPU time, ms): the whole level, and apart from it its parts on the
same state: the compaction of the level's references (``view``), the object split, the
spatial search (``spatial``: pieces and sweeps) and the sides of the spatial splits
(``sides``: clipping and unsplitting). ``rest``: the level less those parts (leaf test,
partition, scatters back into the state). Prints one row per level and the sums.
This script reads the engine's private names: it profiles the engine, it is no API.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
MESHES = {"legocar": "meshes/legocar.obj", "fandisk": "meshes/fandisk.obj", "rocker-arm": "meshes/rocker-arm.obj"}


def cpu_ms(call, repeat):
    import jax
    jax.block_until_ready(call())  # compile
    best = np.inf
    for _ in range(repeat):
        c = time.process_time()
        jax.block_until_ready(call())
        best = min(best, time.process_time() - c)
    return 1e3 * best


def profile(name, args):
    import jax
    import jax.numpy as jnp

    import jaxbvh
    from jaxbvh.builders import SBVHConfig
    from jaxbvh.builders import sbvh as eng
    from jaxbvh.builders import sbvh_rules as rules
    from jaxbvh.builders import sbvh_splits as splits
    from jaxbvh.numerics import half_area, scene_scale

    mesh = jaxbvh.load_mesh(SHARED / "data" / MESHES[name])
    tri = mesh.local_triangles().astype(np.float32)
    config = SBVHConfig(max_leaf=args.max_leaf)
    n = tri.shape[0]
    refs = eng.reference_slots(n, config)
    bins, spatial_bins = config.bins, config.spatial_bins
    lo, hi = tri.min(1), tri.max(1)
    scale = np.float32(scene_scale(lo, hi))
    threshold = np.float32(config.alpha) * half_area(lo.min(0), hi.max(0), scale)
    tri_p = np.zeros((refs, 3, 3), np.float32)
    tri_p[:n] = tri
    t = jnp.asarray(tri_p)
    scene = eng._Scene(t, t.reshape(refs, 9).T, jnp.float32(scale), jnp.float32(threshold), jnp.int32(args.max_leaf),
                       jnp.float32(1), jnp.float32(1))
    state = jax.device_put(eng._initial(np.asarray(t), n))
    live = eng.live_slots(refs)
    programs = eng.level_programs(refs)

    def fits(s, f, m):
        return int(s.next_free - s.level_start) <= f and int(jnp.sum(eng._in_level(s))) <= m

    level_fn = {}

    def parts(f, m):
        if (f, m) in level_fn:
            return level_fn[(f, m)]

        @jax.jit
        def prefix(s):
            view = eng._view(s, m)
            in_level = (view.node >= s.level_start) & (view.node < s.next_free)
            seg = jnp.where(in_level, view.node - s.level_start, f).astype(jnp.int32)
            count = splits.segment(jax.ops.segment_sum, in_level.astype(jnp.int32), seg, f)
            node_lo = splits.segment(jax.ops.segment_min, view.lo, seg, f)
            node_hi = splits.segment(jax.ops.segment_max, view.hi, seg, f)
            return view, seg, count, node_lo, node_hi

        @jax.jit
        def obj(view, seg):
            return splits.object_split(view.lo, view.hi, seg, f, scene.scale, bins)

        @jax.jit
        def spatial(view, seg, node_lo, node_hi, tried, node_bins, count):
            return splits.spatial_split(scene.columns, view.prim, view.lo, view.hi, seg, node_lo, node_hi, tried,
                                        node_bins, count, f, scene.scale, spatial_bins)

        @jax.jit
        def sides(view, seg, node_lo, node_hi, sp, ref_bins, node_bins):
            return splits.spatial_sides(scene.columns, view.prim, view.lo, view.hi, seg, node_lo, node_hi, sp,
                                        ref_bins, node_bins, f, scene.scale, spatial_bins)

        level = jax.jit(partial(eng._level, scene, bins=bins, spatial_bins=spatial_bins, slots=f, live=m))
        level_fn[(f, m)] = (prefix, obj, spatial, sides, level)
        return level_fn[(f, m)]

    depth = 0
    stats = []
    total = {}
    print(f"# {name}: {n} triangles, R = {refs}, M = {live}, level programs (F, M) {programs}")
    print("depth (F,M) open refs tried pieces | level view object spatial sides rest (CPU ms)")
    while int(state.next_free) > int(state.level_start):
        f, m = next(p for p in programs if fits(state, *p))  # as the engine picks
        prefix, obj, spatial, sides, level = parts(f, m)
        view, seg, count, node_lo, node_hi = prefix(state)
        o, bin3 = obj(view, seg)
        open_nodes = int(state.next_free - state.level_start)
        is_open = jnp.arange(f) < open_nodes
        tried = is_open & (o.cost < jnp.inf) & (count > 1) & (splits.overlap_area(o, scene.scale) > scene.threshold)
        node_bins = rules.spatial_bins(count, spatial_bins)
        row = {"level": 0.0, "view": 0.0, "object": 0.0, "spatial": 0.0, "sides": 0.0}
        if not args.stats:
            row = {"level": cpu_ms(lambda: level(state), args.repeat),
                   "view": cpu_ms(lambda: prefix(state), args.repeat),
                   "object": cpu_ms(lambda: obj(view, seg), args.repeat)}
        n_tried = int(tried.sum())
        pieces = 0
        if n_tried and args.stats:
            sp, _ = spatial(view, seg, node_lo, node_hi, tried, node_bins, count)
            area = half_area(node_lo, node_hi, scene.scale)
            take = np.asarray(tried & (sp.cost * (1 + 2**-20) < o.cost))
            tr = np.asarray(tried)
            ov = np.asarray(splits.overlap_area(o, scene.scale))
            stats.append(np.stack([np.full(tr.sum(), depth), np.asarray(count)[tr], ov[tr] / float(threshold) * 1e-5,
                                   ov[tr] / np.asarray(area)[tr], take[tr], (np.asarray(o.cost)[tr]
                                   - np.asarray(sp.cost)[tr]) / np.asarray(o.cost)[tr]], 1))
        if n_tried and not args.stats:
            row["spatial"] = cpu_ms(lambda: spatial(view, seg, node_lo, node_hi, tried, node_bins, count), args.repeat)
            sp, ref_bins = spatial(view, seg, node_lo, node_hi, tried, node_bins, count)
            row["sides"] = cpu_ms(lambda: sides(view, seg, node_lo, node_hi, sp, ref_bins, node_bins), args.repeat)
            livemask = np.asarray((seg < f) & jnp.take(tried, jnp.clip(seg, 0, f - 1)))
            b0, b1 = np.asarray(ref_bins.entry), np.asarray(ref_bins.exit)
            pieces = int(((b1 - b0 + 1) * livemask[:, None]).sum())
        elif not args.stats:
            row["spatial"] = row["sides"] = 0.0
        row["rest"] = row["level"] - row["view"] - row["object"] - row["spatial"] - row["sides"]
        for k, v in row.items():
            total[k] = total.get(k, 0.0) + v
        print(f"{depth:3d} ({f},{m}) {open_nodes:5d} {int(jnp.sum(eng._in_level(state))):6d} {n_tried:5d} "
              f"{pieces:7d} | " + " ".join(f"{row[k]:6.1f}" for k in ("level", "view", "object", "spatial", "sides",
                                                                       "rest")), flush=True)
        state = level(state)
        depth += 1
    if args.stats:
        np.save(f"/tmp/sbvh_stats_{name}.npy", np.concatenate(stats))
    print("sum | " + " ".join(f"{k} {v:.0f}" for k, v in total.items()), flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="legocar,rocker-arm")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--max-leaf", type=int, default=16)
    parser.add_argument("--stats", action="store_true", help="save per tried node: depth, count, overlap / root "
                        "area, overlap / node area, taken, gain (to /tmp/sbvh_stats_MESH.npy); no timing")
    args = parser.parse_args(argv)
    for name in args.meshes.split(","):
        profile(name, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
