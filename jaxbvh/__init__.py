"""jaxbvh: bounding volume hierarchies as JAX array programs.

Public API (flat): build a tree, check it, cost it, optimize it, save and load it. The
layout of a tree is documented once, in :mod:`jaxbvh.tree.layout`.

Packages, one concept each (every JAX module's NumPy twin sits beside it as
``<module>_reference``):

=================  =====================================================================
package            what it holds
=================  =====================================================================
``tree``           the layout, interchange files, frame, invariants, costs, refit,
                   split axes, batches
``builders``       top-down (sweep, binned, median), LBVH, PLOC, insertion
``optimize``       one protocol for every optimizer: rotations (Kensler), reinsertion,
                   treelets, the pipeline
``wide``           collapsing to wide trees (Susano Pinto)
``stochastic``     GRASP and the genetic algorithm (Ng & Trifonov)
``twolevel``       two-level BVHs and partial re-braiding (Benthin et al.)
``rays``           ray generation, traversal, measured costs
``queries``        closest point, box overlap, radius queries and differentiable ray hits
                   inside your own jit / vmap / grad
``io``             meshes and scenes from files
``batch``          many meshes at once: trees stacked in capacity groups, every method
                   vmapped, the batch axis sharded over devices
``cli``            the ``jaxbvh`` command
=================  =====================================================================

``numerics`` holds the rules every algorithm shares (ties, margins, area scale) and
``draws`` the random numbers an algorithm and its twin both consume.

jaxbvh turns on JAX's persistent compilation cache in a per-user folder as it loads its
JAX code, unless you configured JAX's cache yourself or set ``JAXBVH_CACHE=off``
(:mod:`jaxbvh.compile_cache`): compiled programs then serve every later process.

The names below load on first use (PEP 562), so ``import jaxbvh`` and the command line's
``--help`` cost no JAX import; ``jaxbvh.build`` and the rest load JAX then.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: public name -> (module, attribute in it; None: the module itself)
_LAZY = {
    "batch": ("jaxbvh.batch", None), "compile_cache": ("jaxbvh.compile_cache", None), "io": ("jaxbvh.io", None),
    "optimize": ("jaxbvh.optimize", None), "queries": ("jaxbvh.queries", None), "rays": ("jaxbvh.rays", None), "scenes": ("jaxbvh.scenes", None),
    "twolevel": ("jaxbvh.twolevel", None), "insertion": ("jaxbvh.builders.insertion", None),
    "lbvh": ("jaxbvh.builders.lbvh", None), "morton": ("jaxbvh.builders.morton", None),
    "ploc": ("jaxbvh.builders.ploc", None), "BUILDERS": ("jaxbvh.builders.dispatch", "BUILDERS"),
    "BOX_BUILDERS": ("jaxbvh.builders.dispatch", "BOX_BUILDERS"),
    "build": ("jaxbvh.builders.dispatch", "build"), "load_mesh": ("jaxbvh.io", "load_mesh"),
    "reinsert": ("jaxbvh.optimize.reinsert", None), "rotate": ("jaxbvh.optimize.rotate", None),
    "treelet": ("jaxbvh.optimize.treelet", None), "evolve": ("jaxbvh.stochastic.evolve", None),
    "grasp": ("jaxbvh.stochastic.grasp", None), "all_costs": ("jaxbvh.tree.cost", "all_costs"),
    "goldsmith_salmon_cost": ("jaxbvh.tree.cost", "goldsmith_salmon_cost"),
    "ng_trifonov_cost": ("jaxbvh.tree.cost", "ng_trifonov_cost"), "node_costs": ("jaxbvh.tree.cost", "node_costs"),
    "sah": ("jaxbvh.tree.cost", "sah"), "Frame": ("jaxbvh.tree.frame", "Frame"),
    "from_interchange": ("jaxbvh.tree.interchange", "from_interchange"),
    "load": ("jaxbvh.tree.interchange", "load"), "save": ("jaxbvh.tree.interchange", "save"),
    "to_interchange": ("jaxbvh.tree.interchange", "to_interchange"), "BVH": ("jaxbvh.tree.layout", "BVH"),
    "WideBVH": ("jaxbvh.tree.layout", "WideBVH"), "capacity_bucket": ("jaxbvh.tree.layout", "capacity_bucket"),
    "to_jax": ("jaxbvh.tree.layout", "to_jax"), "to_numpy": ("jaxbvh.tree.layout", "to_numpy"),
    "InvalidTreeError": ("jaxbvh.tree.validate", "InvalidTreeError"), "check": ("jaxbvh.tree.validate", "check"),
    "validate": ("jaxbvh.tree.validate", "validate"), "collapse": ("jaxbvh.wide.collapse", None),
    "targets": ("jaxbvh.tree.targets", None),
}

__all__ = [
    "BVH", "WideBVH", "Frame", "InvalidTreeError", "BUILDERS", "BOX_BUILDERS",
    "build", "check", "validate", "sah", "node_costs", "ng_trifonov_cost", "goldsmith_salmon_cost",
    "all_costs", "save", "load", "to_interchange", "from_interchange", "to_numpy", "to_jax",
    "capacity_bucket", "compile_cache", "load_mesh", "batch", "io", "optimize", "queries", "rays", "scenes", "twolevel", "targets",
    "insertion", "lbvh", "morton", "ploc", "reinsert", "rotate", "treelet", "evolve", "grasp", "collapse",
]


def __getattr__(name: str):
    """Load a public name on first use (module docstring) and keep it."""
    if name not in _LAZY:
        raise AttributeError(f"module 'jaxbvh' has no attribute {name!r}")
    module_name, attribute = _LAZY[name]
    # JAX-free until asked to turn the cache on: before anything of ours compiles
    importlib.import_module("jaxbvh.compile_cache").enable_default()
    module = importlib.import_module(module_name)
    value = module if attribute is None else getattr(module, attribute)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
