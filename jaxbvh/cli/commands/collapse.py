"""``jaxbvh collapse INPUT``: collapse a binary BVH into a wide one (Susano Pinto 2010).

INPUT is a binary tree ``.npz`` or a mesh/scene (built with the builder options first,
as ``optimize`` does). ``--method dp`` is the optimal collapse (least R_cost with at
most ``--max-children`` children per node, default 8), ``greedy`` the paper's top-down
pushup (no width limit unless ``--max-children``), ``qbvh`` the 4-wide baseline (every
node at odd depth removed). ``--simd-width W`` prices a node's ``k`` child box tests as
``ceil(k / W)`` (0, the default: ``k``). ``--max-leaf P`` is the builder's leaf size for
a mesh and, with ``--method dp``, also lets the DP merge subtrees of up to ``P``
primitives into one leaf (beyond the paper). The output is validated before it is
written.
"""

from __future__ import annotations

import inspect
import time

import numpy as np

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.io import Mesh
from jaxbvh.wide import collapse
from jaxbvh.wide.collapse import CollapseConfig

#: node_test_cost's own default (one box test per child), read from the library
SIMD_WIDTH = inspect.signature(collapse.node_test_cost).parameters["simd_width"].default

HELP = "collapse a binary BVH into a wide one: optimal DP, greedy pushup or QBVH (Susano Pinto 2010)"

#: CollapseConfig's --method and --max-children; its max_leaf and ci are the builder
#: options' --max-leaf and --ci, and test_cost comes from --simd-width
OPTIONS = config_options.ConfigOptions({"collapse": CollapseConfig}, exclude=("test_cost", "max_leaf", "ci"))


def add_parser(subparsers):
    """Add the ``collapse`` subparser (its options and help) to ``subparsers``; returns it."""
    description = __doc__.split("\n\n", 1)[1].strip().replace("``", "")
    parser = subparsers.add_parser("collapse", help=HELP, description=description)
    parser.add_argument("input", metavar="INPUT",
                        help="a binary tree .npz or a mesh/scene file (built first)")
    OPTIONS.add_to(parser)
    parser.add_argument("--simd-width", type=int, default=SIMD_WIDTH, metavar="W",
                        help=f"cost of testing k child boxes: ceil(k / W), or k for W = 0 (default: {SIMD_WIDTH})")
    parser.add_argument("-o", "--output", metavar="OUT.npz", default=None,
                        help="save the wide tree (interchange .npz with its frame)")
    command_kit.add_builder_args(parser)
    command_kit.add_json(parser)
    return parser


def _config(args, builder, kind: str) -> CollapseConfig:
    """The CollapseConfig of the options (the library's checks); ``--max-leaf`` is the
    builder's leaf size for a mesh, and merges leaves only with ``--method dp``."""
    try:
        test_cost = collapse.node_test_cost(args.simd_width)
    except ValueError as exc:
        raise ValueError(config_options.with_flags(str(exc), {"simd_width": "--simd-width"})) from None
    config = OPTIONS.config(None, args, test_cost=test_cost, ci=builder.ci)
    if config.method != "dp":
        # only an explicit --max-leaf asks for merging (its default shapes a mesh's build)
        if kind == "tree" and "max_leaf" in vars(args) and builder.max_leaf > 1:
            raise ValueError("--max-leaf with a tree input merges leaves, which needs --method dp")
        return config
    return config.replace(max_leaf=builder.max_leaf)


def run(args) -> dict:
    """Run ``jaxbvh collapse`` on parsed ``args``; returns the result the command prints."""
    import jax

    builder = command_kit.builder_config(args)  # the builder options too, before any work
    config = _config(args, builder, "tree" if str(args.input).lower().endswith(".npz") else "mesh")
    names = ["load", "build", "validate", "collapse", "check"] + (["save"] if args.output else [])
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            loaded = (command_kit.load_tree(args.input, binary=True)
                      if str(args.input).lower().endswith(".npz") else command_kit.load_input(args.input))
        if isinstance(loaded, Mesh):
            tree, prim_lo, prim_hi = command_kit.build_mesh_tree(loaded, builder, stages)
            frame = loaded.frame
            info = {"kind": "mesh", **command_kit.mesh_info(loaded), "builder": args.builder}
        else:
            tree, frame = loaded.tree, loaded.frame
            with stages("build"):
                pass
            with stages("validate"):
                command_kit.validate_any(tree)  # load_tree checked it; this is the same check, timed
            prim_lo = prim_hi = None
            info = {"kind": "tree", "input": loaded.path}
        tree = jaxbvh.to_numpy(tree)

        def once():
            return jax.block_until_ready(collapse.collapse(tree, config))

        with stages("collapse"):
            start = time.perf_counter()
            once()  # compiles (cached across runs by the CLI)
            first = time.perf_counter() - start
            start = time.perf_counter()
            result = once()
            seconds = time.perf_counter() - start
        wide = jaxbvh.to_numpy(result.tree)
        with stages("check"):
            command_kit.validate_any(wide, prim_lo, prim_hi, n_prims=jaxbvh.tree.prim_total(tree))
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, wide, frame=frame)

    widths = np.sum(np.asarray(wide.child) >= 0, axis=1)
    out = {"command": "collapse", **info, "method": config.method,
           "max_children": config.widest, "simd_width": args.simd_width,
           "max_leaf": builder.max_leaf,
           "rcost_before": float(result.rcost_before), "rcost": float(result.rcost),
           "rcost_change_percent": 100.0 * (float(result.rcost) / float(result.rcost_before) - 1.0)
           if float(result.rcost_before) else 0.0,
           "leaf_cost_before": float(result.leaf_cost_before), "leaf_cost": float(result.leaf_cost),
           "nodes_before": jaxbvh.tree.node_count(tree), "nodes": jaxbvh.tree.node_count(wide),
           "widest": int(widths.max()),
           "mean_children": float(widths[widths > 0].mean()) if (widths > 0).any() else 0.0,
           "seconds": seconds, "compile_seconds": max(first - seconds, 0.0),
           "valid": True, "output": args.output}
    if result.objective is not None:
        out["dp_objective"] = float(result.objective)
    return out
