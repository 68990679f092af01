"""jaxbvh: bounding volume hierarchies as JAX array programs.

Public API (flat): build a tree, check it, cost it, save and load it. The layout of a
tree is documented once, in :mod:`jaxbvh.tree`.
"""

from jaxbvh.frame import Frame
from jaxbvh.tree import BVH, WideBVH, capacity_bucket, from_interchange, load, save, to_interchange, to_jax, to_numpy
from jaxbvh.validate import InvalidTreeError, check, validate
from jaxbvh.cost import all_costs, goldsmith_salmon_cost, ng_trifonov_cost, node_costs, sah
from jaxbvh.build import BUILDERS, build

__version__ = "0.1.0"

# attribute -> (module, attribute in it, or None for the module itself)
_LAZY = {
    "load_mesh": ("jaxbvh.io", "load_mesh"),
    "io": ("jaxbvh.io", None),
    "rays": ("jaxbvh.rays", None),
    "rotate": ("jaxbvh.rotate", None),
    "insertion": ("jaxbvh.insertion", None),
    "evolve": ("jaxbvh.evolve", None),
    "collapse": ("jaxbvh.collapse", None),
    "grasp": ("jaxbvh.grasp", None),
    "twolevel": ("jaxbvh.twolevel", None),
    "scenes": ("jaxbvh.scenes", None),
    "reinsert": ("jaxbvh.reinsert", None),
    "treelet": ("jaxbvh.treelet", None),
    "optimize": ("jaxbvh.optimize", None),
    "lbvh": ("jaxbvh.lbvh", None),
    "ploc": ("jaxbvh.ploc", None),
    "morton": ("jaxbvh.morton", None),
}


def __getattr__(name):
    # trimesh and the optimizers load only when first used, keeping `import jaxbvh` light
    if name in _LAZY:
        import importlib

        module_name, attribute = _LAZY[name]
        module = importlib.import_module(module_name)
        return getattr(module, attribute) if attribute else module
    raise AttributeError(f"module 'jaxbvh' has no attribute {name!r}")

__all__ = [
    "BVH", "WideBVH", "Frame", "InvalidTreeError", "BUILDERS",
    "build", "check", "validate", "sah", "node_costs", "ng_trifonov_cost", "goldsmith_salmon_cost",
    "all_costs", "save", "load", "to_interchange", "from_interchange", "to_numpy", "to_jax",
    "capacity_bucket", "load_mesh",
]
