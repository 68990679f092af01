"""``jaxbvh optimize INPUT``: improve a BVH by tree rotations (Kensler 2008).

INPUT is a mesh or scene (built with the default builder first) or a tree ``.npz``
(its leaf boxes stand for the primitives, so no mesh is needed). ``--method hc`` is hill
climbing to convergence, ``--method sa`` simulated annealing with Kensler's schedule.
"""

from __future__ import annotations

import time

import jaxbvh
from jaxbvh.commands import _common
from jaxbvh.io import Mesh
from jaxbvh.schedule import DEFAULT_HOTTEST

HELP = "optimize a BVH by tree rotations: hill climbing or simulated annealing (Kensler 2008)"


def add_parser(subparsers):
    parser = subparsers.add_parser("optimize", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="INPUT",
                        help="a mesh/scene file (built with the default builder first) or a "
                             "tree .npz")
    parser.add_argument("--method", choices=("hc", "sa"), default="hc",
                        help="hc: hill climbing to convergence; sa: simulated annealing "
                             "(default: hc)")
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
                        help="most hill-climbing passes, or quench passes after annealing "
                             "(default: 1000)")
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

    from jaxbvh import rotate

    if not args.hottest >= 0:
        raise ValueError(f"--hottest must be >= 0, got {args.hottest}")
    if args.time_budget is not None and not args.time_budget > 0:
        raise ValueError(f"--time-budget must be > 0 seconds, got {args.time_budget}")
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

        total = args.max_passes if args.method == "hc" else args.iterations
        bar = _common.progress(args, total=total, desc=f"{args.method} passes")

        def on_pass(i, sah, moves, temperature):
            bar.update(1)
            bar.set_postfix(sah=f"{float(sah):.4f}", moves=int(moves), T=f"{float(temperature):.3f}")

        with stages("optimize"):
            start = time.perf_counter()
            if args.method == "hc":
                result = rotate.hill_climb(tree, ct=args.ct, ci=args.ci, max_passes=args.max_passes,
                                           on_pass=on_pass, time_budget=args.time_budget)
            else:
                result = rotate.anneal(jax.random.key(args.seed), tree, steps=args.iterations,
                                       hottest=args.hottest, period=args.period,
                                       chains=args.chains, max_quench=args.max_passes,
                                       ct=args.ct, ci=args.ci,
                                       on_pass=on_pass, time_budget=args.time_budget)
            result = jax.block_until_ready(result)
            seconds = time.perf_counter() - start
        bar.close()
        optimized = jaxbvh.to_numpy(result.tree)
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
           "passes": int(result.passes), "moves": int(result.moves),
           "seconds": seconds,  # includes compiling (cached across runs by the CLI)
           "before": before, "after": after,
           "sah_change_percent": 100.0 * (after["sah"] / before["sah"] - 1.0) if before["sah"] else 0.0,
           "valid": True, "output": args.output, "time_budget": args.time_budget}
    if args.method == "sa":
        out.update({"iterations": args.iterations, "period": args.period, "hottest": args.hottest,
                    "chains": args.chains, "seed": args.seed})
        if result.chain_sah is not None:
            out["chain_sah"] = [float(x) for x in result.chain_sah]
    return out
