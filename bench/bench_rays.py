"""Rays per second of our traversal for each tree kind, beside Embree on the same rays.

    python bench/bench_rays.py [--meshes bunny legocar drone] [--rays 50000] [--kinds random camera bounce]

For each shared mesh (../shared/data) and ray kind, traces the same closest-hit rays
through: the tinybvh reference tree (binary, distance order), our own build (binary,
split-axis order; skipped while ``jaxbvh.build`` is not implemented) and 4- and 8-wide
trees collapsed from the reference tree by Pinto's optimal DP (``jaxbvh.collapse``); and
through Embree (embreex, its own BVH, one ``run`` call). Times are the median of ``--repeat`` runs after a warm-up that compiles.
Writes ``bench/results/bench_rays.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

import jaxbvh
from jaxbvh import rays
from jaxbvh.wide import collapse

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parents[1] / "shared" / "data"
MESHES = {"bunny": "meshes/stanford-bunny.obj", "legocar": "meshes/legocar.obj",
          "drone": "scenes/drone/scene.gltf"}


def load_triangles(name):
    import trimesh

    loaded = trimesh.load(DATA / MESHES[name], process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()
    return np.asarray(loaded.vertices, np.float64)[np.asarray(loaded.faces)].astype(np.float32)


def trees_for(name, tri, max_leaf):
    ref_tree, _ = jaxbvh.load(DATA / "trees" / f"{name}_binned_ref.npz")
    out = {"binary (tinybvh, distance order)": ref_tree}
    try:
        built = jaxbvh.build(tri.min(axis=1), tri.max(axis=1), method="binned", max_leaf=max_leaf)
        out["binary (jaxbvh.build binned, axis order)"] = jaxbvh.to_numpy(built)
    except NotImplementedError:
        pass
    out["4-wide (DP collapse of tinybvh)"] = collapse.optimal(ref_tree, max_children=4).tree
    out["8-wide (DP collapse of tinybvh)"] = collapse.optimal(ref_tree, max_children=8).tree
    return out


def timed(fn, repeat):
    times = []
    result = None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def embree_scene(tri):
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        return None
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, tri)
    return scene


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    parser.add_argument("--kinds", nargs="+", default=list(rays.KINDS), choices=list(rays.KINDS))
    parser.add_argument("--rays", type=int, default=50_000)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "results" / "bench_rays"))
    args = parser.parse_args(argv)
    if not DATA.exists():
        raise SystemExit(f"shared data not found at {DATA}")

    rows = []
    for name in args.meshes:
        tri = load_triangles(name)
        ref_tree, _ = jaxbvh.load(DATA / "trees" / f"{name}_binned_ref.npz")
        max_leaf = int(np.asarray(ref_tree.prim_count).max())
        trees = trees_for(name, tri, max_leaf)
        scene = embree_scene(tri)
        for kind in args.kinds:
            origin, direction = rays.make_rays(jax.random.key(0), kind, ref_tree, tri, args.rays)
            embree = None
            if scene is not None:
                scene.run(origin[:1000], direction[:1000])
                seconds, out = timed(lambda: scene.run(origin, direction, output=1), args.repeat)
                embree = {"seconds": seconds, "rays_per_second": len(origin) / seconds,
                          "prim": out["primID"]}
            for label, tree in trees.items():
                # warm-up compiles; then median of repeats
                rays.closest_hit(tree, tri, origin[: args.batch], direction[: args.batch],
                                 batch=args.batch)
                seconds, hits = timed(lambda: rays.closest_hit(tree, tri, origin, direction,
                                                               batch=args.batch), args.repeat)
                cost = rays.empirical_cost(hits)
                row = {"mesh": name, "triangles": int(tri.shape[0]), "kind": kind, "tree": label,
                       "rays": int(len(origin)), "seconds": seconds,
                       "rays_per_second": len(origin) / seconds,
                       "box_tests": cost["box_tests"][0], "prim_tests": cost["prim_tests"][0],
                       "nodes_visited": cost["nodes_visited"][0],
                       "sah": float(jaxbvh.sah(jaxbvh.to_jax(tree)))}
                if embree is not None:
                    row["embree_rays_per_second"] = embree["rays_per_second"]
                    row["embree_over_ours"] = embree["rays_per_second"] / row["rays_per_second"]
                    row["same_prim_as_embree"] = float(np.mean(hits.prim == embree["prim"]))
                rows.append(row)
                print(f"{name:8s} {kind:7s} {label:42s} {row['rays_per_second']:>10,.0f} rays/s"
                      + (f"  embree {embree['rays_per_second']:>11,.0f}  ratio {row['embree_over_ours']:5.1f}x"
                         if embree else ""), flush=True)

    meta = {"machine": platform.platform(), "processor": platform.processor(),
            "cpus": __import__("os").cpu_count(), "jax": jax.__version__,
            "backend": jax.default_backend(), "rays": args.rays, "batch": args.batch,
            "repeat": args.repeat, "embree": "embreex" if embree_scene(np.zeros((1, 3, 3), np.float32))
            is not None else None}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["# Ray traversal throughput (closest hit)\n",
             f"{meta['machine']}, {meta['cpus']} CPUs, JAX {meta['jax']} ({meta['backend']}), "
             f"{args.rays} rays per set, batch {args.batch}, median of {args.repeat}. "
             "Embree: embreex `run` on the same rays (its own BVH).\n",
             "| mesh | rays | tree | rays/s | Embree rays/s | Embree / ours | box tests | prim tests | SAH | same prim |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['mesh']} | {r['kind']} | {r['tree']} | {r['rays_per_second']:,.0f} | "
                     f"{r.get('embree_rays_per_second', float('nan')):,.0f} | "
                     f"{r.get('embree_over_ours', float('nan')):.1f}x | {r['box_tests']:.1f} | "
                     f"{r['prim_tests']:.2f} | {r['sah']:.2f} | {r.get('same_prim_as_embree', float('nan')):.4f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
