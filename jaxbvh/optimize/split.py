"""Splitting leaves into one-primitive leaves, so that the optimizers move primitives (issue 40).

The optimizers (rotations, reinsertion, treelets) move subtrees; a leaf is one subtree to
them, its box all they see. A leaf of several primitives that the builder chose keeps them
together for ever. :func:`split_leaves` makes every such leaf a binary subtree of
one-primitive leaves, from the primitives' boxes; the optimizers then move single
primitives, and the exact bottom-up merge (:mod:`jaxbvh.optimize.leaves`) makes leaves
again wherever one is cheaper. Together the two let the optimizers change leaves both ways.

The split
=========
In rounds, while a leaf holds several primitives, every such leaf at once:

1. its primitives' boxes, clipped to the leaf's box (a spatial split's reference is the part
   of a triangle inside its leaf; with whole primitives the clip changes nothing);
2. the axis of the largest extent of their centres (the first of equal ones); its run of
   ``prim_index`` sorted by centre along it (stable: equal centres keep their order);
3. the cut of the sorted run of the binned-free SAH sweep, lowest ``A(left) N(left) +
   A(right) N(right)`` over the ``count - 1`` cuts (half-areas scaled by the root's power of
   two, as :mod:`jaxbvh.tree.cost`; the first of equal costs);
4. the leaf becomes an interior node (its box and id kept, ``axis`` the sort axis) whose
   children are two new leaves, the runs before and after the cut, each boxed by its
   primitives' clipped boxes. Leaf ``r`` of the round (by ascending node id) takes the free
   ids ``2r`` and ``2r + 1`` in ascending order (free: neither linked nor the root).

A leaf of ``k`` primitives becomes ``2k - 1`` nodes, so a tree of ``P`` references fits in
``2P - 1``: our builders' capacity (``N = 2P``). A smaller capacity splits the leaves of
lowest id while free ids last and reports ``overflow`` (the others stay whole: still a
valid tree). Rounds: ``ceil(log2(largest leaf))`` when the cuts halve, at most the largest
leaf minus one.

Exactness: the SAH of the split tree is not lower (the sweep is greedy); it is a start for
the optimizers, which then see every primitive. Sorting, the sweep's boxes (min/max) and
the cut's costs are the NumPy twin's (:mod:`jaxbvh.optimize.split_reference`) expressions;
the two are equal (``tests/optimize/test_split.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.numerics import extent_scale, half_area, rounded
from jaxbvh.program_store import stored_jit


def _segmented_boxes(lo, hi, offset, longest):
    """Running box of each segment [S, 3] x 2: the union of the boxes from the segment's
    first slot to this one; ``offset`` [S] int32: slots since the segment's first,
    ``longest`` [] int32: the longest segment. Hillis-Steele doubling in a loop
    (``log2(longest)`` sweeps: a small program, where an associative scan unrolls its levels)."""
    slots = lo.shape[0]
    here = jnp.arange(slots, dtype=jnp.int32)

    def body(carry):
        run_lo, run_hi, d = carry
        take = offset >= d
        back = jnp.maximum(here - d, 0)
        run_lo = jnp.where(take[:, None], jnp.minimum(run_lo, run_lo[back]), run_lo)
        run_hi = jnp.where(take[:, None], jnp.maximum(run_hi, run_hi[back]), run_hi)
        return run_lo, run_hi, 2 * d

    run_lo, run_hi, _ = jax.lax.while_loop(lambda c: c[2] < longest, body, (lo, hi, jnp.int32(1)))
    return run_lo, run_hi


def _owners(tree, leaf):
    """``owner`` [S] int32: the leaf whose run holds each slot; ``used`` [S] bool."""
    cap, slots = tree.left.shape[0], tree.prim_index.shape[0]
    ids = jnp.arange(cap, dtype=jnp.int32)
    here = jnp.arange(slots, dtype=jnp.int32)
    start_at = jnp.full(slots, -1, jnp.int32).at[jnp.where(leaf, tree.prim_start, slots)].set(ids, mode="drop")
    last_start = jax.lax.cummax(jnp.where(start_at >= 0, here, -1))
    owner = jnp.where(last_start >= 0, start_at[jnp.maximum(last_start, 0)], 0)
    used = (last_start >= 0) & (here - tree.prim_start[owner] < tree.prim_count[owner])
    return owner, used


def _split_round(tree, prim_lo, prim_hi, scale):
    """One round (module docstring): every leaf of several primitives split once, while
    free ids last. ``(tree, overflow)``."""
    cap, slots = tree.left.shape[0], tree.prim_index.shape[0]
    dtype = tree.lo.dtype
    ids = jnp.arange(cap, dtype=jnp.int32)
    here = jnp.arange(slots, dtype=jnp.int32)
    leaf = (tree.left < 0) & (tree.prim_count > 0)
    real = (tree.left >= 0) | leaf | (ids == tree.root)
    free = ~real
    big = leaf & (tree.prim_count > 1)
    rank = jnp.cumsum(big.astype(jnp.int32)) - 1
    n_free = jnp.sum(free.astype(jnp.int32))
    fits = big & (2 * rank + 1 < n_free)
    free_ids = jnp.nonzero(free, size=cap, fill_value=0)[0].astype(jnp.int32)
    kid_l = free_ids[jnp.clip(2 * rank, 0, cap - 1)]
    kid_r = free_ids[jnp.clip(2 * rank + 1, 0, cap - 1)]

    # 1-2: clipped boxes, the axis of each leaf, its run sorted by centre
    owner, used = _owners(tree, leaf)
    prim = jnp.clip(tree.prim_index, 0, prim_lo.shape[0] - 1)
    splitting = used & fits[owner]
    blo = jnp.maximum(prim_lo[prim].astype(dtype), tree.lo[owner])
    bhi = jnp.minimum(prim_hi[prim].astype(dtype), tree.hi[owner])
    centre = blo + bhi
    inf = jnp.asarray(jnp.inf, dtype)
    c_lo = jnp.full((cap, 3), inf).at[jnp.where(splitting, owner, cap)].min(centre, mode="drop")
    c_hi = jnp.full((cap, 3), -inf).at[jnp.where(splitting, owner, cap)].max(centre, mode="drop")
    axis = jnp.argmax(c_hi - c_lo, axis=1).astype(jnp.int32)
    key = jnp.where(splitting, jnp.take_along_axis(centre, axis[owner][:, None], axis=1)[:, 0], 0)
    # runs stay where they are: slots of a run share its start, other slots keep their own
    run_key = jnp.where(used, tree.prim_start[owner], here)
    order = jnp.lexsort((here, key, run_key))
    prim_index, blo, bhi = tree.prim_index[order], blo[order], bhi[order]

    # 3: the sweep's cut; j = slots of the left half
    start = tree.prim_start[owner]
    count = tree.prim_count[owner]
    k = here - start + 1  # slots up to and including this one
    longest = jnp.max(jnp.where(fits, tree.prim_count, 1))
    left_lo, left_hi = _segmented_boxes(blo, bhi, jnp.where(splitting, k - 1, 0), longest)
    right_lo, right_hi = _segmented_boxes(blo[::-1], bhi[::-1], jnp.where(splitting, count - k, 0)[::-1], longest)
    # the right half of the cut after this slot starts at the next slot
    right_lo = jnp.concatenate([right_lo[::-1][1:], jnp.full((1, 3), inf)])
    right_hi = jnp.concatenate([right_hi[::-1][1:], jnp.full((1, 3), -inf)])
    cost = (rounded(half_area(left_lo, left_hi, scale) * k.astype(dtype))
            + rounded(half_area(right_lo, right_hi, scale) * (count - k).astype(dtype)))
    cut_slot = splitting & (k < count)
    cost = jnp.where(cut_slot, cost, inf)
    best = jnp.full(cap, inf).at[jnp.where(cut_slot, owner, cap)].min(cost, mode="drop")
    first_best = cut_slot & (cost == best[owner])
    j = jnp.full(cap, slots, jnp.int32).at[jnp.where(first_best, owner, cap)].min(k, mode="drop")
    # each half's box: the running boxes at the cut
    at_cut = first_best & (k == j[owner])
    where = jnp.where(at_cut, owner, cap)
    l_lo = jnp.zeros((cap, 3), dtype).at[where].set(left_lo, mode="drop")
    l_hi = jnp.zeros((cap, 3), dtype).at[where].set(left_hi, mode="drop")
    r_lo = jnp.zeros((cap, 3), dtype).at[where].set(right_lo, mode="drop")
    r_hi = jnp.zeros((cap, 3), dtype).at[where].set(right_hi, mode="drop")

    # 4: the new links (each split leaf scatters to its two kids)
    kids = jnp.concatenate([jnp.where(fits, kid_l, cap), jnp.where(fits, kid_r, cap)])
    both = lambda a, b: jnp.concatenate([a, b])  # noqa: E731
    s = tree.prim_start
    parent = tree.parent.at[kids].set(both(ids, ids), mode="drop")
    lo = tree.lo.at[kids].set(both(l_lo, r_lo), mode="drop")
    hi = tree.hi.at[kids].set(both(l_hi, r_hi), mode="drop")
    prim_start = jnp.where(fits, 0, s).at[kids].set(both(s, s + j), mode="drop")
    prim_count = jnp.where(fits, 0, tree.prim_count).at[kids].set(both(j, tree.prim_count - j), mode="drop")
    left = jnp.where(fits, kid_l, tree.left).at[kids].set(-1, mode="drop")
    right = jnp.where(fits, kid_r, tree.right).at[kids].set(-1, mode="drop")
    axis = jnp.where(fits, axis, tree.axis).at[kids].set(-1, mode="drop")
    out = tree.replace(left=left, right=right, parent=parent, lo=lo, hi=hi, prim_start=prim_start,
                       prim_count=prim_count, axis=axis, prim_index=prim_index)
    return out, jnp.any(big & ~fits)


@stored_jit
def split_leaves(tree, prim_lo, prim_hi):
    """``(tree, overflow)``: every leaf of several primitives of ``tree`` (a
    :class:`~jaxbvh.tree.layout.BVH` of JAX arrays) made a binary subtree of
    one-primitive leaves (module docstring). ``prim_lo``, ``prim_hi``: [n, 3] boxes of
    the primitives that ``prim_index`` names. The same capacity; ``overflow`` [] bool:
    free ids ran out, the leaves left whole are still leaves of a valid tree."""
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])

    def more(carry):
        t, over, progress = carry
        return jnp.any((t.left < 0) & (t.prim_count > 1)) & progress

    def body(carry):
        t, over, _ = carry
        before = jnp.sum((t.left >= 0).astype(jnp.int32))
        t, overflow = _split_round(t, prim_lo, prim_hi, scale)
        return t, over | overflow, jnp.sum((t.left >= 0).astype(jnp.int32)) > before

    out, overflow, _ = jax.lax.while_loop(more, body, (tree, jnp.bool_(False), jnp.bool_(True)))
    return out, overflow
