"""``jaxbvh build [MESH]``: build a BVH over a mesh, validate it, report it, save it."""

from __future__ import annotations

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.io import TREE_SUFFIXES

HELP = "build a BVH over a mesh (default: the bundled mesh) and report its costs"


def add_parser(subparsers):
    """Add the ``build`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("build", help=HELP, description=HELP + ".")
    command_kit.add_mesh_arg(parser)
    command_kit.add_builder_args(parser)
    command_kit.add_target(parser)
    parser.add_argument("-o", "--output", metavar="TREE.npz", default=None,
                        help="save the tree (interchange .npz with its scene frame)")
    command_kit.add_json(parser)
    return parser


def run(args) -> dict:
    """Run ``jaxbvh build`` on parsed ``args``; returns the result the command prints."""
    if args.mesh is not None and str(args.mesh).lower().endswith(TREE_SUFFIXES):
        raise ValueError(f"{args.mesh} is a tree file; build takes a mesh "
                         "(use 'jaxbvh stats' for trees)")
    builder = command_kit.builder_config(args)  # every builder option checked before any work
    names = ["load", "build", "validate"] + (["save"] if args.output else [])
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            mesh = command_kit.mesh_or_default(args.mesh)
        tree, _, _ = command_kit.build_mesh_tree(mesh, builder, stages)
        if args.output:
            with stages("save"):
                jaxbvh.save(args.output, tree, frame=mesh.frame)
    result = {"command": "build", **command_kit.mesh_info(mesh),
              "builder": builder.method, "max_leaf": builder.max_leaf}
    if builder.method == "binned":
        result["bins"] = builder.bins
    result.update(command_kit.tree_stats(tree, builder))
    result.update(command_kit.target_report(tree, args, builder))
    result.update({
        "valid": True,
        "frame_origin": [float(x) for x in mesh.frame.origin],
        "frame_scale": float(mesh.frame.scale),
        "seconds": stages.seconds["build"],  # compile + build
        "load_seconds": stages.seconds["load"],
        "validate_seconds": stages.seconds["validate"],
        "output": args.output,
    })
    return result
