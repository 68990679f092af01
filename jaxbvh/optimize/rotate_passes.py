"""One pass of Kensler's rotations over a tree or forest: heights lowest first, windows, a queue.

Part of :mod:`jaxbvh.optimize.rotate`, whose docstring explains the passes (heights,
windows, the queue of changed nodes and the walk to their ancestors) and the forest of
annealing chains. :func:`run_pass` runs one pass; :func:`initial_state` computes the
costs and heights a run starts from; :func:`forest_of` and :func:`chain_of` put K
copies of a tree into one forest and take one back out. The windows over each height
are :mod:`jaxbvh.tree.windows`' (the loop treelet restructuring and collapsing share).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxbvh.numerics import extent_scale, half_area, none_to_oob, take
from jaxbvh.optimize.rotate_moves import State, node_cost, process_window
from jaxbvh.tree import windows as level_windows

# queue lengths up to this are walked in a narrow compiled branch (speed only)
SMALL_QUEUE = 4096


# ----------------------------------------------------------------------------------
# One pass
# ----------------------------------------------------------------------------------


def _enqueue(queue, queued, ids, cap):
    """Append the ids ``< cap`` of ``ids`` to ``queue`` (beyond its size: only counted)."""
    valid = ids < cap
    at = queued + jnp.cumsum(valid.astype(jnp.int32)) - 1
    queue = queue.at[jnp.where(valid, at, queue.shape[0])].set(ids, mode="drop")
    return queue, queued + jnp.sum(valid, dtype=jnp.int32)


def _ancestor_list(st, width, size):
    """The queued nodes and all their ancestors, each once, as a list [size] (``N``: none).

    A walk up the parent links from the first ``width`` queue entries (all of them must
    be there); a node reached by several walks continues only one of them. Returns the
    list, its used length and whether it overflowed ``size`` (then it is incomplete).
    """
    cap = st.child.shape[0]
    mark = jnp.zeros(cap, jnp.int32)  # 0: not listed; else the walk (slot) that listed it

    def claim(mark, ids):
        """Each id not listed yet is listed by one of the walks that reach it."""
        slots = jnp.arange(1, ids.shape[0] + 1, dtype=jnp.int32)
        fresh = take(mark, ids, 1) == 0
        ids = jnp.where(fresh, ids, cap)
        mark = mark.at[ids].set(slots, mode="drop")
        return mark, jnp.where(take(mark, ids, 0) == slots, ids, cap)

    def cond(carry):
        return jnp.any(carry[1] < cap) & (carry[3] <= size)

    def body(carry):  # list the ids not listed yet; then step up to their parents
        mark, ids, listed, used = carry
        mark, ids = claim(mark, ids)
        listed, used = _enqueue(listed, used, ids, cap)
        return mark, none_to_oob(take(st.parent, ids, -1), cap), listed, used

    # the queued nodes go through the same body as the ancestors (one compiled copy of
    # the enqueue, whose scan is most of the walk's compile time)
    start = (mark, none_to_oob(st.queue[:width], cap), jnp.full(size, cap, jnp.int32), jnp.int32(0))
    _, _, listed, used = jax.lax.while_loop(cond, body, start)
    return listed, jnp.minimum(used, size), used > size


def _visit_order(st, interior, everything):
    """Nodes to visit in a pass, sorted by height: ``(order, heights, count)``, each [N].

    The nodes are the queued ones (subtree changed in the last pass) and their
    ancestors, or all interior nodes when ``everything`` or when the queue or the
    ancestor list (four times the queue) overflowed. A superset is always safe: a node
    whose subtree did not change chooses "no move" again. Entries past ``count`` hold ``N``
    (no node) and a huge height; holes (``N``) may also sit inside the first ``count``.
    """
    cap = st.child.shape[0]
    big = jnp.int32(2 ** 31 - 1)
    capacity = st.queue.shape[0]

    def full(_):
        order, keys = _sorted_by_height(jnp.arange(cap, dtype=jnp.int32), st.height, interior)
        return (jnp.where(order >= 0, order, cap), keys,
                jnp.sum(interior, dtype=jnp.int32))

    def listed(width):
        size = min(4 * width, cap)

        def walk(_):
            ids, used, overflow = _ancestor_list(st, width, size)
            valid = ids < cap
            keys = jnp.where(valid, take(st.height, ids, 0), big)
            keys, order = jax.lax.sort((keys, ids), num_keys=1)
            pad = cap - size
            return (jnp.concatenate([order, jnp.full(pad, cap, jnp.int32)]),
                    jnp.concatenate([keys, jnp.full(pad, big, jnp.int32)]), used, overflow)

        return walk

    def skip(_):  # no walk: visit every node
        return (jnp.full(cap, cap, jnp.int32), jnp.full(cap, big, jnp.int32), jnp.int32(0),
                jnp.bool_(True))

    # walks cost (queue size x height) whatever the queue holds, so a short queue walks
    # in a small size; each size is one more compiled branch. The full visit (also taken
    # when a walk's list overflowed) is one branch after the walks, so it is compiled
    # once, not once per walk
    widths = _walk_widths(capacity)
    branches = [skip] + [listed(w) for w in widths]
    pick = jnp.where(everything | (st.queued > capacity), 0,
                     1 + jnp.sum(st.queued > jnp.asarray(widths[:-1]), dtype=jnp.int32))
    order, keys, used, overflow = jax.lax.switch(pick, branches, None)
    return jax.lax.cond(overflow, full, lambda _: (order, keys, used), None)


def _walk_widths(capacity):
    """Queue lengths the ancestor walk is compiled for (the last is the whole queue)."""
    small = min(SMALL_QUEUE, capacity)
    return (small, capacity) if small < capacity else (capacity,)


def _collect_moved(log, count, capacity, cap):
    """The ids in ``log`` (``N``: none) as a queue [capacity] (there must be no more).

    Only the first ``count`` entries can hold ids; the scan covers the shortest of a few
    compiled lengths that reaches ``count`` (the list lengths of the walks, or all), so
    after a short pass this costs little.
    """
    lengths = sorted({min(4 * w, log.shape[0]) for w in _walk_widths(capacity)} | {log.shape[0]})

    def scan(length):
        def run(_):
            # a sort puts the ids (< N) first; on CPU much faster than nonzero (a
            # prefix sum and a scatter)
            part = jnp.sort(log[:length].reshape(-1))[:capacity]
            return jnp.concatenate([part, jnp.full(capacity - part.shape[0], cap, jnp.int32)])
        return run

    pick = jnp.sum(count > jnp.asarray(lengths[:-1]), dtype=jnp.int32)
    return jax.lax.switch(pick, [scan(n) for n in lengths], None)


def _sorted_by_height(ids, height, valid):
    """``ids`` sorted by ``height`` (``valid`` only; the rest last), and the sorted heights.

    One sort of a packed ``height << bits | position`` key (much faster than an argsort
    on CPU); when some height does not fit the packed key, an argsort instead.
    """
    size = ids.shape[0]
    bits = max(1, int(size).bit_length())
    top = (1 << (32 - bits)) - 1  # key of invalid entries; heights must stay below it
    big = jnp.int32(2 ** 31 - 1)
    fits = jnp.max(jnp.where(valid, height, 0)) < top

    def packed(_):
        key = jnp.where(valid, height, top).astype(jnp.uint32)
        packed = jnp.sort((key << bits) | jnp.arange(size, dtype=jnp.uint32))
        pos = (packed & ((1 << bits) - 1)).astype(jnp.int32)
        return pos

    def argsort(_):
        return jnp.argsort(jnp.where(valid, height, big), stable=True).astype(jnp.int32)

    if bits >= 31:
        pos = argsort(None)
    else:
        pos = jax.lax.cond(fits, packed, argsort, None)
    ok = valid[pos]
    return jnp.where(ok, ids[pos], -1), jnp.where(ok, height[pos], big)


def run_pass(st, interior, scale, ct, min_gain, temperature, draws, collect=True, *, annealing,
          windows, chains=1):
    """One pass over the tree (or forest); returns the new state and moves per chain [chains].

    ``collect`` (traced bool): queue the nodes this pass changed for the next pass
    (pointless when that pass visits every node anyway).

    Heights are processed lowest first; a height's nodes go through windows of the
    largest size in ``windows`` while that many remain, then the next size down.
    """
    cap = st.child.shape[0]
    windows = tuple(sorted({min(w, cap) for w in windows}, reverse=True))
    everything = temperature > 0 if annealing else jnp.bool_(False)
    order, keys, count = _visit_order(st, interior, everything)
    order = jnp.concatenate([order, jnp.full(windows[0], cap, jnp.int32)])
    # log[p]: the node at order[p] if it moved and the children its move changed, else N
    # (written a window at a time; a scatter into a compacted queue per window cost
    # more than the moves themselves)
    log = jnp.full(order.shape + (3,), cap, jnp.int32)

    def visit(carry, start, valid):
        st, log, moves = carry
        nodes = jnp.where(valid, jax.lax.dynamic_slice(order, (start,), (valid.shape[0],)), cap)
        st, made, moved = process_window(st, nodes, scale, ct, min_gain, temperature, draws,
                                         annealing, chains)
        log = jax.lax.dynamic_update_slice(log, moved, (start, jnp.int32(0)))
        return st, log, moves + made

    moves = jnp.zeros(chains, jnp.int32)
    st, log, moves = level_windows.by_runs(visit, (st, log, moves), keys, count, windows)
    capacity = st.queue.shape[0]
    queued = 3 * jnp.sum(moves, dtype=jnp.int32)
    # no queue is needed when it overflows or the next pass visits everything anyway
    queue = jax.lax.cond(collect & (queued <= capacity),
                         lambda: _collect_moved(log, count, capacity, cap), lambda: st.queue)
    return st._replace(queue=queue, queued=jnp.where(collect, queued, capacity + 1)), moves


# ----------------------------------------------------------------------------------
# Initial state, forests of chains
# ----------------------------------------------------------------------------------


def initial_state(tree, ct, ci):
    """Scale and optimizer state of ``tree``: costs and heights by bottom-up sweeps."""
    dtype = tree.lo.dtype
    ct = jnp.asarray(ct, dtype)
    ci = jnp.asarray(ci, dtype)
    cap = tree.left.shape[0]
    child = jnp.stack([tree.left, tree.right], axis=1).astype(jnp.int32)
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    area = half_area(tree.lo, tree.hi, scale)
    is_leaf = tree.prim_count > 0
    interior = child[:, 0] >= 0
    left, right = none_to_oob(child[:, 0], cap), none_to_oob(child[:, 1], cap)
    area_l = take(area, left, 0)
    area_r = take(area, right, 0)
    leaf_cost = ci * tree.prim_count.astype(dtype)

    def sweep(cost, height):
        cl = take(cost, left, 0)
        cr = take(cost, right, 0)
        hl = take(height, left, 0)
        hr = take(height, right, 0)
        cost = jnp.where(interior, node_cost(area, area_l, cl, area_r, cr, ct), jnp.where(is_leaf, leaf_cost, ct))
        height = jnp.where(interior, 1 + jnp.maximum(hl, hr), 0)
        return cost, height

    def cond(carry):
        return carry[2]

    def body(carry):
        cost, height, _ = carry
        new_cost, new_height = sweep(cost, height)
        return new_cost, new_height, jnp.any(new_height != height) | jnp.any(new_cost != cost)

    cost0 = jnp.where(is_leaf, leaf_cost, ct)
    height0 = jnp.zeros(cap, jnp.int32)
    cost, height, _ = jax.lax.while_loop(cond, body, (cost0, height0, jnp.bool_(True)))
    st = State(child, tree.parent.astype(jnp.int32), tree.lo, tree.hi, cost, height)
    return scale, st


def to_tree(tree, st):
    """``tree`` (a :class:`~jaxbvh.tree.layout.BVH`) with the links and boxes of the rotation
    state ``st``."""
    return tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent,
                        lo=st.lo, hi=st.hi)


def forest_of(st: State, chains: int) -> State:
    """``chains`` copies of one tree's state as one forest (ids of copy ``k`` offset by ``k N``)."""
    cap = st.child.shape[0]
    def shift(ids):  # [N, ...] ids, -1 none -> [chains * N, ...]
        offset = (jnp.arange(chains, dtype=jnp.int32) * cap).reshape((chains,) + (1,) * ids.ndim)
        moved = jnp.where(ids[None] >= 0, ids[None] + offset, -1)
        return moved.reshape((chains * cap,) + ids.shape[1:])

    def tile(a):
        return jnp.broadcast_to(a[None], (chains,) + a.shape).reshape((chains * cap,) + a.shape[1:])

    return State(shift(st.child), shift(st.parent), tile(st.lo), tile(st.hi), tile(st.cost),
                  tile(st.height))


def chain_of(st: State, k, chains: int) -> State:
    """The tree of copy ``k`` of a forest (links and boxes; ids back to ``0 .. N-1``)."""
    cap = st.child.shape[0] // chains

    def take(a):
        return jax.lax.dynamic_index_in_dim(a.reshape((chains, cap) + a.shape[1:]), k, 0, False)

    def unshift(ids):
        ids = take(ids)
        return jnp.where(ids >= 0, ids - k * cap, -1)

    return State(unshift(st.child), unshift(st.parent), take(st.lo), take(st.hi))


def tree_part(st: State) -> State:  # what keep_best keeps: links and boxes
    """The links and boxes of ``st`` (``child``, ``parent``, ``lo``, ``hi``), what
    ``keep_best`` keeps."""
    return State(st.child, st.parent, st.lo, st.hi)


