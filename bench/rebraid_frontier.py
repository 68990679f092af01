"""Re-braiding's trade of SAH against top-level time, by BRef slots (issue 22's targets).

    python bench/rebraid_frontier.py                 # fandisk and cow by material, a pile of 6 cows
    python bench/rebraid_frontier.py --quick         # the cow by material, three sizes
    python bench/rebraid_frontier.py --rounds 64,8,2 # the opening rounds too

For each scene and BRef array size (``capacity``; ``0`` in ``--slots`` is the scene's
default, :func:`jaxbvh.twolevel.brefs.scene_slots`), ``run_from`` at the default
threshold, timed round-robin with the plain two-level build (``threshold = inf``), warm,
``--repeat`` runs each: ``stage_seconds["top"]`` of both (the re-braided one includes building
the plain top level and the never-worse comparison, as every report of this library
does). SAH: the flattened world-box SAH (``twolevel.sah``, Ct = Ci = 1) of what
``build_from`` kept, over the plain two-level's and over a single binned BVH's; beside
it the object-frame SAH (what the two-level traversal pays) over the plain one's. The
issue's targets: by material <= 0.7 x two-level and <= 1.2 x single, piles <= 0.89 x
two-level, the top level <= 3 x the plain one's time. Writes
bench/results/rebraid_frontier.json and .md (``--quick``: rebraid_frontier_quick.*).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from pathlib import Path

import jax

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from bench.bench_rebraid import TARGET_TOP_RATIO, TARGETS, machine  # noqa: E402
from jaxbvh import scenes, twolevel  # noqa: E402
from jaxbvh.io import load_mesh  # noqa: E402
from jaxbvh.twolevel import objects as fm  # noqa: E402
from jaxbvh.twolevel.config import DEFAULT_THRESHOLD, RebraidConfig  # noqa: E402

MESHES = ROOT.parent / "shared" / "data" / "meshes"
RESULTS = ROOT / "bench" / "results"


def scene_list(quick):
    """``(name, kind, mesh)``: the scenes whose targets the default budget misses."""
    cow = load_mesh(MESHES / "cow.obj").objects[0]
    if quick:
        yield "by-material (cow, 8)", "by-material", scenes.by_material(*cow)
        return
    yield "by-material (fandisk, 8)", "by-material", scenes.by_material(*load_mesh(MESHES / "fandisk.obj").objects[0])
    yield "by-material (cow, 8)", "by-material", scenes.by_material(*cow)
    yield "pile (6 cows)", "pile", scenes.pile(jax.random.key(5), *cow, 6)


def timed_pair(mesh, trees, config, repeat):
    """Warm ``stage_seconds["top"]`` of the plain build and of ``config``'s (keyword knobs
    of a RebraidConfig, and ``capacity``), round-robin; ``(plain times, times, the last
    tree, {"slots", "kept"} of its run)``."""
    config = dict(config)
    capacity = config.pop("capacity", None)
    plain_cfg, config = RebraidConfig(threshold=math.inf), RebraidConfig(**config)
    for cfg in (plain_cfg, config):  # compile
        twolevel.run_from(mesh, trees, cfg, capacity=capacity)
    plain, braided = [], []
    for _ in range(repeat):
        plain.append(twolevel.run_from(mesh, trees, plain_cfg, capacity=capacity).stage_seconds["top"])
        result = twolevel.run_from(mesh, trees, config, capacity=capacity)
        braided.append(result.stage_seconds["top"])
    return plain, braided, result.tree, {"slots": result.slots, "kept": result.kept}


def bench_scene(name, kind, mesh, slots_list, rounds_list, repeat):
    lo, hi = mesh.local_boxes()
    trees = fm.build_objects(mesh)
    single = float(jaxbvh.sah(jaxbvh.build(lo, hi, method="binned")))
    plain = twolevel.build_from(mesh, trees, threshold=math.inf)
    two, two_object = twolevel.sah(plain), twolevel.sah(plain, boxes="object")
    default = twolevel.slots_of(mesh)
    out = {"scene": name, "kind": kind, "triangles": mesh.n_triangles, "instances": len(mesh.instances),
           "two_level": two, "two_level_object": two_object, "single": single, "default_slots": default, "rows": []}
    print(f"\n== {name}: two-level {two:.3f}, single {single:.3f}, default slots {default}", flush=True)
    for slots in slots_list:
        for rounds in rounds_list:
            config = {"capacity": slots or default, "rounds": rounds}
            plain_t, top_t, tl, info = timed_pair(mesh, trees, config, repeat)
            sah = twolevel.sah(tl)
            row = {"slots": info["slots"], "rounds": rounds, "brefs": int(tl.bref_count), "kept": info["kept"],
                   "vs_two_level": sah / two, "vs_single": sah / single,
                   "object_vs_two_level": twolevel.sah(tl, boxes="object") / two_object,
                   "top_ms": 1e3 * min(top_t), "plain_ms": 1e3 * min(plain_t),
                   "ratio_min": min(top_t) / min(plain_t),
                   "ratio_median": statistics.median(top_t) / statistics.median(plain_t)}
            out["rows"].append(row)
            print(f"slots {row['slots']:5d} rounds {rounds:3d}: {row['vs_two_level']:.3f} x two-level, "
                  f"{row['vs_single']:.3f} x single, object frames {row['object_vs_two_level']:.3f}, "
                  f"{row['kept']}; top {row['top_ms']:.2f} ms, plain {row['plain_ms']:.2f}: "
                  f"{row['ratio_min']:.2f}x min, {row['ratio_median']:.2f}x median", flush=True)
    return out


def meets(row, kind):
    """Which of the issue's targets ``row`` meets: ``(two-level, single, time)``."""
    to_two, to_single = TARGETS[kind]
    return (row["vs_two_level"] <= to_two, to_single is None or row["vs_single"] <= to_single,
            row["ratio_median"] <= TARGET_TOP_RATIO)


def markdown(results) -> str:
    yes = {True: "met", False: "missed"}
    lines = ["# Re-braiding's frontier: SAH against top-level time, by BRef slots (issue 22)", "",
             f"Machine: {results['machine']}; load before the run: {results['load']}. JAX {results['jax']}, "
             f"float32, Ct = Ci = 1. Threshold {results['threshold']}; top-level times warm, the plain "
             f"(`threshold = inf`) and the re-braided `build_from` round-robin, {results['repeat']} runs each; "
             "the re-braided one's `stage_seconds[\"top\"]` includes the plain top level and the never-worse "
             "comparison. SAH: world boxes, of what `build_from` kept (`kept`), over the plain two-level's "
             "and a single binned BVH's; *object frames*: the SAH the two-level traversal pays, over the plain "
             "one's. Targets: by material <= 0.7 x two-level and <= 1.2 x single, piles <= 0.89 x two-level, "
             f"the top level <= {TARGET_TOP_RATIO:g} x the plain one's time (median ratio). "
             "Written by `python bench/rebraid_frontier.py`.", ""]
    for scene in results["scenes"]:
        lines += [f"## {scene['scene']}", "",
                  f"{scene['triangles']:,} triangles, {scene['instances']} instances; two-level SAH "
                  f"{scene['two_level']:.3f} (object frames {scene['two_level_object']:.3f}), single BVH "
                  f"{scene['single']:.3f}; default slots {scene['default_slots']}.", "",
                  "| slots | rounds | BRefs | kept | x two-level | x single | object frames x two-level | "
                  "top ms | plain ms | time ratio min / median | targets: two-level, single, time |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in scene["rows"]:
            slots = f"{r['slots']}" + (" (default)" if r["slots"] == scene["default_slots"] else "")
            m = meets(r, scene["kind"])
            single = yes[m[1]] if TARGETS[scene["kind"]][1] is not None else "-"
            lines.append(f"| {slots} | {r['rounds']} | {r['brefs']} | {r['kept']} | {r['vs_two_level']:.3f} | "
                         f"{r['vs_single']:.3f} | {r['object_vs_two_level']:.3f} | {r['top_ms']:.2f} | "
                         f"{r['plain_ms']:.2f} | {r['ratio_min']:.2f} / {r['ratio_median']:.2f} | "
                         f"{yes[m[0]]}, {single}, {yes[m[2]]} |")
        every = [r for r in scene["rows"] if all(meets(r, scene["kind"]))]
        lines += ["", f"Sizes that meet every target: {', '.join(str(r['slots']) for r in every) or 'none'}.", ""]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the cow by material at three sizes")
    parser.add_argument("--slots", default=None,
                        help="BRef array sizes, comma-separated; 0: the scene's default "
                             "(default 0,256,512,768,1024,1536,2048; quick 0,256,512)")
    parser.add_argument("--rounds", default="64", help="opening rounds per level, comma-separated (default 64)")
    parser.add_argument("--repeat", type=int, default=None, help="warm runs of each build (default 7, quick 3)")
    args = parser.parse_args(argv)
    slots = [int(s) for s in (args.slots or ("0,256,512" if args.quick else "0,256,512,768,1024,1536,2048")).split(",")]
    rounds = [int(r) for r in args.rounds.split(",")]
    if any(s < 0 for s in slots) or any(r < 1 for r in rounds):
        parser.error("--slots must be >= 0 and --rounds >= 1")
    repeat = args.repeat or (3 if args.quick else 7)
    results = {"machine": machine(), "load": " ".join(f"{x:.2f}" for x in os.getloadavg()), "jax": jax.__version__,
               "threshold": DEFAULT_THRESHOLD, "repeat": repeat, "scenes": []}
    for name, kind, mesh in scene_list(args.quick):
        results["scenes"].append(bench_scene(name, kind, mesh, slots, rounds, repeat))
    RESULTS.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    (RESULTS / f"rebraid_frontier{suffix}.json").write_text(json.dumps(results, indent=1))
    (RESULTS / f"rebraid_frontier{suffix}.md").write_text(markdown(results))
    print(f"\nwrote {RESULTS / f'rebraid_frontier{suffix}.json'} and .md")


if __name__ == "__main__":
    main()
