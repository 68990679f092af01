"""The tree: its array layout, costs, invariants, files and the small passes every method shares.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``layout``         :class:`BVH`, :class:`WideBVH` and their array layout (documented
                   there, once), capacity buckets, padding
``interchange``    ``.npz`` files other libraries read: :func:`save`, :func:`load`
``frame``          :class:`Frame`, the scene-relative coordinates trees are built in
``validate``       the invariants: :func:`check`, :func:`validate`
``cost``           SAH and the papers' costs for every node (twin: ``cost_reference``)
``refit``          interior boxes as the union of their children
``split_axes``     Kensler's final pass: split axes and child order
``batching``       trees stacked along a leading axis
``walks``          host-side walks (post-order) the NumPy twins share
``targets``        cost targets: the SAH constants, leaf limit and width of a tracer
=================  =====================================================================
"""

from jaxbvh.tree.batching import stack_trees, unstack_trees
from jaxbvh.tree.cost import all_costs, goldsmith_salmon_cost, ng_trifonov_cost, node_costs, sah
from jaxbvh.tree.frame import Frame
from jaxbvh.tree.interchange import INTERCHANGE_KEYS, compact, from_interchange, load, save, to_interchange
from jaxbvh.tree.layout import (
                                BVH,
                                WideBVH,
                                capacity_bucket,
                                concat_ranges,
                                depth,
                                node_count,
                                pad_rows,
                                pad_to,
                                prim_total,
                                real_nodes,
                                to_jax,
                                to_numpy,
)
from jaxbvh.tree.refit import refit_boxes
from jaxbvh.tree.split_axes import assign_split_axes, split_axis_rule
from jaxbvh.tree.validate import InvalidTreeError, check, few_ids, validate

__all__ = [
    "BVH", "WideBVH", "Frame", "InvalidTreeError", "INTERCHANGE_KEYS",
    "capacity_bucket", "concat_ranges", "depth", "node_count", "pad_rows", "pad_to", "prim_total",
    "real_nodes", "to_jax", "to_numpy", "compact", "from_interchange", "load", "save",
    "to_interchange", "check", "few_ids", "validate", "all_costs", "goldsmith_salmon_cost",
    "ng_trifonov_cost", "node_costs", "sah", "refit_boxes", "assign_split_axes", "split_axis_rule",
    "stack_trees", "unstack_trees",
]
