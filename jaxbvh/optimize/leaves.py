"""Merging subtrees into leaves: the exact bottom-up pass (issue 40).

Every interior node ``n`` whose subtree holds ``N(n) <= max_leaf`` primitives may become
one leaf of those primitives. With the best cost of every subtree

    ``C*(n) = min(Ci N(n), Ct + (A_L C*(L) + A_R C*(R)) / A)``   (the leaf only where ``N(n) <= max_leaf``)
    ``C*(leaf) = Ci N(leaf)``

(zero-area nodes weight their children 1, as :mod:`jaxbvh.tree.cost` does), a node is
*merged* where the leaf is strictly cheaper. Merging the topmost merged nodes gives the
tree of lowest SAH among those that keep this tree's topology above its leaves: the
minimum is taken independently at every node, bottom-up, so it is exact (no greedy
choice). The tree's SAH never rises; with ``max_leaf`` 1 nothing can merge.

In JAX the bottom-up minimum and the top-down "inside a merged subtree" flags are
level-by-level sweeps over all nodes at once (each finishes one more level; they stop at
the fixpoint, height + 1 sweeps), as :func:`jaxbvh.tree.cost.node_costs` does. The
merged tree keeps the node ids and capacity; the nodes under a merged node become
padding. When anything merges, ``prim_index`` is laid out again in depth-first order
(left before right, each leaf's run in its old order), so each merged leaf's run is the
runs of the leaves it replaces, concatenated (a triangle that several of them reference,
after spatial splits, kept once: the decision counted every reference, so the SAH only
falls further); when nothing merges the tree is returned unchanged. The NumPy twin (:mod:`jaxbvh.optimize.leaves_reference`) follows the
definition by recursion; the two are equal (``tests/optimize/test_leaves.py``).

Float rule: areas are half-areas scaled by the root's power of two
(:func:`jaxbvh.numerics.extent_scale`), costs are in the tree's dtype, the same
expressions in the same order in both versions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.numerics import extent_scale, half_area
from jaxbvh.program_store import stored_jit


def subtree_costs(tree, max_leaf, ct, ci):
    """``(count, best, merge)``: primitives under every node [N] int32, the best cost
    ``C*`` [N] (tree dtype; padding: ``Ct``) and whether the node is merged [N] bool
    (module docstring). ``max_leaf`` [] int32, ``ct``, ``ci`` [] in the tree's dtype."""
    cap = tree.left.shape[0]
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    area = half_area(tree.lo, tree.hi, scale)
    dtype = area.dtype
    ct, ci = jnp.asarray(ct, dtype), jnp.asarray(ci, dtype)
    interior = tree.left >= 0
    left, right = jnp.where(interior, tree.left, 0), jnp.where(interior, tree.right, 0)
    a_l, a_r = area[left], area[right]
    positive = area > 0
    own = jnp.where(positive, area, 1)

    def sweep(carry):
        count, best, _ = carry
        n = jnp.where(interior, count[left] + count[right], tree.prim_count)
        keep = ct + jnp.where(positive, (a_l * best[left] + a_r * best[right]) / own, best[left] + best[right])
        as_leaf = ci * n.astype(dtype)
        merge = interior & (n <= max_leaf) & (as_leaf < keep)
        return n, jnp.where(interior & ~merge, keep, as_leaf), merge

    def cond(c):
        (count, best, _), (count0, best0, _), i = c
        return (jnp.any(count != count0) | jnp.any(best != best0)) & (i <= cap)

    def body(c):
        now, _, i = c
        return sweep(now), now, i + 1

    start = (tree.prim_count, jnp.where(interior, ct, ci * tree.prim_count.astype(dtype)),
             jnp.zeros(cap, bool))
    out, _, _ = jax.lax.while_loop(cond, body, (sweep(start), start, jnp.int32(0)))
    return out


def _top_down(tree, count, merge):
    """``(hidden, offset, top)``: whether a proper ancestor is merged [N] bool, the first
    slot of every node's primitives in depth-first order [N] int32 (left before right), and
    the topmost merged ancestor of every hidden node [N] int32 (-1 for the others)."""
    cap = tree.left.shape[0]
    parent = tree.parent
    has_parent = parent >= 0
    p = jnp.where(has_parent, parent, 0)
    is_right = has_parent & (tree.right[p] == jnp.arange(cap))
    before = jnp.where(is_right, count[jnp.where(is_right, tree.left[p], 0)], 0)

    def sweep(carry):
        hidden, offset, top = carry
        inside = has_parent & (hidden[p] | merge[p])
        return (inside, jnp.where(has_parent, offset[p] + before, 0),
                jnp.where(inside, jnp.where(hidden[p], top[p], p), -1))

    def cond(c):
        now, old, i = c
        return jnp.any(jnp.stack([jnp.any(a != b) for a, b in zip(now, old)])) & (i <= cap)

    def body(c):
        now, _, i = c
        return sweep(now), now, i + 1

    start = (jnp.zeros(cap, bool), jnp.zeros(cap, jnp.int32), jnp.full(cap, -1, jnp.int32))
    out, _, _ = jax.lax.while_loop(cond, body, (sweep(start), start, jnp.int32(0)))
    return out


def _merged(tree, count, merge, max_leaf):
    cap, slots = tree.left.shape[0], tree.prim_index.shape[0]
    hidden, offset, top = _top_down(tree, count, merge)
    real = (tree.left >= 0) | (tree.prim_count > 0)
    kept = real & ~hidden
    inner = kept & ~merge & (tree.left >= 0)
    leaf = kept & ((tree.prim_count > 0) | merge)
    # slot -> the old leaf whose run holds it: run starts marked, carried forward
    old_leaf = real & (tree.prim_count > 0)
    ids = jnp.arange(cap, dtype=jnp.int32)
    start_at = jnp.full(slots, -1, jnp.int32).at[jnp.where(old_leaf, tree.prim_start, slots)].set(ids, mode="drop")
    last_start = jax.lax.cummax(jnp.where(start_at >= 0, jnp.arange(slots, dtype=jnp.int32), -1))
    owner = jnp.where(last_start >= 0, start_at[jnp.maximum(last_start, 0)], 0)
    k = jnp.arange(slots, dtype=jnp.int32) - tree.prim_start[owner]
    used = (last_start >= 0) & (k < tree.prim_count[owner])
    dest = jnp.where(used, offset[owner] + k, slots)
    laid = jnp.full(slots, -1, tree.prim_index.dtype).at[dest].set(tree.prim_index, mode="drop")
    # a triangle referenced by several merged leaves (spatial splits) is kept once in the
    # new leaf: a slot repeating an earlier slot of its run (at most max_leaf back) goes
    new_leaf = jnp.where(top[owner] >= 0, top[owner], owner)
    run_start = jnp.full(slots, slots, jnp.int32).at[dest].set(offset[new_leaf], mode="drop")
    here = jnp.arange(slots, dtype=jnp.int32)

    def repeats(j, dup):
        back = jnp.maximum(here - j, 0)
        return dup | ((here - j >= run_start) & (laid[back] == laid) & (laid >= 0))

    dup = jax.lax.fori_loop(1, jnp.minimum(max_leaf, slots), repeats, jnp.zeros(slots, bool))
    gone = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum(dup.astype(jnp.int32))])  # [slots + 1]
    prim_index = jnp.full(slots, -1, laid.dtype).at[jnp.where(dup, slots, here - gone[:-1])].set(laid, mode="drop")
    start = jnp.clip(offset, 0, slots)
    end = jnp.clip(offset + count, 0, slots)
    inf = jnp.asarray(jnp.inf, tree.lo.dtype)
    return tree.replace(
        left=jnp.where(inner, tree.left, -1), right=jnp.where(inner, tree.right, -1),
        parent=jnp.where(kept, tree.parent, -1),
        lo=jnp.where(kept[:, None], tree.lo, inf), hi=jnp.where(kept[:, None], tree.hi, -inf),
        prim_start=jnp.where(leaf, offset - gone[start], 0),
        prim_count=jnp.where(leaf, count - (gone[end] - gone[start]), 0),
        axis=jnp.where(inner, tree.axis, -1), prim_index=prim_index)


@stored_jit
def merge_leaves(tree, max_leaf, ct, ci):
    """The pass on a :class:`~jaxbvh.tree.layout.BVH` of JAX arrays (module docstring):
    every subtree of at most ``max_leaf`` [] int32 primitives whose leaf costs less
    (SAH with ``ct``, ``ci`` [] in the tree's dtype) is one leaf. Traceable; the same
    capacity; the tree itself when nothing merges."""
    count, _, merge = subtree_costs(tree, max_leaf, ct, ci)
    return jax.lax.cond(jnp.any(merge), lambda t: _merged(t, count, merge, max_leaf), lambda t: t, tree)
