"""``jaxbvh optimize INPUT``: improve a BVH's topology (:mod:`jaxbvh.optimize`).

INPUT is a mesh or scene (built with the default builder first) or a tree ``.npz``
(its leaf boxes stand for the primitives, so no mesh is needed). ``--method`` names an
optimizer of :data:`jaxbvh.optimize.OPTIMIZERS`: ``hc`` hill climbing of Kensler's
rotations to convergence, ``sa`` simulated annealing (``--schedule``), ``reinsert``
parallel reinsertion (Meister & Bittner 2018), ``treelet`` treelet restructuring
(Karras & Aila 2013), ``pipeline`` (the default) rounds of treelets and reinsertion.

The method's options are the knobs of its ``Config`` (:mod:`jaxbvh.cli.options`): the
command types no default of its own, and ``--help`` lists each method's. A few keep
their established spellings (:data:`FLAGS`). An option of another method is a usage
error naming both (``--hottest`` belongs to ``--method sa``), but for hill climbing and
annealing, which share theirs (:data:`FAMILIES`); the Configs check every value given,
naming the option, before anything is loaded.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.io import Mesh
from jaxbvh.optimize import DEFAULT_METHOD, OPTIMIZERS, optimize, pipeline

HELP = ("optimize a BVH: rotations (hill climbing, annealing), parallel reinsertion, treelet "
        "restructuring, or the pipeline of treelets and reinsertion")

#: config fields the command line spells its own way (every other flag is its field's name)
FLAGS = {
    "leaves": "--treelet-leaves",       # treelet size, also the pipeline's
}
#: spellings the command had before each flag was its field's name (docs/optimizers.md,
#: Words): still accepted, with a DeprecationWarning
RENAMED = {
    "--iterations": {"*": "--steps"},   # annealing's passes that follow the schedule
    "--max-passes": {"sa": "--max-quench", "reinsert": "--max-iterations", "pipeline": "--max-iterations"},
}
#: config fields the command line does not offer: the SAH constants and the leaf limit come
#: with the builder options (--ct, --ci, --max-leaf: they cost and shape the tree too); work sizes never change a result; the
#: pipeline sets its stages' passes, costs and split axes itself
EXCLUDE = ("ct", "ci", "max_leaf", "windows", "frontier", "treelet.max_passes", "treelet.split_axes",
           "reinsert.split_axes")

def leaf_limit(method: str, builder) -> dict:
    """``{"max_leaf": builder.max_leaf}`` for an optimizer whose Config has the knob (the
    pipeline's final leaf merge): ``--max-leaf`` shapes the leaves of both steps."""
    fields = {f.name for f in dataclasses.fields(OPTIMIZERS[method].Config)}
    return {"max_leaf": builder.max_leaf} if "max_leaf" in fields else {}


#: methods whose options serve each other: Kensler's hill climbing is his annealing
#: without the heat, so annealing's options (--steps, --chains, ...) are accepted,
#: and checked, with --method hc; any other method's option is an error
FAMILIES = {"hc": "rotations", "sa": "rotations"}

#: every optimizer's options, from the configs (annealing's --schedule offers the
#: schedules by name, the knob's choices; a function is the library's alone)
OPTIONS = config_options.ConfigOptions({name: o.Config for name, o in OPTIMIZERS.items()},
                                       exclude=EXCLUDE, flags=FLAGS, method_flag="--method",
                                       families=FAMILIES, renamed=RENAMED)


#: memory of one annealing chain per node of the tree (the current, best and proposed
#: trees' arrays, ~50 bytes a node each, with their costs and areas)
BYTES_PER_NODE_PER_CHAIN = 400


def add_parser(subparsers):
    """Add the ``optimize`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("optimize", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="INPUT",
                        help="a mesh/scene file (built with the default builder first) or a "
                             "tree .npz")
    parser.add_argument("--method", choices=tuple(OPTIMIZERS), default=DEFAULT_METHOD,
                        help="; ".join(f"{name}: {o.paper}" for name, o in OPTIMIZERS.items())
                             + f" (default: {DEFAULT_METHOD})")
    command_kit.add_seed(parser, "random seed for annealing")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="seconds of search: compiling (cached after the first run) comes first "
                             "and is reported apart as compile_seconds; the search then stops at the end "
                             "of the chunk of passes that crosses the budget, with the best tree so far, "
                             "after at least one pass (default: run to convergence)")
    parser.add_argument("-o", "--output", metavar="OUT.npz", default=None,
                        help="save the optimized tree (interchange .npz with its frame)")
    OPTIONS.add_to(parser, "method options (fields of each method's Config; defaults per method)")
    command_kit.add_builder_args(parser)
    command_kit.add_target(parser)
    command_kit.add_json(parser)
    return parser


def make_config(args, builder=None):
    """The Config of ``args.method`` from the options given (the Config's defaults for the
    rest), with the SAH constants of ``builder`` (None: of the builder options in ``args``)."""
    builder = command_kit.builder_config(args) if builder is None else builder
    return OPTIONS.config(args.method, args, ct=builder.ct, ci=builder.ci, **leaf_limit(args.method, builder))


def _load(args, builder, stages):
    """``(tree, prim_lo, prim_hi, frame, info)`` of the input (a mesh is built first)."""
    with stages("load"):
        loaded = command_kit.load_input(args.input)
    if isinstance(loaded, Mesh):
        tree, prim_lo, prim_hi = command_kit.build_mesh_tree(loaded, builder, stages)
        return tree, prim_lo, prim_hi, loaded.frame, {"kind": "mesh", **command_kit.mesh_info(loaded),
                                                      "builder": args.builder}
    with stages("build"):
        pass
    with stages("validate"):
        command_kit.validate_any(loaded.tree)
    return loaded.tree, None, None, loaded.frame, {"kind": "tree", "input": loaded.path}


def _check(tree, optimized, prim_lo, prim_hi) -> None:
    command_kit.validate_any(optimized, prim_lo, prim_hi)
    if prim_lo is None:
        # the leaves (whose boxes stand for the primitives) must be untouched
        leaf = np.asarray(tree.prim_count) > 0
        if not (np.array_equal(optimized.lo[leaf], np.asarray(tree.lo)[leaf])
                and np.array_equal(optimized.hi[leaf], np.asarray(tree.hi)[leaf])):
            raise ValueError("optimized tree changed leaf boxes")


def run(args) -> dict:
    """Run ``jaxbvh optimize`` on parsed ``args``; returns the result the command prints."""
    if args.time_budget is not None and not args.time_budget > 0:
        raise ValueError(f"--time-budget must be > 0 seconds, got {args.time_budget}")
    builder = command_kit.builder_config(args)
    config = make_config(args, builder)
    names = ["load", "build", "validate", "optimize", "check"] + (["save"] if args.output else [])
    with command_kit.Stages(args, names) as stages:
        tree, prim_lo, prim_hi, frame, info = _load(args, builder, stages)
        chains = getattr(config, "chains", 1)
        if chains > 1:  # every chain holds its own trees (current, best, proposals)
            nodes = int(np.asarray(tree.prim_count).shape[0])
            command_kit.check_fits("--chains", chains, nodes * BYTES_PER_NODE_PER_CHAIN,
                                   f"{nodes:,}-node trees per chain")
        before = jaxbvh.all_costs(tree, config.ct, config.ci)
        before.update(command_kit.target_report(tree, args, builder))
        totals = {"hc": getattr(config, "max_passes", None), "sa": getattr(config, "steps", None)}
        bar = command_kit.progress(args, total=totals.get(args.method), desc=f"{args.method}")

        def on_step(info):
            bar.update(1)
            bar.set_postfix(stage=info.stage, sah=f"{info.sah:.4f}", moves=info.moves)

        with stages("optimize"):
            start = time.perf_counter()
            result = optimize(tree, args.method, key=command_kit.seed_key(args.seed), config=config,
                              time_budget=args.time_budget, on_step=on_step)
            seconds = time.perf_counter() - start
        bar.close()
        with stages("check"):
            _check(tree, result.tree, prim_lo, prim_hi)
        after = jaxbvh.all_costs(result.tree, config.ct, config.ci)
        after.update(command_kit.target_report(result.tree, args, builder))
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, result.tree, frame=frame)

    out = {"command": "optimize", **info, "method": args.method,
           "passes": int(result.steps), "moves": int(result.moves),
           "seconds": seconds,  # includes compiling (cached across runs)
           "compile_seconds": result.compile_seconds,
           "before": before, "after": after,
           "sah_change_percent": 100.0 * (after["sah"] / before["sah"] - 1.0) if before["sah"] else 0.0,
           "valid": True, "output": args.output, "time_budget": args.time_budget}
    out.update(_settings(args, config, result))
    return out


def _settings(args, config, result) -> dict:
    """The method's own keys of the output (its settings, the pipeline's stages)."""
    out = {}
    if args.method == "sa":
        out.update({"iterations": config.steps, "period": config.period, "hottest": config.hottest,
                    "chains": config.chains, "seed": args.seed,
                    "schedule": config.schedule if isinstance(config.schedule, str) else "custom"})
        if result.chain_sah is not None:
            out["chain_sah"] = [float(x) for x in result.chain_sah]
    stage_configs = {"reinsert": config, "treelet": config}
    if args.method == "pipeline":
        stage_configs = {"reinsert": config.reinsert, "treelet": config.treelet}
    if args.method in ("reinsert", "pipeline"):
        reinsertion = stage_configs["reinsert"]
        out.update({"first_fraction": reinsertion.first_fraction, "max_steps": reinsertion.max_steps})
    if args.method in ("treelet", "pipeline"):
        out["treelet_leaves"] = stage_configs["treelet"].leaves
    if args.method == "pipeline":
        out["stages"] = stages_run(result)
    return out


def stages_run(result) -> list[dict]:
    """Consecutive steps of one stage grouped: ``[{"stage", "steps", "sah"}, ...]`` (SAH after)."""
    grouped = []
    for j in range(int(result.steps)):
        stage = pipeline.STAGES[int(result.history_stage[j])]
        sah = float(result.history[j])
        if not grouped or grouped[-1]["stage"] != stage:
            grouped.append({"stage": stage, "steps": 0, "sah": sah})
        grouped[-1]["steps"] += 1
        grouped[-1]["sah"] = sah
    return grouped
