"""LBVH: the linear BVH of Lauterbach et al. (2009), built as Karras' (2012) radix tree (jitted).

Algorithm
=========
1. **Sort.** Every primitive gets a 64-bit key: its Morton code (30 or 63 bits, of the
   box centre on a cubic grid over the scene) with the primitive id in the low bits, so
   all keys differ and duplicate codes are ordered by id (:mod:`jaxbvh.builders.morton`). One
   sort of the keys orders the primitives along the Morton curve.
2. **Radix tree.** The tree is the binary radix tree of the sorted keys: a node is a
   run of keys sharing a prefix, split where its first differing bit changes from 0 to
   1. Karras numbers the ``n - 1`` internal nodes so that node ``i`` is the one whose
   run starts or ends at position ``i`` and finds each one independently:
   ``delta(i, j)`` is the length of the common prefix of keys ``i`` and ``j`` (``-1``
   outside ``[0, n)``); the run of node ``i`` extends in the direction ``d`` of the
   neighbour with the longer common prefix, as far as ``delta(i, .) > delta(i, i - d)``
   holds (a binary search), and splits at the last position whose prefix with ``i`` is
   longer than the run's own (a second binary search). Here every internal node does
   both searches at once, as ``log2(cap) + 1`` vectorised steps each. Comparisons of
   prefix lengths are done without counting bits: ``delta(i, j) > delta(i, k)`` exactly
   when ``key_i ^ key_j`` is below the highest set bit of ``key_i ^ key_k``.
3. **Boxes,** bottom-up: a node's box is the union of its children's, known once both
   children are. The nodes ready so far form a queue (first, the nodes whose children
   are both primitives); windows of the queue are processed in turn, and a node whose
   sibling is done enqueues its parent (when both siblings finish in the same window,
   the left one does). This is Karras' walk up from the leaves with an atomic counter
   per node, made into array steps: a window never holds a node and its parent, and
   the work is one visit per node.
4. **Leaves and layout** (:mod:`jaxbvh.builders.bottom_up`): subtrees of at most ``max_leaf``
   primitives collapse into leaves by the top-down builders' SAH test, and the tree is
   written in the :class:`~jaxbvh.tree.layout.BVH` layout.

Layout of the result: interior nodes first in Karras' order (root 0), then the leaves
in Morton order; ``axis`` is the axis of the Morton bit a node splits on (its children
are ordered along it: lower cells left), or -1 where the keys differ only in the id
(duplicate codes). Node boxes are unions of primitive boxes (min and max: exact), so
the tree is identical to that of the recursive NumPy twin
(:mod:`jaxbvh.builders.lbvh_reference`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders import morton
from jaxbvh.builders.bottom_up import Linked, to_bvh
from jaxbvh.builders.configs import LBVHConfig
from jaxbvh.numerics import exclusive_sum, take
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH

SENTINEL = np.uint64(2**64 - 1)  # key "outside [0, n)": top bit set, so its prefix with any key is empty


def _highest_bit(x):
    """``2^floor(log2 x)`` of uint64 ``x`` (0 for 0)."""
    shift = (63 - jax.lax.clz(x)).astype(jnp.uint64)
    return jnp.where(x == 0, np.uint64(0), np.uint64(1) << shift)


def radix_tree(key, n, code_len):
    """Karras' internal nodes of sorted distinct keys uint64 [cap] (first ``n`` real); x64 only.

    Returns int32 [cap] arrays for slots ``0 .. n-2``: ``left``, ``right`` (linked ids:
    ``k`` an internal slot, ``cap + p`` the leaf at position ``p``), ``first`` and
    ``count`` (the node's run of positions) and ``axis`` (of the first differing bit, or
    -1 for an id bit). Other slots hold garbage.
    """
    cap = key.shape[0]
    i = jnp.arange(cap, dtype=jnp.int32)
    padded = jnp.concatenate([jnp.full(1, SENTINEL), key, jnp.full(1, SENTINEL)])

    def key_at(j):  # positions -1 and >= cap read the sentinel; padding keys act the same
        return jnp.take(padded, jnp.clip(j + 1, 0, cap + 1), mode="clip")

    x_next = key ^ key_at(i + 1)
    x_prev = key ^ key_at(i - 1)
    # the two neighbours never share equally long prefixes with i
    d = jnp.where(x_next < x_prev, 1, -1).astype(jnp.int32)
    steps = int(cap).bit_length()

    def furthest(limit):
        """Largest m with key_i ^ key_(i + m d) < limit (the predicate holds up to m, fails after)."""
        def step(e, m):
            t = jnp.left_shift(jnp.int32(1), steps - e)
            ok = (key ^ key_at(i + (m + t) * d)) < limit
            return jnp.where(ok, m + t, m)

        return jax.lax.fori_loop(0, steps + 1, step, jnp.zeros(cap, jnp.int32))

    length = furthest(_highest_bit(jnp.where(d > 0, x_prev, x_next)))
    other = i + length * d
    x_node = key ^ key_at(other)
    split = i + furthest(_highest_bit(x_node)) * d + jnp.minimum(d, 0)
    first = jnp.minimum(i, other)
    last = jnp.maximum(i, other)
    left = jnp.where(first == split, cap + split, split)
    right = jnp.where(last == split + 1, cap + split + 1, split + 1)
    bit = jax.lax.clz(x_node).astype(jnp.int32) - 1  # first differing payload bit, from the top
    axis = jnp.where(bit < code_len, bit % 3, -1).astype(jnp.int32)
    return left, right, first, last - first + 1, axis


@partial(stored_jit, static_argnames=("bits",))
def topology(lo, hi, n, origin, scale, *, bits):
    """Steps 1 and 2 (module docstring), jitted: the sort and the radix tree.

    Call inside :func:`jaxbvh.builders.morton.x64`. ``lo``, ``hi`` [cap, 3]: padded boxes
    (first ``n`` real); ``origin``, ``scale``: from :func:`jaxbvh.builders.morton.quantization`;
    ``bits`` (static): 30 or 63. Returns int32 arrays ``(order [cap], left, right, first,
    count, axis)``, the last five [cap] over the internal slots (:mod:`jaxbvh.builders.bottom_up`).
    One compiled program per capacity and ``bits``.
    """
    key, order = morton.sort_keys(morton.keys(lo, hi, n, origin, scale, bits=bits), n)
    return (order,) + radix_tree(key, n, morton.code_length(n, bits))


def fit_boxes(left, right, n, leaf_lo, leaf_hi, *, window: int):
    """Boxes lo, hi [cap, 3] of the internal slots, bottom-up through a queue of ready nodes.

    ``left``, ``right``: linked ids (:mod:`jaxbvh.builders.bottom_up`); ``leaf_lo``, ``leaf_hi``
    [cap, 3]: boxes of the sorted positions. ``window``: nodes per step (speed only).
    """
    cap = leaf_lo.shape[0]
    nodes = 2 * cap
    none = nodes
    slot = jnp.arange(cap, dtype=jnp.int32)
    real = slot < n - 1
    left = jnp.where(real, left, none)
    right = jnp.where(real, right, none)
    parent = jnp.full(nodes, none, jnp.int32).at[left].set(slot, mode="drop").at[right].set(slot, mode="drop")
    is_left = jnp.zeros(nodes, bool).at[left].set(True, mode="drop")
    sibling = jnp.where(is_left, take(right, parent, none), take(left, parent, none))
    lo = jnp.concatenate([jnp.full((cap, 3), jnp.inf, leaf_lo.dtype), leaf_lo])
    hi = jnp.concatenate([jnp.full((cap, 3), -jnp.inf, leaf_hi.dtype), leaf_hi])
    never = jnp.iinfo(jnp.int32).max
    # done_at: the window step a node was fitted in (-1: a primitive, fitted from the start)
    done_at = jnp.concatenate([jnp.full(cap, never, jnp.int32), jnp.full(cap, -1, jnp.int32)])
    ready = real & (left >= cap) & (right >= cap)
    queue = jnp.full(cap + window, none, jnp.int32).at[jnp.where(ready, exclusive_sum(ready), cap + window)].set(
        slot, mode="drop")
    lane = jnp.arange(window, dtype=jnp.int32)
    total = jnp.maximum(n - 1, 0)

    def step(carry):
        lo, hi, done_at, queue, ids, head, tail, w = carry
        valid = lane < tail - head
        ids = jnp.where(valid, ids, none)
        kid_l = take(left, ids, none)
        kid_r = take(right, ids, none)
        box_lo = jnp.minimum(take(lo, kid_l, jnp.inf), take(lo, kid_r, jnp.inf))
        box_hi = jnp.maximum(take(hi, kid_l, -jnp.inf), take(hi, kid_r, -jnp.inf))
        lo = lo.at[ids].set(box_lo, mode="drop")
        hi = hi.at[ids].set(box_hi, mode="drop")
        done_at = done_at.at[ids].set(w, mode="drop")
        up = take(parent, ids, none)
        other = take(done_at, take(sibling, ids, none), never)
        enqueue = valid & (up < none) & ((other < w) | ((other == w) & take(is_left, ids, False)))
        # the parents, compacted, go in at the tail (what lands past them is overwritten later)
        fresh = jnp.full(window, none, jnp.int32).at[jnp.where(enqueue, exclusive_sum(enqueue), window)].set(
            up, mode="drop")
        queue = jax.lax.dynamic_update_slice(queue, fresh, (tail,))
        head = head + jnp.sum(valid, dtype=jnp.int32)
        tail = tail + jnp.sum(enqueue, dtype=jnp.int32)
        # the next window is read after the write (reading it before would make XLA copy the queue)
        return lo, hi, done_at, queue, jax.lax.dynamic_slice(queue, (head,), (window,)), head, tail, w + 1

    # every step fits at least one node while any is left, so n steps always suffice
    carry = (lo, hi, done_at, queue, queue[:window], jnp.int32(0), jnp.sum(ready, dtype=jnp.int32), jnp.int32(0))
    carry = jax.lax.while_loop(lambda c: (c[5] < total) & (c[5] < c[6]) & (c[7] < cap), step, carry)
    return carry[0][:cap], carry[1][:cap]


@partial(stored_jit, static_argnames=("window", "collapse"))
def assemble(lo, hi, n, order, left, right, first, count, axis, max_leaf, ct, ci, scale, *, window, collapse):
    """Steps 3 and 4 (module docstring), jitted: boxes bottom-up, leaves collapsed, the layout.

    ``order`` ... ``axis``: what :func:`topology` returns; ``max_leaf``, ``ct``, ``ci``,
    ``scale``: traced scalars. Static: ``window`` (:func:`window_size`, speed only) and
    ``collapse`` (``max_leaf > 1``); one compiled program per capacity and static values.
    Returns a :class:`~jaxbvh.tree.layout.BVH`.
    """
    # padding positions read padding slots
    leaf_lo, leaf_hi = jnp.take(lo, order, axis=0, mode="clip"), jnp.take(hi, order, axis=0, mode="clip")
    node_lo, node_hi = fit_boxes(left, right, n, leaf_lo, leaf_hi, window=window)
    linked = Linked(n=n, left=left, right=right, lo=node_lo, hi=node_hi, count=count, first=first,
                    axis=axis, leaf_lo=leaf_lo, leaf_hi=leaf_hi, order=order)
    return to_bvh(linked, max_leaf, ct, ci, scale, collapse=collapse)


def window_size(cap: int) -> int:
    """Queue window of the box pass: about cap / 64, within [64, 8192] (speed only)."""
    return int(min(max(cap // 64, 64), 8192))


def build(lo, hi, n, scale, config: LBVHConfig) -> BVH:
    """LBVH over padded boxes ``lo``, ``hi`` [cap, 3] (NumPy or JAX, first ``n`` real).

    ``scale``: the scene's area scale (:func:`jaxbvh.numerics.scene_scale`); ``config``:
    the knobs (``max_leaf``, ``ct``, ``ci``, ``morton_bits``; :func:`jaxbvh.build` makes
    these inputs with :func:`jaxbvh.builders.inputs.prepare`). Returns a
    :class:`~jaxbvh.tree.layout.BVH` of JAX arrays (layout: module docstring).
    """
    bits = config.morton_bits
    dtype = lo.dtype
    lo_j, hi_j = jnp.asarray(lo), jnp.asarray(hi)
    n = int(n)
    origin, grid = morton.quantization(lo_j, hi_j, n, bits)
    with morton.x64():
        order, left, right, first, count, axis = topology(lo_j, hi_j, jnp.int32(n), jnp.asarray(origin),
                                                           jnp.asarray(grid), bits=bits)
    return assemble(lo_j, hi_j, jnp.int32(n), order, left, right, first, count, axis, jnp.int32(config.max_leaf),
                   jnp.asarray(config.ct, dtype), jnp.asarray(config.ci, dtype), jnp.asarray(scale, dtype),
                   window=window_size(lo.shape[0]), collapse=config.max_leaf > 1)
