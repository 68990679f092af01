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

* **Hill climbing** (:func:`hill_climb`): apply the move of least cost if it lowers
  ``C(n)``; repeat passes until one makes no move.
* **Simulated annealing** (:func:`anneal`): candidates in the fixed order above are
  compared with the best found so far (initially "no move"); a better one always becomes
  the best, a worse one when a uniform ``xi`` falls below ``exp(-de / T)`` (``de`` the
  difference in ``C(n)``; never when ``T == 0``), tested as ``de < -T log(xi)``; the
  best is applied. One uniform per
  (pass, node, candidate), drawn by :func:`jaxbvh.draws.annealing_draws` and indexed by node id.
  The temperature of pass ``i`` is ``schedule(i)``, any optax-style schedule
  (default :func:`jaxbvh.optimize.schedules.kensler_schedule`); after ``steps`` passes the tree is
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

After optimizing, :func:`assign_split_axes` (Kensler's final pass) gives every interior
node the axis along which its children are separated most (overlap least) and orders
the children along it, for front-to-back traversal.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.draws import annealing_draws
from jaxbvh.numerics import extent_scale, half_area, none_to_oob, take
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.optimize.budget import TimeBudget
from jaxbvh.optimize.schedules import DEFAULT_HOTTEST, kensler_temperature
from jaxbvh.tree.layout import BVH, capacity_bucket, to_jax
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


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RotateResult:
    """What an optimizer returns.

    ``tree``: the optimized :class:`~jaxbvh.tree.layout.BVH` (same capacity as the input).
    ``sah``: its SAH cost; ``sah_start``: the input's. ``passes``: passes run (the last
    one made no move when the optimizer converged). ``moves``: moves applied in all.
    ``history``: [max_passes] SAH after each pass, NaN after the last pass run.
    For several chains (``anneal(..., chains=K)``), ``chain_sah`` [K] holds every
    chain's final SAH and the other fields describe the best chain.
    """

    tree: Any
    sah: Any
    sah_start: Any
    passes: Any
    moves: Any
    history: Any
    chain_sah: Any = None


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


class _Dynamic(NamedTuple):
    """Run parameters passed as values (changing them does not recompile)."""

    ct: Any
    ci: Any
    min_gain: Any
    steps: Any     # annealing passes that follow the schedule
    limit: Any     # most passes in all
    period: Any    # Kensler schedule (when no schedule is given)
    hottest: Any


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


class _Carry(NamedTuple):
    """The state of a run between passes (a pytree: it can leave and re-enter ``jit``)."""

    st: Any        # _State of the forest
    i: Any         # passes run so far
    done: Any      # [K] bool: chain converged
    passes: Any    # [K] int32
    total: Any     # [K] int32 moves
    history: Any   # [K, history_len] SAH after each pass, NaN after a chain's last
    moves: Any     # [history_len] int32 moves of all chains in each pass
    temps: Any     # [history_len] temperature of each pass
    best: Any      # keep_best: ([K] least SAH seen, links and boxes at it); else None
    start: Any     # SAH of the input tree


def _tree_part(st: _State) -> _State:  # what keep_best keeps: links and boxes
    return _State(st.child, st.parent, st.lo, st.hi)


def _temperature(i, dyn: _Dynamic, dtype, *, annealing, schedule):
    if not annealing:
        return jnp.zeros((), dtype)
    steps = jnp.asarray(dyn.steps, jnp.int32)
    if schedule is None:
        t = kensler_temperature(i, jnp.maximum(steps, 1), dyn.period, dyn.hottest)
    else:
        t = schedule(i)
    t = jnp.asarray(t, dtype)
    return jnp.where(i < steps, jnp.maximum(t, 0), 0)


def _start(tree, keys, dyn: _Dynamic, *, history_len, keep_best, frontier, **_) -> _Carry:
    """The carry before the first pass: K = ``keys.shape[0]`` chains as one forest."""
    chains = keys.shape[0]
    dtype = tree.lo.dtype
    _, one = _init(tree, jnp.asarray(dyn.ct, dtype), dyn.ci)
    cap = one.child.shape[0]
    st = _forest(one, chains)
    # the first pass visits every node: a queue that overflowed
    queue_size = min(frontier, chains * cap)
    st = st._replace(queue=jnp.full(queue_size, chains * cap, jnp.int32),
                     queued=jnp.int32(queue_size + 1))
    start_cost = one.cost[tree.root]
    none = jnp.zeros(chains, jnp.int32)
    best = (jnp.full(chains, start_cost), _tree_part(st)) if keep_best else None
    return _Carry(st, jnp.int32(0), jnp.zeros(chains, bool), none, none,
                  jnp.full((chains, history_len), jnp.nan, dtype), jnp.zeros(history_len, jnp.int32),
                  jnp.zeros(history_len, dtype), best, start_cost)


def _advance(tree, keys, dyn: _Dynamic, carry: _Carry, stop, *, annealing, schedule, history_len,
             keep_best, windows, **_) -> _Carry:
    """Run passes until ``stop`` passes in all, every chain done, or ``dyn.limit``.

    A chain is done after a pass at ``T = 0`` that makes no move; it then makes no move
    in later passes either, so each chain's result is exactly what it gives alone. The
    carry holds everything, so one call up to the limit and many calls of a few passes
    give the same result (the chunked driver, :func:`_run_chunked`, relies on it).
    """
    chains = keys.shape[0]
    dtype = tree.lo.dtype
    ct = jnp.asarray(dyn.ct, dtype)
    min_gain = jnp.asarray(dyn.min_gain, dtype)
    steps = jnp.asarray(dyn.steps, jnp.int32)
    limit = jnp.minimum(jnp.minimum(jnp.asarray(dyn.limit, jnp.int32), history_len), stop)
    cap = tree.left.shape[0]
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    interior = carry.st.child[:, 0] >= 0
    roots = tree.root + cap * jnp.arange(chains, dtype=jnp.int32)
    chain_of_node = jnp.arange(chains * cap, dtype=jnp.int32) // cap

    def temperature(i):
        return _temperature(i, dyn, dtype, annealing=annealing, schedule=schedule)

    def draws_of(i):
        rows = jax.vmap(lambda k: annealing_draws(k, i, cap, dtype))(keys)
        return rows.reshape(chains * cap, 6)

    def cond(c: _Carry):
        return (c.i < limit) & ~jnp.all(c.done)

    def body(c: _Carry):
        i = c.i
        t = temperature(i)
        if annealing:
            draws = jax.lax.cond(t > 0, lambda: draws_of(i),
                                 lambda: jnp.ones((chains * cap, 6), dtype))
        else:
            draws = None
        collect = temperature(i + 1) <= 0
        st, moves = _pass(c.st, interior, scale, ct, min_gain, t, draws, collect,
                          annealing=annealing, windows=windows, chains=chains)
        cost = st.cost[roots]
        running = ~c.done
        history = c.history.at[:, i].set(jnp.where(running, cost, jnp.nan))
        cold = (i + 1 >= steps) if annealing else jnp.bool_(True)
        best = c.best
        if keep_best:
            best_cost, best_st = best
            better = cost < best_cost
            keep = better[chain_of_node]

            def update():
                def pick(new, old):
                    return jnp.where(keep.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
                return jax.tree_util.tree_map(pick, _tree_part(st), best_st)

            best = (jnp.where(better, cost, best_cost),
                    jax.lax.cond(jnp.any(better), update, lambda: best_st))
        return _Carry(st, i + 1, c.done | ((moves == 0) & cold), c.passes + running, c.total + moves,
                      history, c.moves.at[i].set(jnp.sum(moves)), c.temps.at[i].set(t), best, c.start)

    return jax.lax.while_loop(cond, body, carry)


def _results(tree, carry: _Carry, *, keep_best, **_):
    """``(result, sah)`` of a finished carry: ``result(k)`` builds chain ``k``'s
    :class:`RotateResult` (``k`` may be traced), ``sah`` [K] every chain's final SAH."""
    chains = carry.done.shape[0]
    cap = tree.left.shape[0]
    if keep_best:
        final_cost, st = carry.best
    else:
        st = carry.st
        final_cost = st.cost[tree.root + cap * jnp.arange(chains, dtype=jnp.int32)]

    def result(k):
        return RotateResult(_to_tree(tree, _chain_of(st, k, chains)), final_cost[k], carry.start,
                            carry.passes[k], carry.total[k], carry.history[k])

    return result, final_cost


def _optimize(tree, keys, dyn: _Dynamic, **static):
    """The whole run (traceable, vmappable): passes until converged or ``dyn.limit``.

    ``keys`` [K]: one chain per key. The K chains run as one forest of K copies of the
    tree, so every pass processes each height of all chains at once (K chains cost far
    less than K runs). Returns :func:`_results`.
    """
    carry = _start(tree, keys, dyn, **static)
    carry = _advance(tree, keys, dyn, carry, jnp.int32(np.iinfo(np.int32).max), **static)
    return _results(tree, carry, **static)


def _optimize_one(tree, key, dyn, **static):
    """One chain: :func:`_optimize` with a single key, fields without the chain axis."""
    result, _ = _optimize(tree, key[None], dyn, **static)
    return result(0)


_STATIC = ("annealing", "schedule", "history_len", "keep_best", "windows", "frontier",
           "split_axes")


@partial(jax.jit, static_argnames=_STATIC)
def _run_one(tree, key, dyn, *, split_axes, **static):
    return _finish(_optimize_one(tree, key, dyn, **static), split_axes)


@partial(jax.jit, static_argnames=_STATIC)
def _run_chains(tree, keys, dyn, *, split_axes, **static):
    result, chain_sah = _optimize(tree, keys, dyn, **static)
    one = dataclasses.replace(result(jnp.argmin(chain_sah)), chain_sah=chain_sah)
    return _finish(one, split_axes)


@partial(jax.jit, static_argnames=_STATIC)
def _run_batch(trees, keys, dyn, *, split_axes, **static):
    def one(tree, key):
        return _finish(_optimize_one(tree, key, dyn, **static), split_axes)
    return jax.vmap(one)(trees, keys)


# The chunked driver: the same run as _run_one / _run_chains, in pieces of a few passes
# so the host can report progress between them. No host callback runs inside a compiled
# program (JAX does not write programs with host callbacks to its persistent cache, and
# a new callback object would be a new static argument), so every piece is cached.
_start_jit = jax.jit(_start, static_argnames=_STATIC)
_advance_jit = jax.jit(_advance, static_argnames=_STATIC)


@partial(jax.jit, static_argnames=_STATIC)
def _finish_chunked(tree, carry, *, split_axes, **static):
    result, chain_sah = _results(tree, carry, **static)
    one = result(jnp.argmin(chain_sah))
    if chain_sah.shape[0] > 1:
        one = dataclasses.replace(one, chain_sah=chain_sah)
    return _finish(one, split_axes)


#: a chunk of passes grows (doubling, up to this many) while one takes under 0.1 s
MAX_CHUNK = 256


def _run_chunked(tree, keys, dyn, on_pass, static, time_budget=None) -> RotateResult:
    """Run in chunks of passes, calling ``on_pass(i, sah, moves, temperature)`` on the
    host for every pass (``sah``: least over the chains; ``moves``: all chains').

    ``time_budget`` (seconds, or None): stop after the first chunk that ends past it
    (chunks grow only while one takes under 0.1 s, so the overshoot stays small); the
    result is then the best tree so far (the last tree for hill climbing, which only
    improves; the kept best for annealing with ``keep_best``). The clock starts after
    the first chunk (one pass), which also compiles, so compiling is not counted.
    """
    import time

    budget = TimeBudget(time_budget)
    on_pass = on_pass or (lambda *_: None)
    carry = _start_jit(tree, keys, dyn, **static)
    limit = min(int(dyn.limit), static["history_len"])
    done_passes, chunk = 0, 1
    while done_passes < limit:
        clock = time.perf_counter()
        carry = _advance_jit(tree, keys, dyn, carry, jnp.int32(done_passes + chunk), **static)
        # whole (small) arrays to the host: slicing on the device would compile a
        # program per slice shape
        now, done, history, moves, temps = jax.device_get((carry.i, carry.done, carry.history,
                                                           carry.moves, carry.temps))
        now = int(now)
        for j in range(done_passes, now):
            on_pass(j, np.nanmin(history[:, j]), moves[j], temps[j])
        if now < done_passes + chunk or done.all():
            break  # converged (or at the limit)
        if budget.spent():  # the first chunk compiled: the clock starts after it
            break
        done_passes = now
        if time.perf_counter() - clock < 0.1:
            chunk = min(2 * chunk, MAX_CHUNK)
    return _finish_chunked(tree, carry, **static)


def _finish(out: RotateResult, split_axes: bool) -> RotateResult:
    if split_axes:
        out = dataclasses.replace(out, tree=apply_split_axes(out.tree))
    return out


# ----------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------


def _check_tree(tree, name="tree"):
    if not isinstance(tree, BVH):
        raise ValueError(f"{name} must be a binary jaxbvh.BVH, got {type(tree).__name__}")


def _setup(tree, *, ct, ci, min_gain, limit, windows, frontier, steps=0, period=50,
           hottest=DEFAULT_HOTTEST, annealing=False, schedule=None, keep_best=False,
           split_axes=True, on_pass=None, time_budget=None):
    """Checked arguments as (dynamic values, static options)."""
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if not ct >= 0 or not ci >= 0:
        raise ValueError(f"ct and ci must be >= 0, got ct={ct}, ci={ci}")
    if limit < 1:
        raise ValueError(f"the pass limit must be >= 1, got {limit}")
    if not windows or min(windows) < 1:
        raise ValueError(f"windows must be positive sizes, got {windows}")
    if frontier < 1:
        raise ValueError(f"frontier must be >= 1, got {frontier}")
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if period < 1:
        raise ValueError(f"period must be >= 1, got {period}")
    if not hottest >= 0:
        raise ValueError(f"hottest must be >= 0, got {hottest}")
    if schedule is not None and not callable(schedule):
        raise ValueError(f"schedule must be a function step -> temperature, got {schedule!r}")
    dtype = np.dtype(tree.lo.dtype)
    if min_gain is None:
        min_gain = default_min_gain(dtype)
    if not min_gain >= 0:
        raise ValueError(f"min_gain must be >= 0, got {min_gain}")
    dyn = _Dynamic(np.float32(ct), np.float32(ci), np.float32(min_gain), np.int32(steps),
                   np.int32(limit), np.float32(period), np.float32(hottest))
    static = dict(annealing=annealing, schedule=schedule, history_len=capacity_bucket(int(limit)),
                  keep_best=bool(keep_best), windows=tuple(int(w) for w in windows),
                  frontier=int(frontier), split_axes=bool(split_axes))
    if on_pass is not None and not callable(on_pass):
        raise ValueError(f"on_pass must be a function (pass, sah, moves, temperature), got {on_pass!r}")
    return dyn, static


def hill_climb(tree, *, ct: float = 1.0, ci: float = 1.0, max_passes: int = 1000,
               min_gain: float | None = None, split_axes: bool = True,
               windows=DEFAULT_WINDOWS, frontier: int = DEFAULT_FRONTIER,
               on_pass: Callable | None = None, time_budget: float | None = None) -> RotateResult:
    """Kensler's hill climbing: passes of the best improving move per node until none.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity).
    ``max_passes``: stop after this many passes even if not converged (``passes ==
    max_passes`` and the last one moved). ``min_gain``: relative margin a move must beat
    (module docstring). ``split_axes``: run :func:`assign_split_axes` at the end.
    ``windows``, ``frontier``: work sizes (speed only, never the result).
    ``on_pass(pass_index, sah, moves, temperature)``: called on the host for every pass
    (progress bars). With it the run goes in chunks of passes (:func:`_run_chunked`:
    the same tree, the compiled pieces cached like every other program); without it,
    in one compiled call. ``time_budget``: seconds after which to stop (at the end of a
    chunk of passes) with the tree so far; it implies the chunked run.
    The result's tree has the same capacity; it is identical, pass by pass, to
    :func:`jaxbvh.optimize.rotate_reference.hill_climb`.
    """
    _check_tree(tree)
    dyn, static = _setup(tree, ct=ct, ci=ci, min_gain=min_gain, limit=max_passes, windows=windows,
                         frontier=frontier, split_axes=split_axes, on_pass=on_pass,
                         time_budget=time_budget)
    key = jax.random.key(0)
    if on_pass is not None or time_budget is not None:
        return _run_chunked(to_jax(tree), key[None], dyn, on_pass, static, time_budget)
    return _run_one(to_jax(tree), key, dyn, **static)


def anneal(key, tree, *, schedule: Callable | None = None, steps: int = 1250,
           hottest: float = DEFAULT_HOTTEST, period: int = 50, chains: int = 1,
           keep_best: bool = True, max_quench: int = 1000, ct: float = 1.0, ci: float = 1.0,
           min_gain: float | None = None, split_axes: bool = True,
           windows=None, frontier: int = DEFAULT_FRONTIER,
           on_pass: Callable | None = None, time_budget: float | None = None) -> RotateResult:
    """Kensler's simulated annealing of tree rotations.

    ``key``: a ``jax.random`` key. ``schedule``: optax-style ``step -> temperature``
    (default Kensler's, :func:`jaxbvh.optimize.schedules.kensler_schedule` with ``steps``,
    ``period``, ``hottest``); passes ``0 .. steps-1`` use it, then passes at ``T = 0``
    follow (at most ``max_quench``) until one makes no move. Temperatures are in units
    of the node cost ``C(n)``; ``hottest`` defaults to
    :data:`jaxbvh.optimize.schedules.DEFAULT_HOTTEST` (0.15), not the paper's 1.5, which is far
    too hot on this cost (annealing then ends where hill climbing does).
    ``keep_best``: return the tree of least SAH seen after any pass (else the last).
    ``chains``: run that many independent chains (keys ``jax.random.split(key,
    chains)``) and return the best; ``chain_sah`` lists them all. The chains run as
    one forest, so K chains take far less than K times one (each chain's result is
    exactly what it gives alone). ``windows=None`` picks :data:`ANNEAL_WINDOWS` (one
    chain) or a K times wider first window (a forest). Other arguments as
    :func:`hill_climb` (a ``time_budget`` stops the schedule early: pair it with
    ``keep_best``). Changing
    ``steps``, ``period``, ``hottest`` does not recompile (a given ``schedule`` is
    compiled once per function object).
    """
    _check_tree(tree)
    if chains < 1:
        raise ValueError(f"chains must be >= 1, got {chains}")
    if max_quench < 1:
        raise ValueError(f"max_quench must be >= 1, got {max_quench}")
    if windows is None:
        wide = (DEFAULT_WINDOWS[0] * chains,) + DEFAULT_WINDOWS
        windows = ANNEAL_WINDOWS if chains == 1 else wide
    dyn, static = _setup(tree, ct=ct, ci=ci, min_gain=min_gain, limit=steps + max_quench,
                         windows=windows, frontier=frontier, steps=steps, period=period,
                         hottest=hottest, annealing=True, schedule=schedule,
                         keep_best=keep_best, split_axes=split_axes, on_pass=on_pass,
                         time_budget=time_budget)
    tree = to_jax(tree)
    keys = key[None] if chains == 1 else jax.random.split(key, chains)
    if on_pass is not None or time_budget is not None:
        return _run_chunked(tree, keys, dyn, on_pass, static, time_budget)
    if chains == 1:
        return _run_one(tree, key, dyn, **static)
    return _run_chains(tree, keys, dyn, **static)


def optimize_batch(trees, keys=None, *, method: str = "hc", schedule: Callable | None = None,
                   steps: int = 1250, hottest: float = DEFAULT_HOTTEST, period: int = 50,
                   keep_best: bool = True, max_passes: int = 1000, ct: float = 1.0,
                   ci: float = 1.0, min_gain: float | None = None, split_axes: bool = True,
                   windows=DEFAULT_WINDOWS, frontier: int = DEFAULT_FRONTIER) -> RotateResult:
    """Optimize a batch of trees at once (vmapped); every field gains a leading axis.

    ``trees``: a :class:`~jaxbvh.tree.layout.BVH` whose arrays have a leading batch axis B
    (:func:`stack_trees`); the arrays may be sharded over devices along it
    (``jax.sharding``), and the result is sharded the same way. ``keys``: [B] keys for
    ``method="sa"``. ``max_passes`` is the pass limit for ``"hc"`` and the quench limit
    for ``"sa"``.
    """
    _check_tree(trees, "trees")
    if method not in ("hc", "sa"):
        raise ValueError(f"method must be 'hc' or 'sa', got {method!r}")
    batch = trees.left.shape[0]
    annealing = method == "sa"
    if annealing and keys is None:
        raise ValueError("optimize_batch: method 'sa' needs keys (one per tree)")
    if keys is None:
        keys = jax.random.split(jax.random.key(0), batch)
    dyn, static = _setup(trees, ct=ct, ci=ci, min_gain=min_gain,
                         limit=steps + max_passes if annealing else max_passes,
                         windows=windows, frontier=frontier, steps=steps if annealing else 0,
                         period=period, hottest=hottest, annealing=annealing,
                         schedule=schedule if annealing else None,
                         keep_best=keep_best and annealing, split_axes=split_axes)
    return _run_batch(trees, keys, dyn, **static)


