"""``jaxbvh evolve MESH``: a genetic algorithm over Goldsmith–Salmon insertion orders
(Ng & Trifonov 2003, §4).

Each individual is an insertion order; its fitness is the Goldsmith–Salmon cost of the
tree the insertion build makes from it (one primitive per leaf, nodes of up to
``--max-children`` children). The best tree found is validated and optionally saved
(a wide tree: interchange ``.npz`` with ``child`` [nodes, K]).
"""

from __future__ import annotations

import jaxbvh
from jaxbvh.builders import insertion
from jaxbvh.cli.commands import _common
from jaxbvh.io import TREE_SUFFIXES
from jaxbvh.stochastic import evolve

HELP = "genetic algorithm over Goldsmith-Salmon insertion orders (Ng & Trifonov 2003)"


def add_parser(subparsers):
    # option values are checked in run(), so a bad one is a one-line error like bad input
    parser = subparsers.add_parser(
        "evolve", help=HELP, description=HELP + ".",
        usage="%(prog)s MESH [--population 50] [--generations 100] [--crossover 0.7] "
              "[--mutation F] [--seed S] [-o BEST.npz] [--json]")
    _common.add_mesh_arg(parser, required=True)
    parser.add_argument("--population", type=int, default=evolve.DEFAULT_POPULATION, metavar="P",
                        help=f"insertion orders per generation, >= 2 (default: {evolve.DEFAULT_POPULATION})")
    parser.add_argument("--generations", type=int, default=evolve.DEFAULT_GENERATIONS, metavar="G",
                        help=f"generations after the random first one, >= 0 (default: {evolve.DEFAULT_GENERATIONS})")
    parser.add_argument("--crossover", type=float, default=evolve.DEFAULT_CROSSOVER, metavar="R",
                        help=f"probability that a pair of parents crosses, in [0, 1] "
                             f"(default: {evolve.DEFAULT_CROSSOVER})")
    parser.add_argument("--mutation", type=float, default=evolve.DEFAULT_MUTATION, metavar="F",
                        help="expected swaps per individual and generation as a fraction of the "
                             f"triangles, in [0, 1] (default: 1/500 = {evolve.DEFAULT_MUTATION})")
    parser.add_argument("--max-children", type=int, default=insertion.DEFAULT_MAX_CHILDREN, metavar="K",
                        help="most children of a node, >= 2 (default: "
                             f"{insertion.DEFAULT_MAX_CHILDREN}; see jaxbvh.insertion)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default: 0)")
    parser.add_argument("-o", "--output", metavar="BEST.npz", default=None,
                        help="save the best tree (interchange .npz with its scene frame)")
    _common.add_json(parser)
    return parser


def run(args) -> dict:
    import jax

    if args.population < 2:
        raise ValueError(f"--population must be >= 2, got {args.population}")
    if args.generations < 0:
        raise ValueError(f"--generations must be >= 0, got {args.generations}")
    if not 0.0 <= args.crossover <= 1.0:
        raise ValueError(f"--crossover must be in [0, 1], got {args.crossover}")
    if not 0.0 <= args.mutation <= 1.0:
        raise ValueError(f"--mutation must be in [0, 1] (expected swaps / triangles), got {args.mutation}")
    if args.max_children < 2:
        raise ValueError(f"--max-children must be >= 2, got {args.max_children}")
    if str(args.mesh).lower().endswith(TREE_SUFFIXES):
        raise ValueError(f"{args.mesh} is a tree file; evolve builds from a mesh")
    names = ["load", "evolve", "validate"] + (["save"] if args.output else [])
    with _common.Stages(args, names) as stages:
        with stages("load"):
            mesh = _common.mesh_or_default(args.mesh)
            lo, hi = mesh.local_boxes()
        bar = _common.progress(args, total=args.generations + 1, desc="generations")

        def on_generation(g, best):
            bar.update(1)
            bar.set_postfix(best=f"{best:.4f}")

        with stages("evolve"):
            result = evolve.evolve(jax.random.key(args.seed), lo, hi, population=args.population,
                                   generations=args.generations, crossover=args.crossover,
                                   mutation=args.mutation, max_children=args.max_children,
                                   on_generation=on_generation)
        bar.close()
        tree = jaxbvh.to_numpy(result.tree)
        with stages("validate"):
            jaxbvh.validate(tree, lo, hi)
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, tree, frame=mesh.frame)
    out = {"command": "evolve", **_common.mesh_info(mesh),
           "population": args.population, "generations": args.generations,
           "crossover": args.crossover, "mutation": args.mutation,
           "expected_swaps": args.mutation * mesh.n_triangles, "max_children": args.max_children,
           "seed": args.seed,
           "initial_best": result.initial_best, "best": result.best, "random_median": result.random_median,
           "best_vs_median_percent": 100.0 * (result.best / result.random_median - 1.0)
           if result.random_median else 0.0,
           "history": [float(x) for x in result.history],
           "seconds": result.seconds,  # includes compiling (cached across runs by the CLI)
           "tree": _common.tree_stats(tree), "valid": True, "output": args.output}
    return out
