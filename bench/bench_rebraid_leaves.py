"""Two-level BVHs: object BVHs with one primitive per leaf (the paper's) against the
builders' default leaves (SAH leaf termination, up to ``jaxbvh.configs.DEFAULT_MAX_LEAF``).

    python bench/bench_rebraid_leaves.py           # 7 scenes, 4,000 random rays each

For each scene: ``twolevel.build`` (re-braided at the default threshold and budget) with
object BVHs from ``BinnedConfig(max_leaf=1)`` and from ``BinnedConfig()``; the SAH of the
flattened world-space tree (Ct = Ci = 1), box and primitive tests per random ray (the
two-level traversal), stored nodes, and whether every hit distance is the same. Writes
bench/results/rebraid_leaves.{md,json}. Scenes need ../shared/data (cow, fandisk, drone,
legocar); the room and the forest are procedural.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from jaxbvh import rays, scenes, twolevel  # noqa: E402
from jaxbvh.builders.configs import BinnedConfig  # noqa: E402
from jaxbvh.files import atomic_write  # noqa: E402
from jaxbvh.io import load_mesh  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
RAYS = 4000


def scene_list():
    cow = load_mesh(DATA / "meshes" / "cow.obj").objects[0]
    yield "by-material (fandisk, 8)", scenes.by_material(*load_mesh(DATA / "meshes" / "fandisk.obj").objects[0])
    yield "by-material (cow, 8)", scenes.by_material(*cow)
    yield "pile (12 cows)", scenes.pile(jax.random.key(5), *cow, 12)
    yield "room (254 objects)", scenes.furnished_room(jax.random.key(8))
    yield "drone", load_mesh(DATA / "scenes" / "drone" / "scene.gltf")
    yield "legocar", load_mesh(DATA / "meshes" / "legocar.obj")
    trees = [scenes.tree_mesh(jax.random.key(k)) for k in range(2)]
    yield "forest (64 trees)", scenes.instanced_scene(jax.random.key(0), trees, 64, spread=0.5, upright=True,
                                                      name="forest")


def measure(mesh, leaf, origin, direction):
    lo, hi = mesh.local_boxes()
    tl = twolevel.build(mesh, BinnedConfig(max_leaf=leaf))
    flat = twolevel.flatten(tl)
    jaxbvh.validate(flat, lo, hi)
    hits = twolevel.closest_hit(tl, origin, direction)
    return {"sah": float(jaxbvh.sah(jaxbvh.to_jax(flat))), "box_tests": float(np.mean(hits.box_tests)),
            "prim_tests": float(np.mean(hits.prim_tests)), "nodes": int(twolevel.stored_nodes(tl)["total"])}, np.asarray(hits.t)


def main():
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load_start = os.getloadavg()
    rows = []
    for name, mesh in scene_list():
        lo, hi = mesh.local_boxes()
        single = jaxbvh.to_numpy(jaxbvh.build(lo, hi, method="binned", max_leaf=1))
        origin, direction = rays.make_rays(jax.random.key(2), "random", single, None, RAYS)
        one, t_one = measure(mesh, 1, origin, direction)
        default, t_default = measure(mesh, BinnedConfig().max_leaf, origin, direction)
        row = {"scene": name, "triangles": mesh.n_triangles, "one": one, "default": default,
               "same_hits": bool(np.array_equal(t_one, t_default))}
        rows.append(row)
        print(f"{name:26s} SAH {one['sah']:8.3f} -> {default['sah']:8.3f} ({default['sah'] / one['sah']:.3f})  "
              f"box/ray {one['box_tests']:.1f} -> {default['box_tests']:.1f}  nodes {one['nodes']:,} -> "
              f"{default['nodes']:,}  same hits: {row['same_hits']}", flush=True)
    meta = {"date": started, "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
            "load_start": load_start, "load_end": os.getloadavg(), "rays": RAYS, "jax": jax.__version__}
    RESULTS.mkdir(parents=True, exist_ok=True)
    with atomic_write(RESULTS / "rebraid_leaves.json", "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)
    lines = ["# Two-level BVHs: object leaves of one primitive against the default leaves", "",
             f"`python bench/bench_rebraid_leaves.py`; {started}; {meta['machine']}; load average "
             f"{load_start[0]:.1f} at start, {meta['load_end'][0]:.1f} at end; JAX {jax.__version__} on CPU, float32, "
             f"Ct = Ci = 1. `twolevel.build` at the default threshold and budget, object BVHs from "
             f"`BinnedConfig(max_leaf=1)` (the paper's) and `BinnedConfig()` (max_leaf "
             f"{BinnedConfig().max_leaf}, SAH leaf termination). SAH of the flattened world-space tree; "
             f"tests per ray: {RAYS:,} random rays through the two-level traversal.", "",
             "| scene | triangles | SAH: one / default (ratio) | box tests per ray | prim tests per ray | stored nodes | same hits |",
             "|---|---:|---|---|---|---|---|"]
    for r in rows:
        o, d = r["one"], r["default"]
        lines.append(f"| {r['scene']} | {r['triangles']:,} | {o['sah']:.3f} / {d['sah']:.3f} ({d['sah'] / o['sah']:.3f}) | "
                     f"{o['box_tests']:.1f} / {d['box_tests']:.1f} | {o['prim_tests']:.2f} / {d['prim_tests']:.2f} | "
                     f"{o['nodes']:,} / {d['nodes']:,} | {'yes' if r['same_hits'] else 'no'} |")
    with atomic_write(RESULTS / "rebraid_leaves.md", "w") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
