"""``jaxbvh export TREE MESH --format tinybvh -o OUT.bin``: a tree for a C++ tracer.

The tree is checked against its mesh first (:func:`jaxbvh.cli.command_kit.check_against_mesh`:
the leaves hold the mesh's triangles in the tree's frame and precision), then written
with the mesh's world-space triangles by :func:`jaxbvh.io.export_tinybvh` (format:
:mod:`jaxbvh.io.tinybvh`). An existing OUT is an error, before any work, unless
``--overwrite`` (as ``jaxbvh batch``).
"""

from __future__ import annotations

import os

import numpy as np

from jaxbvh.cli import command_kit
from jaxbvh.io import load_mesh
from jaxbvh.io.tinybvh import FLAG_REFERENCES, export_tinybvh
from jaxbvh.tree.validate import InvalidTreeError

HELP = "write a tree (.npz) and its mesh's triangles for a C++ tracer (tinybvh's node file)"
#: the file formats ``--format`` offers
FORMATS = ("tinybvh",)


def add_parser(subparsers):
    """Add the ``export`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("export", help=HELP, description=HELP + ".")
    parser.add_argument("tree", metavar="TREE", help="a binary tree .npz (jaxbvh build -o, jaxbvh "
                                                    "optimize -o) over MESH's triangles")
    parser.add_argument("mesh", metavar="MESH", help="the mesh the tree was built over")
    parser.add_argument("--format", choices=FORMATS, default=FORMATS[0],
                        help="tinybvh: tinybvh's BVHNode records (world space, float32), primIdx and the "
                             "triangles, as ../shared/peer/tinybvh_trace --tree reads them (default: %(default)s)")
    parser.add_argument("-o", "--output", metavar="OUT.bin", required=True, help="the file to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace OUT if it exists (default: an existing OUT is an error, before any work)")
    command_kit.add_json(parser)
    return parser


def check_output(path: str, overwrite: bool) -> None:
    """``ValueError`` when ``path`` is in the way: a folder, or (unless ``overwrite``) a file."""
    if os.path.isdir(path):
        raise ValueError(f"{path} is a folder; -o names the file to write")
    if (os.path.exists(path) or os.path.islink(path)) and not overwrite:
        raise ValueError(f"{path} exists: pass --overwrite to replace it, or choose another -o")


def run(args) -> dict:
    """Run ``jaxbvh export`` on parsed ``args``; returns the result the command prints."""
    check_output(args.output, args.overwrite)
    with command_kit.Stages(args, ["load", "check", "write"]) as stages:
        with stages("load"):
            loaded = command_kit.load_tree(args.tree, check=False)  # checked below, with the mesh
            arity = int(np.asarray(loaded.tree.child).shape[1])
            if arity != 2:
                raise ValueError(f"{args.tree}: a {arity}-wide tree; tinybvh's node file holds binary trees "
                                 "(export the binary tree it was collapsed from: tinybvh makes its 4- and "
                                 "8-wide layouts from the binary tree itself)")
            mesh = load_mesh(args.mesh)
        with stages("check"):
            checked = command_kit.check_against_mesh(loaded, mesh)
            if checked.problems:
                raise InvalidTreeError(checked.problems)
        with stages("write"):
            written = export_tinybvh(args.output, loaded.tree, mesh.triangles, loaded.frame)
    return {"command": "export", "tree": loaded.path, "mesh": str(mesh.path), "format": args.format,
            "output": args.output, "triangles": written["triangles"], "nodes": written["nodes"],
            "primitive_ids": written["primitive_ids"],
            "spatial_splits": bool(written["flags"] & FLAG_REFERENCES), "bytes": written["bytes"],
            "checked_in": checked.precision}
