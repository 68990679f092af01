"""Batches of trees: one pytree whose arrays gain a leading axis, every tree padded to one capacity.

:func:`stack_trees` pads each tree with inert entries (:func:`jaxbvh.tree.layout.pad_to`)
to the capacity bucket of the largest and stacks them, so that one jitted, vmapped call
runs over all of them (and the batch axis can be sharded over devices);
:func:`unstack_trees` gives the trees back, still padded.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxbvh.tree.layout import capacity_bucket, pad_to, to_numpy


def stack_trees(trees):
    """One batched :class:`BVH` from several, all padded to one capacity bucket: every
    field gains a leading axis [B] (``left`` [B, N], ``lo`` [B, N, 3], ``root`` [B]), NumPy."""
    trees = [to_numpy(t) for t in trees]
    if not trees:
        raise ValueError("stack_trees: no trees")
    nodes = capacity_bucket(max(t.left.shape[0] for t in trees))
    prims = capacity_bucket(max(t.prim_index.shape[0] for t in trees))
    padded = [pad_to(t, nodes, prims) for t in trees]
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *padded)


def unstack_trees(trees) -> list:
    """The trees of a batch (:func:`stack_trees`, :func:`optimize_batch`; fields [B, ...])
    as a list of B NumPy trees, still padded."""
    t = to_numpy(trees)
    return [jax.tree_util.tree_map(lambda a: a[i], t) for i in range(t.left.shape[0])]
