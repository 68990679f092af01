"""``jaxbvh stats MESH_OR_TREE``: costs and shape of a saved tree, or of a fresh build."""

from __future__ import annotations

import jaxbvh
from jaxbvh.commands import _common
from jaxbvh.io import Mesh, boxes_in_frame

HELP = "report nodes, depth, leaf sizes and costs of a tree (.npz) or of a mesh's BVH"


def add_parser(subparsers):
    parser = subparsers.add_parser("stats", help=HELP, description=HELP + ".")
    parser.add_argument("input", metavar="MESH_OR_TREE",
                        help="a tree .npz (jaxbvh build -o, or another library's export) "
                             "or a mesh file, built with the default builder")
    parser.add_argument("--mesh", metavar="MESH", default=None,
                        help="for a tree: also validate it against this mesh's triangle boxes")
    _common.add_builder_args(parser)
    _common.add_json(parser)
    return parser


def run(args) -> dict:
    names = ["load", "build", "validate"]
    with _common.Stages(args, names) as stages:
        with stages("load"):
            loaded = _common.load_input(args.input)
        if isinstance(loaded, Mesh):
            if args.mesh is not None:
                raise ValueError(f"--mesh applies to a tree file; {args.input} is a mesh")
            tree, _, _ = _common.build_mesh_tree(loaded, args, stages)
            result = {"command": "stats", "kind": "mesh", **_common.mesh_info(loaded),
                      "builder": args.builder, "max_leaf": args.max_leaf}
            result.update(_common.tree_stats(tree, args.ct, args.ci))
            result.update({"valid": True, "validated_against": "mesh",
                           "seconds": stages.seconds["build"]})
            return result
        return _tree_stats(loaded, args, stages)


def _tree_stats(loaded, args, stages) -> dict:
    tree, frame = loaded.tree, loaded.frame
    result = {"command": "stats", "kind": "tree", "input": loaded.path}
    with stages("validate"):
        if args.mesh is not None:
            mesh = _common.mesh_or_default(args.mesh)
            world_lo, world_hi = mesh.prim_boxes()
            dtype = tree.lo.dtype
            lo, hi = boxes_in_frame(world_lo, world_hi, frame, dtype)
            problems = jaxbvh.check(tree, lo, hi)
            referenced = int(tree.prim_count.sum())
            if referenced != mesh.n_triangles:
                problems.insert(0, f"the tree's leaves hold {referenced} primitives but "
                                   f"{mesh.path} has {mesh.n_triangles} triangles")
            result.update({"mesh": str(mesh.path), "triangles": mesh.n_triangles,
                           "degenerate": mesh.degenerate})
            against = "mesh"
        else:
            problems = jaxbvh.check(tree)
            against = "structure only (pass --mesh to check boxes)"
    result.update(_common.tree_stats(tree, args.ct, args.ci))
    result.update({
        "frame_origin": [float(x) for x in frame.origin],
        "frame_scale": float(frame.scale),
        "valid": not problems,
        "validated_against": against,
    })
    if problems:
        result["problems"] = problems[:10]
    return result
