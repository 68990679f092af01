"""Helpers shared by the subcommands: input loading, timing, progress, tree stats, output."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import re
import sys
import time

import numpy as np

import jaxbvh
from jaxbvh import configs
from jaxbvh.builders.configs import BUILDERS, DEFAULT_BUILDER, BinnedConfig, BuilderConfig, PLOCConfig
from jaxbvh.io import Mesh, TreeFile, bundled_mesh_path, load_any, load_mesh
from jaxbvh.tree import layout as tree_mod
from jaxbvh.tree.interchange import compact
from jaxbvh.tree.validate import InvalidTreeError, check


def add_json(parser) -> None:
    parser.add_argument("--json", action="store_true",
                        help="print the result as one JSON object on stdout")


def add_mesh_arg(parser, required: bool = False) -> None:
    """Positional MESH defaulting to the bundled mesh."""
    if required:
        parser.add_argument("mesh", metavar="MESH", help="mesh file (OBJ, PLY, STL, glTF, ...)")
    else:
        parser.add_argument("mesh", metavar="MESH", nargs="?", default=None,
                            help="mesh file (OBJ, PLY, STL, glTF, ...); default: the bundled "
                                 "mesh (Spot, 5,856 triangles)")


# ----------------------------------------------------------------------------------
# Options from Configs: one default, one check, in the library
# ----------------------------------------------------------------------------------


def flag(name: str) -> str:
    """The option of a Config knob: ``max_leaf`` -> ``--max-leaf``."""
    return "--" + name.replace("_", "-")


def add_config_options(parser, config_class, names=None, *, helps: dict | None = None,
                       check_now: bool = False) -> None:
    """Add an option per knob ``names`` (default: all) of the frozen Config ``config_class``.

    Each option is :func:`flag` of the knob's name, stored under the knob's name; its
    default is the knob's default (the one place it is written), its type that of the
    default (or the knob's metadata ``type`` when the default is None), its help,
    metavar and choices from the knob's metadata (:mod:`jaxbvh.configs`); ``helps``
    replaces a knob's help. ``check_now``: run the knob's check while parsing (a bad
    value is then argparse's usage error); otherwise :func:`config_from_args` checks it
    in ``run`` (a one-line error like bad input).
    """
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    for name in names if names is not None else fields:
        f = fields[name]
        meta = f.metadata
        kind = meta.get("type") or type(f.default)
        check = meta.get("check") if check_now else None

        def parse(text, kind=kind, check=check, name=name):
            try:
                value = kind(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
            try:
                return value if check is None else check(name, value)
            except ValueError as exc:
                raise argparse.ArgumentTypeError(with_flags(str(exc), [name])) from None

        text = (helps or {}).get(name, meta.get("help", ""))
        if f.default is not None:
            text += " (default: %(default)s)"
        extra = {key: meta[key] for key in ("metavar", "choices") if key in meta}
        parser.add_argument(flag(name), dest=name, type=parse, default=f.default, help=text, **extra)


def with_flags(message: str, names) -> str:
    """``message`` with each knob of ``names`` written as its option (``max_leaf`` -> ``--max-leaf``)."""
    for name in sorted(names, key=len, reverse=True):
        message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flag(name), message)
    return message


@contextlib.contextmanager
def options_named(names):
    """Re-raise a ``ValueError`` from the library with the knobs ``names`` written as options."""
    try:
        yield
    except ValueError as exc:
        raise ValueError(with_flags(str(exc), names)) from None


def config_from_args(config_class, args, **values):
    """``config_class`` made from the options in ``args`` named like its knobs, and ``values``.

    The Config checks them (the library's rules, once); a bad one is a ``ValueError``
    naming the option.
    """
    given = [name for name in configs.names(config_class) if hasattr(args, name)]
    values = {**{name: getattr(args, name) for name in given}, **values}
    with options_named(given):
        return config_class(**values)


def add_builder_args(parser, *, helps: dict | None = None) -> None:
    """``--builder`` and the builders' knobs (:mod:`jaxbvh.builders.configs`), checked while parsing."""
    parser.add_argument("--builder", choices=list(BUILDERS), default=DEFAULT_BUILDER,
                        help="sweep, binned or median (top-down SAH engine), lbvh or ploc (bottom-up "
                             "from Morton order: much faster on big inputs) (default: %(default)s)")
    helps = {"bins": "bins per axis for --builder binned",
             "radius": "neighbours on each side a cluster looks at, for --builder ploc",
             "morton_bits": "Morton code length for --builder lbvh and ploc", **(helps or {})}
    add_config_options(parser, BuilderConfig, ["max_leaf"], helps=helps, check_now=True)
    add_config_options(parser, BinnedConfig, ["bins"], helps=helps, check_now=True)
    add_config_options(parser, PLOCConfig, ["radius", "morton_bits"], helps=helps, check_now=True)
    add_config_options(parser, BuilderConfig, ["ct", "ci"], helps=helps, check_now=True)


def builder_config(args) -> BuilderConfig:
    """The Config of ``args.builder`` with the builder options in ``args``."""
    return config_from_args(BUILDERS[args.builder], args)


def _int_at_least(minimum: int):
    """argparse ``type`` accepting integers >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def mesh_or_default(path) -> Mesh:
    """The mesh at ``path``, or the bundled mesh when ``path`` is None."""
    return load_mesh(bundled_mesh_path() if path is None else path)


def load_input(path, *, check: bool = True) -> Mesh | TreeFile:
    """A mesh, or a tree for ``.npz`` paths; the bundled mesh when ``path`` is None.

    A tree is checked (:func:`check_tree_file`) unless ``check=False``.
    """
    loaded = mesh_or_default(None) if path is None else load_any(path)
    if check and isinstance(loaded, TreeFile):
        check_tree_file(loaded)
    return loaded


def load_tree(path, *, binary: bool = False, check: bool = True) -> TreeFile:
    """The tree ``.npz`` at ``path``, checked (:func:`check_tree_file`); a mesh path is an error.

    ``binary=True`` also refuses a wide tree (for commands that need two children);
    ``check=False`` leaves the check to the caller (who has primitive boxes for it).
    """
    loaded = load_any(path)
    if not isinstance(loaded, TreeFile):
        raise ValueError(f"{path} is not a tree file (.npz); build one with jaxbvh build -o TREE.npz")
    if check:
        check_tree_file(loaded)
    if binary and np.asarray(loaded.tree.child).shape[1] != 2:
        raise ValueError(f"{path}: a binary tree is needed, but it is "
                         f"{np.asarray(loaded.tree.child).shape[1]}-wide")
    return loaded


def check_tree_file(loaded: TreeFile, prim_lo=None, prim_hi=None) -> TreeFile:
    """Raise :class:`~jaxbvh.tree.validate.InvalidTreeError` (naming the file) if the tree is broken.

    Every command that reads a tree calls this before any jitted loop: a cycle, a
    shared child or a NaN box would otherwise make a traversal or an optimizer loop run
    to its bound or return nonsense. The check is :func:`jaxbvh.check`: structure,
    primitive ids, finite boxes that contain their children, and with ``prim_lo``,
    ``prim_hi`` [n, 3] (in the tree's frame) leaves that contain their primitives.
    """

    problems = check(loaded.tree, prim_lo, prim_hi)
    if problems:
        raise InvalidTreeError([f"{loaded.path}: {problems[0]}"] + problems[1:])
    return loaded


def require_matplotlib(option: str) -> None:
    """Raise a one-line error naming the extra to install when matplotlib is missing."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        raise ValueError(f"{option} needs matplotlib, which is not installed: "
                         "pip install 'jaxbvh[plot]' (or pip install matplotlib)")


# ----------------------------------------------------------------------------------
# Progress and timing
# ----------------------------------------------------------------------------------


def show_progress(args) -> bool:
    """Progress bars only for people: stderr is a terminal and ``--json`` is off."""
    return not getattr(args, "json", False) and sys.stderr.isatty()


def progress(args, total: int | None = None, desc: str = ""):
    """A tqdm bar on stderr (disabled when :func:`show_progress` says so)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, disable=not show_progress(args),
                leave=False, dynamic_ncols=True)


class Stages:
    """A progress bar over named stages, timing each: ``with stages("build"): ...``."""

    def __init__(self, args, names: list[str]):
        self.bar = progress(args, total=len(names), desc=names[0] if names else "")
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        self.bar.set_description(name)
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = time.perf_counter() - start
            self.bar.update(1)

    def close(self):
        self.bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ----------------------------------------------------------------------------------
# Building and describing trees
# ----------------------------------------------------------------------------------


def build_mesh_tree(mesh: Mesh, args, stages: Stages):
    """Build over ``mesh.local_boxes()`` with the builder options in ``args``; validated.

    Returns ``(tree, lo, hi)``, the tree as NumPy arrays trimmed to the capacity of its
    node count (:func:`jaxbvh.tree.layout.compact`); ``stages`` records "build" (compile + build,
    until the arrays are ready) and "validate" seconds.
    """
    import jax

    lo, hi = mesh.local_boxes()
    with stages("build"):
        tree = jaxbvh.build(lo, hi, builder_config(args))
        # the capacity a saved copy loads with: same shape, same compiled programs
        tree = compact(jax.block_until_ready(tree))
    with stages("validate"):
        jaxbvh.validate(tree, lo, hi)
    return tree, lo, hi


def tree_stats(tree, ct: float = 1.0, ci: float = 1.0) -> dict:
    """Nodes, leaves, depth, leaf sizes and all costs of ``tree`` as plain Python values."""

    t = jaxbvh.to_numpy(tree)
    real = tree_mod.real_nodes(t)
    counts = np.asarray(t.prim_count)[real]
    leaf_sizes = counts[counts > 0]
    depths = tree_mod.depth(t)
    stats = {
        "nodes": int(real.sum()),
        "leaves": int(leaf_sizes.size),
        "depth": int(depths[real].max()) if real.any() else 0,
        "leaf_size_min": int(leaf_sizes.min()) if leaf_sizes.size else 0,
        "leaf_size_mean": float(leaf_sizes.mean()) if leaf_sizes.size else 0.0,
        "leaf_size_max": int(leaf_sizes.max()) if leaf_sizes.size else 0,
        "primitives": int(leaf_sizes.sum()),
        "capacity": int(np.asarray(t.prim_count).shape[0]),
        "dtype": str(np.asarray(t.lo).dtype),
    }
    stats.update(jaxbvh.all_costs(tree, ct, ci))
    return stats


def mesh_info(mesh: Mesh) -> dict:
    return {
        "input": str(mesh.path),
        "triangles": mesh.n_triangles,
        "degenerate": int(mesh.degenerate),
        "objects": len(mesh.objects),
        "instances": len(mesh.instances),
    }


# ----------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------


def _plain(value):
    """JSON-able form of numpy scalars/arrays, paths and non-finite floats."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def _format(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4f}" if abs(value) < 1e6 else f"{value:.4g}"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_format(v) for v in value) if value else "-"
    return str(value)


def format_table(result: dict) -> str:
    """Two-column ``key  value`` table; nested dicts become ``outer.inner`` rows."""
    rows: list[tuple[str, str]] = []

    def add(prefix, mapping):
        for key, value in mapping.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                add(name + ".", value)
            else:
                rows.append((name, _format(value)))

    add("", _plain(result))
    width = max((len(k) for k, _ in rows), default=0)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def print_result(result: dict, as_json: bool = False, file=None) -> None:
    file = file or sys.stdout
    if as_json:
        print(json.dumps(_plain(result), allow_nan=False), file=file)
    else:
        print(format_table(result), file=file)
