"""``jaxbvh trace TREE MESH``: trace rays through a saved tree, report tests per ray."""

from __future__ import annotations

import inspect
import math
import os
import warnings

import numpy as np

import jaxbvh
from jaxbvh import rays
from jaxbvh.cli import command_kit
from jaxbvh.cli import options as config_options
from jaxbvh.configs import SAHCosts
from jaxbvh.files import atomic_write
from jaxbvh.io import load_mesh
from jaxbvh.rays import traversal as traverse
from jaxbvh.rays.measure import KINDS, MODES
from jaxbvh.tree import layout as tree_layout
from jaxbvh.tree.validate import InvalidTreeError

#: --ct, --ci: the SAH constants of the cost reported beside the ray counts
COSTS = config_options.ConfigOptions({"trace": SAHCosts})
#: the traversal's own defaults of --mode and --batch (read from the library, not retyped)
TRAVERSAL = {name: p.default for name, p in inspect.signature(traverse.trace).parameters.items()}

HELP = "trace rays through a tree (.npz) over its mesh; report box and primitive tests per ray"


def add_parser(subparsers):
    """Add the ``trace`` subparser (its options and help) to ``subparsers``; returns it."""
    parser = subparsers.add_parser("trace", help=HELP, description=HELP + ".")
    parser.add_argument("tree", metavar="TREE", help="a tree .npz (jaxbvh build -o, or another "
                                                    "library's export) over MESH's triangles")
    parser.add_argument("mesh", metavar="MESH", help="the mesh the tree was built over")
    parser.add_argument("--rays", type=command_kit.int_option(1), default=100_000, metavar="N",
                        help="number of rays (camera: about N pixels, 4:3) (default: 100000)")
    parser.add_argument("--kind", choices=KINDS, default="random",
                        help="random: origins in the root box, uniform directions; camera: "
                             "pinhole framing the scene; bounce: diffuse rays off the surface "
                             "(default: random)")
    parser.add_argument("--mode", choices=MODES, default=TRAVERSAL["mode"],
                        help="closest hit, any hit (shadow rays) or all hits (default: %(default)s)")
    command_kit.add_seed(parser)
    parser.add_argument("--batch", type=command_kit.int_option(1), default=TRAVERSAL["batch"], metavar="B",
                        help="rays per jitted batch (default: %(default)s)")
    parser.add_argument("--save", metavar="HITS.npz", default=None,
                        help="write origin, direction (world space), t and prim (-1: miss) "
                             "and the per-ray counters")
    parser.add_argument("--image", metavar="OUT.png", default=None,
                        help="render camera rays: shaded normals, depth and a heat map of box "
                             "tests per pixel (the measured rays with --kind camera, else a "
                             "separate 320 x 240 camera view); needs matplotlib")
    COSTS.add_to(parser)
    command_kit.add_json(parser)
    return parser


#: memory one ray takes, all told: origin and direction as made (float64 at most), in the
#: batch and as saved, its hit record and counters, and the summary's copies
BYTES_PER_RAY = 192

#: a tree deeper than this many times a balanced tree's depth gets a warning (and ...
DEEP_FACTOR = 8
#: ... deeper than this many levels: shallow trees are cheap whatever their shape)
DEEP_LEVELS = 64


def depth_warning(tree, rays: int, batch: int) -> str | None:
    """A warning when the tree's depth makes traversal cost explode, else None.

    A ray that reaches the deepest leaf takes about ``2 * depth`` loop steps (a node step
    per level, and the sibling it pushed), and a batch of rays runs as long as its
    longest ray; a balanced tree over the same leaves is ``ceil(log2 leaves)`` deep.
    """
    t = jaxbvh.to_numpy(tree)
    real = tree_layout.real_nodes(t)
    height = int(tree_layout.depth(t)[real].max()) if real.any() else 0
    leaves = int((np.asarray(t.prim_count) > 0).sum())
    balanced = max(1, math.ceil(math.log2(max(leaves, 2))))
    if height <= DEEP_LEVELS or height <= DEEP_FACTOR * balanced:
        return None
    batches = math.ceil(rays / max(1, min(batch, rays)))
    return (f"tree depth {height:,} (a balanced tree over its {leaves:,} leaves: {balanced}): a ray "
            f"may take up to ~{2 * height:,} steps (balanced: ~{2 * balanced}), and each of the "
            f"{batches:,} batches runs as long as its longest ray: up to ~{batches * 2 * height:,} "
            "sequential steps in all")


def run(args) -> dict:
    """Run ``jaxbvh trace`` on parsed ``args``; returns the result the command prints."""
    costs = COSTS.config(None, args)
    command_kit.check_fits("--rays", args.rays, BYTES_PER_RAY, "rays, their hits and counters")
    if args.image:
        command_kit.require_matplotlib("--image")
    with command_kit.Stages(args, ["load", "trace", "write"]) as stages:
        with stages("load"):
            loaded = command_kit.load_tree(args.tree, check=False)  # checked below, with the mesh
            mesh = load_mesh(args.mesh)
            tree, frame = loaded.tree, loaded.frame
            dtype = np.asarray(tree.lo).dtype
            # before any jitted loop; a leaf box that misses its triangle would lose hits.
            # The triangles are those the check passed in (the tree's stored precision)
            checked = command_kit.check_against_mesh(loaded, mesh)
            if checked.problems:
                raise InvalidTreeError(checked.problems)
            triangles = checked.triangles
            key = command_kit.seed_key(args.seed)
            origin, direction = rays.make_rays(key, args.kind, tree, triangles, args.rays)
            deep = depth_warning(tree, args.rays, args.batch)
            if deep:
                warnings.warn(deep, stacklevel=1)
        with stages("trace"):
            # measure traces one batch first to compile: the bar counts it too
            warm = min(args.rays, args.batch)
            with command_kit.progress(args, total=args.rays + warm, desc="rays") as bar:
                hits, summary = rays.measure(tree, triangles, origin, direction, mode=args.mode,
                                             ct=costs.ct, ci=costs.ci, batch=args.batch,
                                             on_batch=bar.update)
        result = {"command": "trace", "tree": loaded.path, "mesh": str(mesh.path),
                  "triangles": mesh.n_triangles, "checked_in": checked.precision, "kind": args.kind, "seed": args.seed,
                  "arity": int(np.asarray(tree.child).shape[1]),
                  "stack_capacity": traverse.stack_capacity(tree)}
        result.update(summary)
        with stages("write"):
            if args.save:
                # np.savez's rule for a name without the suffix (it adds .npz)
                saved = args.save if args.save.endswith(".npz") else args.save + ".npz"
                with atomic_write(saved) as f:
                    np.savez(f, origin=frame.to_world(origin), direction=direction.astype(np.float64),
                             t=np.where(hits.prim >= 0, hits.t.astype(np.float64) * frame.scale, np.inf),
                             prim=hits.prim, box_tests=hits.box_tests, prim_tests=hits.prim_tests,
                             nodes_visited=hits.nodes_visited)
                result["saved"] = saved
            if args.image:
                if args.kind == "camera":
                    image_hits, image_dir, size = hits, direction, rays.camera_size(args.rays)
                    note = "the measured camera rays"
                else:  # render a separate 320 x 240 camera view
                    size = (320, 240)
                    root = int(tree.root)
                    o, image_dir = rays.camera_rays(tree.lo[root], tree.hi[root], *size, dtype=dtype)
                    image_hits = rays.closest_hit(tree, triangles, o, image_dir, batch=args.batch)
                    note = (f"a separate {size[0]} x {size[1]} camera view, closest hits; the table "
                            f"measures the {args.kind} rays")
                render(args.image, image_hits, triangles, image_dir, *size, note=note)
                result["image"] = args.image
                result["image_rays"] = note
                result["image_box_tests"] = float(np.mean(image_hits.box_tests))
    return result


def render(path, hits, triangles, direction, width: int, height: int, note: str = "") -> None:
    """Write a PNG: shaded normals, depth and box tests per pixel of camera rays.

    ``note`` (which rays the picture shows) becomes the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hit = hits.prim >= 0
    tri = np.asarray(triangles, np.float64)[np.maximum(hits.prim, 0)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    facing = np.sum(normal * direction, axis=1) > 0
    normal[facing] *= -1  # towards the camera
    colour = np.where(hit[:, None], 0.5 * (normal + 1), 1.0).reshape(height, width, 3)
    depth = np.where(hit, hits.t, np.nan).reshape(height, width)
    boxes = np.asarray(hits.box_tests).reshape(height, width)

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    axes[0].imshow(colour)
    axes[0].set_title("normals (facing the camera)")
    im = axes[1].imshow(depth, cmap="viridis_r")
    axes[1].set_title("depth t (tree frame)")
    fig.colorbar(im, ax=axes[1], shrink=0.8)
    im = axes[2].imshow(boxes, cmap="inferno")
    axes[2].set_title(f"box tests per ray (mean {boxes.mean():.1f})")
    fig.colorbar(im, ax=axes[2], shrink=0.8)
    for ax in axes:
        ax.set_axis_off()
    if note:
        fig.suptitle(note)
    try:
        # a file object has no name to infer the format from: the suffix's (.png by default)
        with atomic_write(path) as f:
            fig.savefig(f, dpi=100, format=os.path.splitext(path)[1][1:].lower() or "png")
    finally:
        plt.close(fig)
