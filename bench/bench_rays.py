"""Closest-hit rays per second before and after a traversal change, beside Embree, in one run.

    python bench/bench_rays.py [--before /path/to/old/checkout] [--meshes bunny legocar drone bunny4]
                               [--rays 20000] [--kinds random camera bounce]
    python bench/bench_rays.py --native   # the native engine beside the JAX walk and Embree

``--native`` measures, in one process, the native engine (:mod:`jaxbvh.rays.native`), the
JAX walk and Embree on the same trees and rays (rays per CPU s; hits and counters of the
two engines compared), the chains (CPU and wall s, steps per CPU s), one thread against
all, and the first call of a fresh process with empty and warm caches; it writes
``bench/results/bench_rays_native.json`` and ``.md``. Without it:

Every measurement runs in a child process per implementation (``--before``: a checkout
whose ``jaxbvh`` is imported instead of this one, e.g. the main branch before the change;
without it only this checkout is measured), on the same trees and rays:

* meshes: the shared meshes (../shared/data) with their tinybvh reference tree (binary,
  distance order) and its 4-wide optimal collapse; ``bunny4``: the bunny subdivided once
  (277,804 triangles) with a ``jaxbvh.build`` binned tree (built once, saved, loaded by
  both children); ray kinds random, camera, bounce; Embree (embreex ``run``, its own BVH)
  on the same rays, and the fraction of rays with Embree's primitive;
* depth: chains of 50, 500, 5,000 and 6,320 triangles (a binary tree that peels one
  triangle per level, depth = triangles - 1) with random rays: traversal steps per
  second (``nodes_visited + prim_tests`` per ray) must not fall with depth;
* stack (this checkout only, ``--stacks``): the walk's stack size against the default
  (:data:`jaxbvh.rays.stack_walk.STACK`), down to ``k`` entries, where nearly every
  backtrack is a climb by parent links: rays/s and box tests on the first mesh's binary
  tree and on the deepest chain;
* compile: CPU seconds of the first call (trace, compile, run) minus a warm call, and the
  backend compile seconds JAX reports, for a binary and a 4-wide closest-hit program.

Times are CPU seconds of the child process (``getrusage``; the machine is shared, so
wall time says little; ``uptime`` is recorded) and the median of ``--repeat`` warm runs.
Writes ``bench/results/bench_rays.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
REPO = ROOT.parent
DATA = ROOT.parents[1] / "shared" / "data"
MESHES = {"bunny": "meshes/stanford-bunny.obj", "legocar": "meshes/legocar.obj",
          "drone": "scenes/drone/scene.gltf", "bunny4": "meshes/stanford-bunny.obj"}
CHAINS = (50, 500, 5000, 6320)
DEFAULT_STACKS = (2,)
KINDS = ("random", "camera", "bounce")


def load_triangles(name):
    """Triangles [T, 3, 3] float32 of a shared mesh (``bunny4``: the bunny subdivided once)."""
    import trimesh

    loaded = trimesh.load(DATA / MESHES[name], process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()
    vertices, faces = np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces)
    if name == "bunny4":
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return vertices[faces].astype(np.float32)


def chain_tree(triangles):
    """Binary tree peeling one triangle per level (depth ``T - 1``), in centroid-x order.

    Interior node ``j`` holds triangles ``j .. T-1``: its children are the leaf of
    triangle ``j`` and interior node ``j + 1`` (the last interior node: two leaves).
    """
    from jaxbvh.tree import from_interchange

    n = triangles.shape[0]
    order = np.argsort(triangles.mean(axis=1)[:, 0], kind="stable").astype(np.int32)
    lo_p, hi_p = triangles.min(axis=1)[order], triangles.max(axis=1)[order]
    n_int = n - 1
    leaf = n_int + np.arange(n)
    child = np.full((n_int + n, 2), -1, np.int32)
    child[:n_int, 0] = leaf[:n_int]
    child[:n_int, 1] = np.arange(1, n_int + 1)
    child[n_int - 1, 1] = leaf[n - 1]
    lo = np.empty((n_int + n, 3), np.float32)
    hi = np.empty((n_int + n, 3), np.float32)
    lo[leaf], hi[leaf] = lo_p, hi_p
    lo[:n_int] = np.minimum.accumulate(lo_p[::-1], axis=0)[::-1][:n_int]
    hi[:n_int] = np.maximum.accumulate(hi_p[::-1], axis=0)[::-1][:n_int]
    start = np.zeros(n_int + n, np.int32)
    count = np.zeros(n_int + n, np.int32)
    start[leaf], count[leaf] = np.arange(n), 1
    return from_interchange(dict(child=child, prim_start=start, prim_count=count, prim_index=order,
                                 lo=lo, hi=hi, root=np.int32(0)))


def cpu_seconds():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(fn, repeat):
    """Median ``(cpu, wall)`` seconds of ``repeat`` calls, and the last result."""
    cpu, wall, result = [], [], None
    for _ in range(repeat):
        c, w = cpu_seconds(), time.perf_counter()
        result = fn()
        wall.append(time.perf_counter() - w)
        cpu.append(cpu_seconds() - c)
    return statistics.median(cpu), statistics.median(wall), result


def embree_run(tri, origin, direction, repeat):
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        return None
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, tri)
    scene.run(origin[:1000], direction[:1000])
    cpu, wall, out = timed(lambda: scene.run(origin, direction, output=1), repeat)
    return {"cpu": cpu, "wall": wall, "prim": np.asarray(out["primID"])}


def warp_run(tri, origin, direction, repeat):
    """Closest hits by NVIDIA Warp's ``mesh_query_ray`` on its CPU device, or None without
    ``warp-lang`` (optional; not a jaxbvh dependency): ``wp.Mesh`` (Warp's own BVH) built
    once per mesh, outside the timing; one warm-up launch (compiles the kernel), then the
    median CPU and wall seconds of ``repeat`` launches + synchronize on arrays made before."""
    try:
        import warp as wp
    except ImportError:
        return None
    # Warp prints its module loads to stdout, where the child writes its JSON
    with contextlib.redirect_stdout(sys.stderr):
        return _warp_run(wp, tri, origin, direction, repeat)


def _warp_run(wp, tri, origin, direction, repeat):
    wp.config.quiet = True
    wp.init()
    vertices = wp.array(tri.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device="cpu")
    indices = wp.array(np.arange(tri.shape[0] * 3, dtype=np.int32), dtype=wp.int32, device="cpu")
    mesh = wp.Mesh(points=vertices, indices=indices)

    @wp.kernel
    def closest(mesh_id: wp.uint64, origin: wp.array(dtype=wp.vec3), direction: wp.array(dtype=wp.vec3),
                t: wp.array(dtype=float), face: wp.array(dtype=int)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh_id, origin[i], direction[i], 1.0e30)
        if q.result:
            t[i] = q.t
            face[i] = q.face
        else:
            face[i] = -1

    o = wp.array(np.asarray(origin, np.float32), dtype=wp.vec3, device="cpu")
    d = wp.array(np.asarray(direction, np.float32), dtype=wp.vec3, device="cpu")
    t = wp.zeros(len(origin), dtype=float, device="cpu")
    face = wp.zeros(len(origin), dtype=int, device="cpu")

    def launch():
        wp.launch(closest, dim=len(origin), inputs=[mesh.id, o, d, t, face], device="cpu")
        wp.synchronize()

    launch()
    cpu, wall, _ = timed(launch, repeat)
    return {"cpu": cpu, "wall": wall, "prim": face.numpy().copy(), "mesh": mesh}


def child(args):
    """Measure with the ``jaxbvh`` on ``sys.path``; print one JSON document."""
    import jax

    import jaxbvh
    from jaxbvh import rays
    from jaxbvh.wide import collapse

    compile_s = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **_: compile_s.append(secs) if name.endswith("backend_compile_duration") else None)
    kw = {} if args.batch is None else {"batch": args.batch}
    rows = []

    def trace(tree, tri, o, d):
        return rays.closest_hit(tree, tri, o, d, **kw)

    for name in args.meshes:
        tri = load_triangles(name)
        if name == "bunny4":
            ref_tree, _ = jaxbvh.load(args.big_tree)
            trees = {"binary (jaxbvh.build binned)": ref_tree}
        else:
            ref_tree, _ = jaxbvh.load(DATA / "trees" / f"{name}_binned_ref.npz")
            trees = {"binary (tinybvh)": ref_tree,
                     "4-wide (collapse of tinybvh)": collapse.optimal(ref_tree, max_children=4).tree}
        for kind in args.kinds:
            origin, direction = rays.make_rays(jax.random.key(0), kind, ref_tree, tri, args.rays)
            embree = embree_run(tri, origin, direction, args.repeat) if args.embree else None
            for label, tree in trees.items():
                n_compiles = len(compile_s)
                c0, w0 = cpu_seconds(), time.perf_counter()
                trace(tree, tri, origin, direction)
                first_cpu = cpu_seconds() - c0
                first_wall = time.perf_counter() - w0
                cpu, wall, hits = timed(lambda: trace(tree, tri, origin, direction), args.repeat)
                first_cpu -= cpu  # the first call's run, beside its trace and compile
                row = {"section": "mesh", "mesh": name, "triangles": int(tri.shape[0]), "kind": kind,
                       "tree": label, "rays": int(len(origin)), "cpu": cpu, "wall": wall,
                       "rays_per_cpu_s": len(origin) / cpu, "first_call_cpu": first_cpu,
                       "first_call_wall": first_wall, "backend_compile_s": sum(compile_s[n_compiles:]),
                       "box_tests": float(np.mean(hits.box_tests)),
                       "prim_tests": float(np.mean(hits.prim_tests)),
                       "steps": float(np.mean(hits.nodes_visited + hits.prim_tests))}
                if embree is not None:
                    row["embree_rays_per_cpu_s"] = len(origin) / embree["cpu"]
                    row["same_prim_as_embree"] = float(np.mean(hits.prim == embree["prim"]))
                rows.append(row)
                print(f"{name} {kind} {label}: {row['rays_per_cpu_s']:,.0f} rays/cpu-s", file=sys.stderr,
                      flush=True)

    bunny = load_triangles("bunny")
    rng = np.random.default_rng(0)
    for n in args.chains:
        tri = bunny[np.sort(rng.choice(len(bunny), n, replace=False))]
        tree = chain_tree(tri)
        # the old walk costs depth x depth: fewer rays on deep chains keep it bounded
        r = args.chain_rays if n <= 500 or not args.few_deep else max(100, args.chain_rays // 100)
        origin, direction = rays.make_rays(jax.random.key(1), "random", tree, tri, r)
        trace(tree, tri, origin, direction)
        cpu, wall, hits = timed(lambda: trace(tree, tri, origin, direction), 1)
        steps = float(np.mean(hits.nodes_visited + hits.prim_tests))
        rows.append({"section": "depth", "mesh": f"chain of {n}", "triangles": n, "kind": "random",
                     "tree": f"binary chain, depth {n - 1}", "rays": r, "cpu": cpu, "wall": wall,
                     "rays_per_cpu_s": r / cpu, "steps": steps, "steps_per_cpu_s": r * steps / cpu,
                     "box_tests": float(np.mean(hits.box_tests)),
                     "prim_tests": float(np.mean(hits.prim_tests))})
        print(f"chain {n}: {r / cpu:,.0f} rays/cpu-s, {r * steps / cpu:,.0f} steps/cpu-s", file=sys.stderr,
              flush=True)
        if n == max(args.chains):
            deepest = (f"chain of {n}", tree, tri, origin, direction)
    if args.stacks:
        first = args.meshes[0]
        tri = load_triangles(first)
        tree = jaxbvh.load(args.big_tree if first == "bunny4" else DATA / "trees" / f"{first}_binned_ref.npz")[0]
        sets = [(first, kind, tree, tri, *rays.make_rays(jax.random.key(0), kind, tree, tri, args.rays))
                for kind in ("random", "camera")]
        if args.chains:
            sets.append((deepest[0], "random", *deepest[1:]))
        for name, kind, tree, tri, origin, direction in sets:
            for capacity in [None, *args.stacks]:
                def go():
                    return rays.closest_hit(tree, tri, origin, direction, capacity=capacity, **kw)
                go()
                cpu, wall, hits = timed(go, 1 if name.startswith("chain") else args.repeat)
                rows.append({"section": "stack", "mesh": name, "kind": kind, "capacity": capacity or "default",
                             "rays": len(origin), "cpu": cpu, "rays_per_cpu_s": len(origin) / cpu,
                             "box_tests": float(np.mean(hits.box_tests)),
                             "steps": float(np.mean(hits.nodes_visited + hits.prim_tests))})
                print(f"stack {capacity} {name} {kind}: {len(origin) / cpu:,.0f} rays/cpu-s", file=sys.stderr,
                      flush=True)
    json.dump({"rows": rows, "uptime": os.getloadavg()}, sys.stdout)


def native_child(args):
    """The native engine beside the JAX walk and Embree on the same trees and rays, in one
    process; prints one JSON document (``--native``)."""
    import jax

    import jaxbvh
    from jaxbvh import rays
    from jaxbvh.rays import native
    from jaxbvh.rays import traversal_reference as ref
    from jaxbvh.rays.stack_walk import STACK
    from jaxbvh.wide import collapse

    rows = []

    def both(tree, tri, o, d, jax_rays=None):
        """Warm CPU and wall seconds of each engine (JAX on the first ``jax_rays`` rays)."""
        n_jax = len(o) if jax_rays is None else min(jax_rays, len(o))
        rays.closest_hit(tree, tri, o[:256], d[:256], engine="native")
        rays.closest_hit(tree, tri, o[:n_jax], d[:n_jax], engine="jax")  # the same batch shape: compiled
        nat_cpu, nat_wall, nat = timed(lambda: rays.closest_hit(tree, tri, o, d, engine="native"), args.repeat)
        # packing excluded: the same tree and triangles as JAX arrays (immutable), packed once
        # by the first call and reused (jaxbvh.rays.native.PACKED_TREES)
        jtree, jtri = jax.tree_util.tree_map(jax.numpy.asarray, tree), jax.numpy.asarray(tri)
        rays.closest_hit(jtree, jtri, o[:256], d[:256], engine="native")
        cached_cpu, _, cached = timed(lambda: rays.closest_hit(jtree, jtri, o, d, engine="native"), args.repeat)
        assert np.array_equal(cached.prim, nat.prim) and np.array_equal(cached.box_tests, nat.box_tests)
        jax_cpu, jax_wall, jx = timed(lambda: rays.closest_hit(tree, tri, o[:n_jax], d[:n_jax], engine="jax"), 1)
        names = ("prim", "box_tests", "prim_tests", "nodes_visited", "leaves_visited")
        differ = np.flatnonzero(np.any([getattr(nat, name)[:n_jax] != getattr(jx, name) for name in names], axis=0))
        # XLA contracts multiply-adds (numba does not): a hit distance an ulp apart can cull
        # a box differently; the NumPy twin (no contraction) decides who follows the rules
        checked = differ[:50]
        twin = ref.trace(tree, tri, o[checked], d[checked], capacity=STACK) if checked.size else []
        same = {"rays_differing_from_jax": int(differ.size), "twin_checked": int(checked.size),
                "equal_to_twin": bool(all(r[name] == getattr(nat, name)[i] for i, r in zip(checked, twin)
                                          for name in names))}
        return {"rays": int(len(o)), "native_cpu": nat_cpu, "native_wall": nat_wall,
                "native_rays_per_cpu_s": len(o) / nat_cpu, "native_cached_cpu": cached_cpu,
                "native_cached_rays_per_cpu_s": len(o) / cached_cpu, "jax_rays": int(n_jax), "jax_cpu": jax_cpu,
                "jax_wall": jax_wall, "jax_rays_per_cpu_s": n_jax / jax_cpu,
                "native_over_jax": (len(o) / nat_cpu) / (n_jax / jax_cpu), "equal_to_jax": same,
                "steps": float(np.mean(nat.nodes_visited + nat.prim_tests)),
                "box_tests": float(np.mean(nat.box_tests))}, nat

    for name in args.meshes:
        tri = load_triangles(name)
        if name == "bunny4":
            ref_tree, _ = jaxbvh.load(args.big_tree)
            trees = {"binary (jaxbvh.build binned)": ref_tree}
        else:
            ref_tree, _ = jaxbvh.load(DATA / "trees" / f"{name}_binned_ref.npz")
            trees = {"binary (tinybvh)": ref_tree,
                     "4-wide (collapse of tinybvh)": collapse.optimal(ref_tree, max_children=4).tree}
        for kind in args.kinds:
            origin, direction = rays.make_rays(jax.random.key(0), kind, ref_tree, tri, args.rays)
            embree = embree_run(tri, origin, direction, args.repeat)
            warp = warp_run(tri, origin, direction, args.repeat)
            for label, tree in trees.items():
                row, hits = both(tree, tri, origin, direction)
                row.update(section="mesh", mesh=name, triangles=int(tri.shape[0]), kind=kind, tree=label)
                if embree is not None:
                    row["embree_rays_per_cpu_s"] = len(origin) / embree["cpu"]
                    row["same_prim_as_embree"] = float(np.mean(hits.prim == embree["prim"]))
                if warp is not None:
                    row["warp_rays_per_cpu_s"] = len(origin) / warp["cpu"]
                    row["same_prim_as_warp"] = float(np.mean(hits.prim == warp["prim"]))
                rows.append(row)
                print(f"{name} {kind} {label}: native {row['native_rays_per_cpu_s']:,.0f}, jax "
                      f"{row['jax_rays_per_cpu_s']:,.0f} rays/cpu-s", file=sys.stderr, flush=True)
    # threads: rays per CPU s of one thread against THREADS (the kernel releases the GIL)
    tri = load_triangles(args.meshes[0])
    tree, _ = jaxbvh.load(DATA / "trees" / f"{args.meshes[0]}_binned_ref.npz")
    origin, direction = rays.make_rays(jax.random.key(0), "random", tree, tri, args.rays)
    threads = native.THREADS
    for _ in range(2):  # alternated
        for n in (1, max(2, len(os.sched_getaffinity(0)))):
            native.THREADS = n
            cpu, wall, _ = timed(lambda: rays.closest_hit(tree, tri, origin, direction, engine="native"), args.repeat)
            rows.append({"section": "threads", "mesh": args.meshes[0], "threads": n, "rays": len(origin),
                         "cpu": cpu, "wall": wall, "rays_per_cpu_s": len(origin) / cpu,
                         "rays_per_wall_s": len(origin) / wall})
    native.THREADS = threads
    bunny = load_triangles("bunny")
    rng = np.random.default_rng(0)
    for n in args.chains:
        tri = bunny[np.sort(rng.choice(len(bunny), n, replace=False))]
        tree = chain_tree(tri)
        origin, direction = rays.make_rays(jax.random.key(1), "random", tree, tri, args.chain_rays)
        # the JAX walk runs ~500 rays per CPU s through the deep chains: a fifth of the rays
        row, hits = both(tree, tri, origin, direction, jax_rays=args.chain_rays if n <= 500 else args.chain_rays // 5)
        row.update(section="depth", mesh=f"chain of {n}", triangles=n, kind="random",
                   tree=f"binary chain, depth {n - 1}",
                   native_steps_per_cpu_s=len(origin) * row["steps"] / row["native_cpu"],
                   jax_steps_per_cpu_s=row["jax_rays"] * row["steps"] / row["jax_cpu"])
        rows.append(row)
        print(f"chain {n}: native {row['native_cpu']:.2f} CPU s, {row['native_wall']:.2f} wall s", file=sys.stderr,
              flush=True)
    json.dump({"rows": rows, "uptime": os.getloadavg()}, sys.stdout)


FIRST_CALL = """
import resource, time, sys
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
c, w = cpu(), time.perf_counter()
import jax, jaxbvh
from jaxbvh import rays
from jaxbvh.io import bundled_mesh_path, load_mesh
mesh = load_mesh(bundled_mesh_path())
tri = mesh.local_triangles()
tree = jaxbvh.build(*mesh.local_boxes())
o, d = rays.make_rays(jax.random.key(0), "random", tree, tri, 1000)
ready = cpu()
rays.closest_hit(tree, tri, o, d, engine=sys.argv[1])
print(cpu() - ready, cpu() - c)
"""


def first_calls():
    """CPU s of a process's first closest-hit call (spot, 1,000 rays) per engine, with empty
    caches (cold) and in a second process (warm: the kernels loaded from jaxbvh's cache)."""
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "NUMBA_CACHE_DIR", "JAXBVH_CACHE")}
        env["JAXBVH_CACHE_DIR"] = tmp
        env["PYTHONPATH"] = str(REPO)
        for engine in ("native", "jax"):
            for state in ("cold", "warm"):
                done = subprocess.run([sys.executable, "-c", FIRST_CALL, engine], env=env, check=True,
                                      stdout=subprocess.PIPE, text=True)
                call, process = map(float, done.stdout.split())
                out.append({"engine": engine, "cache": state, "first_call_cpu": call, "process_cpu": process,
                            "load": os.getloadavg()[0]})
                print(out[-1], file=sys.stderr, flush=True)
            # the next engine starts cold too: its programs are not in the folder yet
    return out


def native_main(args, extra):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("XLA_FLAGS", None)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--native", "--rays", str(args.rays),
           "--repeat", str(args.repeat), "--chain-rays", str(args.chain_rays), "--meshes", *args.meshes,
           "--kinds", *args.kinds, "--chains", *map(str, args.chains), *extra]
    result = json.loads(subprocess.run(cmd, env=env, check=True, stdout=subprocess.PIPE, text=True).stdout)
    result["first_calls"] = first_calls()
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "rays": args.rays, "repeat": args.repeat,
            "chain_rays": args.chain_rays}
    if args.previous:
        # an earlier run's native figures, side by side (another process, another load)
        previous = json.loads(Path(args.previous).read_text())
        meta["previous"] = {"file": args.previous_label or str(args.previous), "uptime": previous.get("uptime")}
        before = {(r["mesh"], r["kind"], r["tree"]): r for r in previous["rows"] if r["section"] in ("mesh", "depth")}
        for r in result["rows"]:
            old = before.get((r.get("mesh"), r.get("kind"), r.get("tree")))
            if r["section"] in ("mesh", "depth") and old is not None:
                r["before"] = {"native_rays_per_cpu_s": old["native_rays_per_cpu_s"],
                               "native_over_jax": old["native_over_jax"]}
    write_native(Path(args.out), meta, result)


def equal(row):
    """The ``equal`` cell: rays whose hits or counters differ from JAX's, and the twin's verdict."""
    e = row["equal_to_jax"]
    if not e["rays_differing_from_jax"]:
        return "yes"
    return f"all but {e['rays_differing_from_jax']} (= twin: {'yes' if e['equal_to_twin'] else 'NO'})"


def write_native(out, meta, result):
    from jaxbvh.files import atomic_write

    rows = result["rows"]
    prev = meta.get("previous")
    lines = ["# Ray traversal: the native engine beside the JAX walk, Warp and Embree (closest hit)\n",
             f"{meta['machine']}, {meta['cpus']} CPUs, shared (load average at the end {result['uptime']}). "
             f"{meta['rays']:,} rays per set; rays per CPU-second of the process, warm, all in one process on the "
             f"same trees and rays. Native: median of {meta['repeat']} calls of `closest_hit`, the tree as loaded "
             "(NumPy arrays: packed into the kernel's layout in every call, `per call`) and the same tree as JAX "
             "arrays (immutable: packed by a first call and reused, `packing excluded`). JAX: one run after a "
             "warm-up. Warp: `warp-lang` `mesh_query_ray` in a kernel on its `cpu` device, `wp.Mesh` (its own "
             f"BVH) built once per mesh and not timed, one warm-up launch, median of {meta['repeat']} launches + "
             f"synchronize. Embree: embreex `run`, its own BVH, median of {meta['repeat']}. Warp / native and "
             "Embree / native divide by native with packing excluded (none of the three builds or packs in the "
             "timing). `same prim`: the fraction of rays whose primitive (or miss) is the native engine's. "
             "`equal`: native and JAX give the same prim, box tests, primitive tests, nodes and leaves visited on "
             "every ray but the number given, and on those (up to 50 checked) native equals the NumPy twin (XLA "
             "contracts multiply-adds in Möller–Trumbore, numba and NumPy do not, so a hit distance an ulp apart "
             "can cull a box differently).\n"]
    if prev:
        lines.append(f"`before`: the native figures of an earlier run ({prev['file']}, load average at its end "
                     f"{prev['uptime']}), another process at another load: compare ratios to JAX, not rays/s.\n")
    lines += ["| mesh | rays | tree | JAX rays/s | native rays/s (per call) | native / JAX | native rays/s "
              "(packing excluded) | native (excl.) / JAX | before: native rays/s | before: native / JAX | "
              "Warp rays/s | Warp / native | same prim as Warp | Embree rays/s | Embree / native | "
              "same prim as Embree | equal | steps/ray |",
              "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    nan = float("nan")
    for r in (r for r in rows if r["section"] == "mesh"):
        emb = r.get("embree_rays_per_cpu_s", nan)
        warp = r.get("warp_rays_per_cpu_s", nan)
        excl = r["native_cached_rays_per_cpu_s"]
        old = r.get("before", {})
        lines.append(f"| {r['mesh']} ({r['triangles']:,}) | {r['kind']} | {r['tree']} | {r['jax_rays_per_cpu_s']:,.0f} | "
                     f"{r['native_rays_per_cpu_s']:,.0f} | {r['native_over_jax']:.1f}x | {excl:,.0f} | "
                     f"{excl / r['jax_rays_per_cpu_s']:.1f}x | {old.get('native_rays_per_cpu_s', nan):,.0f} | "
                     f"{old.get('native_over_jax', nan):.1f}x | {warp:,.0f} | {warp / excl:.1f}x | "
                     f"{r.get('same_prim_as_warp', nan):.4f} | {emb:,.0f} | {emb / excl:.1f}x | "
                     f"{r.get('same_prim_as_embree', nan):.4f} | {equal(r)} | {r['steps']:.1f} |")
    if not any("warp_rays_per_cpu_s" in r for r in rows):
        lines.append("\n(Warp columns empty: `warp-lang` was not installed in this run.)")
    lines += ["\n## Depth: chains (one triangle peeled per level), random rays, warm\n",
              "| chain | depth | rays (native) | native CPU s | native wall s | native steps/CPU s | "
              "rays (JAX) | JAX CPU s | JAX steps/CPU s | native / JAX | before: native / JAX | equal | steps/ray |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for r in (r for r in rows if r["section"] == "depth"):
        lines.append(f"| {r['mesh']} | {r['triangles'] - 1} | {r['rays']:,} | {r['native_cpu']:.2f} | "
                     f"{r['native_wall']:.2f} | {r['native_steps_per_cpu_s']:,.0f} | {r['jax_rays']:,} | "
                     f"{r['jax_cpu']:.2f} | {r['jax_steps_per_cpu_s']:,.0f} | {r['native_over_jax']:.1f}x | "
                     f"{r.get('before', {}).get('native_over_jax', float('nan')):.1f}x | {equal(r)} | "
                     f"{r['steps']:.0f} |")
    lines += ["\n## Threads (native, first mesh's binary tree, random rays; alternated)\n",
              "| threads | rays/CPU s | rays/wall s |", "|---:|---:|---:|"]
    for r in (r for r in rows if r["section"] == "threads"):
        lines.append(f"| {r['threads']} | {r['rays_per_cpu_s']:,.0f} | {r['rays_per_wall_s']:,.0f} |")
    lines += ["\n## First call (spot, 1,000 random rays, a fresh process; jaxbvh's cache in an empty folder)\n",
              "| engine | cache | first call CPU s | process CPU s (imports, mesh, build, call) | load |",
              "|---|---|---:|---:|---:|"]
    for r in result["first_calls"]:
        lines.append(f"| {r['engine']} | {r['cache']} | {r['first_call_cpu']:.2f} | {r['process_cpu']:.2f} | "
                     f"{r['load']:.1f} |")
    with atomic_write(out.with_suffix(".json"), "w") as f:
        json.dump({"meta": meta, **result}, f, indent=1)
    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


def run_child(path, args, extra):
    env = dict(os.environ, PYTHONPATH=str(path))
    env.pop("XLA_FLAGS", None)
    env["JAXBVH_CACHE"] = "off"  # compile time is measured; a warm cache would hide it
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--rays", str(args.rays),
           "--repeat", str(args.repeat), "--chain-rays", str(args.chain_rays),
           "--meshes", *args.meshes, "--kinds", *args.kinds, "--chains", *map(str, args.chains), *extra]
    if path == REPO:  # stack sizes are this checkout's knob
        cmd += ["--stacks", *map(str, DEFAULT_STACKS if args.stacks is None else args.stacks)]
    out = subprocess.run(cmd, env=env, check=True, stdout=subprocess.PIPE, text=True)
    return json.loads(out.stdout)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="checkout whose jaxbvh is the 'before' (e.g. main)")
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    parser.add_argument("--chains", nargs="*", type=int, default=list(CHAINS))
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument("--chain-rays", type=int, default=20_000)
    parser.add_argument("--stacks", nargs="*", type=int, default=None,
                        help=f"stack sizes to measure beside the default (this checkout only; default {DEFAULT_STACKS})")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--out", default=str(ROOT / "results" / "bench_rays"))
    # child-only options
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--batch", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--embree", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--few-deep", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--old-walk", action="store_true", help="--before is the walk before the wavefront")
    parser.add_argument("--big-tree", help=argparse.SUPPRESS)
    parser.add_argument("--previous", help="--native: an earlier bench_rays_native.json whose native figures "
                        "are shown as 'before'")
    parser.add_argument("--previous-label", help="what --previous is, for the table (default: its path)")
    parser.add_argument("--native", action="store_true",
                        help="the native engine beside the JAX walk and Embree (bench/results/bench_rays_native)")
    args = parser.parse_args(argv)
    if args.child:
        return native_child(args) if args.native else child(args)
    if not DATA.exists():
        raise SystemExit(f"shared data not found at {DATA}")

    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp) / "bunny4_binned.npz"
        extra = []
        if "bunny4" in args.meshes:
            import jaxbvh

            tri = load_triangles("bunny4")
            jaxbvh.save(big, jaxbvh.build(tri.min(axis=1), tri.max(axis=1), method="binned"))
            extra = ["--big-tree", str(big)]
        if args.native:
            out = args.out if args.out != str(ROOT / "results" / "bench_rays") else str(ROOT / "results" / "bench_rays_native")
            args.out = out
            return native_main(args, extra)
        results = {}
        if args.before:
            # --old-walk: the stack-per-ray walk before the wavefront (its best batch, and
            # deep chains with 1/100 of the rays: it costs depth x depth)
            old = ["--batch", "256", "--few-deep"] if args.old_walk else []
            results["before"] = run_child(args.before, args, extra + old)
        results["after"] = run_child(REPO, args, extra + ["--embree"])

    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "rays": args.rays,
            "repeat": args.repeat, "before": args.before, "old_walk": args.old_walk,
            "load": {k: v["uptime"] for k, v in results.items()}}
    write(Path(args.out), meta, results)


def write(out, meta, results):
    from jaxbvh.files import atomic_write

    after = results["after"]["rows"]
    before = {(r["mesh"], r["kind"], r["tree"]): r for r in results.get("before", {"rows": []})["rows"]}
    lines = ["# Ray traversal throughput (closest hit), before and after\n",
             f"{meta['machine']}, {meta['cpus']} CPUs (shared: load average {meta['load']}). "
             f"{meta['rays']} rays per set; rays per CPU-second of the process (median of "
             f"{meta['repeat']} warm runs). Before: {meta['before']}"
             f"{' (batch 256)' if meta.get('old_walk') else ' (its defaults)'}; after: this checkout "
             "(default batch, lanes and stack). Embree: embreex `run` on the same rays, its own BVH.\n",
             "| mesh | rays | tree | before rays/s | after rays/s | after / before | Embree rays/s | "
             "Embree / after | same prim as Embree | steps/ray | compile CPU s before | after |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in (r for r in after if r["section"] == "mesh"):
        b = before.get((r["mesh"], r["kind"], r["tree"]))
        emb = r.get("embree_rays_per_cpu_s", float("nan"))
        lines.append(
            f"| {r['mesh']} ({r['triangles']:,}) | {r['kind']} | {r['tree']} | "
            f"{b['rays_per_cpu_s'] if b else float('nan'):,.0f} | {r['rays_per_cpu_s']:,.0f} | "
            f"{r['rays_per_cpu_s'] / b['rays_per_cpu_s'] if b else float('nan'):.1f}x | {emb:,.0f} | "
            f"{emb / r['rays_per_cpu_s']:.1f}x | {r.get('same_prim_as_embree', float('nan')):.4f} | "
            f"{r['steps']:.1f} | {b['first_call_cpu'] if b else float('nan'):.1f} | "
            f"{r['first_call_cpu']:.1f} |")
    lines += ["\nCompile CPU s: CPU seconds of the first call minus a warm call on the same rays "
              "(trace and compile; the persistent compile cache is off in the children). A row whose "
              "program (tree kind, capacity bucket, stack, batch shape) an earlier row compiled reuses it.\n",
              "## Depth: chains (one triangle peeled per level), random rays\n",
              "| chain | depth | rays | before rays/s | before steps/s | after rays/s | after steps/s | "
              "steps/ray | after CPU s |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in (r for r in after if r["section"] == "depth"):
        b = before.get((r["mesh"], r["kind"], r["tree"]))
        lines.append(f"| {r['mesh']} | {r['triangles'] - 1} | {r['rays']:,} | "
                     f"{b['rays_per_cpu_s'] if b else float('nan'):,.0f} | "
                     f"{b['steps_per_cpu_s'] if b else float('nan'):,.0f} | {r['rays_per_cpu_s']:,.0f} | "
                     f"{r['steps_per_cpu_s']:,.0f} | {r['steps']:.0f} | {r['cpu']:.2f} |")
    lines.append("\nSteps per ray = nodes visited + primitive tests (the walk's work, the same "
                 "before and after)." + (" Before traced deep chains with 1/100 of the rays."
                                         if meta.get("old_walk") else ""))
    stack = [r for r in after if r["section"] == "stack"]
    if stack:
        lines += ["\n## Stack size (after): the default against short stacks that climb by parent links\n",
                  "| mesh | rays | stack entries | rays/s | box tests/ray | steps/ray | CPU s |",
                  "|---|---|---|---:|---:|---:|---:|"]
        for r in stack:
            lines.append(f"| {r['mesh']} | {r['kind']} | {r['capacity']} | {r['rays_per_cpu_s']:,.0f} | "
                         f"{r['box_tests']:.1f} | {r['steps']:.1f} | {r['cpu']:.2f} |")
    with atomic_write(out.with_suffix(".json"), "w") as f:
        json.dump({"meta": meta, **results}, f, indent=1)
    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
