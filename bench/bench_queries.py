"""Closest-point queries per second on real meshes, beside NVIDIA Warp's ``mesh_query_point_no_sign``.

    python bench/bench_queries.py [--meshes bunny legocar] [--points 20000] [--batch 1024]

For each shared mesh (../shared/data; the bundled spot when absent) and point set
(``box``: uniform in the scene box grown by 10%; ``near``: on the surface moved along the
normal by up to 1% of the diagonal), times :func:`jaxbvh.queries.closest_point` through a
tree of ``jaxbvh.build`` (default builder), warm (after a call that compiles), the
points in batches of ``--batch`` (one compiled shape), median of ``--repeat`` runs; wall
and process CPU seconds. Warp (``pip install warp-lang``, optional: skipped when absent)
answers the same points with its own BVH on the CPU device. "same prim" is the fraction of
points whose triangle is Warp's, "max |d - d_warp|" the largest distance difference.

A depth check: the same points through a 2,000-deep chain tree (every node has a leaf
child) and a balanced tree over the first 2,000 triangles of the first mesh, reported as
time per walk step (steps = box tests / k + primitive tests), which should not depend on
depth. Writes ``bench/results/bench_queries.json`` and ``.md``. Run without the test
suite's XLA_FLAGS (a plain python process).

``--raycast [--before CHECKOUT]``: rays instead, :func:`jaxbvh.queries.raycast` (closest
hit inside jit, in batches of ``--ray-batch`` rays) on the shared meshes' reference trees
with random and camera rays, beside :func:`jaxbvh.rays.closest_hit` (the host driver)
and Embree (embreex) on the same rays in the same process; ``--before``: the same in a
child process that imports another checkout's ``jaxbvh`` (e.g. main). Process CPU
seconds, median of ``--repeat`` warm runs, and the first call's CPU seconds (trace and
compile, persistent cache off). Writes ``bench/results/bench_queries_raycast.json`` and ``.md``.

``--native``: the native engine (:mod:`jaxbvh.queries.native_search`, numba) beside the
JAX engine and Warp on the same point sets and the same depth trees, points per CPU-second
(the JAX engine on the first ``--jax-points`` points only: it is 100x slower), and the
first native call in a fresh process with empty caches (cold) and in a second process
(warm). Writes ``bench/results/bench_queries_native.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxbvh
from jaxbvh import queries
from jaxbvh.files import atomic_write
from jaxbvh.io import bundled_mesh_path, load_mesh
from jaxbvh.tree import from_interchange

ROOT = Path(__file__).resolve().parent
DATA = ROOT.parents[1] / "shared" / "data"
MESHES = {"bunny": "meshes/stanford-bunny.obj", "legocar": "meshes/legocar.obj", "spot": None}


def cpu_seconds():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def point_sets(tri, n, rng):
    lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
    pad = 0.1 * (hi - lo)
    box = rng.uniform(lo - pad, hi + pad, (n, 3))
    diag = float(np.linalg.norm(hi - lo))
    pick = rng.integers(0, len(tri), n)
    normal = np.cross(tri[pick, 1] - tri[pick, 0], tri[pick, 2] - tri[pick, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    near = np.einsum("pc,pcx->px", rng.dirichlet([1, 1, 1], n), tri[pick]) \
        + rng.uniform(-0.01, 0.01, (n, 1)) * diag * normal
    return {"box": box.astype(np.float32), "near": near.astype(np.float32)}


def ours(tree, tri, points, batch, engine="jax"):
    """closest_point over ``points`` in batches of ``batch`` (last one padded) by ``engine``:
    NumPy results."""
    n = len(points)
    parts = []
    for start in range(0, n, batch):
        chunk = np.zeros((batch, 3), np.float32)
        piece = points[start:start + batch]
        chunk[: len(piece)] = piece
        parts.append((len(piece), queries.closest_point(tree, tri, chunk, engine=engine)))
    jax.block_until_ready([p for _, p in parts])
    return {k: np.concatenate([np.asarray(getattr(p, k))[:m] for m, p in parts])
            for k in ("distance", "prim", "box_tests", "prim_tests")}


def timed(fn, repeat):
    walls, cpus, result = [], [], None
    for _ in range(repeat):
        w, c = time.perf_counter(), cpu_seconds()
        result = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(cpu_seconds() - c)
    return result, statistics.median(walls), statistics.median(cpus)


def warp_query(tri):
    """A function points -> (distance, face) by Warp's mesh_query_point_no_sign on the CPU, or None."""
    try:
        import warp as wp
    except ImportError:
        return None
    wp.config.quiet = True
    wp.init()
    vertices = wp.array(tri.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device="cpu")
    indices = wp.array(np.arange(tri.shape[0] * 3, dtype=np.int32), dtype=wp.int32, device="cpu")
    mesh = wp.Mesh(points=vertices, indices=indices)

    @wp.kernel
    def closest(mesh_id: wp.uint64, points: wp.array(dtype=wp.vec3), dist: wp.array(dtype=float),
                face: wp.array(dtype=int)):
        i = wp.tid()
        q = wp.mesh_query_point_no_sign(mesh_id, points[i], 1.0e30)
        if q.result:
            p = wp.mesh_eval_position(mesh_id, q.face, q.u, q.v)
            dist[i] = wp.length(points[i] - p)
            face[i] = q.face
        else:
            face[i] = -1

    def run(points):
        pts = wp.array(points, dtype=wp.vec3, device="cpu")
        dist = wp.zeros(len(points), dtype=float, device="cpu")
        face = wp.zeros(len(points), dtype=int, device="cpu")
        wp.launch(closest, dim=len(points), inputs=[mesh.id, pts, dist, face], device="cpu")
        wp.synchronize()
        return dist.numpy(), face.numpy()

    return run


def chain_tree(lo, hi):
    """Interior node i: leaf i on the left, the rest of the chain on the right (depth n - 1)."""
    n = lo.shape[0]
    inner, total = n - 1, 2 * n - 1
    child = np.full((total, 2), -1, np.int32)
    start, count = np.zeros(total, np.int32), np.zeros(total, np.int32)
    b_lo, b_hi = np.zeros((total, 3), lo.dtype), np.zeros((total, 3), lo.dtype)
    start[inner:], count[inner:] = np.arange(n), 1
    b_lo[inner:], b_hi[inner:] = lo, hi
    for i in reversed(range(inner)):
        rest = i + 1 if i + 1 < inner else total - 1
        child[i] = [inner + i, rest]
        b_lo[i], b_hi[i] = np.minimum(lo[i], b_lo[rest]), np.maximum(hi[i], b_hi[rest])
    return from_interchange(dict(child=child, prim_start=start, prim_count=count, prim_index=np.arange(n, dtype=np.int32),
                                 lo=b_lo, hi=b_hi, root=np.int32(0)))


def raycast_rows(meshes, n_rays, batch, repeat, embree):
    """Rows of rays/s for ``queries.raycast`` and ``rays.closest_hit`` (and Embree) with the
    ``jaxbvh`` on ``sys.path``."""
    from jaxbvh import rays

    rows = []
    for name in meshes:
        if name == "spot":
            continue
        mesh = load_mesh(DATA / MESHES[name])
        tri = mesh.triangles.astype(np.float32)
        tree, _ = jaxbvh.load(DATA / "trees" / f"{name}_binned_ref.npz")
        for kind in ("random", "camera"):
            origin, direction = rays.make_rays(jax.random.key(0), kind, tree, tri, n_rays)
            origin, direction = np.asarray(origin, np.float32), np.asarray(direction, np.float32)
            n = len(origin) // batch * batch
            o, d = origin[:n].reshape(-1, batch, 3), direction[:n].reshape(-1, batch, 3)
            jtree, jtri = jaxbvh.tree.to_jax(tree), jax.numpy.asarray(tri)

            def cast():
                out = [queries.raycast(jtree, jtri, o[i], d[i]) for i in range(len(o))]
                jax.block_until_ready(out)
                return np.concatenate([np.asarray(h.prim) for h in out]), \
                    np.concatenate([np.asarray(h.box_tests) for h in out])

            c = cpu_seconds()
            cast()
            first = cpu_seconds() - c
            (prim, box), _, cpu = timed(cast, repeat)
            row = dict(mesh=name, triangles=int(len(tri)), rays=kind, n=n, raycast_rays_per_cpu_s=n / cpu,
                       raycast_cpu_s=cpu, raycast_first_call_cpu_s=first - cpu, box_tests=float(box.mean()))
            rays.closest_hit(tree, tri, origin[:n], direction[:n])
            hits, _, cpu = timed(lambda: rays.closest_hit(tree, tri, origin[:n], direction[:n]), repeat)
            row.update(closest_hit_rays_per_cpu_s=n / cpu, same_prim_as_closest_hit=float(np.mean(hits.prim == prim)))
            if embree:
                try:
                    from embreex import rtcore_scene
                    from embreex.mesh_construction import TriangleMesh
                except ImportError:
                    pass
                else:
                    scene = rtcore_scene.EmbreeScene()
                    TriangleMesh(scene, tri)
                    scene.run(origin[:1000], direction[:1000])
                    out, _, cpu = timed(lambda: scene.run(origin[:n], direction[:n], output=1), repeat)
                    row.update(embree_rays_per_cpu_s=n / cpu,
                               same_prim_as_embree=float(np.mean(np.asarray(out["primID"]) == prim)))
            rows.append(row)
            print(row, file=sys.stderr, flush=True)
    return rows


def raycast_main(args):
    if args.child:
        json.dump(dict(rows=raycast_rows(args.meshes, args.rays, args.ray_batch, args.repeat, False),
                       load=os.getloadavg()), sys.stdout)
        return
    runs = {}
    env = dict(os.environ, JAXBVH_CACHE="off")  # the first call's compile is measured
    env.pop("XLA_FLAGS", None)
    if args.before:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--raycast", "--child", "--meshes", *args.meshes,
               "--rays", str(args.rays), "--ray-batch", str(args.ray_batch), "--repeat", str(args.repeat)]
        out = subprocess.run(cmd, env=dict(env, PYTHONPATH=str(args.before)), check=True, stdout=subprocess.PIPE,
                             text=True)
        runs["before"] = json.loads(out.stdout)
    runs["after"] = dict(rows=raycast_rows(args.meshes, args.rays, args.ray_batch, args.repeat, True),
                         load=os.getloadavg())
    meta = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(), jax=jax.__version__,
                ray_batch=args.ray_batch, repeat=args.repeat, before=args.before,
                load={k: v["load"] for k, v in runs.items()})
    out = args.out.with_name(args.out.name + "_raycast")
    with atomic_write(out.with_suffix(".json"), "w") as f:
        json.dump(dict(meta=meta, **runs), f, indent=1)
    before = {(r["mesh"], r["rays"]): r for r in runs.get("before", {"rows": []})["rows"]}
    lines = ["# Rays inside jit: jaxbvh.queries.raycast, before and after, beside rays.closest_hit and Embree", "",
             f"CPU, {meta['cpus']} cores, load averages {meta['load']}; JAX {meta['jax']}; batches of "
             f"{meta['ray_batch']} rays per raycast call; rays per CPU-second of the process, median of "
             f"{meta['repeat']} warm runs. Before: {meta['before']} (raycast by the stackless parent walk, "
             "one vmap-ed while_loop per batch); after: this checkout (raycast runs the rays' wavefront walk). "
             "Embree: embreex `run`, its own BVH. First call: CPU s of the first call minus a warm one "
             "(trace and compile of the raycast program).", "",
             "| mesh | rays | raycast before rays/s | raycast after rays/s | after / before | closest_hit rays/s | "
             "Embree rays/s | Embree / raycast | same prim (Embree) | box tests before | after | "
             "first call CPU s before | after |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    nan = float("nan")
    for r in runs["after"]["rows"]:
        b = before.get((r["mesh"], r["rays"]), {})
        emb = r.get("embree_rays_per_cpu_s", nan)
        after_rate, before_rate = r["raycast_rays_per_cpu_s"], b.get("raycast_rays_per_cpu_s", nan)
        lines.append(f"| {r['mesh']} ({r['triangles']:,}) | {r['rays']} | {before_rate:,.0f} | {after_rate:,.0f} | "
                     f"{after_rate / before_rate:.1f}x | {r['closest_hit_rays_per_cpu_s']:,.0f} | {emb:,.0f} | "
                     f"{emb / after_rate:.1f}x | {r.get('same_prim_as_embree', nan):.4f} | "
                     f"{b.get('box_tests', nan):.1f} | {r['box_tests']:.1f} | "
                     f"{b.get('raycast_first_call_cpu_s', nan):.1f} | {r['raycast_first_call_cpu_s']:.1f} |")
    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.md')}")


FIRST_CALL = """
import resource, sys, numpy as np
import jaxbvh
from jaxbvh import queries
from jaxbvh.io import bundled_mesh_path, load_mesh
mesh = load_mesh(bundled_mesh_path())
lo, hi = mesh.local_boxes()
tree = jaxbvh.build(lo, hi)
points = np.random.default_rng(0).uniform(lo.min(0), hi.max(0), (1000, 3)).astype(np.float32)
tri = np.asarray(mesh.local_triangles())
r = resource.getrusage(resource.RUSAGE_SELF)
c = r.ru_utime + r.ru_stime
queries.closest_point(tree, tri, points, engine="native").distance.block_until_ready()
r = resource.getrusage(resource.RUSAGE_SELF)
print(r.ru_utime + r.ru_stime - c)
"""


def native_main(args):
    import tempfile

    rng = np.random.default_rng(0)
    rows, depth_rows = [], []
    jax_n = args.jax_points
    for name in args.meshes:
        path = DATA / MESHES[name] if MESHES[name] and (DATA / MESHES[name]).exists() else bundled_mesh_path()
        mesh = load_mesh(path)
        lo, hi = mesh.local_boxes()
        tri = mesh.local_triangles()
        tree = jaxbvh.build(lo, hi)
        warp = warp_query(tri)
        for kind, pts in point_sets(tri, args.points, rng).items():
            ours(tree, tri, pts[: args.batch], args.batch, "native")  # compiles or loads the kernel
            nat, _, cpu = timed(lambda: ours(tree, tri, pts, args.batch, "native"), args.repeat)
            ours(tree, tri, pts[: args.batch], args.batch, "jax")  # compiles
            jx, _, jcpu = timed(lambda: ours(tree, tri, pts[:jax_n], args.batch, "jax"), args.repeat)
            row = dict(mesh=name, triangles=int(len(tri)), points=kind, n=len(pts), native_cpu_s=cpu,
                       native_points_per_cpu_s=len(pts) / cpu, jax_n=jax_n, jax_cpu_s=jcpu,
                       jax_points_per_cpu_s=jax_n / jcpu,
                       same_prim_as_jax=float(np.mean(nat["prim"][:jax_n] == jx["prim"])),
                       same_box_tests_as_jax=float(np.mean(nat["box_tests"][:jax_n] == jx["box_tests"])),
                       max_abs_diff_jax=float(np.max(np.abs(nat["distance"][:jax_n] - jx["distance"]))),
                       box_tests=float(nat["box_tests"].mean()), prim_tests=float(nat["prim_tests"].mean()))
            if warp is not None:
                warp(pts[:64])
                (wd, wf), _, wcpu = timed(lambda: warp(pts), args.repeat)
                row.update(warp_cpu_s=wcpu, warp_points_per_cpu_s=len(pts) / wcpu,
                           same_prim_as_warp=float(np.mean(wf == nat["prim"])))
            rows.append(row)
            print(row, flush=True)
    mesh = load_mesh(DATA / MESHES[args.meshes[0]] if MESHES[args.meshes[0]] else bundled_mesh_path())
    tri = mesh.local_triangles()[:2000]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    pts = point_sets(tri, args.depth_points, rng)["near"]
    for label, tree in (("balanced (jaxbvh.build)", jaxbvh.build(lo, hi, max_leaf=1)),
                        ("2,000-deep chain", chain_tree(lo, hi))):
        height = int(np.max(jaxbvh.tree.depth(tree)))
        row = dict(tree=label, height=height)
        for engine, n in (("native", len(pts)), ("jax", min(jax_n, len(pts)))):
            ours(tree, tri, pts[: args.batch], args.batch, engine)
            res, _, cpu = timed(lambda: ours(tree, tri, pts[:n], args.batch, engine), args.repeat)
            steps = res["box_tests"].sum() / 2 + res["prim_tests"].sum()
            row.update({f"{engine}_points_per_cpu_s": n / cpu, f"{engine}_ns_per_step": 1e9 * cpu / steps,
                        "steps_per_point": float(steps / n)})
        depth_rows.append(row)
        print(row, flush=True)
    first = {}
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env.pop("NUMBA_CACHE_DIR", None)
    with tempfile.TemporaryDirectory() as folder:
        env["JAXBVH_CACHE_DIR"] = folder
        for label in ("cold", "warm"):
            out = subprocess.run([sys.executable, "-c", FIRST_CALL], env=env, check=True, stdout=subprocess.PIPE,
                                 text=True)
            first[label] = float(out.stdout.strip().splitlines()[-1])
    meta = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(), load=os.getloadavg(),
                jax=jax.__version__, batch=args.batch, repeat=args.repeat, first_call_cpu_s=first)
    out = args.out.with_name(args.out.name + "_native")
    with atomic_write(out.with_suffix(".json"), "w") as f:
        json.dump(dict(meta=meta, rows=rows, depth=depth_rows), f, indent=1)
    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write(render_native(meta, rows, depth_rows))
    print(f"wrote {out.with_suffix('.md')}")


def render_native(meta, rows, depth_rows):
    nan = float("nan")
    first = meta["first_call_cpu_s"]
    lines = ["# Closest point: the native engine (numba) beside the JAX engine and Warp", "",
             f"CPU, {meta['cpus']} cores, load average {', '.join(f'{x:.1f}' for x in meta['load'])} at the end "
             f"(a shared machine); JAX {meta['jax']}; batches of {meta['batch']} points per call; points per "
             f"CPU-second of the process, median of {meta['repeat']} warm runs. Native: "
             "`closest_point(..., engine=\"native\")`, one thread. JAX: `engine=\"jax\"` (a `vmap`-ed "
             "`while_loop` per batch), on the first points of the set only. Warp: `mesh_query_point_no_sign` on "
             "its CPU device, its own BVH (a dash: warp-lang not installed in this run). \"same prim / box tests as "
             "JAX\": the fraction of the points both engines ran where the native engine's triangle / box-test "
             "count is the JAX engine's; max \\|d - d_jax\\|: the largest distance difference.", "",
             "| mesh | triangles | points | native points/CPU s | JAX points/CPU s | native / JAX | Warp points/CPU s "
             "| Warp / native | same prim as JAX | same box tests as JAX | max \\|d - d_jax\\| | same prim as Warp "
             "| box tests | prim tests |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "warp_points_per_cpu_s" in r:
            warp = r["warp_points_per_cpu_s"]
            warp = (f"{warp:,.0f}", f"{warp / r['native_points_per_cpu_s']:.2f}x", f"{r['same_prim_as_warp']:.4f}")
        else:
            warp = ("—", "—", "—")
        lines.append(f"| {r['mesh']} | {r['triangles']:,} | {r['points']} | {r['native_points_per_cpu_s']:,.0f} | "
                     f"{r['jax_points_per_cpu_s']:,.0f} | "
                     f"{r['native_points_per_cpu_s'] / r['jax_points_per_cpu_s']:.0f}x "
                     f"| {warp[0]} | {warp[1]} | {r['same_prim_as_jax']:.4f} | "
                     f"{r['same_box_tests_as_jax']:.4f} | {r['max_abs_diff_jax']:.1e} "
                     f"| {warp[2]} | {r['box_tests']:.0f} | {r['prim_tests']:.1f} |")
    lines += ["", "Depth: the same near-surface points through a balanced tree and a 2,000-deep chain over the "
              "first 2,000 triangles of the first mesh (steps = box tests / 2 + primitive tests).", "",
              "| tree | height | steps per point | native points/CPU s | native ns per step | JAX points/CPU s | "
              "JAX ns per step |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in depth_rows:
        lines.append(f"| {r['tree']} | {r['height']:,} | {r['steps_per_point']:.0f} | "
                     f"{r['native_points_per_cpu_s']:,.0f} | {r['native_ns_per_step']:.0f} | "
                     f"{r['jax_points_per_cpu_s']:,.0f} | {r['jax_ns_per_step']:.0f} |")
    lines += ["", f"First native call (1,000 points, spot), CPU s of the call in a new process: cold (empty "
              f"JAXBVH_CACHE_DIR: numba compiles the kernel, float32) {first['cold']:.2f}; warm (a second process, "
              f"numba's cache in that folder) {first['warm']:.2f}.", "",
              "Notes. \"same prim as JAX\" below 1 with the same box tests everywhere: exact ties, a point closest "
              "to a vertex that several triangles share. The native engine evaluates the NumPy twin's formulas "
              "bit for bit and names the lowest id; XLA rounds the shared vertex's distance differently from one "
              "triangle to the next (a fused multiply-add), so the JAX engine can name another of the equidistant "
              "triangles (checked on spot's box points: the 7 of 256 that differ all have native == twin). "
              "The ratio native / JAX is of one CPU thread against XLA's program on the same thread count; "
              "the JAX engine's ns per step falls on the chain because every lane of a batch walks the same long "
              "path there (no lane waits for a slower one)."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "legocar"], choices=sorted(MESHES))
    ap.add_argument("--points", type=int, default=20_000)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--depth-points", type=int, default=2_000)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench_queries")
    ap.add_argument("--render", action="store_true", help="only rewrite the .md from the saved .json")
    ap.add_argument("--raycast", action="store_true", help="rays through queries.raycast instead (docstring)")
    ap.add_argument("--before", help="with --raycast: a checkout whose jaxbvh is the 'before' (e.g. main)")
    ap.add_argument("--rays", type=int, default=20_000)
    ap.add_argument("--ray-batch", type=int, default=4096)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--native", action="store_true", help="the native engine beside jax and Warp (docstring)")
    ap.add_argument("--jax-points", type=int, default=2048, help="with --native: points the JAX engine answers")
    args = ap.parse_args(argv)
    if args.raycast:
        return raycast_main(args)
    if args.native:
        return native_main(args)
    if args.render:
        saved = json.loads(args.out.with_suffix(".json").read_text())
        with atomic_write(args.out.with_suffix(".md"), "w") as f:
            f.write(render(saved["meta"], saved["rows"], saved["depth"]))
        return
    rng = np.random.default_rng(0)
    rows, depth_rows = [], []
    for name in args.meshes:
        path = DATA / MESHES[name] if MESHES[name] and (DATA / MESHES[name]).exists() else bundled_mesh_path()
        mesh = load_mesh(path)
        lo, hi = mesh.local_boxes()
        tri = mesh.local_triangles()
        tree = jaxbvh.build(lo, hi)
        warp = warp_query(tri)
        for kind, pts in point_sets(tri, args.points, rng).items():
            w, c = time.perf_counter(), cpu_seconds()
            ours(tree, tri, pts[: args.batch], args.batch)  # compiles (once per tree shape)
            first = (time.perf_counter() - w, cpu_seconds() - c)
            res, wall, cpu = timed(lambda: ours(tree, tri, pts, args.batch), args.repeat)
            row = dict(mesh=name, triangles=int(len(tri)), points=kind, n=len(pts), first_call_s=first[0],
                       first_call_cpu_s=first[1], wall_s=wall, cpu_s=cpu, points_per_s=len(pts) / wall,
                       box_tests=float(res["box_tests"].mean()), prim_tests=float(res["prim_tests"].mean()))
            if warp is not None:
                warp(pts[:64])  # compiles the kernel
                (wd, wf), wwall, wcpu = timed(lambda: warp(pts), args.repeat)
                row.update(warp_wall_s=wwall, warp_cpu_s=wcpu, warp_points_per_s=len(pts) / wwall,
                           same_prim=float(np.mean(wf == res["prim"])),
                           max_abs_diff=float(np.max(np.abs(wd - res["distance"]))))
            rows.append(row)
            print(row, flush=True)
    # depth: a chain against a balanced tree over the same triangles
    mesh = load_mesh(DATA / MESHES[args.meshes[0]] if MESHES[args.meshes[0]] else bundled_mesh_path())
    tri = mesh.local_triangles()[:2000]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    pts = point_sets(tri, args.depth_points, rng)["near"]
    for label, tree in (("balanced (jaxbvh.build)", jaxbvh.build(lo, hi, max_leaf=1)), ("2,000-deep chain", chain_tree(lo, hi))):
        height = int(np.max(jaxbvh.tree.depth(tree)))
        ours(tree, tri, pts[: args.batch], args.batch)
        res, wall, cpu = timed(lambda: ours(tree, tri, pts, args.batch), args.repeat)
        steps = res["box_tests"].sum() / 2 + res["prim_tests"].sum()
        depth_rows.append(dict(tree=label, height=height, points_per_s=len(pts) / wall, wall_s=wall, cpu_s=cpu,
                               steps_per_point=float(steps / len(pts)), ns_per_step=1e9 * wall / steps))
        print(depth_rows[-1], flush=True)
    meta = dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                load=os.getloadavg(), jax=jax.__version__, batch=args.batch, repeat=args.repeat)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.out.with_suffix(".json"), "w") as f:
        json.dump(dict(meta=meta, rows=rows, depth=depth_rows), f, indent=1)
    with atomic_write(args.out.with_suffix(".md"), "w") as f:
        f.write(render(meta, rows, depth_rows))


def render(meta, rows, depth_rows):
    lines = ["# Closest-point queries per second (jaxbvh.queries.closest_point, Warp beside)", "",
             f"CPU, {meta['cpus']} cores, load average {', '.join(f'{x:.1f}' for x in meta['load'])} at the end; "
             f"JAX {meta['jax']}; batches of {meta['batch']} points; median of {meta['repeat']} warm runs. "
             "Warp: `mesh_query_point_no_sign` on its CPU device (one thread), its own BVH.", "",
             "| mesh | triangles | points | jaxbvh points/s | CPU s | first call s | box tests | prim tests "
             "| Warp points/s | Warp CPU s | ratio (wall) | ratio (CPU s) | same prim | max \\|d - d_warp\\| |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        warp = (f"{r['warp_points_per_s']:,.0f} | {r['warp_cpu_s']:.3f} | {r['warp_points_per_s'] / r['points_per_s']:.1f}x | "
                f"{r['cpu_s'] / r['warp_cpu_s']:.0f}x | "
                f"{r['same_prim']:.4f} | {r['max_abs_diff']:.1e}") if "warp_points_per_s" in r else "— | — | — | — | — | —"
        lines.append(f"| {r['mesh']} | {r['triangles']:,} | {r['points']} | {r['points_per_s']:,.0f} | {r['cpu_s']:.2f} "
                     f"| {r['first_call_s']:.1f} | {r['box_tests']:.0f} | {r['prim_tests']:.1f} | {warp} |")
    lines += ["", "Depth (the stackless walk's cost per step should not depend on the tree's height): the same "
              "near-surface points, the first 2,000 triangles of the first mesh.", "",
              "| tree | height | points/s | steps per point | ns per step |", "|---|---:|---:|---:|---:|"]
    for r in depth_rows:
        lines.append(f"| {r['tree']} | {r['height']:,} | {r['points_per_s']:,.0f} | {r['steps_per_point']:.0f} "
                     f"| {r['ns_per_step']:.0f} |")
    lines += ["", "Notes. Ties: points far from the surface are often closest to a vertex shared by several "
              "triangles; we report the lowest id, Warp another, hence \"same prim\" well below 1 on the box "
              "points while the distances agree. Degenerate triangles: Warp skips zero-area triangles, we do "
              "not (one is a segment, and its distance is the segment's), so a point on a degenerate triangle "
              "of legocar is at 0 for us and at a neighbour's distance for Warp (the largest differences). "
              "The jaxbvh column is a `vmap`-ed `while_loop` per batch, which runs as long as its slowest "
              "point; Warp compiles one C++ loop per point. The machine was shared (load above), so compare "
              "the ratios within a row, and CPU seconds rather than wall time."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
