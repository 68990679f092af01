"""How much SAH can better opening decisions buy at a fixed BRef budget? (issue 22, a study)

    python bench/opening_study.py            # fandisk and cow by material, a pile of 6 cows
    python bench/opening_study.py --quick    # the cow by material only, small greedy

Every number comes from the NumPy twin :func:`jaxbvh.twolevel.brefs_reference.build_top_level`
(the tests hold the engine equal to it BRef by BRef; the library's own order is checked
here against ``build_from``'s SAH). Three parts, per scene and slot count:

1. **Opening orders.** The twin's ``_open_once`` ranks the candidates (interior BRefs wider
   than ``threshold`` x the segment's largest extent along that axis ``dim``) widest first
   along ``dim`` when they do not all fit into the segment's room. Here it is replaced by
   a copy with another ranking (``ORDERS``); everything else (termination, rounds, binning,
   partition, spare split) stays the library's.
2. **Greedy cut search** (achievable, not a proof): start from one BRef per instance and
   repeatedly open the BRef of the current cut whose opening lowers the SAH of the
   flattened tree most, the plain top level (the twin at ``threshold = inf``) rebuilt over
   the cut for every trial; only the ``--greedy-candidates`` largest-area BRefs of the cut
   are tried per step; the best cut met on the way counts, and the search stops at
   ``--greedy-seconds``.
3. **Lower bounds** that no opening order and no top level over <= ``slots`` BRefs can beat
   (module comment "Lower bounds" below).

SAH: the flattened world-box SAH (:func:`jaxbvh.twolevel.sah`, Ct = Ci = 1), the root on
the plain root's box as ``build_from`` puts it; raw (no never-worse comparison). Writes
bench/results/opening_study.json and .md (``--quick``: opening_study_quick.*).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jaxbvh  # noqa: E402
from bench.bench_rebraid import machine  # noqa: E402
from jaxbvh import scenes, twolevel  # noqa: E402
from jaxbvh.io import bundled_mesh_path, load_mesh  # noqa: E402
from jaxbvh.twolevel import brefs_reference as ref  # noqa: E402
from jaxbvh.twolevel import objects as fm  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"


# ----------------------------------------------------------------------------------
# Opening orders: a copy of the twin's _open_once with the ranking as a parameter
# ----------------------------------------------------------------------------------


def _half_area(lo, hi):
    d = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0)
    return d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]


def _width(refs, p, ids, dim):
    return float(refs.hi[p, dim] - refs.lo[p, dim])


def _area(refs, p, ids, dim):
    return float(_half_area(refs.lo[p], refs.hi[p]))


def _sah_weight(refs, p, ids, dim):
    return _area(refs, p, ids, dim) * float(refs.prims[p])


def _overlap(refs, p, ids, dim):
    """Sum of the half-areas of the box's intersections with the segment's other BRefs."""
    others = ids[ids != p]
    lo = np.maximum(refs.lo[others], refs.lo[p])
    hi = np.minimum(refs.hi[others], refs.hi[p])
    inside = np.all(hi >= lo, axis=1)
    return float(_half_area(lo[inside], hi[inside]).sum())


# name: (rank key, larger first; threshold filter on)
ORDERS = {
    "widest (library)": (_width, True),
    "largest half-area": (_area, True),
    "half-area x prims": (_sah_weight, True),
    "largest overlap": (_overlap, True),
    "widest, no filter": (_width, False),
    "half-area x prims, no filter": (_sah_weight, False),
}


def _open_once_by(key, filtered):
    """``ref._open_once`` with candidates ranked by ``key(refs, p, ids, dim)`` (largest
    first, ties to the lower slot) and, unless ``filtered``, every interior BRef a candidate."""

    def open_once(refs, f, instances, ids, end, extra, box_lo, box_hi, threshold, estimate):
        candidates = [p for p in ids if ref._is_interior(f, refs.node[p])
                      and (not filtered or ref._wide(refs, p, box_lo, box_hi, threshold))]
        room = extra - end
        if room < len(candidates):
            dim = int(np.argmax(box_hi - box_lo))
            rank = {p: key(refs, p, ids, dim) for p in candidates}
            candidates = sorted(sorted(candidates, key=lambda p: (-rank[p], p))[:room])
        for k, p in enumerate(candidates):
            n, i, slot = refs.node[p], refs.inst[p], end + k
            kid_l, kid_r = int(f.left[n]), int(f.right[n])
            refs.node[slot], refs.inst[slot], refs.prims[slot] = kid_r, i, f.subtree_prims[kid_r]
            refs.lo[slot], refs.hi[slot] = ref._bref_box(instances, kid_r, i)
            refs.node[p], refs.prims[p] = kid_l, f.subtree_prims[kid_l]
            refs.lo[p], refs.hi[p] = ref._bref_box(instances, kid_l, i)
        return end + len(candidates)

    return open_once


@contextlib.contextmanager
def patched(module, name, value):
    saved = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, saved)


def as_two_level(top, brefs, forest, instances, n, root_lo, root_hi):
    """The twin's ``(top, brefs by slot)`` as a :class:`jaxbvh.twolevel.TwoLevelBVH` whose
    BRef ids are slots, the root on the plain root's box (as ``build_from``)."""
    lo, hi = np.array(top.lo), np.array(top.hi)
    lo[int(top.root)], hi[int(top.root)] = root_lo, root_hi
    top = dataclasses.replace(top, lo=lo, hi=hi)
    return twolevel.TwoLevelBVH(top=top, bref_node=brefs["node"], bref_instance=brefs["instance"],
                                bref_lo=brefs["lo"], bref_hi=brefs["hi"], bref_prims=brefs["prims"],
                                bref_count=np.int32(int((brefs["node"] >= 0).sum())), forest=forest,
                                instances=instances, n_instances=np.int32(n))


# ----------------------------------------------------------------------------------
# Costs of a cut: the flattened SAH as top-level interior areas + fixed subtree costs
# ----------------------------------------------------------------------------------
#
# The flattened tree's unnormalised SAH (Ct = Ci = 1) is the sum of the half-areas of the
# top level's interior nodes plus, for every BRef b = (node, instance) of the cut, S(b):
# the cost of b's subtree with every node on its BRef box (S(b) = A(b) + S(left) + S(right)
# for an interior node, A(b) x its primitives for a leaf). S depends on the cut only
# through its members, so it is computed once per placed node.


class PlacedCosts:
    """``area[i][n]``, ``cost[i][n]`` (float64 [forest nodes] per instance; unused nodes 0):
    BRef-box half-area and subtree cost S of forest node ``n`` under instance ``i``."""

    def __init__(self, forest, instances, n):
        f = jaxbvh.to_numpy(forest)
        self.left, self.right = np.asarray(f.left), np.asarray(f.right)
        self.prim_count = np.asarray(f.prim_count)
        nf = self.left.shape[0]
        self.area, self.cost, self.nodes = [], [], []
        for i in range(n):
            root = int(f.root[int(instances.object[i])])
            levels, frontier = [], np.array([root])
            for _ in range(nf + 1):  # bounded by the forest's depth
                if frontier.size == 0:
                    break
                levels.append(frontier)
                inner = frontier[self.left[frontier] >= 0]
                frontier = np.concatenate([self.left[inner], self.right[inner]])
            every = np.concatenate(levels)
            rows = every + int(instances.box_shift[i])
            area = np.zeros(nf)
            area[every] = _half_area(instances.world_lo[rows], instances.world_hi[rows])
            cost = np.zeros(nf)
            for level in reversed(levels):
                inner = self.left[level] >= 0
                cost[level] = np.where(inner, area[level] + cost[self.left[level]] * inner
                                       + cost[self.right[level]] * inner,
                                       area[level] * self.prim_count[level])
            self.area.append(area)
            self.cost.append(cost)
            self.nodes.append(every[self.left[every] >= 0])  # interior nodes under instance i


def top_of_cut(cut, forest, instances):
    """The plain top level (the twin at ``threshold = inf``) over the BRefs ``cut``
    [(node, instance)]: ``(top, brefs)`` as ``ref.build_top_level``."""
    f = jaxbvh.to_numpy(forest)

    def cut_brefs(f, instances, n_refs, slots, dtype):
        refs = ref._BRefArray(node=np.full(slots, -1, np.int64), inst=np.full(slots, -1, np.int64),
                              lo=np.full((slots, 3), np.inf, dtype), hi=np.full((slots, 3), -np.inf, dtype),
                              prims=np.zeros(slots, np.int64))
        for k, (n, i) in enumerate(cut):
            refs.node[k], refs.inst[k] = n, i
            refs.lo[k], refs.hi[k] = ref._bref_box(instances, n, i)
            refs.prims[k] = f.subtree_prims[n]
        return refs

    with patched(ref, "_instances_brefs", cut_brefs):
        return ref.build_top_level(f, instances, len(cut), threshold=math.inf, slots=len(cut))


def parts(top, cut, costs, root_area):
    """``(top level, below)`` of the flattened SAH (normalised by ``root_area``): the top
    level's interior half-areas (its root on ``root_area``) and the cut's subtree costs S."""
    inner = np.asarray(top.left) >= 0
    areas = _half_area(np.asarray(top.lo)[inner], np.asarray(top.hi)[inner])
    is_root = np.flatnonzero(inner) == int(top.root)
    return ((float(areas[~is_root].sum()) + root_area) / root_area,
            float(sum(costs.cost[i][n] for n, i in cut)) / root_area)


def cut_sah(cut, costs, forest, instances, root_area):
    """Flattened world SAH of the plain top level over ``cut`` plus the cut's subtrees."""
    return sum(parts(top_of_cut(cut, forest, instances)[0], cut, costs, root_area))


def greedy(cut, slots, costs, forest, instances, root_area, candidates, seconds):
    """Open, one BRef at a time, the one of the ``candidates`` largest-area interior BRefs
    of the cut whose opening gives the lowest :func:`cut_sah` (even where it rises: one
    opening of an object spanning the scene mostly does, the next ones pay it back),
    until ``slots`` BRefs, no interior BRef is left, or ``seconds`` pass. Returns
    ``(sah, cut, trials, finished)`` of the best cut met on the way."""
    cut = list(cut)
    best_sah, best_cut = cut_sah(cut, costs, forest, instances, root_area), cut
    start, trials = time.perf_counter(), 0
    while len(cut) < slots:
        if time.perf_counter() - start > seconds:
            return best_sah, best_cut, trials, False
        inner = [k for k, (n, i) in enumerate(cut) if costs.left[n] >= 0]
        inner.sort(key=lambda k: -costs.area[cut[k][1]][cut[k][0]])
        step_sah, step_cut = math.inf, None
        for k in inner[:candidates]:
            n, i = cut[k]
            trial = cut[:k] + [(int(costs.left[n]), i)] + cut[k + 1:] + [(int(costs.right[n]), i)]
            value = cut_sah(trial, costs, forest, instances, root_area)
            trials += 1
            if value < step_sah:
                step_sah, step_cut = value, trial
        if step_cut is None:
            break
        cut = step_cut
        if step_sah < best_sah:
            best_sah, best_cut = step_sah, step_cut
    return best_sah, best_cut, trials, True


# ----------------------------------------------------------------------------------
# Lower bounds
# ----------------------------------------------------------------------------------
#
# For a cut C of k <= K BRefs (each a node of an instance's object tree; the instances'
# roots opened m = k - n times) and any top level over it, the unnormalised SAH is
# T + sum_{b in C} S(b), T the top level's interior half-areas.
#
# LB1: T >= A_root, and opening node v replaces S(v) by S(l) + S(r) = S(v) - A(v), so
# sum_C S(b) >= sum_roots S - (the m largest A over interior nodes): a child's box lies
# in its parent's, so the m largest areas can always be taken ancestor-closed.
#
# LB2 also counts the top level's other interior nodes. Map every interior node v to the
# largest-area leaf of its child with the smaller maximum: each leaf is the image of at
# most one node (the first ancestor where a larger leaf joins it) and the largest leaf of
# all of none, and v's box contains its image's. So the k - 2 non-root interior nodes
# cost at least sum_C A(b) - 2 max_C A(b) >= sum_C A(b) - 2 max_roots A. With S'(b) =
# S(b) + A(b), opening v changes sum_C S' by A(l) + A(r) - 2 A(v) <= 0: the gain
# g(v) = 2 A(v) - A(l) - A(r); any m nodes gain at most the m largest g (ancestor-closure
# dropped, which only lowers the bound). LB2 = A_root - 2 max_roots A + sum_roots S'
# - (the m largest g).


def lower_bounds(costs, roots, slots, root_area):
    """``(LB1, LB2)`` for ``slots`` BRefs over the instances' ``roots`` [(node, instance)],
    normalised by ``root_area`` (module comment above)."""
    n, m = len(roots), slots - len(roots)
    root_cost = sum(costs.cost[i][v] for v, i in roots)
    root_area_sum = sum(costs.area[i][v] for v, i in roots)
    areas = np.concatenate([costs.area[i][costs.nodes[i]] for i in range(n)])
    gains = np.concatenate([2 * a[v] - a[costs.left[v]] - a[costs.right[v]]
                            for a, v in zip(costs.area, costs.nodes)])
    lb1 = root_area + root_cost - np.sort(areas)[::-1][:m].sum()
    biggest = max(costs.area[i][v] for v, i in roots)
    lb2 = root_area - 2 * biggest + root_cost + root_area_sum - np.sort(gains)[::-1][:m].sum()
    return lb1 / root_area, max(lb1, lb2) / root_area


# ----------------------------------------------------------------------------------
# The study
# ----------------------------------------------------------------------------------


def scene_list(args):
    """``(name, mesh, slot counts)``: the default slots, and 256 (a pile: 4x the default)."""
    cow_path = DATA / "meshes" / "cow.obj"
    cow = load_mesh(cow_path if cow_path.exists() else bundled_mesh_path()).objects[0]
    fandisk = DATA / "meshes" / "fandisk.obj"
    if not args.quick and fandisk.exists():
        yield "by-material (fandisk, 8)", scenes.by_material(*load_mesh(fandisk).objects[0]), [None, 256]
    yield "by-material (cow, 8)", scenes.by_material(*cow), [None] if args.quick else [None, 256]
    if not args.quick:
        yield "pile (6 cows)", scenes.pile(jax.random.key(5), *cow, 6), [None, "4x"]


def study_scene(name, mesh, slot_counts, args):
    n = len(mesh.instances)
    trees = fm.build_objects(mesh)
    forest, instances = fm.pack(mesh, trees)
    forest, instances = jaxbvh.to_numpy(forest), jaxbvh.to_numpy(instances)
    lo, hi = mesh.local_boxes()
    single = float(jaxbvh.sah(jaxbvh.build(lo, hi, method="binned")))
    plain = twolevel.build_from(mesh, trees, threshold=math.inf)
    two_level = twolevel.sah(plain)
    top = jaxbvh.to_numpy(plain.top)
    root_lo, root_hi = top.lo[int(top.root)], top.hi[int(top.root)]
    root_area = float(_half_area(root_lo, root_hi))
    costs = PlacedCosts(forest, instances, n)
    roots = [(int(forest.root[int(instances.object[i])]), i) for i in range(n)]
    check = cut_sah(roots, costs, forest, instances, root_area)
    assert abs(check / two_level - 1) < 1e-4, (check, two_level)  # the decomposition is the SAH
    default = twolevel.slots_of(mesh)
    print(f"\n== {name}: {mesh.n_triangles:,} triangles, {n} instances; two-level SAH {two_level:.3f}, "
          f"single {single:.3f}, default slots {default}", flush=True)
    rows = []
    for setting in slot_counts:
        slots = default if setting is None else 4 * default if setting == "4x" else int(setting)
        label = f"{slots} ({'default' if setting is None else setting})"
        engine = twolevel.build_from(mesh, trees, capacity=slots)
        entry = {"slots": slots, "label": label, "engine_sah": twolevel.sah(engine), "orders": []}
        for order, (key, filtered) in ORDERS.items():
            start = time.perf_counter()
            with patched(ref, "_open_once", _open_once_by(key, filtered)):
                top_r, br = ref.build_top_level(forest, instances, n, slots=slots)
            tl = as_two_level(top_r, br, forest, instances, n, root_lo, root_hi)
            value = twolevel.sah(tl)
            used = int((br["node"] >= 0).sum())
            cut = [(int(v), int(i)) for v, i in zip(br["node"], br["instance"]) if v >= 0]
            top_part, below = parts(top_r, cut, costs, root_area)
            entry["orders"].append({"order": order, "sah": value, "brefs": used, "top": top_part, "below": below,
                                    "seconds": time.perf_counter() - start})
            print(f"  {label} {order:30s} SAH {value:8.3f}  x two-level {value / two_level:.3f}  "
                  f"x single {value / single:.3f}  BRefs {used}", flush=True)
        library = entry["orders"][0]["sah"]
        if engine.bref_count > n and abs(library / entry["engine_sah"] - 1) > 1e-4:
            print(f"  note: twin widest {library:.4f} != build_from {entry['engine_sah']:.4f} "
                  "(build_from kept the plain top level?)", flush=True)
        entry["lower_bound_root_only"], entry["lower_bound"] = lower_bounds(costs, roots, slots, root_area)
        entry["least_below"] = entry["lower_bound_root_only"] - 1.0  # LB1 less the root's own area
        print(f"  {label} lower bounds: {entry['lower_bound_root_only']:.3f} (x two-level "
              f"{entry['lower_bound_root_only'] * root_area / root_area / two_level:.3f}), "
              f"{entry['lower_bound']:.3f} (x two-level {entry['lower_bound'] / two_level:.3f}, "
              f"x single {entry['lower_bound'] / single:.3f})", flush=True)
        if args.greedy_seconds > 0 and slots <= args.greedy_slots:
            start = time.perf_counter()
            value, cut, trials, done = greedy(roots, slots, costs, forest, instances, root_area,
                                              args.greedy_candidates, args.greedy_seconds)
            entry["greedy"] = {"sah": value, "brefs": len(cut), "trials": trials, "finished": done,
                               "seconds": time.perf_counter() - start}
            print(f"  {label} greedy: SAH {value:.3f} x two-level {value / two_level:.3f} x single "
                  f"{value / single:.3f}, {len(cut)} BRefs, {trials} trials, "
                  f"{'done' if done else 'stopped at the time cap'} in {entry['greedy']['seconds']:.0f} s",
                  flush=True)
        rows.append(entry)
    return {"scene": name, "triangles": mesh.n_triangles, "instances": n, "two_level": two_level,
            "single": single, "default_slots": default, "settings": rows}


def markdown(results) -> str:
    lines = ["# Opening study (issue 22): how much SAH can better opening decisions buy?", "",
             f"Machine: {results['machine']}; load before the run: {results['load']}. JAX {results['jax']}, "
             "float32, Ct = Ci = 1. Every SAH is the flattened world-box SAH (`twolevel.sah`) of a "
             "top level built by the NumPy twin `brefs_reference.build_top_level` (the engine equals it "
             "BRef by BRef by the tests; the library's order here equals `build_from`'s SAH wherever "
             "`build_from` kept the re-braided level), raw: without `build_from`'s never-worse comparison. "
             "Threshold 0.1, rounds 64, exact primitive counts; only the ranking of candidates that do "
             "not all fit into a segment's room changes (`bench/opening_study.py`, `ORDERS`).", ""]
    for s in results["scenes"]:
        lines += [f"## {s['scene']}", "",
                  f"{s['triangles']:,} triangles, {s['instances']} instances; two-level SAH "
                  f"{s['two_level']:.3f}, single BVH {s['single']:.3f} (two-level / single "
                  f"{s['two_level'] / s['single']:.3f}); default slots {s['default_slots']}.", "",
                  "*top* and *below*: the SAH's two parts, x two-level (the top level's interior nodes; the "
                  "subtrees of the cut's BRefs). *least below*: no cut of at most that many BRefs has a "
                  "smaller *below* (LB1 less the root), so a top level over it may cost at most "
                  "0.7 x two-level - least below for the 0.7 target.", "",
                  "| slots | order | SAH | x two-level | x single | BRefs used | top | below |",
                  "|---|---|---|---|---|---|---|---|"]
        for e in s["settings"]:
            for o in e["orders"]:
                lines.append(f"| {e['label']} | {o['order']} | {o['sah']:.3f} | {o['sah'] / s['two_level']:.3f} | "
                             f"{o['sah'] / s['single']:.3f} | {o['brefs']} | {o['top'] / s['two_level']:.3f} | "
                             f"{o['below'] / s['two_level']:.3f} |")
            if "greedy" in e:
                g = e["greedy"]
                lines.append(f"| {e['label']} | greedy cut search ({g['trials']} trials, "
                             f"{'finished' if g['finished'] else 'time cap'}) | {g['sah']:.3f} | "
                             f"{g['sah'] / s['two_level']:.3f} | {g['sah'] / s['single']:.3f} | {g['brefs']} | | |")
            for key, what in (("lower_bound_root_only", "lower bound LB1"), ("lower_bound", "lower bound LB2")):
                v = e[key]
                lines.append(f"| {e['label']} | {what} | {v:.3f} | {v / s['two_level']:.3f} | "
                             f"{v / s['single']:.3f} | <= {e['slots']} | | "
                             + (f"least {e['least_below'] / s['two_level']:.3f} |" if key == "lower_bound_root_only"
                                else "|"))
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the cow by material at its default slots only")
    parser.add_argument("--greedy-slots", type=int, default=None,
                        help="greedy search only up to this many slots (default 256, quick 90)")
    parser.add_argument("--greedy-candidates", type=int, default=None,
                        help="largest-area BRefs tried per greedy step (default 8, quick 4)")
    parser.add_argument("--greedy-seconds", type=float, default=None,
                        help="time cap of one greedy search (default 150, quick 20; 0: none run)")
    args = parser.parse_args(argv)
    args.greedy_slots = args.greedy_slots or (90 if args.quick else 256)
    args.greedy_candidates = args.greedy_candidates or (4 if args.quick else 8)
    args.greedy_seconds = (20.0 if args.quick else 150.0) if args.greedy_seconds is None else args.greedy_seconds
    results = {"machine": machine(), "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
               "jax": jax.__version__, "quick": args.quick, "scenes": []}
    for name, mesh, slot_counts in scene_list(args):
        results["scenes"].append(study_scene(name, mesh, slot_counts, args))
    RESULTS.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    (RESULTS / f"opening_study{suffix}.json").write_text(json.dumps(results, indent=1))
    (RESULTS / f"opening_study{suffix}.md").write_text(markdown(results))
    print(f"\nwrote {RESULTS / f'opening_study{suffix}.json'} and .md")


if __name__ == "__main__":
    main()
