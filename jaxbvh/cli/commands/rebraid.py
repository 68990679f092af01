"""``jaxbvh rebraid SCENE``: two-level, re-braided and single BVHs side by side (Benthin et al. 2017).

Builds the object BVHs of SCENE once, then three trees over the same triangles: the
plain two-level BVH (a top level over the instances), the re-braided one (the top level
opens object nodes) and a single BVH over all world triangles, and prints the paper's
three-way table: SAH (all three flattened to world space, one footing; "SAH obj": with
the nodes below a top-level leaf costed in their object frames, as the two-level
traversal tests them, see ``jaxbvh.twolevel.sah``), stored nodes,
BRefs, total and top-level build seconds, and with ``--rays N`` box and primitive tests
per ray. Build times are warm: every build runs once untimed first, so compiling is not
counted (the CLI also caches compiled code on disk). The BRef array gets the scene's
default size unless ``--budget`` says otherwise (``slots`` in the JSON; ``kept`` says
whether the re-braided top level was kept or, not lowering the SAH, the plain one).

A plain mesh (one object, one identity instance) has nothing to re-braid: its two-level
BVH is the single BVH, so the command builds that once, as ``jaxbvh build`` does (its
seconds then include compiling), and reports it in all three rows (``path``: ``"single
object"``).
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

import jaxbvh
from jaxbvh import rays, twolevel
from jaxbvh.builders.configs import BOX_BUILDERS
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.io import load_mesh
from jaxbvh.rays import traversal as traverse
from jaxbvh.twolevel import objects as fm
from jaxbvh.twolevel.config import RebraidConfig

HELP = "compare two-level, re-braided and single BVHs of a multi-object scene (Benthin et al. 2017)"

#: the top level's knobs (--threshold, --budget, --top-bins, --overlap, --estimate): RebraidConfig's
OPTIONS = config_options.ConfigOptions({"rebraid": RebraidConfig})


def add_parser(subparsers):
    """Add the ``rebraid`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("rebraid", help=HELP, description=HELP + ".")
    parser.add_argument("scene", metavar="SCENE", help="a scene or mesh file (glTF, OBJ, ...); its "
                        "objects and instances are kept")
    OPTIONS.add_to(parser)
    # the builder of the object BVHs and of the single BVH: the two-level builder's
    # (binned SAH, leaves up to OBJECT_MAX_LEAF whichever builder), not jaxbvh.build's sweep.
    # Builders from boxes only: the two-level BVH's objects and BRefs are built from boxes
    # (no spatial splits)
    command_kit.add_builder_args(parser, default=fm.DEFAULT_BUILDER, methods=BOX_BUILDERS,
                                 max_leaf=fm.OBJECT_MAX_LEAF)
    parser.add_argument("--object-space", action="store_true",
                        help="build every object in its own frame, also those placed by one instance "
                        "(default: those are built in world space)")
    parser.add_argument("--rays", type=command_kit._int_at_least(1), default=None, metavar="N",
                        help="trace N random rays through all three: box and primitive tests per ray")
    command_kit.add_seed(parser, "random seed of the rays")
    parser.add_argument("-o", "--output", metavar="FLAT.npz", default=None,
                        help="save the re-braided tree flattened to world space (validated first)")
    command_kit.add_json(parser)
    return parser


def _timed(fn):
    import jax

    fn()  # compile (untimed)
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def run(args) -> dict:
    """Run ``jaxbvh rebraid`` on parsed ``args``; returns the result the command prints."""
    import jax

    config = OPTIONS.config(None, args)  # refused before any work
    builder = command_kit.builder_config(args)
    names = ["load", "objects", "two-level", "rebraid", "single", "check"] + (["rays"] if args.rays else []) \
        + (["save"] if args.output else [])  # a plain mesh skips objects, two-level and rebraid
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            mesh = load_mesh(args.scene)
        if len(mesh.instances) == 1:
            return _one_object(args, config, mesh, builder, stages)
        with stages("objects"):
            trees, t_objects = _timed(lambda: fm.build_objects(mesh, builder, world_space=not args.object_space))
        results = {}
        for name, threshold in (("two_level", math.inf), ("rebraid", config.threshold)):
            top = config.replace(threshold=threshold)
            with stages(name.replace("_", "-")):
                twolevel.run_from(mesh, trees, top)  # compile
                results[name] = twolevel.run_from(mesh, trees, top)
        lo, hi = mesh.local_boxes()
        with stages("single"):
            single, t_single = _timed(lambda: jaxbvh.build(lo, hi, builder))
        with stages("check"):
            single = jaxbvh.to_numpy(single)
            jaxbvh.validate(single, lo, hi)
            out = {}
            flats = {}
            for name, built in results.items():
                tl, timings = built.tree, built.stage_seconds
                flat = twolevel.flatten(tl)
                jaxbvh.validate(flat, lo, hi)
                flats[name] = flat
                nodes = twolevel.stored_nodes(tl)
                out[name] = {"sah": float(jaxbvh.sah(jaxbvh.to_jax(flat))),
                             "sah_object": twolevel.sah(tl, boxes="object"), "nodes": nodes["total"],
                             "top_nodes": nodes["top"], "flat_nodes": jaxbvh.tree.node_count(flat),
                             "brefs": int(tl.bref_count),
                             "seconds": t_objects + timings["pack"] + timings["top"],
                             "top_seconds": timings["top"]}
            out["single"] = {"sah": float(jaxbvh.sah(jaxbvh.to_jax(single))),
                             "nodes": jaxbvh.tree.node_count(single), "seconds": t_single}
        if args.rays:
            with stages("rays"):
                tri = mesh.local_triangles()
                origin, direction = rays.make_rays(jax.random.key(args.seed), "random", single, tri, args.rays)
                single_hits = traverse.closest_hit(single, tri, origin, direction)
                hits = {name: twolevel.closest_hit(built.tree, origin, direction) for name, built in results.items()}
                hits["single"] = single_hits
                for name, h in hits.items():
                    out[name]["box_tests"] = float(np.mean(h.box_tests))
                    out[name]["prim_tests"] = float(np.mean(h.prim_tests))
                    same = np.isclose(h.t, single_hits.t, rtol=1e-4) | (np.isinf(h.t) & np.isinf(single_hits.t))
                    out[name]["hits_agree"] = float(np.mean(same))
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, flats["rebraid"], frame=mesh.frame)

    result = {"command": "rebraid", **command_kit.mesh_info(mesh), "builder": builder.method,
              "threshold": config.threshold, "budget": config.budget, "path": "two-level",
              "slots": results["rebraid"].slots, "kept": results["rebraid"].kept,
              "two_level": out["two_level"], "rebraid": out["rebraid"], "single": out["single"],
              "rebraid_vs_two_level": out["rebraid"]["sah"] / out["two_level"]["sah"],
              "rebraid_vs_single": out["rebraid"]["sah"] / out["single"]["sah"],
              "top_time_ratio": (out["rebraid"]["top_seconds"] / out["two_level"]["top_seconds"]
                                 if out["two_level"]["top_seconds"] > 0 else None),
              "valid": True, "output": args.output}
    return _report(args, result)


def _report(args, result: dict) -> dict:
    if not args.json:
        print(table(result), file=sys.stdout)
        print(file=sys.stdout)
    return result


def _one_object(args, config, mesh, builder, stages) -> dict:
    """A plain mesh (one object, one identity instance): the two-level BVH *is* the object's
    BVH, which is the single BVH, so the command builds that once, as ``jaxbvh build`` does,
    and reports it in all three rows (no top level, no flattening, one validation)."""
    import jax

    lo, hi = mesh.local_boxes()
    with stages("single"):  # built once, as `jaxbvh build` does (seconds include compiling)
        start = time.perf_counter()
        single = jax.block_until_ready(jaxbvh.build(lo, hi, builder))
        seconds = time.perf_counter() - start
    with stages("check"):
        single = jaxbvh.to_numpy(single)
        jaxbvh.validate(single, lo, hi)
        nodes = jaxbvh.tree.node_count(single)
        row = {"sah": float(jaxbvh.sah(jaxbvh.to_jax(single))), "nodes": nodes, "seconds": seconds}
    if args.rays:
        with stages("rays"):
            tri = mesh.local_triangles()
            origin, direction = rays.make_rays(jax.random.key(args.seed), "random", single, tri, args.rays)
            hits = traverse.closest_hit(single, tri, origin, direction)
            row.update(box_tests=float(np.mean(hits.box_tests)), prim_tests=float(np.mean(hits.prim_tests)),
                       hits_agree=1.0)
    if args.output:
        with stages("save"):
            jaxbvh.save(args.output, single, frame=mesh.frame)
    # the two-level rows: one top-level leaf naming the object's root, costed as nothing
    leveled = dict(row, sah_object=row["sah"], nodes=nodes + 1, top_nodes=1, flat_nodes=nodes, brefs=1,
                   top_seconds=0.0)
    result = {"command": "rebraid", **command_kit.mesh_info(mesh), "builder": builder.method,
              "threshold": config.threshold, "budget": config.budget, "path": "single object", "slots": 1,
              "kept": "single object", "two_level": leveled, "rebraid": dict(leveled), "single": row,
              "rebraid_vs_two_level": 1.0, "rebraid_vs_single": 1.0, "top_time_ratio": None,
              "valid": True, "output": args.output}
    return _report(args, result)


def table(result: dict) -> str:
    """The paper's three-way table (Tables 1-2 in one) as aligned text."""
    base = result["two_level"]["sah"]
    has_rays = "box_tests" in result["single"]
    head = ["", "SAH", "vs two-level", "SAH obj", "nodes", "BRefs", "build s", "top s"] + \
        (["box tests/ray", "prim tests/ray"] if has_rays else [])
    rows = [head]
    for name in ("two_level", "rebraid", "single"):
        r = result[name]
        row = [name.replace("_", "-"), f"{r['sah']:.3f}", f"{r['sah'] / base:.3f}x",
               f"{r.get('sah_object', r['sah']):.3f}", f"{r['nodes']:,}",
               f"{r['brefs']:,}" if "brefs" in r else "-", f"{r['seconds']:.3f}",
               f"{r['top_seconds']:.4f}" if "top_seconds" in r else "-"]
        if has_rays:
            row += [f"{r['box_tests']:.1f}", f"{r['prim_tests']:.2f}"]
        rows.append(row)
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    return "\n".join("  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in
                               enumerate(zip(row, widths))) for row in rows)
