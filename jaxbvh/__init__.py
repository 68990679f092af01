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
``io``             meshes and scenes from files
``batch``          many meshes at once: trees stacked in capacity groups, every method
                   vmapped, the batch axis sharded over devices
``cli``            the ``jaxbvh`` command
=================  =====================================================================

``numerics`` holds the rules every algorithm shares (ties, margins, area scale) and
``draws`` the random numbers an algorithm and its twin both consume.

Importing jaxbvh turns on JAX's persistent compilation cache in a per-user folder, unless
you configured JAX's cache yourself or set ``JAXBVH_CACHE=off``
(:mod:`jaxbvh.compile_cache`): compiled programs then serve every later process.
"""

from jaxbvh import batch, compile_cache, io, optimize, rays, scenes, twolevel
from jaxbvh.builders import insertion, lbvh, morton, ploc
from jaxbvh.builders.dispatch import BUILDERS, build
from jaxbvh.io import load_mesh
from jaxbvh.optimize import reinsert, rotate, treelet
from jaxbvh.stochastic import evolve, grasp
from jaxbvh.tree.cost import all_costs, goldsmith_salmon_cost, ng_trifonov_cost, node_costs, sah
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.interchange import from_interchange, load, save, to_interchange
from jaxbvh.tree.layout import BVH, WideBVH, capacity_bucket, to_jax, to_numpy
from jaxbvh.tree.validate import InvalidTreeError, check, validate
from jaxbvh.wide import collapse

__version__ = "0.1.0"

compile_cache.enable_default()

__all__ = [
    "BVH", "WideBVH", "Frame", "InvalidTreeError", "BUILDERS",
    "build", "check", "validate", "sah", "node_costs", "ng_trifonov_cost", "goldsmith_salmon_cost",
    "all_costs", "save", "load", "to_interchange", "from_interchange", "to_numpy", "to_jax",
    "capacity_bucket", "compile_cache", "load_mesh", "batch", "io", "optimize", "rays", "scenes", "twolevel", "insertion", "lbvh",
    "morton", "ploc", "reinsert", "rotate", "treelet", "evolve", "grasp", "collapse",
]
