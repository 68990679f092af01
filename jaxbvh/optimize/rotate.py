"""Tree rotations (Kensler 2008): hill climbing and simulated annealing, scored in parallel.

The moves
=========
At an interior node ``n`` with children ``L``, ``R`` and grandchildren ``LL``, ``LR``
(of ``L``) and ``RL``, ``RR`` (of ``R``) there are six moves, always in this order::

    0: L <-> RL    1: L <-> RR    2: R <-> LL    3: R <-> LR    4: LL <-> RL    5: LL <-> RR

Each one swaps the contents of two child *slots* (``child[n, 0]`` is the slot of ``L``,
``child[R, 0]`` that of ``RL``, ...), so node ids never change and the untouched child
keeps its slot. Rotations need the grandchild to exist; swaps need both children
interior. A move changes the boxes of ``n``'s children only, never ``n``'s own box, so
its effect on the tree's SAH has the sign of its effect on ``n``'s own cost ``C(n)``
(:mod:`jaxbvh.tree.cost`), which is computed in O(1) from the children's and grandchildren's
areas and costs. :func:`score_moves` does that for all six moves of every node in one
vectorised call.

Passes
======
A pass visits interior nodes children first and, at each, recomputes ``C(n)`` and
applies one move (or none). A move at ``n`` reads and writes only ``n``'s subtree, so
nodes of equal *height* (longest path to a leaf, measured when the pass starts) have
disjoint subtrees and can be processed at once; processing heights lowest first gives
exactly the tree the sequential post-order visit gives (:mod:`jaxbvh.optimize.rotate_reference`).
Each height is processed in windows of a few fixed sizes, so a pass costs work
proportional to the nodes it visits, not ``nodes x height``.

Only nodes whose subtree changed since they last chose "no move" can choose differently
(the choice at a node that finds no improving move is the same at every temperature),
so after the first pass a cold pass visits just those nodes and their ancestors. Each
window logs the nodes its moves changed (the moved node and its changed children); after
the pass a sort compacts the log into a queue, and the next pass walks up from the
queued nodes to list their ancestors and sorts that list by height. Apart from filling a
few tree-sized arrays, no cold pass sorts or scans the whole tree, so its work follows
the moves made, not the tree size (when the queue or the list overflows, the pass visits
every node instead: always safe).

Several annealing chains run as one *forest* of copies of the tree (ids of copy ``k``
offset by ``k N``): a pass processes each height of all chains together.

* **Hill climbing** (:func:`hill_climb`, :data:`HILL_CLIMB`): apply the move of least cost if it lowers
  ``C(n)``; repeat passes until one makes no move.
* **Simulated annealing** (:func:`anneal`, :data:`ANNEAL`): candidates in the fixed order above are
  compared with the best found so far (initially "no move"); a better one always becomes
  the best, a worse one when a uniform ``xi`` falls below ``exp(-de / T)`` (``de`` the
  difference in ``C(n)``; never when ``T == 0``), tested as ``de < -T log(xi)``; the
  best is applied. One uniform per
  (pass, node, candidate), drawn by :func:`jaxbvh.draws.annealing_draws` and indexed by node id.
  The temperature of pass ``i`` is ``schedule(i)``, any optax-style schedule or a name
  of :data:`jaxbvh.optimize.schedules.SCHEDULES` (default Kensler's ramped sine,
  :func:`jaxbvh.optimize.schedules.kensler_schedule`); after ``steps`` passes the tree is
  quenched at ``T = 0`` until a pass makes no move.

Exactness
=========
Decisions must not hinge on the last bit: XLA may fuse multiply-adds, so two evaluations
of the same cost can differ by an ulp, and a move that leaves a box unchanged could look
like an improvement ("phantom moves", passes that never end, results that depend on the
thread count). A move counts as better only when it lowers ``C(n)`` by more than
``min_gain * C(n)`` (default ``64 * eps`` of the float type); among the improving moves
hill climbing takes the first whose cost is within that margin of the least, and
annealing counts a worse candidate within the margin as a tie (``de = 0``). The NumPy
reference uses the same rule, so both give the same tree. "No node" is the out-of-range
index ``N`` with ``mode="drop"``/``"fill"``, never ``-1`` (which would wrap).

After optimizing, :func:`~jaxbvh.tree.split_axes.assign_split_axes` (Kensler's final
pass) gives every interior node the axis along which its children are separated most
(overlap least) and orders the children along it, for front-to-back traversal.

On the optimizer protocol
=========================
Both methods are optimizers of :mod:`jaxbvh.optimize.protocol`: :data:`HILL_CLIMB`
(``"hc"``, :class:`HillClimbConfig`) and :data:`ANNEAL` (``"sa"``, :class:`AnnealConfig`).
Their ``init`` differ (:func:`init_hill_climb`, :func:`init_anneal`); they share one
:func:`step` (one pass, of every chain) and one :func:`result` (the best chain). The
state's ``inner`` (:class:`Inner`) is the forest and each chain's figures; ``params``
(:class:`Params`) the costs, the margin and Kensler's schedule numbers, traced, so
changing them does not recompile; ``static`` (:class:`Static`) the modes and work sizes.
A step leaves a done state unchanged, so :func:`optimize_batch` is ``step`` vmapped over
a batch of trees until all are done. :func:`hill_climb` and :func:`anneal` are thin
wrappers over :func:`jaxbvh.optimize.driver.run` (chunks, ``on_step``, time budget).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.draws import annealing_draws
from jaxbvh.numerics import extent_scale, half_area, none_to_oob, take
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.optimize.driver import run
from jaxbvh.optimize.protocol import (
    Optimizer,
    OptimizeResult,
    OptimizerState,
    check_config,
    check_costs,
    check_tree,
    float_dtype,
    history_length,
    keep_if_done,
    make_result,
    new_progress,
    record,
)
from jaxbvh.optimize.schedules import DEFAULT_HOTTEST, KENSLER_PERIOD, KENSLER_STEPS, SCHEDULES, kensler_temperature
from jaxbvh.tree.layout import to_jax
from jaxbvh.tree.split_axes import apply_split_axes

MOVES = ("L<->RL", "L<->RR", "R<->LL", "R<->LR", "LL<->RL", "LL<->RR")

# The two slots each move swaps, as (which node, which side). Node codes: 0 = n, 1 = L, 2 = R.
_SLOT_A = ((0, 0), (0, 0), (0, 1), (0, 1), (1, 0), (1, 0))
_SLOT_B = ((2, 0), (2, 1), (1, 0), (1, 1), (2, 0), (2, 1))
_CHANGES_L = (False, False, True, True, True, True)
_CHANGES_R = (True, True, False, False, True, True)

# Window sizes (speed only). Each size is one more compiled copy of the window step
# (~1.5 s of compile), so hill climbing (few passes) uses one; annealing (hundreds of
# passes) adds a narrow one for the sparse upper heights (2x faster on legocar), and a
# forest of K chains starts K times wider.
DEFAULT_WINDOWS = (512,)
ANNEAL_WINDOWS = (512, 64)
DEFAULT_FRONTIER = 131072  # queue of changed nodes; more in one pass: visit every node
_SMALL_QUEUE = 4096


class _State(NamedTuple):
    child: Any   # [N, 2] int32, -1 none
    parent: Any  # [N] int32
    lo: Any      # [N, 3]
    hi: Any      # [N, 3]
    cost: Any = None    # [N] C(n), kept current for every real node
    height: Any = None  # [N] int32, 0 for leaves; current for every real node
    queue: Any = None   # [Q] int32: nodes the last pass changed (moved, new children)
    queued: Any = None  # int32: at least their number (> Q: the queue overflowed)


# ----------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------




def _select(choice, options):
    """``options[choice]`` elementwise: ``options`` a list of 6 arrays [W, ...]."""
    out = options[0]
    c = choice.reshape(choice.shape + (1,) * (out.ndim - 1))
    for k in range(1, len(options)):
        out = jnp.where(c == k, options[k], out)
    return out


def node_cost(parent_area, area_a, cost_a, area_b, cost_b, ct):
    """``C(n)`` of an interior node from its two children (formula of :mod:`jaxbvh.tree.cost`)."""
    positive = parent_area > 0
    weighted = (area_a * cost_a + area_b * cost_b) / jnp.where(positive, parent_area, 1)
    return ct + jnp.where(positive, weighted, cost_a + cost_b)



# ----------------------------------------------------------------------------------
# Scoring: all six moves of a set of nodes
# ----------------------------------------------------------------------------------


class _Part(NamedTuple):
    lo: Any
    hi: Any
    area: Any
    cost: Any
    height: Any


def _gather_part(st, ids, scale):
    lo = take(st.lo, ids, jnp.inf)
    hi = take(st.hi, ids, -jnp.inf)
    return _Part(lo, hi, half_area(lo, hi, scale), take(st.cost, ids, 0), take(st.height, ids, 0))


def _combine(a: _Part, b: _Part, scale, ct) -> _Part:
    lo = jnp.minimum(a.lo, b.lo)
    hi = jnp.maximum(a.hi, b.hi)
    area = half_area(lo, hi, scale)
    return _Part(lo, hi, area, node_cost(area, a.area, a.cost, b.area, b.cost, ct),
                 1 + jnp.maximum(a.height, b.height))


def _score(st, nodes, scale, ct):
    """Scores of the six moves at ``nodes`` [W] (``N`` = no node).

    Returns a dict of [W] / [W, 6] arrays: the family ids, the current cost ``cur``,
    ``cand`` (cost of ``n`` after each move), ``legal``, the new parts of ``L`` and
    ``R`` after each move, and the new height of ``n``.
    """
    cap = st.child.shape[0]
    kids = take(st.child, nodes, -1)
    left, right = kids[:, 0], kids[:, 1]
    lk = take(st.child, left, -1)
    rk = take(st.child, right, -1)
    ll, lr, rl, rr = lk[:, 0], lk[:, 1], rk[:, 0], rk[:, 1]
    n_area = half_area(take(st.lo, nodes, jnp.inf), take(st.hi, nodes, -jnp.inf), scale)
    parts = tuple(_gather_part(st, i, scale) for i in (left, right, ll, lr, rl, rr))
    L, R, LL, LR, RL, RR = jax.lax.optimization_barrier(parts)  # gathered once (compile time)

    cur = node_cost(n_area, L.area, L.cost, R.area, R.cost, ct)

    def cost_n(a, b):
        return node_cost(n_area, a.area, a.cost, b.area, b.cost, ct), 1 + jnp.maximum(a.height, b.height)

    r0 = _combine(L, RR, scale, ct)   # 0: L <-> RL, R = (L, RR)
    r1 = _combine(RL, L, scale, ct)   # 1: L <-> RR, R = (RL, L)
    l2 = _combine(R, LR, scale, ct)   # 2: R <-> LL, L = (R, LR)
    l3 = _combine(LL, R, scale, ct)   # 3: R <-> LR, L = (LL, R)
    l4 = _combine(RL, LR, scale, ct)  # 4: LL <-> RL, L = (RL, LR), R = (LL, RR)
    r4 = _combine(LL, RR, scale, ct)
    l5 = _combine(RR, LR, scale, ct)  # 5: LL <-> RR, L = (RR, LR), R = (RL, LL)
    r5 = _combine(RL, LL, scale, ct)
    n_after = [cost_n(RL, r0), cost_n(RR, r1), cost_n(l2, LL), cost_n(l3, LR), cost_n(l4, r4),
               cost_n(l5, r5)]
    new_left = [L, L, l2, l3, l4, l5]
    new_right = [r0, r1, R, R, r4, r5]

    real = nodes < cap
    l_in, r_in = ll >= 0, rl >= 0
    interior = real & (left >= 0)
    legal = jnp.stack([r_in, r_in, l_in, l_in, l_in & r_in, l_in & r_in], axis=1) & interior[:, None]

    return dict(
        left=left, right=right, grand=(ll, lr, rl, rr), interior=interior, cur=cur,
        cand=jnp.stack([c for c, _ in n_after], axis=1),
        n_height=[h for _, h in n_after],
        cur_height=1 + jnp.maximum(L.height, R.height),
        legal=legal, new_left=new_left, new_right=new_right,
    )


def score_moves(tree, ct=1.0, ci=1.0):
    """Cost of every node before and after each of the six moves (one jitted call).

    Returns ``(current [N], after [N, 6], legal [N, 6])``: ``current`` is ``C(n)``,
    ``after[n, m]`` what ``C(n)`` becomes after move ``m`` (:data:`MOVES`), ``legal``
    whether the move exists there. Leaves and padding have no legal move.
    """
    return _score_moves(to_jax(tree), ct, ci)


@jax.jit
def _score_moves(tree, ct, ci):
    scale, st = _init(tree, ct, ci)
    s = _score(st, jnp.arange(tree.left.shape[0]), scale, jnp.asarray(ct, tree.lo.dtype))
    return s["cur"], s["cand"], s["legal"]


# ----------------------------------------------------------------------------------
# Decisions and application
# ----------------------------------------------------------------------------------


def _choose_greedy(cand, cur, legal, tol):
    """Hill climbing: the first move within ``tol`` of the least cost, if it improves."""
    improving = legal & (cand < (cur - tol)[:, None])
    least = jnp.min(jnp.where(improving, cand, jnp.inf), axis=1)
    near = improving & (cand <= (least + tol)[:, None])
    return jnp.where(jnp.any(improving, axis=1), jnp.argmax(near, axis=1), -1)


def _choose_annealing(cand, cur, legal, tol, temperature, draws):
    """Kensler's annealing rule: candidates in order against the best so far.

    ``xi < exp(-de / T)`` is evaluated as ``de < -T log(xi)``: the same test,
    with the logarithm taken once per candidate outside the sequential chain (six
    chained exponentials made XLA's compile time explode).
    """
    hot = temperature > 0
    reach = jnp.where(hot, -temperature * jnp.log(draws), -1)  # [W, 6]; -1: accept none
    best = cur
    choice = jnp.full(cur.shape, -1, jnp.int32)
    for m in range(6):
        delta = cand[:, m] - best
        # a tie within tol counts as de = 0 (always taken when hot): an ulp of noise in
        # de must not decide against a tiny reach
        excess = jnp.where(delta <= tol, 0, delta)
        accept = legal[:, m] & ((delta < -tol) | (excess < reach[:, m]))
        best = jnp.where(accept, cand[:, m], best)
        choice = jnp.where(accept, m, choice)
    return choice


def _process(st, nodes, scale, ct, min_gain, temperature, draws, annealing, chains):
    """Score ``nodes`` (disjoint subtrees), pick a move for each, apply them all.

    Returns the new state, the moves made per chain [chains] (a forest of ``chains``
    equal-capacity trees, node ``k * (N / chains) + i`` being node ``i`` of tree ``k``)
    and the nodes each move changed ([W, 3]: the node and its changed children, ``N``
    where none).
    """
    cap = st.child.shape[0]
    s = _score(st, nodes, scale, ct)
    cur, cand, legal = s["cur"], s["cand"], s["legal"]
    tol = min_gain * jnp.abs(cur)
    # materialise the scores once: otherwise XLA copies their computation into every
    # step of the choosers, and compile time triples
    cand, cur, tol = jax.lax.optimization_barrier((cand, cur, tol))
    if annealing:
        rows = take(draws, nodes, 1)
        choice = _choose_annealing(cand, cur, legal, tol, temperature, rows)
    else:
        choice = _choose_greedy(cand, cur, legal, tol)
    # materialise the choice once: it feeds every scatter below, and XLA would otherwise
    # recompute the whole choice inside several of them
    choice = jax.lax.optimization_barrier(jnp.where(s["interior"], choice, -1))
    moved = choice >= 0
    m = jnp.maximum(choice, 0)
    left, right = s["left"], s["right"]
    oob = jnp.full_like(nodes, cap)
    interior_nodes = jnp.where(s["interior"], nodes, cap)

    # swap the two slots' contents
    family = (nodes, left, right)
    a_node = _select(m, [family[a] for a, _ in _SLOT_A])
    b_node = _select(m, [family[b] for b, _ in _SLOT_B])
    a_side = _select(m, [jnp.int32(side) for _, side in _SLOT_A])
    b_side = _select(m, [jnp.int32(side) for _, side in _SLOT_B])
    a_node = jnp.where(moved, a_node, cap)
    b_node = jnp.where(moved, b_node, cap)
    # the slots' contents are ids the scoring already gathered; reading child again here
    # (or through a flat view) makes XLA copy the whole array for every window
    ll, lr, rl, rr = s["grand"]
    content = {(0, 0): left, (0, 1): right, (1, 0): ll, (1, 1): lr, (2, 0): rl, (2, 1): rr}
    a_val = jnp.where(moved, _select(m, [content[slot] for slot in _SLOT_A]), -1)
    b_val = jnp.where(moved, _select(m, [content[slot] for slot in _SLOT_B]), -1)
    child = (st.child.at[a_node, a_side].set(b_val, mode="drop")
             .at[b_node, b_side].set(a_val, mode="drop"))
    parent = st.parent.at[jnp.where(moved, b_val, cap)].set(a_node, mode="drop")
    parent = parent.at[jnp.where(moved, a_val, cap)].set(b_node, mode="drop")

    # new boxes, costs and heights of the changed children, and of n
    def pick(parts):
        return _Part(*(_select(m, list(f)) for f in zip(*parts)))

    new_l, new_r = pick(s["new_left"]), pick(s["new_right"])
    l_changes = moved & _select(m, [jnp.bool_(x) for x in _CHANGES_L])
    r_changes = moved & _select(m, [jnp.bool_(x) for x in _CHANGES_R])
    l_at = jnp.where(l_changes, left, oob)
    r_at = jnp.where(r_changes, right, oob)
    lo = st.lo.at[l_at].set(new_l.lo, mode="drop").at[r_at].set(new_r.lo, mode="drop")
    hi = st.hi.at[l_at].set(new_l.hi, mode="drop").at[r_at].set(new_r.hi, mode="drop")
    n_cost = jnp.where(moved, _select(m, [cand[:, k] for k in range(6)]), cur)
    n_height = jnp.where(moved, _select(m, s["n_height"]), s["cur_height"])
    cost = (st.cost.at[l_at].set(new_l.cost, mode="drop").at[r_at].set(new_r.cost, mode="drop")
            .at[interior_nodes].set(n_cost, mode="drop"))
    height = (st.height.at[l_at].set(new_l.height, mode="drop")
              .at[r_at].set(new_r.height, mode="drop")
              .at[interior_nodes].set(n_height, mode="drop"))
    new = st._replace(child=child, parent=parent, lo=lo, hi=hi, cost=cost, height=height)
    if chains == 1:
        per_chain = jnp.sum(moved, dtype=jnp.int32)[None]
    else:  # a one-hot sum: a scatter-add with this many collisions is slow on CPU
        chain = nodes // (cap // chains)
        per_chain = jnp.sum((chain[:, None] == jnp.arange(chains)) & moved[:, None], axis=0,
                            dtype=jnp.int32)
    return new, per_chain, jnp.stack([jnp.where(moved, nodes, cap), l_at, r_at], axis=1)


# ----------------------------------------------------------------------------------
# One pass
# ----------------------------------------------------------------------------------


def _enqueue(queue, queued, ids, cap):
    """Append the ids ``< cap`` of ``ids`` to ``queue`` (beyond its size: only counted)."""
    valid = ids < cap
    # associative_scan rather than jnp.cumsum: about 2x faster on CPU (measured)
    at = queued + jax.lax.associative_scan(jnp.add, valid.astype(jnp.int32)) - 1
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

    def body(carry):
        mark, ids, listed, used = carry
        up = none_to_oob(take(st.parent, ids, -1), cap)
        mark, up = claim(mark, up)
        listed, used = _enqueue(listed, used, up, cap)
        return mark, up, listed, used

    mark, ids = claim(mark, none_to_oob(st.queue[:width], cap))
    listed, used = _enqueue(jnp.full(size, cap, jnp.int32), jnp.int32(0), ids, cap)
    _, _, listed, used = jax.lax.while_loop(cond, body, (mark, ids, listed, used))
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

            def from_list(_):
                valid = ids < cap
                keys = jnp.where(valid, take(st.height, ids, 0), big)
                keys, order = jax.lax.sort((keys, ids), num_keys=1)
                pad = cap - size
                return (jnp.concatenate([order, jnp.full(pad, cap, jnp.int32)]),
                        jnp.concatenate([keys, jnp.full(pad, big, jnp.int32)]), used)

            return jax.lax.cond(overflow, full, from_list, None)

        return walk

    # walks cost (queue size x height) whatever the queue holds, so a short queue walks
    # in a small size; each size is one more compiled branch
    widths = _walk_widths(capacity)
    branches = [full] + [listed(w) for w in widths]
    pick = jnp.where(everything | (st.queued > capacity), 0,
                     1 + jnp.sum(st.queued > jnp.asarray(widths[:-1]), dtype=jnp.int32))
    return jax.lax.switch(pick, branches, None)


def _walk_widths(capacity):
    """Queue lengths the ancestor walk is compiled for (the last is the whole queue)."""
    small = min(_SMALL_QUEUE, capacity)
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


def _pass(st, interior, scale, ct, min_gain, temperature, draws, collect=True, *, annealing,
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

    def window_loop(carry, width, last):
        """Windows of ``width`` while at least ``width`` (``last``: any) nodes remain."""
        def cond(c):
            _, _, start, end, _ = c
            return (end - start >= width) | (last & (start < end))

        def body(c):
            st, log, start, end, moves = c
            nodes = jax.lax.dynamic_slice(order, (start,), (width,))
            nodes = jnp.where(start + jnp.arange(width) < end, nodes, cap)
            st, made, moved = _process(st, nodes, scale, ct, min_gain, temperature, draws,
                                       annealing, chains)
            log = jax.lax.dynamic_update_slice(log, moved, (start, 0))
            return st, log, start + jnp.minimum(width, end - start), end, moves + made

        return jax.lax.while_loop(cond, body, carry)

    def cond(carry):
        return carry[2] < count

    def body(carry):
        st, log, start, moves = carry
        end = jnp.searchsorted(keys, keys[start], side="right").astype(jnp.int32)
        carry = (st, log, start, end, moves)
        for i, width in enumerate(windows):
            carry = window_loop(carry, width, i == len(windows) - 1)
        st, log, start, _, moves = carry
        return st, log, start, moves

    moves = jnp.zeros(chains, jnp.int32)
    st, log, _, moves = jax.lax.while_loop(cond, body, (st, log, jnp.int32(0), moves))
    capacity = st.queue.shape[0]
    queued = 3 * jnp.sum(moves)
    # no queue is needed when it overflows or the next pass visits everything anyway
    queue = jax.lax.cond(collect & (queued <= capacity),
                         lambda: _collect_moved(log, count, capacity, cap), lambda: st.queue)
    return st._replace(queue=queue, queued=jnp.where(collect, queued, capacity + 1)), moves


# ----------------------------------------------------------------------------------
# Initial state, whole runs
# ----------------------------------------------------------------------------------


def _init(tree, ct, ci):
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
    st = _State(child, tree.parent.astype(jnp.int32), tree.lo, tree.hi, cost, height)
    return scale, st


def _to_tree(tree, st):
    return tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent,
                        lo=st.lo, hi=st.hi)


def _forest(st: _State, chains: int) -> _State:
    """``chains`` copies of one tree's state as one forest (ids of copy ``k`` offset by ``k N``)."""
    cap = st.child.shape[0]
    def shift(ids):  # [N, ...] ids, -1 none -> [chains * N, ...]
        offset = (jnp.arange(chains, dtype=jnp.int32) * cap).reshape((chains,) + (1,) * ids.ndim)
        moved = jnp.where(ids[None] >= 0, ids[None] + offset, -1)
        return moved.reshape((chains * cap,) + ids.shape[1:])

    def tile(a):
        return jnp.broadcast_to(a[None], (chains,) + a.shape).reshape((chains * cap,) + a.shape[1:])

    return _State(shift(st.child), shift(st.parent), tile(st.lo), tile(st.hi), tile(st.cost),
                  tile(st.height))


def _chain_of(st: _State, k, chains: int) -> _State:
    """The tree of copy ``k`` of a forest (links and boxes; ids back to ``0 .. N-1``)."""
    cap = st.child.shape[0] // chains

    def take(a):
        return jax.lax.dynamic_index_in_dim(a.reshape((chains, cap) + a.shape[1:]), k, 0, False)

    def unshift(ids):
        ids = take(ids)
        return jnp.where(ids >= 0, ids - k * cap, -1)

    return _State(unshift(st.child), unshift(st.parent), take(st.lo), take(st.hi))


def _tree_part(st: _State) -> _State:  # what keep_best keeps: links and boxes
    return _State(st.child, st.parent, st.lo, st.hi)


# ----------------------------------------------------------------------------------
# The optimizer protocol: configs, state, init / step / result
# ----------------------------------------------------------------------------------


def _check_common(config) -> None:
    """The checks hill climbing and annealing share (``ValueError`` naming the knob)."""
    check_costs(config.ct, config.ci)
    if config.min_gain is not None and not config.min_gain >= 0:
        raise ValueError(f"min_gain must be >= 0, got {config.min_gain}")
    if config.windows is not None:
        if not config.windows or min(config.windows) < 1:
            raise ValueError(f"windows must be positive sizes, got {config.windows}")
        object.__setattr__(config, "windows", tuple(int(w) for w in config.windows))
    if config.frontier < 1:
        raise ValueError(f"frontier must be >= 1, got {config.frontier}")


@dataclasses.dataclass(frozen=True)
class HillClimbConfig:
    """Knobs of Kensler's hill climbing (module docstring), with the defaults.

    ``ct``, ``ci``: SAH constants. ``max_passes``: stop after this many passes even if
    not converged. ``min_gain``: relative margin a move must beat (None: ``64 * eps`` of
    the tree's float type, :func:`jaxbvh.numerics.min_gain`). ``split_axes``: Kensler's
    final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`) in ``result``.
    ``windows``, ``frontier``: work sizes (speed only, never the result; each window
    size is one more compiled copy of the window step).
    """

    ct: float = 1.0
    ci: float = 1.0
    max_passes: int = 1000
    min_gain: float | None = None
    split_axes: bool = True
    windows: tuple = DEFAULT_WINDOWS
    frontier: int = DEFAULT_FRONTIER

    def __post_init__(self):
        if self.max_passes < 1:
            raise ValueError(f"max_passes must be >= 1, got {self.max_passes}")
        if self.windows is None:
            raise ValueError("windows must be positive sizes, got None")
        _check_common(self)


@dataclasses.dataclass(frozen=True)
class AnnealConfig:
    """Knobs of Kensler's simulated annealing (module docstring), with the defaults.

    ``schedule``: the temperature of each pass: a name from
    :data:`jaxbvh.optimize.schedules.SCHEDULES` (made with ``steps``, ``hottest``,
    ``period``) or any optax-style function ``step -> T``. The default, ``"kensler"``,
    is Kensler's ramped sine with ``steps``, ``period``, ``hottest`` passed as traced
    values (changing them does not recompile; another schedule compiles once per
    function object). ``steps``: passes ``0 .. steps-1`` follow the schedule (Kensler's
    N = 1250); then passes at ``T = 0`` follow, at most ``max_quench``, until one makes
    no move. ``hottest``: peak temperature in units of the node cost ``C(n)``
    (:data:`jaxbvh.optimize.schedules.DEFAULT_HOTTEST`, 0.15, not the paper's 1.5, which
    is far too hot on this cost). ``period``: the sine's period f in passes (50).
    ``chains``: independent chains (keys ``jax.random.split(key, chains)``) run as one
    forest; the best is returned. ``keep_best``: return the tree of least SAH seen after
    any pass (else the last). ``windows``: None picks :data:`ANNEAL_WINDOWS` (one chain)
    or a K times wider first window (a forest). Others as :class:`HillClimbConfig`.
    """

    schedule: str | Callable = "kensler"
    steps: int = KENSLER_STEPS
    hottest: float = DEFAULT_HOTTEST
    period: int = KENSLER_PERIOD
    chains: int = 1
    keep_best: bool = True
    max_quench: int = 1000
    ct: float = 1.0
    ci: float = 1.0
    min_gain: float | None = None
    split_axes: bool = True
    windows: tuple | None = None
    frontier: int = DEFAULT_FRONTIER

    def __post_init__(self):
        if isinstance(self.schedule, str):
            if self.schedule not in SCHEDULES:
                raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)} or a function "
                                 f"step -> temperature, got {self.schedule!r}")
        elif not callable(self.schedule):
            raise ValueError(f"schedule must be a function step -> temperature, got {self.schedule!r}")
        if self.steps < 0:
            raise ValueError(f"steps must be >= 0, got {self.steps}")
        if not self.hottest >= 0:
            raise ValueError(f"hottest must be >= 0, got {self.hottest}")
        if self.period < 1:
            raise ValueError(f"period must be >= 1, got {self.period}")
        if self.chains < 1:
            raise ValueError(f"chains must be >= 1, got {self.chains}")
        if self.max_quench < 1:
            raise ValueError(f"max_quench must be >= 1, got {self.max_quench}")
        _check_common(self)


class Params(NamedTuple):
    """Settings passed as traced values (changing them does not recompile)."""

    ct: Any        # [] tree dtype: SAH cost of a traversal step
    ci: Any        # [] tree dtype: SAH cost of a primitive test
    min_gain: Any  # [] tree dtype: relative margin a move must beat (module docstring)
    steps: Any     # [] int32: passes that follow the schedule (0 for hill climbing)
    period: Any    # [] float32: Kensler's period f (default schedule only)
    hottest: Any   # [] float32: Kensler's peak temperature h (default schedule only)


class Static(NamedTuple):
    """Settings that fix the compiled program (pytree metadata of the state)."""

    annealing: bool   # simulated annealing (else hill climbing)
    schedule: Any     # step -> T; None: Kensler's, from params (traced)
    keep_best: bool   # result() gives the tree of least SAH seen (annealing)
    chains: int       # K chains, run as one forest
    windows: tuple    # window sizes (speed only)
    frontier: int     # queue of changed nodes (speed only)
    split_axes: bool  # Kensler's final pass in result()


class Inner(NamedTuple):
    """The rotations' own loop state: K chains as one forest, and each chain's figures.

    ``H`` is the history length of the state's :class:`~jaxbvh.optimize.protocol.Progress`
    (which holds the figures of all chains together: least SAH, moves summed).
    """

    forest: Any         # _State of the forest: links, boxes, costs, heights, queue
    keys: Any           # [K] jax.random keys of the chains (annealing); None for hill climbing
    done: Any           # [K] bool: the chain converged (a pass at T = 0 made no move)
    passes: Any         # [K] int32: passes the chain ran (up to the one that converged)
    moves: Any          # [K] int32: moves the chain applied in all
    history: Any        # [K, H] SAH of the chain's tree after each pass, NaN after its last
    history_moves: Any  # [K, H] int32: the chain's moves in each pass
    best: Any           # keep_best: ([K] least SAH seen, _State links and boxes at it); else None


def _temperature(i, params: Params, dtype, static: Static):
    """Temperature of pass ``i`` (traced): the schedule's, clamped at 0, and 0 from ``steps`` on."""
    if not static.annealing:
        return jnp.zeros((), dtype)
    if static.schedule is None:
        t = kensler_temperature(i, jnp.maximum(params.steps, 1), params.period, params.hottest)
    else:
        t = static.schedule(i)
    return jnp.where(i < params.steps, jnp.maximum(jnp.asarray(t, dtype), 0), 0)


def _draws(keys, i, temperature, cap: int, dtype):
    """The uniforms of pass ``i`` for the forest [K N, 6] (ones when cold: none is read)."""
    chains = keys.shape[0]

    def hot():
        rows = jax.vmap(lambda k: annealing_draws(k, i, cap, dtype))(keys)
        return rows.reshape(chains * cap, 6)

    return jax.lax.cond(temperature > 0, hot, lambda: jnp.ones((chains * cap, 6), dtype))


def _keep_best(best, cost, forest: _State, cap: int):
    """``best`` after a pass that left chain roots at ``cost`` [K]: each chain whose SAH
    fell below its least so far keeps its links and boxes."""
    best_cost, best_st = best
    chains = cost.shape[0]
    better = cost < best_cost
    keep = better[jnp.arange(chains * cap, dtype=jnp.int32) // cap]

    def update():
        def pick(new, old):
            return jnp.where(keep.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
        return jax.tree_util.tree_map(pick, _tree_part(forest), best_st)

    return jnp.where(better, cost, best_cost), jax.lax.cond(jnp.any(better), update, lambda: best_st)


@partial(jax.jit, static_argnames=("chains", "frontier", "keep_best", "history"))
def _start(tree, params: Params, keys, *, chains, frontier, keep_best, history):
    """The inner state before the first pass (K = ``chains`` copies as one forest) and
    the input's SAH (``C`` of the root)."""
    dtype = tree.lo.dtype
    _, one = _init(tree, params.ct, params.ci)
    cap = one.child.shape[0]
    st = _forest(one, chains)
    # the first pass visits every node: a queue that overflowed
    queue_size = min(frontier, chains * cap)
    st = st._replace(queue=jnp.full(queue_size, chains * cap, jnp.int32),
                     queued=jnp.int32(queue_size + 1))
    start_cost = one.cost[tree.root]
    none = jnp.zeros(chains, jnp.int32)
    best = (jnp.full(chains, start_cost), _tree_part(st)) if keep_best else None
    inner = Inner(st, keys, jnp.zeros(chains, bool), none, none,
                  jnp.full((chains, history), jnp.nan, dtype), jnp.zeros((chains, history), jnp.int32),
                  best)
    return inner, start_cost


def _init_state(tree, config, keys, static: Static, steps: int, limit: int) -> OptimizerState:
    """The state of either method before its first pass (host code; ``config`` checked)."""
    check_tree(tree)
    tree = to_jax(tree)
    dtype = float_dtype(tree)
    min_gain = default_min_gain(dtype) if config.min_gain is None else config.min_gain
    params = Params(jnp.asarray(config.ct, dtype), jnp.asarray(config.ci, dtype),
                    jnp.asarray(min_gain, dtype), jnp.int32(steps),
                    jnp.float32(getattr(config, "period", KENSLER_PERIOD)),
                    jnp.float32(getattr(config, "hottest", DEFAULT_HOTTEST)))
    inner, start_cost = _start(tree, params, keys, chains=static.chains, frontier=static.frontier,
                               keep_best=static.keep_best, history=history_length(limit))
    return OptimizerState(tree, new_progress(start_cost, limit, dtype), params, inner, static)


def init_hill_climb(tree, config: HillClimbConfig | None = None, key=None) -> OptimizerState:
    """Hill climbing's state before the first pass.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity).
    ``config``: a :class:`HillClimbConfig` (None: the defaults). ``key``: unused (the
    method is deterministic).
    """
    del key
    config = check_config(config, HillClimbConfig, "hc")
    static = Static(annealing=False, schedule=None, keep_best=False, chains=1, windows=config.windows,
                    frontier=int(config.frontier), split_axes=bool(config.split_axes))
    return _init_state(tree, config, None, static, 0, config.max_passes)


def init_anneal(tree, config: AnnealConfig | None = None, key=None) -> OptimizerState:
    """Annealing's state before the first pass: K chains of the tree as one forest.

    ``tree``: as :func:`init_hill_climb`. ``config``: an :class:`AnnealConfig` (None:
    the defaults). ``key``: a ``jax.random`` key (None: ``jax.random.key(0)``); chain
    ``k`` draws from ``jax.random.split(key, K)[k]`` (one chain: ``key`` itself).
    """
    config = check_config(config, AnnealConfig, "sa")
    key = jax.random.key(0) if key is None else key
    chains = int(config.chains)
    keys = key[None] if chains == 1 else jax.random.split(key, chains)
    windows = config.windows
    if windows is None:
        windows = ANNEAL_WINDOWS if chains == 1 else (DEFAULT_WINDOWS[0] * chains,) + DEFAULT_WINDOWS
    schedule = config.schedule
    if isinstance(schedule, str):  # Kensler's: traced from params; others made once (cached)
        schedule = None if schedule == "kensler" else SCHEDULES[schedule](
            max(int(config.steps), 1), float(config.hottest), int(config.period))
    static = Static(annealing=True, schedule=schedule, keep_best=bool(config.keep_best), chains=chains,
                    windows=windows, frontier=int(config.frontier), split_axes=bool(config.split_axes))
    return _init_state(tree, config, keys, static, int(config.steps), config.steps + config.max_quench)


def step(state: OptimizerState) -> OptimizerState:
    """One pass over every chain's tree (hill climbing or annealing, as the state says).

    A chain is done after a pass at ``T = 0`` that makes no move; it then makes no move
    in later passes either, so each chain's result is exactly what it gives alone. The
    progress records the least SAH over the running chains and the moves of all of them
    (``sah``: the least over all chains of what ``result`` would return).
    """
    tree, params, static, inner = state.tree, state.params, state.static, state.inner
    dtype = tree.lo.dtype
    cap = tree.left.shape[0]
    i = state.progress.step
    t = _temperature(i, params, dtype, static)
    draws = _draws(inner.keys, i, t, cap, dtype) if static.annealing else None
    collect = _temperature(i + 1, params, dtype, static) <= 0
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    forest, moves = _pass(inner.forest, inner.forest.child[:, 0] >= 0, scale, params.ct, params.min_gain,
                          t, draws, collect, annealing=static.annealing, windows=static.windows,
                          chains=static.chains)
    cost = forest.cost[tree.root + cap * jnp.arange(static.chains, dtype=jnp.int32)]
    running = ~inner.done
    cold = (i + 1 >= params.steps) if static.annealing else jnp.bool_(True)
    best = _keep_best(inner.best, cost, forest, cap) if static.keep_best else None
    inner = Inner(forest, inner.keys, inner.done | ((moves == 0) & cold), inner.passes + running,
                  inner.moves + moves, inner.history.at[:, i].set(jnp.where(running, cost, jnp.nan), mode="drop"),
                  inner.history_moves.at[:, i].set(jnp.where(running, moves, 0), mode="drop"), best)
    progress = record(state.progress, jnp.min(jnp.where(running, cost, jnp.inf)), jnp.sum(moves),
                      converged=jnp.all(inner.done))
    progress = progress._replace(sah=jnp.min(best[0] if static.keep_best else cost))
    return keep_if_done(state, state.replace(inner=inner, progress=progress))


def result(state: OptimizerState) -> OptimizeResult:
    """The best chain's tree (same capacity as the input) and its figures.

    The best chain is the first whose final SAH is within ``min_gain`` (relative) of
    the least (the margin of the module docstring).

    ``steps``, ``moves``, ``converged``, ``history``, ``history_moves`` are the best
    chain's; ``chain_sah`` [K] every chain's final SAH when K > 1 (else None).
    ``sah``: the SAH of the returned tree (``keep_best``: the least seen).
    """
    tree, static, inner = state.tree, state.static, state.inner
    chains, cap = static.chains, tree.left.shape[0]
    if static.keep_best:
        final_cost, st = inner.best
    else:
        st = inner.forest
        final_cost = st.cost[tree.root + cap * jnp.arange(chains, dtype=jnp.int32)]
    # the first chain within the margin of the least: an ulp of noise in the costs (another
    # fusion, e.g. under vmap) must not pick another chain
    least = jnp.min(final_cost)
    k = jnp.argmax(final_cost <= least + state.params.min_gain * jnp.abs(least))
    out = _to_tree(tree, _chain_of(st, k, chains))
    if static.split_axes:
        out = apply_split_axes(out)
    progress = state.progress._replace(
        step=inner.passes[k], moves=inner.moves[k], converged=inner.done[k], sah=final_cost[k],
        history=inner.history[k], history_moves=inner.history_moves[k])
    return make_result(out, progress, final_cost if chains > 1 else None)


HILL_CLIMB = Optimizer("hc", HillClimbConfig, init_hill_climb, step, result,
                       paper="Kensler 2008 (tree rotations, hill climbing)")
ANNEAL = Optimizer("sa", AnnealConfig, init_anneal, step, result,
                   paper="Kensler 2008 (tree rotations, simulated annealing)")


# ----------------------------------------------------------------------------------
# Convenience entry points
# ----------------------------------------------------------------------------------


def hill_climb(tree, *, time_budget: float | None = None, on_step: Callable | None = None,
               **config) -> OptimizeResult:
    """Kensler's hill climbing: passes of the best improving move per node until none.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity).
    ``config``: fields of :class:`HillClimbConfig` (e.g. ``max_passes``, ``ct``,
    ``split_axes``). ``time_budget``, ``on_step(info)``: as
    :func:`jaxbvh.optimize.driver.run` (without them the run is one compiled call; with
    them it goes in chunks of passes, giving the same tree). The tree is identical, pass
    by pass, to :func:`jaxbvh.optimize.rotate_reference.hill_climb`.
    """
    return run(HILL_CLIMB, tree, HillClimbConfig(**config), time_budget=time_budget, on_step=on_step)


def anneal(key, tree, *, time_budget: float | None = None, on_step: Callable | None = None,
           **config) -> OptimizeResult:
    """Kensler's simulated annealing of tree rotations.

    ``key``: a ``jax.random`` key. ``tree``: as :func:`hill_climb`. ``config``: fields
    of :class:`AnnealConfig` (e.g. ``schedule``, any optax schedule or a name of
    :data:`jaxbvh.optimize.schedules.SCHEDULES`; ``steps``, ``hottest``, ``period``,
    ``chains``). ``time_budget``, ``on_step(info)``: as :func:`hill_climb` (a budget
    stops the schedule early: pair it with ``keep_best``). With K chains the result is
    the best chain's, and ``chain_sah`` lists all K (each chain's result is exactly
    what it gives alone).
    """
    return run(ANNEAL, tree, AnnealConfig(**config), key=key, time_budget=time_budget, on_step=on_step)


@partial(jax.jit, static_argnums=(0, 1))
def _run_batch(step_fn, result_fn, states):
    """``step_fn`` vmapped over the batch until every state is done, then ``result_fn``."""
    states = jax.lax.while_loop(lambda s: ~jnp.all(s.progress.done), jax.vmap(step_fn), states)
    return jax.vmap(result_fn)(states)


def optimize_batch(trees, keys=None, *, method: str = "hc", **config) -> OptimizeResult:
    """Optimize a batch of trees at once: the protocol's ``step`` vmapped over the batch.

    ``trees``: a :class:`~jaxbvh.tree.layout.BVH` whose arrays have a leading batch axis B
    (:func:`jaxbvh.tree.batching.stack_trees`); the arrays may be sharded over devices
    along it (``jax.sharding``), and the result is sharded the same way. ``method``:
    ``"hc"`` or ``"sa"``; ``config``: fields of its Config (:class:`HillClimbConfig`,
    :class:`AnnealConfig`). ``keys``: [B] keys for ``"sa"``. Every field of the result
    gains a leading axis; each tree stops when it is done (its state is then a fixed
    point of ``step``), so each gets exactly its own single-tree result.
    """
    check_tree(trees, "trees")
    optimizers = {"hc": HILL_CLIMB, "sa": ANNEAL}
    if method not in optimizers:
        raise ValueError(f"method must be 'hc' or 'sa', got {method!r}")
    optimizer = optimizers[method]
    if method == "sa" and keys is None:
        raise ValueError("optimize_batch: method 'sa' needs keys (one per tree)")
    config = optimizer.Config(**config)
    trees = to_jax(trees)
    if keys is None:
        states = jax.vmap(lambda tree: optimizer.init(tree, config))(trees)
    else:
        states = jax.vmap(lambda tree, key: optimizer.init(tree, config, key))(trees, keys)
    return _run_batch(optimizer.step, optimizer.result, states)
