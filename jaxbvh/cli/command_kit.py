"""Helpers shared by the subcommands: input loading, timing, progress, tree stats, output."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from typing import NamedTuple

import numpy as np

import jaxbvh
from jaxbvh.builders.configs import BUILDERS, DEFAULT_BUILDER, TRIANGLE_BUILDERS, BuilderConfig
from jaxbvh.cli import options as config_options
from jaxbvh.cli.front import int_option
from jaxbvh.tree import targets
from jaxbvh.configs import INT_MAX, SAHCosts
from jaxbvh.io import Mesh, TreeFile, bundled_mesh_path, load_any, load_mesh
from jaxbvh.tree import layout as tree_mod
from jaxbvh.tree.interchange import compact
from jaxbvh.tree.validate import InvalidTreeError, check


def add_json(parser) -> None:
    """Add ``--json`` (print the result as one JSON object on stdout) to ``parser``."""
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
# Options every command shares: the builder's (from its Configs), the seed
# ----------------------------------------------------------------------------------

#: the most trials or generations a command runs (grasp --trials, evolve --generations):
#: each builds at least one tree (a generation: --population of them), tens of
#: milliseconds on a small mesh, so this many is already hours; the library has no bound
MAX_RUNS = 100_000

#: the random seed of a command that draws (grasp, evolve, sa, rays) unless --seed says
DEFAULT_SEED = 0

#: the builders' knobs as options (jaxbvh.cli.options): --max-leaf, --bins, --radius,
#: --morton-bits, --ct, --ci. The builders are one family: one set of options serves every
#: builder (a knob of another builder is checked, not used, as jaxbvh.build's keyword form
#: ignores it), and every builder shares each knob's rule, so values are checked while
#: parsing. pad and dtype stay the library's.
BUILDER_EXCLUDE = ("pad", "dtype")


def builder_options(default: BuilderConfig | None = None, methods=BUILDERS,
                    max_leaf: int | None = None) -> config_options.ConfigOptions:
    """The builder options of the builders ``methods`` (names); ``default``: a Config whose
    values are its builder's defaults (None: every builder's class defaults); ``max_leaf``:
    every builder's default leaf limit instead of its class default (None: the class's)."""
    configs = {m: BUILDERS[m] if max_leaf is None else BUILDERS[m](max_leaf=max_leaf) for m in methods}
    if default is not None:
        configs[default.method] = default
    return config_options.ConfigOptions(configs, exclude=BUILDER_EXCLUDE, method_flag="--builder",
                                        families=dict.fromkeys(configs, "builders"),
                                        check_while_parsing=True)


def add_builder_args(parser, *, default: BuilderConfig | None = None, methods=BUILDERS,
                     max_leaf: int | None = None) -> None:
    """``--builder`` and the builders' knobs (:mod:`jaxbvh.builders.configs`); ``default``:
    the builder (its method and values) when no option says otherwise (None:
    :data:`~jaxbvh.builders.configs.DEFAULT_BUILDER` with its class defaults);
    ``methods``: the builders a command offers (a command that builds from boxes alone
    leaves out :data:`~jaxbvh.builders.configs.TRIANGLE_BUILDERS`); ``max_leaf``: every
    builder's default leaf limit (None: each Config's own)."""
    method = DEFAULT_BUILDER if default is None else default.method
    triangles = any(m in TRIANGLE_BUILDERS for m in methods)
    parser.add_argument("--builder", choices=list(methods), default=method,
                        help="sweep, binned or median (top-down SAH engine), lbvh or ploc (bottom-up "
                             "from Morton order: much faster on big inputs)"
                             + (", sbvh (spatial splits: triangles in several leaves)" if triangles else "")
                             + " (default: %(default)s)")
    options = builder_options(default, methods, max_leaf)
    options.add_to(parser, "builder options (knobs of each builder's Config)")
    parser.set_defaults(builder_options=options)


def builder_config(args) -> BuilderConfig:
    """The Config of ``args.builder`` with the builder options in ``args`` (one-line
    ``ValueError`` naming the option if refused); a ``--target`` (:func:`add_target`) sets
    ``ct``, ``ci`` and ``max_leaf`` where ``--ct``, ``--ci``, ``--max-leaf`` are not given."""
    target = getattr(args, "target", None)
    fixed = {} if target is None else targets.costs(target)  # the flags given replace these
    return args.builder_options.config(args.builder, args, **fixed)


def add_target(parser) -> None:
    """``--target NAME``: the cost model of the tracer the tree is for (:mod:`jaxbvh.tree.targets`)."""
    parser.add_argument("--target", choices=list(targets.TARGETS), default=None, metavar="NAME",
                        help="cost model of the tracer the tree is for: its Ct, Ci and leaf limit for the "
                             "builder and optimizer (--ct, --ci, --max-leaf given win), and its cost in the "
                             f"report; one of {', '.join(targets.TARGETS)} (default: {targets.DEFAULT_TARGET}, "
                             "the SAH with the builder options' values)")


def target_report(tree, args, builder) -> dict:
    """``{"target", "target_cost"}`` of ``tree`` for ``--target`` with the builder's
    constants (empty when no target is given)."""
    target = getattr(args, "target", None)
    if target is None:
        return {}
    return {"target": target, "target_cost": targets.target_cost(tree, target, ct=builder.ct, ci=builder.ci,
                                                                 max_leaf=builder.max_leaf)}


def add_seed(parser, what: str = "random seed") -> None:
    """``--seed S`` (default :data:`DEFAULT_SEED`): any integer (:func:`seed_key`)."""
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, metavar="S",
                        help=f"{what}, any integer (default: {DEFAULT_SEED})")


def seed_key(seed: int):
    """The ``jax.random`` key of a command-line seed; any integer maps to a key.

    Seeds in ``[0, 2^32)`` give ``jax.random.key(seed)`` (what the library gives them).
    ``jax.random.key`` keeps only 32 bits of others (without x64: ``2^32`` would be seed
    0 again) and overflows past 64 bits, so any other seed folds the 32-bit words of its
    magnitude, then its word count and sign, into a key: distinct seeds, distinct keys.
    """
    import jax

    seed = int(seed)
    if 0 <= seed < 2 ** 32:
        return jax.random.key(seed)
    magnitude = abs(seed)
    words = [(magnitude >> (32 * i)) & 0xFFFFFFFF for i in range(max(1, (magnitude.bit_length() + 31) // 32))]
    key = jax.random.key(words[0])
    for word in words[1:] + [len(words), int(seed < 0)]:
        key = jax.random.fold_in(key, word)
    return key


#: the old name of :func:`int_option`
_int_at_least = int_option


def memory_bytes() -> int:
    """Memory this process may count on: ``MemAvailable`` of ``/proc/meminfo`` where there
    is one, else the machine's physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 2 ** 63


def check_fits(option: str, value: int, bytes_each: float, what: str) -> None:
    """Refuse (one-line ``ValueError`` naming ``option``) a ``value`` whose arrays would
    take more than half of :func:`memory_bytes`: ``bytes_each`` per unit of ``value``;
    ``what`` says what one unit holds (for the message)."""
    need, have = value * bytes_each, memory_bytes()
    if need > have / 2:
        raise ValueError(f"{option} {value:,} needs about {_size(need)} ({what}); "
                         f"this machine has {_size(have)} available")


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:,.0f} {unit}" if unit == "B" else f"{n:,.1f} {unit}"
        n /= 1024
    return f"{n:,.1f} PB"


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


def check_tree_file(loaded: TreeFile, prim_lo=None, prim_hi=None, *, triangles=None) -> TreeFile:
    """Raise :class:`~jaxbvh.tree.validate.InvalidTreeError` (naming the file) if the tree is broken.

    Every command that reads a tree calls this before any jitted loop: a cycle, a
    shared child or a NaN box would otherwise make a traversal or an optimizer loop run
    to its bound or return nonsense. The check is :func:`jaxbvh.check`: structure,
    primitive ids, finite boxes that contain their children, and with ``prim_lo``,
    ``prim_hi`` [n, 3] (in the tree's frame) leaves that contain their primitives. A tree
    that names a primitive in several leaves (spatial splits) is checked in references
    mode, its leaf boxes together covering each of ``triangles`` [n, 3, 3] when given.
    """
    references = references_per_primitive(loaded.tree) > 1
    problems = check(loaded.tree, prim_lo, prim_hi, references=references,
                     triangles=triangles if references else None)
    if problems:
        raise InvalidTreeError([f"{loaded.path}: {problems[0]}"] + problems[1:])
    return loaded


class MeshCheck(NamedTuple):
    """A tree file checked against its mesh (:func:`check_against_mesh`)."""

    triangles: np.ndarray  # float [F, 3, 3]: the mesh's triangles in the tree's frame and dtype
    problems: list         # str: broken invariants, the first naming the file; empty: valid
    precision: str         # the float type the triangles were rounded to for the check


def check_against_mesh(loaded: TreeFile, mesh: Mesh) -> MeshCheck:
    """Check a tree file against the mesh it was built over, in its stored precision.

    The mesh's float64 world triangles are moved into the tree's frame and rounded (to
    nearest, as the builders do) to the dtype the tree's boxes are stored in; every leaf
    must contain its triangles exactly there, so float16 boxes rounded to nearest
    (widened to float32 on load) are refused. A float64 tree whose boxes contain the
    triangles only as rounded to float32 (a float32 build saved as float64: its boxes
    miss the float64 triangles by up to half a float32 ulp) is valid at float32: the
    triangles returned, which rays are traced against, are then the float32 ones, and
    ``precision`` says so. A tree that names a primitive in several leaves (spatial
    splits) is checked in references mode: its leaf boxes together cover each triangle.
    """
    tree, frame = loaded.tree, loaded.frame
    dtype = np.asarray(tree.lo).dtype
    local = mesh.triangles if frame.is_identity else frame.to_local(mesh.triangles)
    referenced = int(np.asarray(tree.prim_count).sum())
    if referenced != mesh.n_triangles and not references_per_primitive(tree) > 1:
        problem = (f"{loaded.path}: the tree's leaves hold {referenced} primitives but "
                   f"{mesh.path} has {mesh.n_triangles} triangles")
        return MeshCheck(local.astype(dtype), [problem], str(dtype))
    stored = _checked_in(loaded, local, dtype, dtype)
    if stored.problems and dtype == np.float64:
        as_float32 = _checked_in(loaded, local, np.dtype(np.float32), dtype)
        if not as_float32.problems:
            return as_float32
    return stored


def _checked_in(loaded: TreeFile, local, precision, dtype) -> MeshCheck:
    """The check of :func:`check_against_mesh` with the triangles ``local`` (float64, in
    the tree's frame) rounded to ``precision`` and widened (exactly) to ``dtype``."""
    triangles = local.astype(precision).astype(dtype)
    references = references_per_primitive(loaded.tree) > 1
    problems = check(loaded.tree, triangles.min(axis=1), triangles.max(axis=1), references=references,
                     triangles=triangles if references else None)
    if problems:
        problems = [f"{loaded.path}: {problems[0]}"] + problems[1:]
    return MeshCheck(triangles, problems, str(np.dtype(precision)))


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
        """Close the progress bar."""
        self.bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ----------------------------------------------------------------------------------
# Building and describing trees
# ----------------------------------------------------------------------------------


def build_mesh_tree(mesh: Mesh, builder: BuilderConfig, stages: Stages):
    """Build over ``mesh.local_boxes()`` with ``builder``; validated.

    Returns ``(tree, lo, hi)``, the tree as NumPy arrays trimmed to the capacity of its
    node count (:func:`jaxbvh.tree.layout.compact`); ``stages`` records "build" (compile + build,
    until the arrays are ready) and "validate" seconds.
    """
    import jax

    lo, hi = mesh.local_boxes()
    triangles = mesh.local_triangles() if builder.method in TRIANGLE_BUILDERS else None
    with stages("build"):
        tree = jaxbvh.build(lo, hi, builder, triangles=triangles)
        # the capacity a saved copy loads with: same shape, same compiled programs
        tree = compact(jax.block_until_ready(tree))
    with stages("validate"):
        if triangles is None:
            jaxbvh.validate(tree, lo, hi)
        else:  # a triangle may sit in several leaves: each leaf box holds a piece of it
            jaxbvh.validate(tree, lo, hi, references=True, triangles=triangles)
    return tree, lo, hi


def references_per_primitive(tree) -> float:
    """Leaf slots per distinct primitive the leaves name (1.0 without references)."""
    t = jaxbvh.to_numpy(tree)
    leaves = np.flatnonzero(np.asarray(t.prim_count) > 0)
    if not leaves.size:
        return 1.0
    slots = tree_mod.concat_ranges(np.asarray(t.prim_start)[leaves], np.asarray(t.prim_count)[leaves])
    prims = np.asarray(t.prim_index)[slots]
    return float(prims.size / max(np.unique(prims).size, 1))


def validate_any(tree, prim_lo=None, prim_hi=None, **kwargs):
    """:func:`jaxbvh.validate`, in references mode when the tree names a primitive in
    several leaves (an SBVH, ours or another library's); returns the tree."""
    references = references_per_primitive(tree) > 1
    if references:
        kwargs.pop("n_prims", None)  # counted from the ids (leaf slots are references, not primitives)
    return jaxbvh.validate(tree, prim_lo, prim_hi, references=references, **kwargs)


def tree_stats(tree, costs=SAHCosts()) -> dict:
    """Nodes, leaves, depth, leaf sizes and all costs of ``tree`` as plain Python values;
    ``costs``: a Config with the SAH's ``ct``, ``ci`` (a builder's, or :class:`SAHCosts`)."""

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
        # > 1 only in trees with references (spatial splits): leaf slots per distinct primitive
        "references_per_triangle": references_per_primitive(t),
        "capacity": int(np.asarray(t.prim_count).shape[0]),
        "dtype": str(np.asarray(t.lo).dtype),
    }
    stats.update(jaxbvh.all_costs(tree, costs.ct, costs.ci))
    return stats


def mesh_info(mesh: Mesh) -> dict:
    """The report's entries about ``mesh``: input path, triangles, degenerate triangles,
    objects, instances (JSON-ready)."""
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


def json_ready(value):
    """JSON-able form of numpy scalars/arrays, paths and non-finite floats."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, np.generic):
        return json_ready(value.item())
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

    add("", json_ready(result))
    width = max((len(k) for k, _ in rows), default=0)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def print_result(result: dict, as_json: bool = False, file=None) -> None:
    """Print a command's ``result``: one JSON object with ``as_json``, else a table of its
    entries (default file: stdout)."""
    file = file or sys.stdout
    if as_json:
        print(json.dumps(json_ready(result), allow_nan=False), file=file)
    else:
        print(format_table(result), file=file)
