"""Two-level BVHs with partial re-braiding: top-level build time vs SAH (Benthin et al. 2017).

    python bench/bench_rebraid.py            # drone, legocar (../shared/data), a forest of 256
                                             # tree instances, a crowd of 64 cows, dynamic-in-static
    python bench/bench_rebraid.py --quick    # smaller synthetic scenes, fewer rays and repeats

For every scene: object BVHs (binned SAH, 16 bins, one primitive per leaf), the plain
two-level top level (``threshold = inf``), the re-braided one (threshold 0.1, budget 4x
the instances) and a single BVH over all world triangles (same builder), compared as the
paper's Tables 1-2: total SAH of the flattened trees (Ct = Ci = 1), stored nodes, BRefs,
build seconds (objects + top level; single: everything) and top-level seconds, and box /
primitive tests per random ray. Then a sweep of thresholds x budgets (top-level seconds
vs SAH, the shape of the paper's Figure 4 for SAH) and the dynamic-in-static frame
times (the paper's Table 3): rebuild the moving object, then the top level, vs
rebuilding a single BVH over everything.

Times are wall seconds, median of ``--repeat`` warm runs (every function runs once
untimed first, so compiling is not counted). Writes bench/results/rebraid.json and
rebraid.md.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from jaxbvh import (
    rays,
    scenes,  # noqa: E402
    twolevel,
)
from jaxbvh.io import bundled_mesh_path, load_mesh  # noqa: E402
from jaxbvh.rays import traversal as traverse
from jaxbvh.twolevel import brefs
from jaxbvh.twolevel import objects as fm  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
THRESHOLDS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
BUDGETS = (1.5, 2.0, 4.0, 8.0)
# the targets
TARGET_VS_TWO_LEVEL = 0.9
TARGET_VS_SINGLE = 1.15
TARGET_TOP_RATIO = 3.0


def timed(fn, repeat):
    """``(result, median warm seconds)``; the first call (compile) is not timed."""
    out = jax.block_until_ready(fn())
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return out, statistics.median(times)


def scene_list(args):
    if (DATA / "scenes" / "drone" / "scene.gltf").exists():
        yield "drone", load_mesh(DATA / "scenes" / "drone" / "scene.gltf")
    if (DATA / "meshes" / "legocar.obj").exists():
        yield "legocar", load_mesh(DATA / "meshes" / "legocar.obj")
    trees = [scenes.tree_mesh(jax.random.key(k)) for k in range(2)]
    n_trees = 64 if args.quick else 256
    yield f"forest ({n_trees} trees)", scenes.instanced_scene(jax.random.key(0), trees, n_trees, spread=0.5,
                                                              upright=True, name="forest")
    cow = DATA / "meshes" / "cow.obj"
    crowd = load_mesh(cow if cow.exists() else bundled_mesh_path())
    n_crowd = 16 if args.quick else 64
    yield f"crowd ({n_crowd} {crowd.name})", scenes.instanced_scene(jax.random.key(1), [crowd.objects[0]],
                                                                    n_crowd, spread=0.5, name="crowd")


def tests_per_ray(tl_or_tree, mesh, origin, direction):
    if isinstance(tl_or_tree, twolevel.TwoLevelBVH):
        hits = twolevel.closest_hit(tl_or_tree, origin, direction)
    else:
        hits = traverse.closest_hit(tl_or_tree, mesh.local_triangles(), origin, direction)
    return float(np.mean(hits.box_tests)), float(np.mean(hits.prim_tests)), hits


def bench_scene(name, mesh, args):
    print(f"\n== {name}: {mesh.n_triangles:,} triangles, {len(mesh.objects)} objects, "
          f"{len(mesh.instances)} instances", flush=True)
    lo, hi = mesh.local_boxes()
    row = {"scene": name, "triangles": mesh.n_triangles, "objects": len(mesh.objects),
           "instances": len(mesh.instances)}
    trees, t_objects = timed(lambda: fm.build_objects(mesh), args.repeat)
    single, t_single = timed(lambda: jaxbvh.build(lo, hi, method="binned"), args.repeat)
    single = jaxbvh.to_numpy(single)
    jaxbvh.validate(single, lo, hi)
    row["objects_seconds"] = t_objects

    # top-level seconds of every configuration, timed round-robin (the load on a shared
    # machine drifts; interleaving keeps the ratios between configurations fair)
    forest, inst = fm.pack(mesh, trees)
    _, pack_seconds = timed(lambda: fm.pack(mesh, trees), args.repeat)
    n = len(mesh.instances)
    configs = [(math.inf, 4.0), (0.1, 4.0)]
    if n > 1:
        configs += [(t, b) for b in BUDGETS for t in THRESHOLDS if (t, b) != (0.1, 4.0)]
    top_times = {c: [] for c in configs}
    if n > 1:
        for c in configs:  # compile
            jax.block_until_ready(brefs.build_top_level(forest, inst, n, threshold=c[0], budget=c[1]))
        for _ in range(args.repeat):
            for c in configs:
                start = time.perf_counter()
                jax.block_until_ready(brefs.build_top_level(forest, inst, n, threshold=c[0], budget=c[1]))
                top_times[c].append(time.perf_counter() - start)
    top_seconds = {c: statistics.median(v) if v else 0.0 for c, v in top_times.items()}

    def variant(threshold, budget, world_trees=trees):
        tl = twolevel.build_from(mesh, world_trees, threshold=threshold, budget=budget)
        flat = twolevel.flatten(tl)
        jaxbvh.validate(flat, lo, hi)  # the flattened tree is always valid
        timings = {"top": top_seconds.get((threshold, budget), float("nan")), "pack": pack_seconds}
        return tl, flat, timings

    origin, direction = rays.make_rays(jax.random.key(2), "random", single, None, args.rays)
    out = {}
    for label, threshold in (("two_level", math.inf), ("rebraid", 0.1)):
        tl, flat, timings = variant(threshold, 4.0)
        box, prim, _ = tests_per_ray(tl, mesh, origin, direction)
        out[label] = {"sah": float(jaxbvh.sah(jaxbvh.to_jax(flat))), "sah_object": twolevel.sah(tl, boxes="object"),
                      "nodes": twolevel.stored_nodes(tl)["total"],
                      "brefs": int(tl.bref_count), "seconds": t_objects + timings["pack"] + timings["top"],
                      "top_seconds": timings["top"], "box_tests": box, "prim_tests": prim}
    box, prim, _ = tests_per_ray(single, mesh, origin, direction)
    out["single"] = {"sah": float(jaxbvh.sah(jaxbvh.to_jax(single))), "nodes": jaxbvh.tree.node_count(single),
                     "seconds": t_single, "box_tests": box, "prim_tests": prim}
    row.update(out)
    row["rebraid_vs_two_level"] = out["rebraid"]["sah"] / out["two_level"]["sah"]
    row["rebraid_vs_single"] = out["rebraid"]["sah"] / out["single"]["sah"]
    row["object_rebraid_vs_two_level"] = out["rebraid"]["sah_object"] / out["two_level"]["sah_object"]
    row["object_rebraid_vs_single"] = out["rebraid"]["sah_object"] / out["single"]["sah"]
    row["top_ratio"] = (out["rebraid"]["top_seconds"] / out["two_level"]["top_seconds"]
                        if out["two_level"]["top_seconds"] > 0 else None)
    for label in ("two_level", "rebraid", "single"):
        r = out[label]
        print(f"  {label:10s} SAH {r['sah']:9.3f}"
              + (f" (object frames {r['sah_object']:.3f})" if "sah_object" in r else "") + f"  nodes {r['nodes']:>9,}  build {r['seconds']:.4f} s"
              + (f"  top {r['top_seconds'] * 1e3:.2f} ms  BRefs {r['brefs']}" if "brefs" in r else "")
              + f"  box/ray {r['box_tests']:.1f}  prim/ray {r['prim_tests']:.2f}", flush=True)

    # objects placed by one instance: in world space (default) or in their own frame
    if any(len([1 for o, _ in mesh.instances if o == k]) == 1 for k in range(len(mesh.objects))) and \
            not all(np.array_equal(t, np.eye(4)) for _, t in mesh.instances):
        obj_trees = fm.build_objects(mesh, world_space=False)
        row["object_space"] = {}
        for label, threshold in (("two_level", math.inf), ("rebraid", 0.1)):
            tl, flat, _ = variant(threshold, 4.0, obj_trees)
            row["object_space"][label] = float(jaxbvh.sah(jaxbvh.to_jax(flat)))
        print(f"  object space: two-level {row['object_space']['two_level']:.3f}, "
              f"rebraid {row['object_space']['rebraid']:.3f}", flush=True)

    # the sweep: top-level seconds vs SAH
    sweep = []
    if len(mesh.instances) > 1:
        for budget in BUDGETS:
            for threshold in THRESHOLDS:
                tl, flat, timings = variant(threshold, budget)
                entry = {"threshold": threshold, "budget": budget, "brefs": int(tl.bref_count),
                         "sah": float(jaxbvh.sah(jaxbvh.to_jax(flat))), "sah_object": twolevel.sah(tl, boxes="object"),
                         "top_seconds": timings["top"]}
                if budget == 4.0 and args.sweep_rays:
                    entry["box_tests"], entry["prim_tests"], _ = tests_per_ray(tl, mesh, origin[:args.sweep_rays],
                                                                               direction[:args.sweep_rays])
                sweep.append(entry)
                print(f"  sweep budget {budget:g} threshold {threshold:g}: SAH {entry['sah']:.3f} "
                      f"BRefs {entry['brefs']} top {timings['top'] * 1e3:.2f} ms", flush=True)
    row["sweep"] = sweep
    return row


def bench_dynamic(args):
    cow = DATA / "meshes" / "cow.obj"
    mover = load_mesh(cow if cow.exists() else bundled_mesh_path())
    v, f = mover.objects[0]
    n_static = 16 if args.quick else 64
    dyn = scenes.dynamic_scene(jax.random.key(3), v, f, n_static=n_static, frames=args.frames)
    first = dyn.frame(0)
    print(f"\n== dynamic-in-static: {first.n_triangles:,} triangles ({mover.name}: {f.shape[0]:,} moving), "
          f"{len(first.instances)} instances, {args.frames} frames", flush=True)
    static = fm.build_objects(first, only=range(dyn.moving_object))
    frames = []
    # warm up every jitted piece on frame 0
    mesh = first
    trees = dict(static) | fm.build_objects(mesh, only=[dyn.moving_object])
    for threshold in (math.inf, 0.1):
        twolevel.build_from(mesh, trees, threshold=threshold)
    lo, hi = mesh.local_boxes()
    jax.block_until_ready(jaxbvh.build(lo, hi, method="binned"))
    for k in range(args.frames):
        mesh = dyn.frame(k)
        mesh.local_boxes()  # world triangles, boxes and frame are computed once per frame, untimed
        entry = {"frame": k}
        for label, threshold in (("two_level", math.inf), ("rebraid", 0.1)):
            start = time.perf_counter()
            trees = dict(static) | fm.build_objects(mesh, only=[dyn.moving_object])
            moving = time.perf_counter() - start
            timings = {}
            tl = twolevel.build_from(mesh, trees, threshold=threshold, timings=timings)
            entry[label] = {"object_seconds": moving, "pack_seconds": timings["pack"],
                            "top_seconds": timings["top"],
                            "seconds": moving + timings["pack"] + timings["top"], "sah": twolevel.sah(tl)}
        lo, hi = mesh.local_boxes()
        start = time.perf_counter()
        single = jax.block_until_ready(jaxbvh.build(lo, hi, method="binned"))
        entry["single"] = {"seconds": time.perf_counter() - start, "sah": float(jaxbvh.sah(single))}
        frames.append(entry)
        print(f"  frame {k}: " + ", ".join(f"{lab} {entry[lab]['seconds'] * 1e3:.1f} ms SAH {entry[lab]['sah']:.2f}"
                                            for lab in ("two_level", "rebraid", "single")), flush=True)
    summary = {}
    for label in ("two_level", "rebraid", "single"):
        summary[label] = {key: statistics.median(e[label][key] for e in frames)
                          for key in frames[0][label]}
    return {"triangles": first.n_triangles, "moving_triangles": int(f.shape[0]),
            "instances": len(first.instances), "frames": frames, "median": summary}


def machine() -> str:
    """CPU model and core count, e.g. for the results header."""
    import os

    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores ({platform.machine()})"


def markdown(results) -> str:
    lines = ["# Two-level BVHs with partial re-braiding (Benthin et al. 2017)", "",
             f"Machine: {results['machine']}; JAX {results['jax']} on CPU, float32, Ct = Ci = 1. "
             "The CPU was shared with other jobs while this ran, so times are noisy (medians of "
             f"{results['repeat']} warm runs, compile excluded).", "",
             "Object BVHs and the single BVH: binned SAH (16 bins, one triangle per leaf). Objects "
             "placed by one instance are built in world space; shared objects in their own frame "
             "(their world boxes are the conservative boxes of the 8 transformed corners). SAH: of "
             "the flattened world-space trees, interior nodes + leaves. Re-braid: threshold 0.1, "
             "budget 4 x instances. Rays: random rays in the scene box, closest hit.", "",
             "## Table 1-2 shape", "",
             "SAH (object frames): the same with every node below a top-level leaf costed by the area "
             "of its box as transformed (what the two-level traversal tests; equal to SAH when nothing "
             "is instanced).", "",
             "| scene | triangles | objects / instances | | SAH | vs two-level | SAH (object frames) | nodes | "
             "BRefs | build s | top ms | box / ray | prim / ray |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in results["scenes"]:
        for label in ("two_level", "rebraid", "single"):
            r = row[label]
            head = (row["scene"], f"{row['triangles']:,}", f"{row['objects']} / {row['instances']}") \
                if label == "two_level" else ("", "", "")
            top = f"{r['top_seconds'] * 1e3:.2f}" if "top_seconds" in r else "-"
            cells = [*head, label.replace("_", "-"), f"{r['sah']:.3f}", f"{r['sah'] / row['two_level']['sah']:.3f}x",
                     f"{r['sah_object']:.3f}" if "sah_object" in r else f"{r['sah']:.3f}", f"{r['nodes']:,}", str(r.get("brefs", "-")), f"{r['seconds']:.3f}", top,
                     f"{r['box_tests']:.1f}", f"{r['prim_tests']:.2f}"]
            lines.append("| " + " | ".join(cells) + " |")

    def verdict(value, target):
        return f"{value:.3f} ({'met' if value <= target else 'missed'})"

    lines += ["", "## Targets", "",
              f"Re-braided SAH <= {TARGET_VS_TWO_LEVEL} x two-level and <= {TARGET_VS_SINGLE} x single; "
              f"top-level re-braid time <= {TARGET_TOP_RATIO} x the plain top level; flattened trees always "
              "valid (every tree of this run was validated against the scene's triangle boxes).", "",
              "| scene | rebraid / two-level | rebraid / single | same, SAH in object frames | top time ratio | "
              "objects placed once built in object space: two-level / rebraid SAH |", "|---|---|---|---|---|---|"]
    for row in results["scenes"]:
        ratio = verdict(row["top_ratio"], TARGET_TOP_RATIO) if row["top_ratio"] else "-"
        obj = row.get("object_space")
        obj = f"{obj['two_level']:.3f} / {obj['rebraid']:.3f}" if obj else "-"
        lines.append(f"| {row['scene']} | {verdict(row['rebraid_vs_two_level'], TARGET_VS_TWO_LEVEL)} | "
                     f"{verdict(row['rebraid_vs_single'], TARGET_VS_SINGLE)} | "
                     f"{row['object_rebraid_vs_two_level']:.3f} / {row['object_rebraid_vs_single']:.3f} | {ratio} | {obj} |")
    lines += ["", "## Sweep: top-level time vs SAH", "",
              "| scene | budget | threshold | BRefs | SAH | vs two-level | SAH (object frames) | top ms | box / ray |",
              "|---|---|---|---|---|---|---|---|---|"]
    for row in results["scenes"]:
        for e in row["sweep"]:
            lines.append(f"| {row['scene']} | {e['budget']:g} | {e['threshold']:g} | {e['brefs']} | "
                         f"{e['sah']:.3f} | {e['sah'] / row['two_level']['sah']:.3f} | {e['sah_object']:.3f} | "
                         f"{e['top_seconds'] * 1e3:.2f} | "
                         + (f"{e['box_tests']:.1f} |" if "box_tests" in e else "- |"))
    if results.get("dynamic"):
        d = results["dynamic"]
        m = d["median"]
        lines += ["", "## Dynamic-in-static (Table 3 shape)", "",
                  f"{d['triangles']:,} triangles, {d['moving_triangles']:,} of them moving and deforming, "
                  f"{d['instances']} instances; median over {len(d['frames'])} frames. Two-level and re-braid: "
                  "rebuild the moving object's BVH (world space), pack the forest, build the top level; single: "
                  "rebuild everything.", "",
                  "| | per-frame build ms | moving object ms | pack ms | top level ms | SAH |",
                  "|---|---|---|---|---|---|"]
        for label in ("two_level", "rebraid", "single"):
            r = m[label]
            lines.append(f"| {label.replace('_', '-')} | {r['seconds'] * 1e3:.1f} | "
                         + (f"{r['object_seconds'] * 1e3:.1f} | {r['pack_seconds'] * 1e3:.1f} | "
                            f"{r['top_seconds'] * 1e3:.1f}" if "top_seconds" in r else "- | - | -")
                         + f" | {r['sah']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smaller synthetic scenes, fewer rays")
    parser.add_argument("--repeat", type=int, default=None, help="timed warm runs (default 5, quick 3)")
    parser.add_argument("--rays", type=int, default=None, help="random rays per scene (default 20000, quick 4000)")
    parser.add_argument("--sweep-rays", type=int, default=None,
                        help="rays for the threshold sweep at budget 4 (default 4000, quick 1000; 0: none)")
    parser.add_argument("--frames", type=int, default=8, help="dynamic-in-static frames (default 8)")
    parser.add_argument("--scenes", nargs="*", default=None, help="only these scenes (name prefixes)")
    parser.add_argument("--no-dynamic", action="store_true")
    args = parser.parse_args(argv)
    args.repeat = args.repeat or (3 if args.quick else 5)
    args.rays = args.rays or (4000 if args.quick else 20000)
    args.sweep_rays = (1000 if args.quick else 4000) if args.sweep_rays is None else args.sweep_rays
    results = {"machine": machine(),
               "jax": jax.__version__, "repeat": args.repeat, "quick": args.quick, "scenes": []}
    for name, mesh in scene_list(args):
        if args.scenes and not any(name.startswith(s) for s in args.scenes):
            continue
        results["scenes"].append(bench_scene(name, mesh, args))
    if not args.no_dynamic:
        results["dynamic"] = bench_dynamic(args)
    RESULTS.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    (RESULTS / f"rebraid{suffix}.json").write_text(json.dumps(results, indent=1))
    (RESULTS / f"rebraid{suffix}.md").write_text(markdown(results))
    print(f"\nwrote {RESULTS / f'rebraid{suffix}.json'} and .md")


if __name__ == "__main__":
    main()
