"""Where the re-braiding engine's time goes, level by level, and what follows the live work.

    python bench/profile_rebraid.py [--scenes fandisk,cow] [--slots 512,1024,2048] [--repeat 5]

Runs the top-level engine (:mod:`jaxbvh.twolevel.brefs_level`) one level at a time from
the host on the by-material scenes (``jaxbvh.scenes.by_material``: fandisk from
../shared/data, the cow) and prints per level: the slots of live segments (their BRefs
and their spare room, which opening may still fill), the slots of the segments that
split (two or more BRefs), the BRefs of live segments, all BRefs, the live and the
splitting segments, those with spare room (opening levels), and the level's time (min
of ``--repeat``, wall and process CPU, ms, each level dispatched alone: it includes one
call's dispatch, which the compiled loop does not pay).

A level processes the whole array (``C`` slots) whatever is live; ``bucketed`` is the
sum over levels of the capacity bucket of the live slots (or of the splitting slots), the
array a level program sized to its live part would need. A level's cost in the compiled
loop is close to proportional to its array (tenth round: 0.12 ms at 128 slots, 0.74 at
1,024, 1.61 at 2,048, median), so the estimate of what such a program saves is, over the
levels without opening (whose spare room keeps every slot live), the level's time less
its dispatch (the levels' sum less the engine's time, per level) times the share of its
array it would not need: an upper bound, before the program's gathers and scatters;
beside it, ``run_from``'s ``stage_seconds["top"]`` at the same slots (min of ``--repeat``).
This script reads the engine's private names: it
profiles the engine, it is no API.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared"
MESHES = {"fandisk": "meshes/fandisk.obj", "cow": "meshes/cow.obj"}


def best_of(call, repeat):
    """``(wall, cpu)`` ms: the minimum of ``repeat`` warm calls each."""
    import jax
    jax.block_until_ready(call())  # compile
    wall, cpu = np.inf, np.inf
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(call())
        wall, cpu = min(wall, time.perf_counter() - w), min(cpu, time.process_time() - c)
    return 1e3 * wall, 1e3 * cpu


def level_counts(state, cap):
    """The live work of the level about to run: a dict of int counts (module docstring)."""
    import jax
    import jax.numpy as jnp

    from jaxbvh.numerics import take
    from jaxbvh.twolevel.brefs_segments import segment

    segs, pos = state.segs, jnp.arange(cap)
    in_live = take(segs.live, segs.of, False)
    is_ref = in_live & (pos < take(segs.end, segs.of, 0))
    count = segment(jax.ops.segment_sum, is_ref.astype(jnp.int32), jnp.where(is_ref, segs.of, cap), cap)
    split = segs.live & (count >= 2)
    out = dict(live_slots=in_live, split_slots=in_live & take(split, segs.of, False), live_brefs=is_ref,
               brefs=state.refs.node >= 0, live_segments=segs.live, split_segments=split,
               with_room=split & (segs.extra > segs.end))
    return {k: int(jnp.sum(v)) for k, v in out.items()}


def profile(name, slots, args):
    import jax
    import jax.numpy as jnp

    from jaxbvh import scenes, twolevel
    from jaxbvh.io import load_mesh
    from jaxbvh.tree.layout import capacity_bucket
    from jaxbvh.twolevel import brefs, brefs_level
    from jaxbvh.twolevel import objects as fm
    from jaxbvh.twolevel.config import DEFAULT_BINS, DEFAULT_OVERLAP, DEFAULT_ROUNDS, DEFAULT_THRESHOLD
    from jaxbvh.twolevel.rebraid import slots_of

    mesh = scenes.by_material(*load_mesh(SHARED / "data" / MESHES[name]).objects[0])
    trees = fm.build_objects(mesh)
    forest, inst = fm.pack(mesh, trees)
    slots = slots or slots_of(mesh)
    cap = capacity_bucket(slots)
    f = jax.tree_util.tree_map(jnp.asarray, brefs.without_triangles(forest))
    placed = jax.tree_util.tree_map(jnp.asarray, inst)
    dtype = f.lo.dtype
    knobs = (jnp.asarray(DEFAULT_THRESHOLD, dtype), jnp.asarray(DEFAULT_OVERLAP, dtype), jnp.int32(DEFAULT_ROUNDS))
    n = jnp.int32(len(mesh.instances))
    level = jax.jit(partial(brefs_level.level, cap=cap, bins=DEFAULT_BINS, estimate=False))
    engine = partial(brefs.build_levels, f, placed, n, jnp.int32(slots), *knobs, cap=cap, bins=DEFAULT_BINS,
                     estimate=False)
    state = brefs_level.initial(f, placed, n, jnp.int32(slots), cap=cap)
    rows = []
    for _ in range(cap + 1):  # the engine's own bound: a top level of C slots has at most C + 1 levels
        if not bool(jnp.any(state.segs.live)):
            break
        row = level_counts(state, cap)
        row["wall"], row["cpu"] = best_of(lambda s=state: level(f, placed, s, *knobs), args.repeat)
        rows.append(row)
        state = level(f, placed, state, *knobs)
    else:
        raise RuntimeError(f"top level still open after {cap + 1} levels")
    e_wall, e_cpu = best_of(engine, args.repeat)
    top = []
    for _ in range(args.repeat + 1):  # the first compiles
        top.append(1e3 * twolevel.run_from(mesh, trees, capacity=slots).stage_seconds["top"])
    # what a level call costs beyond the compiled loop's level (its dispatch), on average
    d_wall = max(sum(r["wall"] for r in rows) - e_wall, 0.0) / len(rows)
    print(f"\n{name}: {slots} slots (array {cap}), {len(rows)} levels; run_from's top {min(top[1:]):.2f} ms, "
          f"engine {e_wall:.2f} ms wall, {e_cpu:.2f} ms CPU (min of {args.repeat}); a level call's dispatch "
          f"{d_wall:.2f} ms (levels' sum less the engine, per level)")
    print("level  live-slots  split-slots  live-BRefs  BRefs  live-segs  split-segs  with-room  wall-ms  cpu-ms")
    for i, r in enumerate(rows):
        print(f"{i:5d}  {r['live_slots']:10d}  {r['split_slots']:11d}  {r['live_brefs']:10d}  {r['brefs']:5d}  "
              f"{r['live_segments']:9d}  {r['split_segments']:10d}  {r['with_room']:9d}  {r['wall']:7.2f}  "
              f"{r['cpu']:6.2f}")
    full = len(rows) * cap
    for key in ("live_slots", "split_slots"):
        bucketed = sum(capacity_bucket(max(r[key], 1)) for r in rows)
        # time: each level without opening, less its dispatch, scaled by the share of its array not needed
        saved = sum(max(r["wall"] - d_wall, 0.0) * (1 - capacity_bucket(max(r[key], 1)) / cap)
                    for r in rows if r["with_room"] == 0)
        print(f"  {key}: sum {sum(r[key] for r in rows)}, bucketed {bucketed} of {full} slots "
              f"({1 - bucketed / full:.0%} fewer); a level program sized to them: at most {saved:.2f} ms "
              f"({saved / e_wall:.0%} of the engine, {saved / min(top[1:]):.0%} of the top) saved")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", default="fandisk,cow", help="by-material scenes: fandisk, cow")
    parser.add_argument("--slots", default="0,512,1024,2048", help="BRef slots (0: the scene's default)")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    for name in args.scenes.split(","):
        for slots in (int(s) for s in args.slots.split(",")):
            profile(name, slots, args)


if __name__ == "__main__":
    main()
