"""``jaxbvh evolve MESH``: a genetic algorithm over Goldsmith–Salmon insertion orders
(Ng & Trifonov 2003, §4).

Each individual is an insertion order; its fitness is the Goldsmith–Salmon cost of the
tree the insertion build makes from it (one primitive per leaf, nodes of up to
``--max-children`` children). The best tree found is validated and optionally saved
(a wide tree: interchange ``.npz`` with ``child`` [nodes, K]).
"""

from __future__ import annotations

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.io import TREE_SUFFIXES
from jaxbvh.stochastic import evolve
from jaxbvh.stochastic.evolve import EvolveConfig

HELP = "genetic algorithm over Goldsmith-Salmon insertion orders (Ng & Trifonov 2003)"

#: EvolveConfig's knobs as options, but the precision (the library's)
OPTIONS = config_options.ConfigOptions({"evolve": EvolveConfig}, exclude=("dtype",))


#: memory of one member of a generation per triangle: its insertion order, its tree
#: (two nodes a triangle, ~50 bytes a node) and the offspring's copies
BYTES_PER_TRIANGLE_PER_MEMBER = 256


def add_parser(subparsers):
    """Add the ``evolve`` subparser (its options and help) to ``subparsers``; returns it."""
    # option values are checked in run() by EvolveConfig, so a bad one is a one-line error like bad input
    parser = subparsers.add_parser("evolve", help=HELP, description=HELP + ".")
    command_kit.add_mesh_arg(parser, required=True)
    OPTIONS.add_to(parser)
    command_kit.add_seed(parser)
    parser.add_argument("-o", "--output", metavar="BEST.npz", default=None,
                        help="save the best tree (interchange .npz with its scene frame)")
    command_kit.add_json(parser)
    return parser


def run(args) -> dict:
    """Run ``jaxbvh evolve`` on parsed ``args``; returns the result the command prints."""
    config = OPTIONS.config(None, args)  # the library's checks, one-line errors
    if config.generations > command_kit.MAX_RUNS:
        raise ValueError(f"--generations {config.generations:,} is more than this command runs: "
                         f"at most {command_kit.MAX_RUNS:,} (each builds a tree: hours of work already)")
    if str(args.mesh).lower().endswith(TREE_SUFFIXES):
        raise ValueError(f"{args.mesh} is a tree file; evolve builds from a mesh")
    names = ["load", "evolve", "validate"] + (["save"] if args.output else [])
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            mesh = command_kit.mesh_or_default(args.mesh)
            lo, hi = mesh.local_boxes()
        # every member of a generation is an insertion order and the tree built from it
        command_kit.check_fits("--population", config.population, mesh.n_triangles * BYTES_PER_TRIANGLE_PER_MEMBER,
                               f"an insertion order and a tree of {mesh.n_triangles:,} triangles per member")
        bar = command_kit.progress(args, total=config.generations + 1, desc="generations")

        def on_step(info):  # once per generation
            bar.update(1)
            bar.set_postfix(best=f"{info.sah:.4f}")

        with stages("evolve"):
            result = evolve.evolve(command_kit.seed_key(args.seed), lo, hi, config, on_step=on_step)
        bar.close()
        tree = jaxbvh.to_numpy(result.tree)
        with stages("validate"):
            jaxbvh.validate(tree, lo, hi)
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, tree, frame=mesh.frame)
    out = {"command": "evolve", **command_kit.mesh_info(mesh),
           "population": config.population, "generations": config.generations,
           "crossover": config.crossover, "mutation": config.mutation,
           "expected_swaps": config.mutation * mesh.n_triangles, "max_children": config.max_children,
           "seed": args.seed,
           "initial_best": result.initial_best, "best": result.best, "random_median": result.random_median,
           "best_vs_median_percent": 100.0 * (result.best / result.random_median - 1.0)
           if result.random_median else 0.0,
           "history": [float(x) for x in result.history],
           "seconds": result.seconds,  # includes compiling (cached across runs by the CLI)
           "compile_seconds": result.compile_seconds,  # the part of it spent compiling
           "stop": result.stop,
           "tree": command_kit.tree_stats(tree), "valid": True, "output": args.output}
    return out
