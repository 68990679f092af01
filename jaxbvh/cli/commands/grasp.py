"""``jaxbvh grasp MESH``: best of many randomized full-sweep builds (Ng & Trifonov 2003, §3.4).

Every trial builds the full-sweep tree (one triangle per leaf) with random deviations
from the greedy split (``--noise`` per node, or ``--deviations`` per tree); the tree of
the lowest objective is kept, validated and optionally saved.
"""

from __future__ import annotations

import time

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.io import TREE_SUFFIXES
from jaxbvh.stochastic import grasp
from jaxbvh.stochastic.grasp import DEFAULT_DEVIATIONS, GraspConfig

HELP = "best of many randomized full-sweep builds (GRASP, Ng & Trifonov 2003)"

#: GraspConfig's knobs as options, but those of memory and precision (the library's)
OPTIONS = config_options.ConfigOptions({"grasp": GraspConfig}, exclude=("chunk_prims", "pad", "dtype"), helps={
    "deviations": "instead of --noise: expected deviations per tree, noise = D / (triangles - 1); "
                  f"with neither, {DEFAULT_DEVIATIONS:g} (jaxbvh.stochastic.grasp.DEFAULT_DEVIATIONS)"})


def add_parser(subparsers):
    """Add the ``grasp`` subparser (its options and help) to ``subparsers``; returns it."""
    # option values are checked in run() by GraspConfig, so a bad one is a one-line error like bad input
    parser = subparsers.add_parser("grasp", help=HELP, description=HELP + ".")
    command_kit.add_mesh_arg(parser, required=True)
    OPTIONS.add_to(parser)
    command_kit.add_seed(parser)
    parser.add_argument("-o", "--output", metavar="BEST.npz", default=None,
                        help="save the best tree (interchange .npz with its scene frame)")
    command_kit.add_json(parser)
    return parser


def run(args) -> dict:
    """Run ``jaxbvh grasp`` on parsed ``args``; returns the result the command prints."""
    import jax
    import numpy as np

    config = OPTIONS.config(None, args)  # the library's checks, one-line errors
    if config.trials > command_kit.MAX_RUNS:
        raise ValueError(f"--trials {config.trials:,} is more than this command runs: "
                         f"at most {command_kit.MAX_RUNS:,} (each builds a tree: hours of work already)")
    if str(args.mesh).lower().endswith(TREE_SUFFIXES):
        raise ValueError(f"{args.mesh} is a tree file; grasp builds from a mesh")
    names = ["load", "grasp", "validate"] + (["save"] if args.output else [])
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            mesh = command_kit.mesh_or_default(args.mesh)
            lo, hi = mesh.local_boxes()
        noise = grasp.resolve_noise(lo.shape[0], config.noise, config.deviations)
        bar = command_kit.progress(args, total=config.trials, desc="trials")

        def on_step(info):  # once per trial, after the forest call that finishes it
            bar.update(info.step + 1 - bar.n)
            bar.set_postfix(best=f"{info.sah:.4f}")

        with stages("grasp"):
            start = time.perf_counter()
            result = grasp.grasp(command_kit.seed_key(args.seed), lo, hi, config, on_step=on_step)
            tree = jax.block_until_ready(result.tree)
            seconds = time.perf_counter() - start
        bar.close()
        with stages("validate"):
            jaxbvh.validate(tree, lo, hi)
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, tree, frame=mesh.frame)

    objectives = result.objectives
    return {
        "command": "grasp", **command_kit.mesh_info(mesh),
        "objective": config.objective,
        "base": result.base,  # the greedy sweep tree
        "best": result.objective,
        "best_of_10": result.best_of(10) if config.trials >= 10 else None,
        "median": float(np.median(objectives)),
        "improvement_percent": 100.0 * (1.0 - result.objective / result.base) if result.base else 0.0,
        "better_trials": int(np.sum(objectives < result.base)),
        "best_trial": result.best_trial,
        "trials": config.trials,
        "noise": noise,
        "deviations": noise * max(lo.shape[0] - 1, 0),
        "rcl": result.rcl,
        "seed": args.seed,
        "sah": float(jaxbvh.sah(tree)),
        "ng_trifonov": float(jaxbvh.ng_trifonov_cost(tree)),
        "seconds": seconds,  # all trials and the greedy build, compile included
        "compile_seconds": result.compile_seconds,  # the part of it spent compiling
        "stop": result.stop,
        "valid": True,
        "output": args.output,
    }
