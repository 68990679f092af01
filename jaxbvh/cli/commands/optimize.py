"""``jaxbvh optimize INPUT``: improve a BVH's topology (:mod:`jaxbvh.optimize.pipeline`).

INPUT is a mesh or scene (built with the default builder first) or a tree ``.npz``
(its leaf boxes stand for the primitives, so no mesh is needed). ``--method hc`` is hill
climbing of Kensler's rotations to convergence, ``--method sa`` simulated annealing with
Kensler's schedule, ``--method reinsert`` parallel reinsertion (Meister & Bittner 2018),
``--method treelet`` treelet restructuring (Karras & Aila 2013), ``--method pipeline``
(the default) rounds of treelets and reinsertion (:mod:`jaxbvh.optimize.pipeline`).
"""

from __future__ import annotations

import time

import jaxbvh
from jaxbvh.cli.commands import _common
from jaxbvh.io import Mesh
from jaxbvh.optimize.pipeline import METHODS, optimize
from jaxbvh.optimize.reinsert import DEFAULT_FIRST_FRACTION, DEFAULT_MAX_STEPS
from jaxbvh.optimize.schedules import DEFAULT_HOTTEST
from jaxbvh.optimize.treelet import DEFAULT_LEAVES, MAX_LEAVES

DEFAULT_METHOD = "pipeline"

HELP = ("optimize a BVH: rotations (hill climbing, annealing), parallel reinsertion, treelet "
        "restructuring, or the pipeline of treelets and reinsertion")


def add_parser(subparsers):
    parser = subparsers.add_parser("optimize", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="INPUT",
                        help="a mesh/scene file (built with the default builder first) or a "
                             "tree .npz")
    parser.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD,
                        help="hc: rotations, hill climbing to convergence; sa: rotations, "
                             "simulated annealing; reinsert: parallel reinsertion; treelet: "
                             "treelet restructuring; pipeline: rounds of treelets then "
                             f"reinsertion (default: {DEFAULT_METHOD})")
    parser.add_argument("--iterations", type=_common._int_at_least(1), default=1250, metavar="N",
                        help="annealing passes N of the schedule (Kensler: 1250; default 1250)")
    parser.add_argument("--period", type=_common._int_at_least(1), default=50, metavar="F",
                        help="period of the temperature sine in passes (default: 50)")
    parser.add_argument("--hottest", type=float, default=DEFAULT_HOTTEST, metavar="H",
                        help="peak temperature h, in units of the node cost C(n) "
                             f"(default: {DEFAULT_HOTTEST}; the paper's 0.8-2.2 are far "
                             "too hot on this cost, see jaxbvh.schedule.DEFAULT_HOTTEST)")
    parser.add_argument("--chains", type=_common._int_at_least(1), default=1, metavar="K",
                        help="independent annealing chains, the best is kept (default: 1)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="random seed for annealing (default: 0)")
    parser.add_argument("--max-passes", type=_common._int_at_least(1), default=1000, metavar="P",
                        help="most passes (hc, treelet) or iterations (reinsert), or quench "
                             "passes after annealing (default: 1000)")
    parser.add_argument("--first-fraction", type=float, default=DEFAULT_FIRST_FRACTION,
                        metavar="F",
                        help="reinsert: about the share of nodes (largest parent area first) "
                             "searched at first, growing to all (default: 1/32)")
    parser.add_argument("--max-steps", type=_common._int_at_least(1), default=DEFAULT_MAX_STEPS,
                        metavar="S",
                        help="reinsert: search steps per node and iteration (default: "
                             f"{DEFAULT_MAX_STEPS})")
    parser.add_argument("--treelet-leaves", type=_common._int_at_least(2), default=DEFAULT_LEAVES,
                        metavar="N",
                        help=f"treelet: leaves per treelet, 2 .. {MAX_LEAVES} (default: "
                             f"{DEFAULT_LEAVES}, as Karras & Aila)")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="stop after about this many seconds (compiling apart) with the best "
                             "tree so far (default: run to convergence)")
    parser.add_argument("-o", "--output", metavar="OUT.npz", default=None,
                        help="save the optimized tree (interchange .npz with its frame)")
    _common.add_builder_args(parser)
    _common.add_json(parser)
    return parser


def run(args) -> dict:
    import jax

    if not args.hottest >= 0:
        raise ValueError(f"--hottest must be >= 0, got {args.hottest}")
    if args.time_budget is not None and not args.time_budget > 0:
        raise ValueError(f"--time-budget must be > 0 seconds, got {args.time_budget}")
    if not 0 < args.first_fraction <= 1:
        raise ValueError(f"--first-fraction must be in (0, 1], got {args.first_fraction}")
    if args.treelet_leaves > MAX_LEAVES:
        raise ValueError(f"--treelet-leaves must be at most {MAX_LEAVES}, got {args.treelet_leaves}")
    names = ["load", "build", "validate", "optimize", "check"] + (["save"] if args.output else [])
    with _common.Stages(args, names) as stages:
        with stages("load"):
            loaded = _common.load_input(args.input)
        if isinstance(loaded, Mesh):
            tree, prim_lo, prim_hi = _common.build_mesh_tree(loaded, args, stages)
            frame = loaded.frame
            info = {"kind": "mesh", **_common.mesh_info(loaded), "builder": args.builder}
        else:
            tree, frame = loaded.tree, loaded.frame
            with stages("build"):
                pass
            with stages("validate"):
                jaxbvh.validate(tree)
            prim_lo = prim_hi = None
            info = {"kind": "tree", "input": loaded.path}
        before = jaxbvh.all_costs(tree, args.ct, args.ci)

        totals = {"hc": args.max_passes, "sa": args.iterations}
        bar = _common.progress(args, total=totals.get(args.method), desc=f"{args.method}")

        def on_step(stage, step, sah, moves):
            bar.update(1)
            bar.set_postfix(stage=stage, sah=f"{float(sah):.4f}", moves=int(moves))

        reinsert_options = dict(max_iterations=args.max_passes, max_steps=args.max_steps,
                                first_fraction=args.first_fraction)
        treelet_options = dict(leaves=args.treelet_leaves)
        options = {
            "hc": dict(max_passes=args.max_passes),
            "sa": dict(steps=args.iterations, hottest=args.hottest, period=args.period,
                       chains=args.chains, max_quench=args.max_passes),
            "reinsert": reinsert_options,
            "treelet": dict(treelet_options, max_passes=args.max_passes),
            "pipeline": dict(reinsert=reinsert_options, treelet=treelet_options),
        }[args.method]
        with stages("optimize"):
            start = time.perf_counter()
            result = optimize(tree, args.method, key=jax.random.key(args.seed), ct=args.ct,
                              ci=args.ci, time_budget=args.time_budget, on_step=on_step, **options)
            seconds = time.perf_counter() - start
        bar.close()
        optimized = result.tree
        with stages("check"):
            jaxbvh.validate(optimized, prim_lo, prim_hi)
            if prim_lo is None:
                # the leaves (whose boxes stand for the primitives) must be untouched
                import numpy as np

                leaf = np.asarray(tree.prim_count) > 0
                if not (np.array_equal(optimized.lo[leaf], np.asarray(tree.lo)[leaf])
                        and np.array_equal(optimized.hi[leaf], np.asarray(tree.hi)[leaf])):
                    raise ValueError("optimized tree changed leaf boxes")
        after = jaxbvh.all_costs(optimized, args.ct, args.ci)
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, optimized, frame=frame)

    out = {"command": "optimize", **info, "method": args.method,
           "passes": result.steps, "moves": result.moves,
           "seconds": seconds,  # includes compiling (cached across runs by the CLI)
           "before": before, "after": after,
           "sah_change_percent": 100.0 * (after["sah"] / before["sah"] - 1.0) if before["sah"] else 0.0,
           "valid": True, "output": args.output, "time_budget": args.time_budget}
    if args.method == "sa":
        out.update({"iterations": args.iterations, "period": args.period, "hottest": args.hottest,
                    "chains": args.chains, "seed": args.seed})
        if result.chain_sah is not None:
            out["chain_sah"] = [float(x) for x in result.chain_sah]
    if args.method in ("reinsert", "pipeline"):
        out.update({"first_fraction": args.first_fraction, "max_steps": args.max_steps})
    if args.method in ("treelet", "pipeline"):
        out["treelet_leaves"] = args.treelet_leaves
    if args.method == "pipeline":
        stages_run = []  # consecutive steps of one stage grouped: stage, steps, SAH after
        for stage, _, sah, _ in result.trace:
            if not stages_run or stages_run[-1]["stage"] != stage:
                stages_run.append({"stage": stage, "steps": 0, "sah": sah})
            stages_run[-1]["steps"] += 1
            stages_run[-1]["sah"] = sah
        out["stages"] = stages_run
    return out
