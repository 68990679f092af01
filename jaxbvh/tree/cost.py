"""Tree costs, evaluated for every node at once (jitted).

All three costs are dimensionless ratios of surface areas, so they are the same in any
frame and at any scale:

* **SAH** (Kensler 2008): ``C(n) = Ct + (S_L C_L + S_R C_R) / S`` for an interior node
  (a sum over all children for a wide node), ``C(n) = Ci * N`` for a leaf of ``N``
  primitives; the tree's cost is the root's. A zero-area node (all of its primitives in
  one point or on one line) is hit whenever a ray reaches it, so its children are
  weighted 1: ``C(n) = Ct + sum C_child``.
* **Ng & Trifonov** objective: total surface area of the interior boxes, divided by the
  root's area (the number of interior nodes when the root has zero area).
* **Goldsmith & Salmon** cost: sum over nodes of area x number of children (a leaf of
  ``N > 1`` primitives has ``N`` children, a one-primitive leaf is the primitive itself),
  divided by the root's area (the unweighted sum when the root has zero area).

Numerics. Areas are computed from box extents multiplied by a power of two chosen from
the root's largest extent, so they neither overflow (1e30 coordinates in float32) nor
underflow (1e-30), and the scaling itself is exact. Half-areas are used throughout; the
factor 2 cancels in every ratio. XLA on CPU flushes subnormal inputs to zero before any
scaling can rescue them, so :func:`all_costs` (the host entry) first scales boxes whose
root extent is small up by that power of two on the host, in NumPy, where subnormals are
exact: the costs of a tree stored at 1e-40 are those of the same tree at 1.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import extent_scale, half_area, root_exponent
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import to_jax, to_numpy


def _children(tree):
    return tree.child  # [N, k], -1 = none; BVH builds it from left/right


def _scaled_areas(tree):
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    return half_area(tree.lo, tree.hi, scale)


@stored_jit
def node_costs(tree, ct=1.0, ci=1.0):
    """SAH cost ``C(n)`` of every node [N] (padding: ``Ct``, never used).

    Evaluated bottom-up for all nodes at once: each sweep finishes one more level, and
    sweeps stop when nothing changes (height + 1 sweeps).
    """
    child = _children(tree)
    area = _scaled_areas(tree)
    dtype = area.dtype
    ct = jnp.asarray(ct, dtype)
    ci = jnp.asarray(ci, dtype)
    is_leaf = tree.prim_count > 0
    has_child = child >= 0
    child_area = jnp.where(has_child, area[jnp.maximum(child, 0)], 0)
    own_area = area[:, None]
    leaf_cost = ci * tree.prim_count.astype(dtype)

    def sweep(cost):
        child_cost = jnp.where(has_child, cost[jnp.maximum(child, 0)], 0)
        weighted = jnp.sum(child_area * child_cost, axis=1)
        unweighted = jnp.sum(child_cost, axis=1)
        interior = ct + jnp.where(own_area[:, 0] > 0, weighted / jnp.where(own_area[:, 0] > 0, own_area[:, 0], 1), unweighted)
        return jnp.where(is_leaf, leaf_cost, interior)

    def cond(state):
        cost, previous, i = state
        return jnp.any(cost != previous) & (i <= child.shape[0])

    def body(state):
        cost, _, i = state
        return sweep(cost), cost, i + 1

    start = jnp.where(is_leaf, leaf_cost, ct)
    cost, _, _ = jax.lax.while_loop(cond, body, (sweep(start), start, jnp.int32(0)))
    return cost


@stored_jit
def sah(tree, ct=1.0, ci=1.0):
    """The tree's SAH cost (the root's ``C``), a scalar in the tree's float dtype (one
    program: the root picked outside one would compile five small ones)."""
    return node_costs(tree, ct, ci)[tree.root]


@stored_jit
def ng_trifonov_cost(tree):
    """Total half-area of interior boxes / root half-area (scalar)."""
    area = _scaled_areas(tree)
    interior = jnp.any(_children(tree) >= 0, axis=1)
    root_area = area[tree.root]
    total = jnp.sum(jnp.where(interior, area, 0))
    return jnp.where(root_area > 0, total / jnp.where(root_area > 0, root_area, 1),
                     jnp.sum(interior).astype(area.dtype))


@stored_jit
def goldsmith_salmon_cost(tree):
    """Sum of area x children over nodes / root area (scalar); see module docstring."""
    area = _scaled_areas(tree)
    n_children = jnp.sum(_children(tree) >= 0, axis=1) + jnp.where(tree.prim_count > 1, tree.prim_count, 0)
    root_area = area[tree.root]
    weighted = jnp.sum(area * n_children)
    return jnp.where(root_area > 0, weighted / jnp.where(root_area > 0, root_area, 1),
                     jnp.sum(n_children).astype(area.dtype))


def _scaled_up_on_host(tree):
    """``tree`` with boxes scaled by ``2^k`` so the root's largest extent lies in [0.5, 1),
    when that needs ``k > 0`` (small boxes, possibly subnormal: module docstring); else
    unchanged. Exact: a power of two, and no coordinate can overflow (a nonzero extent is
    at least one ulp of the coordinates it spans, so they grow to at most ~2^53)."""
    t = to_numpy(tree)
    root = int(np.asarray(t.root))
    lo, hi = np.asarray(t.lo), np.asarray(t.hi)
    if not (np.isfinite(lo[root]).all() and np.isfinite(hi[root]).all()):
        return tree
    exponent = root_exponent(lo[root], hi[root])
    if exponent <= 0:
        return tree
    return dataclasses.replace(t, lo=np.ldexp(lo, exponent).astype(lo.dtype),
                               hi=np.ldexp(hi, exponent).astype(hi.dtype))


def all_costs(tree, ct=1.0, ci=1.0) -> dict[str, float]:
    """``{"sah", "ng_trifonov", "goldsmith_salmon"}`` as Python floats."""

    t = to_jax(_scaled_up_on_host(tree))
    return {
        "sah": float(sah(t, ct, ci)),
        "ng_trifonov": float(ng_trifonov_cost(t)),
        "goldsmith_salmon": float(goldsmith_salmon_cost(t)),
    }
