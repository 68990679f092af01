"""Calibrate the cost targets (:mod:`jaxbvh.tree.targets`) from tinybvh's kernels (issue 40).

    python bench/calibrate_targets.py                       # legocar and spot, res 96
    python bench/calibrate_targets.py --meshes legocar --res 96 --repeats 3

For every mesh, a few trees of different shapes (builders, leaf limits) are written to
tinybvh's node file and traced in one run of the shared tracer (``../shared/peer/
tinybvh_trace``, TRACE.md there) in its four layouts, on its primary, random and bounce
rays: the time per ray (thread CPU time, min over ``--repeats``). The same trees are then
traced here by :func:`jaxbvh.rays.closest_hit` on rays of the same three kinds (the
primary rays are the tracer's own camera; the random and bounce rays are drawn from the
same distributions, not the same samples), counting per ray the node visits and the
triangle tests *of the tree each kernel runs*:

* ``BVH``, ``BVH_SoA``: the binary tree as it is (children in order of entry distance,
  as tinybvh's kernels visit them);
* ``BVH4_CPU``, ``BVH8_CPU``: the tree after tinybvh's ``CombineLeafs(4)`` (every subtree
  of at most 4 triangles one leaf: :func:`jaxbvh.optimize.leaves.merge_leaves` with a
  prohibitive ``Ct``, which merges whatever it may), collapsed by tinybvh's own rule
  (``MBVH::ConvertFrom``: a node adopts its largest-area interior child while the
  children fit in ``M``; reproduced in :func:`tinybvh_collapse`) and counted through
  the skip flags (:mod:`jaxbvh.rays.traversal`): one visit per wide node. Trees with
  leaves of more than 4 triangles are left out of these two fits (tinybvh's
  ``SplitLeafs(4)`` would change them).

The fit, per layout, by non-negative least squares over every (tree, ray set): ``ns per ray = c0[set] +
a * node visits + b * triangle tests``. The target's costs are ``Ct = a / b`` and ``Ci =
1`` (cost in triangle tests; only the ratio changes which tree is best). For the wide
layouts a second fit against the *binary* tree's counts (the tree after the leaf merge,
no collapse) gives the ``Ct`` the binary optimizers use for that target (``binary_ct``).
Errors: the relative residual of each point (RMS and max). Writes
``bench/results/targets.{json,md}``; the numbers go into :data:`jaxbvh.tree.targets.TARGETS`
by hand (the table is code, this script is its evidence).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import nnls

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.bench_render import DATA, INPUTS, LAYOUT_CLASS, LAYOUTS, PEER, RESULTS, SETS, load, tracer  # noqa: E402

#: the trees of every mesh: name -> (builder, options); shapes from deep one-triangle
#: leaves to shallow 16-triangle ones (a high Ct or a low Ci makes the builder's SAH leaf
#: test keep big leaves), good and poor builders, so that node visits and triangle tests
#: vary apart
TREES = {"sweep1": ("sweep", {"max_leaf": 1}), "sweep4": ("sweep", {"max_leaf": 4}),
         "sweep8ci": ("sweep", {"max_leaf": 8, "ci": 0.3}), "sweep16ct": ("sweep", {"max_leaf": 16, "ct": 6.0}),
         "median1": ("median", {"max_leaf": 1}), "binned4": ("binned", {"max_leaf": 4}),
         "lbvh1": ("lbvh", {"max_leaf": 1}), "ploc4": ("ploc", {"max_leaf": 4})}
WIDTH = {"bvh4": 4, "bvh8": 8}
#: tinybvh's ConvertFrom merges subtrees of up to this many triangles (CombineLeafs(4))
COMBINE = 4


# ----------------------------------------------------------------------------------
# The rays (world space, as the tracer makes them)
# ----------------------------------------------------------------------------------


def primary_rays(lo, hi, res):
    """The tracer's pinhole camera (tinybvh_trace.cpp), float32: ``(origin, direction)`` [res², 3]."""
    f = np.float32
    centre, ext = (lo + hi) * f(0.5), hi - lo
    radius = f(0.5) * np.linalg.norm(ext)
    axis = np.array([0.62, 0.45, 0.64], f)
    axis /= np.linalg.norm(axis)
    eye = centre + axis * (f(1.5) * radius)
    fwd = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(fwd, np.array([0, 1, 0], f))
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    h = f(math.tan(0.5 * 60.0 * math.pi / 180.0))
    x = (2 * (np.arange(res, dtype=f) + f(0.5)) / res - 1) * h
    y = (1 - 2 * (np.arange(res, dtype=f) + f(0.5)) / res) * h
    sx, sy = np.meshgrid(x, y)
    d = fwd[None] + right[None] * sx.reshape(-1, 1) + up[None] * sy.reshape(-1, 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(eye, d.shape).astype(f), d.astype(f)


def random_rays(lo, hi, n, rng):
    """Origins uniform in the box, directions uniform on the sphere (the tracer's distribution)."""
    o = lo + rng.random((n, 3), np.float32) * (hi - lo)
    z = 1 - 2 * rng.random(n, np.float32)
    phi = 2 * np.pi * rng.random(n, np.float32)
    r = np.sqrt(np.maximum(0, 1 - z * z))
    return o.astype(np.float32), np.stack([r * np.cos(phi), r * np.sin(phi), z], 1).astype(np.float32)


def bounce_rays(origin, direction, t, prim, tris, n_pix, radius, rng):
    """Cosine-weighted rays from the primary hits (the tracer's rule: about ``n_pix`` rays)."""
    hit = np.isfinite(t) & (prim >= 0)
    per_hit = max(1, round(n_pix / max(int(hit.sum()), 1)))
    o, d, p = np.repeat(origin[hit], per_hit, 0), np.repeat(direction[hit], per_hit, 0), np.repeat(prim[hit], per_hit)
    tt = np.repeat(t[hit], per_hit)
    v0, v1, v2 = tris[p, 0], tris[p, 1], tris[p, 2]
    normal = np.cross(v1 - v0, v2 - v0)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    ok = length[:, 0] > 0
    normal = normal / np.where(length > 0, length, 1)
    normal = np.where((np.sum(normal * d, 1) > 0)[:, None], -normal, normal)
    point = o + d * tt[:, None] + normal * (1e-4 * radius)
    tangent = np.where((np.abs(normal[:, :1]) > 0.9), np.cross(normal, [0, 1, 0]), np.cross(normal, [1, 0, 0]))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bitangent = np.cross(normal, tangent)
    u1, u2 = rng.random(len(p)), rng.random(len(p))
    rr, phi = np.sqrt(u1), 2 * np.pi * u2
    out = (tangent * (rr * np.cos(phi))[:, None] + bitangent * (rr * np.sin(phi))[:, None]
           + normal * np.sqrt(np.maximum(0, 1 - u1))[:, None])
    return point[ok].astype(np.float32), out[ok].astype(np.float32)


# ----------------------------------------------------------------------------------
# The trees each kernel runs
# ----------------------------------------------------------------------------------


def tinybvh_collapse(tree, width: int) -> np.ndarray:
    """The interior nodes ``MBVH<width>::ConvertFrom`` removes, as skip flags [N] bool.

    From the root down, a node adopts the children of its interior child of largest box
    area (ties: the first) while ``children - 1 + that child's children <= width``;
    then its children are done the same way (tinybvh v1.6.7, tiny_bvh.h)."""
    left, right = np.asarray(tree.left), np.asarray(tree.right)
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    ext = hi - lo
    area = ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0]
    skip = np.zeros(left.shape[0], bool)
    stack = [int(tree.root)]
    while stack:
        node = stack.pop()
        kids = [int(left[node]), int(right[node])]
        while len(kids) < width:
            best, best_area = -1, 0.0
            for i, c in enumerate(kids):
                if left[c] >= 0 and len(kids) + 1 <= width and area[c] > best_area:
                    best, best_area = i, area[c]
            if best < 0:
                break
            c = kids[best]
            skip[c] = True
            kids[best] = int(left[c])
            kids.append(int(right[c]))
        stack.extend(c for c in kids if left[c] >= 0)
    return skip


def counts(tree, tris, origin, direction, skip=None) -> dict:
    """Mean node visits (interior nodes whose children were tested; with skip flags, wide
    nodes) and triangle tests per ray, closest hit."""
    from jaxbvh.rays import closest_hit

    hits = closest_hit(tree, tris, origin, direction, skip=skip)
    leaves = np.asarray(hits.leaves_visited)
    interior = np.asarray(hits.nodes_visited) - leaves
    return {"visits": float(interior.mean()), "tris": float(np.asarray(hits.prim_tests).mean()),
            "leaves": float(leaves.mean())}


def one_mesh(name, args, exe, work):
    import jax.numpy as jnp

    import jaxbvh
    from jaxbvh.io import export_tinybvh, load_mesh
    from jaxbvh.optimize.leaves import merge_leaves

    path = Path(INPUTS.get(name, name))
    path = path if path.is_absolute() or path.exists() else DATA / path
    mesh = load_mesh(path)
    lo, hi = mesh.local_boxes()
    tris_local = np.asarray(mesh.local_triangles(), np.float32)
    world = np.asarray(mesh.triangles, np.float64)
    work = work / Path(name).stem
    work.mkdir(parents=True, exist_ok=True)
    files, trees = {}, {}
    for tree_name, (builder, options) in TREES.items():
        tree = jaxbvh.to_numpy(jaxbvh.build(lo, hi, method=builder, **options))
        tree = tree.replace(axis=np.full_like(tree.axis, -1))  # visit by entry distance, as tinybvh does
        trees[tree_name] = tree
        files[tree_name] = work / f"{tree_name}.bin"
        export_tinybvh(files[tree_name], tree, world, mesh.frame)
    tris_bin = work / "tris.bin"
    subprocess.run([sys.executable, str(PEER / "dump_tris.py"), str(path), str(tris_bin)], check=True,
                   capture_output=True)
    cmd = [str(exe), str(tris_bin), "--peer", "none", "--layouts", ",".join(LAYOUTS), "--repeats",
           str(args.repeats), "--res", str(args.res), "--seed", "1", "--label", name]
    for tree_name, f in files.items():
        cmd += ["--tree", f"{tree_name}={f}"]
    load_before = load()
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    lines = [json.loads(x) for x in done.stdout.splitlines() if x.startswith("{")]
    times = {(x["tree"], x["layout"], x["set"]): 1e6 * x["cpu_ms_min"] / x["rays"]
             for x in lines if x["kind"] == "trace"}
    max_leaf_of = {x["tree"]: x["max_leaf"] for x in lines if x["kind"] == "tree"}

    # the rays, world space -> the trees' frame (directions only shrink by the frame's scale)
    wlo, whi = world.reshape(-1, 3).min(0).astype(np.float32), world.reshape(-1, 3).max(0).astype(np.float32)
    n = args.res * args.res
    rng = np.random.default_rng(1)
    rays = {"primary": primary_rays(wlo, whi, args.res), "random": random_rays(wlo, whi, n, rng)}
    to_local = lambda o: mesh.frame.to_local(o.astype(np.float64)).astype(np.float32)  # noqa: E731
    from jaxbvh.rays import closest_hit

    ref = trees["sweep1"]
    po, pd = rays["primary"]
    hits = closest_hit(ref, tris_local, to_local(po), pd)
    t_world = np.where(np.asarray(hits.prim) >= 0, np.asarray(hits.t, np.float64) * mesh.frame.scale, np.inf)
    radius = 0.5 * float(np.linalg.norm(whi - wlo))
    rays["bounce"] = bounce_rays(po.astype(np.float64), pd.astype(np.float64), t_world, np.asarray(hits.prim),
                                 world, n, radius, rng)
    points = []
    for tree_name, tree in trees.items():
        merged = jaxbvh.to_numpy(merge_leaves(jaxbvh.to_jax(tree), jnp.int32(COMBINE), jnp.float32(1e6),
                                              jnp.float32(1.0)))
        skips = {layout: tinybvh_collapse(merged, w) for layout, w in WIDTH.items()}
        for ray_set in SETS:
            o, d = rays[ray_set]
            o = to_local(o)
            binary = counts(tree, tris_local, o, d)
            combined = counts(merged, tris_local, o, d)
            for layout in LAYOUTS:
                if (tree_name, layout, ray_set) not in times:
                    continue
                wide = layout in WIDTH
                if wide and max_leaf_of[tree_name] > COMBINE:
                    continue  # SplitLeafs(4) would change this tree; not modelled
                c = counts(merged, tris_local, o, d, skip=skips[layout]) if wide else binary
                points.append({"mesh": name, "tree": tree_name, "layout": layout, "set": ray_set,
                               "ns_per_ray": times[(tree_name, layout, ray_set)], **c,
                               "binary_visits": (combined if wide else binary)["visits"],
                               "rays_here": int(o.shape[0])})
        print(f"{name}/{tree_name}: counted (load {load()})", file=sys.stderr, flush=True)
    return {"mesh": name, "triangles": int(world.shape[0]), "load_trace": [load_before, load()],
            "trees": {k: [b, o] for k, (b, o) in TREES.items()}, "points": points,
            "tracer": [x for x in lines if x["kind"] != "trace"]}


# ----------------------------------------------------------------------------------
# The fit
# ----------------------------------------------------------------------------------


def fit(points, visits_key="visits", leaf_key="tris"):
    """Non-negative least squares ``ns = c0[set] + a visits + b leaf_work`` over ``points``:
    one intercept per ray set (coherent primary rays and incoherent random rays differ in
    what a ray costs besides its tests: setup, caches), one price per node visit and per
    unit of leaf work (a triangle test, or a leaf visit for the wide kernels, which test a
    leaf's up to 4 triangles at once). ``{c0_ns: {set: ns}, node_ns, leaf_ns, ratio,
    rms_rel, max_rel, n}``."""
    sets = sorted({p["set"] for p in points})
    y = np.array([p["ns_per_ray"] for p in points])
    x = np.array([[float(p["set"] == s) for s in sets] + [p[visits_key], p[leaf_key]] for p in points])
    coef, _ = nnls(x, y)  # no cost can be negative
    a, b = coef[-2], coef[-1]
    rel = (x @ coef - y) / y
    return {"c0_ns": {s: float(c) for s, c in zip(sets, coef[:-2])}, "node_ns": float(a), "leaf_ns": float(b),
            "ratio": float(a / b) if b > 0 else float("inf"), "rms_rel": float(np.sqrt(np.mean(rel ** 2))),
            "max_rel": float(np.max(np.abs(rel))), "n": len(points), "visits": visits_key, "leaf_work": leaf_key}


def fits(meshes) -> dict:
    """Per layout: the fit (triangle tests for the binary kernels, leaf visits for the wide
    ones), the per-triangle fit beside it, per ray set fits, and for the wide layouts the
    fit against the binary tree's visits (``binary``)."""
    points = [p for m in meshes for p in m["points"]]
    out = {}
    for layout in LAYOUTS:
        mine = [p for p in points if p["layout"] == layout]
        if len(mine) < 6:
            continue
        wide = layout in WIDTH
        leaf = "leaves" if wide else "tris"
        f = {"fit": fit(mine, "visits", leaf), "per_triangle": fit(mine, "visits", "tris"),
             "per_set": {s: fit([p for p in mine if p["set"] == s], "visits", leaf) for s in SETS}}
        # a leaf visit in triangles: the mean occupancy of the leaves visited
        f["tris_per_leaf_visit"] = float(np.sum([p["tris"] for p in mine]) / np.sum([p["leaves"] for p in mine]))
        if wide:
            f["binary"] = fit(mine, "binary_visits", leaf)
        out[layout] = f
    wide = [p for p in points if p["layout"] in WIDTH]
    if len(wide) >= 12:
        out["wide"] = {key: joint_fit(wide, key) for key in ("visits", "binary_visits")}
        out["wide"]["tris_per_leaf_visit"] = float(np.sum([p["tris"] for p in wide]) / np.sum([p["leaves"] for p in wide]))
    return out


def joint_fit(points, visits_key):
    """The wide kernels together: one intercept per (layout, ray set), one node price per
    layout, one leaf-visit price shared (both kernels test a leaf's triangles with the same
    4-wide code). Node visits and leaf visits rise together across trees (correlation
    about 0.9 within a ray set), so one layout's points alone fix their ratio poorly; the
    shared leaf price uses both layouts' points."""
    keys = sorted({(p["layout"], p["set"]) for p in points})
    layouts = sorted(WIDTH)
    y = np.array([p["ns_per_ray"] for p in points])
    x = np.array([[float((p["layout"], p["set"]) == k) for k in keys]
                  + [p[visits_key] * (p["layout"] == w) for w in layouts] + [p["leaves"]] for p in points])
    coef, _ = nnls(x, y)
    rel = (x @ coef - y) / y
    return {"node_ns": {w: float(c) for w, c in zip(layouts, coef[len(keys):-1])}, "leaf_ns": float(coef[-1]),
            "rms_rel": float(np.sqrt(np.mean(rel ** 2))), "max_rel": float(np.max(np.abs(rel))), "n": len(points)}


def markdown(report) -> str:
    m = report["machine"]
    out = ["# Cost targets calibrated on tinybvh's kernels (`bench/calibrate_targets.py`)", "",
           f"{m['cpu']}, {m['cores']} cores, shared (load {report['load_start']} → {report['load_end']}); "
           f"tinybvh v1.6.7 kernels, one thread; {report['res']}² rays per set, min of {report['repeats']} "
           f"rounds of thread CPU time; {report['utc']} UTC. Meshes: "
           + ", ".join(f"{r['mesh']} ({r['triangles']:,} triangles)" for r in report["meshes"])
           + "; trees per mesh: " + ", ".join(f"{k} ({b}, {json.dumps(o)})" for k, (b, o) in TREES.items()) + ".", "",
           "Fit per layout over every (mesh, tree, ray set), non-negative least squares: ns per ray = c0[ray set] + "
           "a · node visits + b · leaf work, with the counts of `jaxbvh.rays` on the tree each kernel runs (module "
           "docstring). Leaf work: triangle tests for `BVH` and `BVH_SoA`, which test one triangle at a time; leaf "
           "visits for `BVH4_CPU` and `BVH8_CPU`, which test a leaf's up to 4 triangles at once (their per-triangle "
           "fit is shown beside). Wide layouts: node visits are wide-node visits; the last column fits the same "
           "times against the binary tree's visits after the leaf merge (what the binary optimizers see).", "",
           "| layout | points | c0 (ns) primary / random / bounce | ns / node visit | ns / leaf work | leaf work "
           "| node / leaf work | rel. error RMS / max | per ray set: node / leaf work | per triangle: ns / node, ns / "
           "triangle (error RMS) | binary tree's visits: ns / visit, ratio (error RMS) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for layout, f in report["fits"].items():
        if layout == "wide":
            continue
        g, t = f["fit"], f["per_triangle"]
        b = f.get("binary")
        binary = f"{b['node_ns']:.2f}, {b['ratio']:.3f} ({100 * b['rms_rel']:.1f}%)" if b else "–"
        c0 = " / ".join(f"{g['c0_ns'].get(s, float('nan')):.0f}" for s in SETS)
        per_set = " / ".join(f"{f['per_set'][s]['ratio']:.2f}" for s in SETS)
        work = "leaf visit" if g["leaf_work"] == "leaves" else "triangle test"
        out.append(f"| {LAYOUT_CLASS[layout]} | {g['n']} | {c0} | {g['node_ns']:.2f} | {g['leaf_ns']:.2f} | {work} "
                   f"| **{g['ratio']:.3f}** | {100 * g['rms_rel']:.1f}% / {100 * g['max_rel']:.1f}% | {per_set} "
                   f"| {t['node_ns']:.2f}, {t['leaf_ns']:.2f} ({100 * t['rms_rel']:.1f}%) | {binary} |")
    out += ["", "Triangles per leaf visit (all points of a layout): "
            + ", ".join(f"{LAYOUT_CLASS[k]} {f['tris_per_leaf_visit']:.2f}" for k, f in report["fits"].items()
                        if k != "wide") + "."]
    w = report["fits"].get("wide")
    if w:
        occupancy = w["tris_per_leaf_visit"]
        out += ["", "## The targets", "",
                "Wide kernels fitted together (one leaf-visit price for both; `joint_fit`), in triangle tests: a leaf "
                f"visit tests {occupancy:.2f} triangles on average, so one triangle test = leaf price / {occupancy:.2f}. "
                "`node_ct`: a wide node visit; `ct`: a visit of a node of the binary tree after the leaf merge "
                "(what the optimizers price). Binary kernels: `ct` = the fit's node / triangle ratio.", "",
                "| target | ct | node_ct | ci | fit error RMS / max (wide visits; binary visits) |", "|---|---|---|---|---|"]
        fits = report["fits"]
        for layout in ("bvh", "soa"):
            if layout in fits:
                g = fits[layout]["fit"]
                out.append(f"| tinybvh-{layout} | {g['ratio']:.2f} | {g['ratio']:.2f} | 1 | {100 * g['rms_rel']:.1f}% / "
                           f"{100 * g['max_rel']:.1f}% |")
        for layout in WIDTH:
            a, b = w["visits"], w["binary_visits"]
            node_ct = a["node_ns"][layout] / (a["leaf_ns"] / occupancy)
            ct = b["node_ns"][layout] / (b["leaf_ns"] / occupancy)
            out.append(f"| tinybvh-{layout} | {ct:.2f} | {node_ct:.2f} | 1 | {100 * a['rms_rel']:.1f}% / "
                       f"{100 * a['max_rel']:.1f}%; {100 * b['rms_rel']:.1f}% / {100 * b['max_rel']:.1f}% |")
    out += ["", "## Points", "", "| mesh | tree | layout | set | ns/ray | node visits | binary visits | triangle tests "
            "| leaf visits |", "|---|---|---|---|---|---|---|---|---|"]
    for r in report["meshes"]:
        for p in r["points"]:
            out.append(f"| {p['mesh']} | {p['tree']} | {p['layout']} | {p['set']} | {p['ns_per_ray']:.1f} | "
                       f"{p['visits']:.2f} | {p['binary_visits']:.2f} | {p['tris']:.2f} | {p['leaves']:.2f} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", nargs="+", default=["legocar", "spot"])
    parser.add_argument("--res", type=int, default=96)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "jaxbvh-calibrate")
    parser.add_argument("--peer-build", type=Path, default=Path(os.environ.get("PEER_BUILD", "/tmp/jaxbvh-peer")))
    parser.add_argument("--name", default="targets")
    parser.add_argument("--refit", action="store_true", help="fit again the points of the saved JSON (no runs)")
    args = parser.parse_args(argv)
    if args.refit:
        report = json.loads((RESULTS / f"{args.name}.json").read_text())
        report["fits"] = fits(report["meshes"])
        write(report, args.name)
        return 0
    exe = tracer(args.peer_build)
    cpu = next((x.split(":", 1)[1].strip() for x in open("/proc/cpuinfo") if x.startswith("model name")),
               platform.processor())
    report = {"machine": {"cpu": cpu, "cores": os.cpu_count(), "platform": platform.platform()},
              "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "load_start": load(), "res": args.res,
              "repeats": args.repeats, "meshes": []}
    start = resource.getrusage(resource.RUSAGE_SELF)
    for name in args.meshes:
        report["meshes"].append(one_mesh(name, args, exe, args.work))
        report["fits"] = fits(report["meshes"])
        report["load_end"] = load()
        write(report, args.name)
        print(markdown(report).split("## Points")[0], file=sys.stderr, flush=True)
    end = resource.getrusage(resource.RUSAGE_SELF)
    report["cpu_seconds"] = (end.ru_utime - start.ru_utime) + (end.ru_stime - start.ru_stime)
    write(report, args.name)
    return 0


def write(report, name) -> None:
    from jaxbvh.files import atomic_write

    RESULTS.mkdir(parents=True, exist_ok=True)
    with atomic_write(RESULTS / f"{name}.json", "w") as f:
        json.dump(report, f, indent=1)
    with atomic_write(RESULTS / f"{name}.md", "w") as f:
        f.write(markdown(report))


if __name__ == "__main__":
    sys.exit(main())
