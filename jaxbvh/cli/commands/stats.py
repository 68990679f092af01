"""``jaxbvh stats MESH_OR_TREE``: costs and shape of a saved tree, or of a fresh build."""

from __future__ import annotations

import jaxbvh
from jaxbvh.cli import command_kit
from jaxbvh.io import Mesh

HELP = ("report nodes, depth, leaf sizes and costs of a tree (.npz) or of a mesh's BVH; "
        "exit status 1 if the tree is invalid")


def add_parser(subparsers):
    """Add the ``stats`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("stats", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="MESH_OR_TREE",
                        help="a tree .npz (jaxbvh build -o, or another library's export) "
                             "or a mesh file, built with the default builder")
    parser.add_argument("--mesh", metavar="MESH", default=None,
                        help="for a tree: also validate it against this mesh's triangle boxes")
    command_kit.add_builder_args(parser)
    command_kit.add_json(parser)
    return parser


def run(args) -> dict:
    """Run ``jaxbvh stats`` on parsed ``args``; returns the result the command prints."""
    builder = command_kit.builder_config(args)  # every builder option checked before any work
    names = ["load", "build", "validate"]
    with command_kit.Stages(args, names) as stages:
        with stages("load"):
            loaded = command_kit.load_input(args.input, check=False)  # problems are reported below
        if isinstance(loaded, Mesh):
            if args.mesh is not None:
                raise ValueError(f"--mesh applies to a tree file; {args.input} is a mesh")
            tree, _, _ = command_kit.build_mesh_tree(loaded, builder, stages)
            result = {"command": "stats", "kind": "mesh", **command_kit.mesh_info(loaded),
                      "builder": builder.method, "max_leaf": builder.max_leaf}
            result.update(command_kit.tree_stats(tree, builder))
            result.update({"valid": True, "validated_against": "mesh",
                           "seconds": stages.seconds["build"]})
            return result
        return _tree_stats(loaded, args, builder, stages)


def _tree_stats(loaded, args, costs, stages) -> dict:
    """Report of a tree file. A broken structure (cycle, shared child, bad ids, NaN or
    inverted boxes) is reported without costs: they would mean nothing. ``valid`` is
    False (exit status 1) when any check fails. ``costs``: the SAH constants (the builder
    options' ``--ct``, ``--ci``)."""
    tree, frame = loaded.tree, loaded.frame
    result = {"command": "stats", "kind": "tree", "input": loaded.path}
    with stages("validate"):
        problems = jaxbvh.check(tree)
        against = "structure only (pass --mesh to check boxes)"
        if not problems and args.mesh is not None:
            mesh = command_kit.mesh_or_default(args.mesh)
            # in the precision the boxes are stored in (command_kit.check_against_mesh)
            checked = command_kit.check_against_mesh(loaded, mesh)
            problems = checked.problems
            result["checked_in"] = checked.precision
            result.update({"mesh": str(mesh.path), "triangles": mesh.n_triangles,
                           "degenerate": mesh.degenerate})
            against = "mesh"
    structure_ok = against == "mesh" or not problems
    if structure_ok:
        result.update(command_kit.tree_stats(tree, costs))
    result.update({
        "frame_origin": [float(x) for x in frame.origin],
        "frame_scale": float(frame.scale),
        "valid": not problems,
        "validated_against": against if structure_ok else "structure (broken: no costs)",
    })
    if problems:
        result["problems"] = problems[:10]
    return result
