"""The six moves of Kensler's tree rotations at a window of nodes: scoring, choice, application.

Part of :mod:`jaxbvh.optimize.rotate`, whose docstring explains the moves, the choice
rules and the exactness margin. :func:`score` scores all six moves of a set of nodes
(a :class:`Scores`); :func:`process_window` scores a window of nodes with disjoint
subtrees, chooses a move for each (hill climbing or annealing) and applies them all at
once.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.numerics import half_area, rounded, take

#: the six moves, in the fixed order of the choice rules (names: the two slots swapped)
MOVES = ("L<->RL", "L<->RR", "R<->LL", "R<->LR", "LL<->RL", "LL<->RR")

# The six moves as index tables over an axis of moves (and one of parts): the scoring and
# the application are written once, vectorised over the moves, instead of once per move
# in Python (which XLA compiled into a kernel per move and field: compile time only,
# the same arithmetic on every value).
#
# The parts of a node n, in this order along the part axis: its children and grandchildren
_L, _R, _LL, _LR, _RL, _RR = range(6)
# The two slots each move swaps, as (which node, which side); node codes 0 = n, 1 = L,
# 2 = R; _PART_OF_SLOT: the part each slot holds
_SLOT_A = ((0, 0), (0, 0), (0, 1), (0, 1), (1, 0), (1, 0))
_SLOT_B = ((2, 0), (2, 1), (1, 0), (1, 1), (2, 0), (2, 1))
_PART_OF_SLOT = {(0, 0): _L, (0, 1): _R, (1, 0): _LL, (1, 1): _LR, (2, 0): _RL, (2, 1): _RR}
_CHANGES_L = (False, False, True, True, True, True)
_CHANGES_R = (True, True, False, False, True, True)
# The eight new children the moves make, each the union of two parts (a, b), in this
# order after the six parts (entries 6 .. 13 of the "extended" part axis):
#   r0 = (L, RR), r1 = (RL, L), l2 = (R, LR), l3 = (LL, R), l4 = (RL, LR), r4 = (LL, RR),
#   l5 = (RR, LR), r5 = (RL, LL)
_COMBINED_A = (_L, _RL, _R, _LL, _RL, _LL, _RR, _RL)
_COMBINED_B = (_RR, _L, _LR, _R, _LR, _RR, _LR, _LL)
_R0, _R1, _L2, _L3, _L4, _R4, _L5, _R5 = range(6, 14)
# n's children after each move (extended part indices): C(n) after move m is the cost of
# n over (_N_LEFT[m], _N_RIGHT[m]); _NEW_LEFT / _NEW_RIGHT: what L's / R's slot holds
# after the move (read only where the move changes that slot, _CHANGES_L / _CHANGES_R)
_N_LEFT = (_RL, _RR, _L2, _L3, _L4, _L5)
_N_RIGHT = (_R0, _R1, _LL, _LR, _R4, _R5)
_NEW_LEFT = (_L, _L, _L2, _L3, _L4, _L5)
_NEW_RIGHT = (_R0, _R1, _R, _R, _R4, _R5)
# every per-move setting the application reads, one row per move (read with one gather)
_A_NODE, _B_NODE, _A_SIDE, _B_SIDE, _A_PART, _B_PART, _NEW_L, _NEW_R, _CHANGE_L, _CHANGE_R = range(10)
_MOVE_TABLE = tuple(zip((a for a, _ in _SLOT_A), (b for b, _ in _SLOT_B), (side for _, side in _SLOT_A),
                        (side for _, side in _SLOT_B), (_PART_OF_SLOT[slot] for slot in _SLOT_A),
                        (_PART_OF_SLOT[slot] for slot in _SLOT_B), _NEW_LEFT, _NEW_RIGHT,
                        map(int, _CHANGES_L), map(int, _CHANGES_R)))


class State(NamedTuple):
    """The working tree (or forest) of a rotation run: links, boxes, costs, heights, queue."""

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


def _pick(values, index):
    """``values[w, index[w]]`` along axis 1: ``values`` [W, K, ...], ``index`` [W] int."""
    at = index.reshape(index.shape + (1,) * (values.ndim - 1))
    return jnp.take_along_axis(values, at, axis=1)[:, 0]


def node_cost(parent_area, area_a, cost_a, area_b, cost_b, ct):
    """``C(n)`` of an interior node from its two children (formula of :mod:`jaxbvh.tree.cost`)."""
    positive = parent_area > 0
    # products rounded alone (numerics.rounded): vmapped or not, one rounding
    weighted = (rounded(area_a * cost_a) + rounded(area_b * cost_b)) / jnp.where(positive, parent_area, 1)
    return ct + jnp.where(positive, weighted, cost_a + cost_b)


# ----------------------------------------------------------------------------------
# Scoring: all six moves of a set of nodes
# ----------------------------------------------------------------------------------


class _Part(NamedTuple):
    """Boxes and figures of nodes, with any leading shape ([W, K] for K parts per node)."""

    lo: Any      # [..., 3]
    hi: Any      # [..., 3]
    area: Any    # [...] scaled half-area
    cost: Any    # [...] C
    height: Any  # [...] int32


def _parts_at(part: _Part, index) -> _Part:
    """The parts at ``index`` (a static tuple) along axis 1."""
    index = jnp.asarray(index, jnp.int32)
    return _Part(*(x[:, index] for x in part))


def _combine(a: _Part, b: _Part, scale, ct) -> _Part:
    lo = jnp.minimum(a.lo, b.lo)
    hi = jnp.maximum(a.hi, b.hi)
    area = half_area(lo, hi, scale)
    return _Part(lo, hi, area, node_cost(area, a.area, a.cost, b.area, b.cost, ct),
                 1 + jnp.maximum(a.height, b.height))


class Scores(NamedTuple):
    """The six moves of a set of nodes ``n`` [W], scored (:func:`score`)."""

    ids: Any         # [W, 6] int32: L, R, LL, LR, RL, RR (N: none)
    interior: Any    # [W] bool: n is a real interior node
    cur: Any         # [W]: C(n) now
    cand: Any        # [W, 6]: C(n) after each move
    n_height: Any    # [W, 6] int32: height of n after each move
    cur_height: Any  # [W] int32: height of n now
    legal: Any       # [W, 6] bool: the move exists at n
    parts: Any       # _Part [W, 14, ...]: the six parts, then the eight unions the moves make

    @property
    def left(self):
        return self.ids[:, _L]

    @property
    def right(self):
        return self.ids[:, _R]


def score(st, nodes, scale, ct) -> Scores:
    """Scores of the six moves at ``nodes`` [W] (``N`` = no node), a :class:`Scores`.

    ``scale``: the power of two areas are measured with; ``ct``: the SAH traversal cost.
    """
    cap = st.child.shape[0]
    kids = take(st.child, nodes, -1)
    left, right = kids[:, 0], kids[:, 1]
    lk = take(st.child, left, -1)
    rk = take(st.child, right, -1)
    ids = jnp.stack([left, right, lk[:, 0], lk[:, 1], rk[:, 0], rk[:, 1]], axis=1)  # [W, 6]
    n_area = half_area(take(st.lo, nodes, jnp.inf), take(st.hi, nodes, -jnp.inf), scale)
    lo = take(st.lo, ids, jnp.inf)
    hi = take(st.hi, ids, -jnp.inf)
    part = _Part(lo, hi, half_area(lo, hi, scale), take(st.cost, ids, 0), take(st.height, ids, 0))
    part = jax.lax.optimization_barrier(part)  # gathered once (compile time)

    cur = node_cost(n_area, part.area[:, _L], part.cost[:, _L], part.area[:, _R], part.cost[:, _R], ct)
    combined = _combine(_parts_at(part, _COMBINED_A), _parts_at(part, _COMBINED_B), scale, ct)
    ext = _Part(*(jnp.concatenate([a, b], axis=1) for a, b in zip(part, combined)))  # [W, 14, ...]
    a, b = _parts_at(ext, _N_LEFT), _parts_at(ext, _N_RIGHT)
    cand = node_cost(n_area[:, None], a.area, a.cost, b.area, b.cost, ct)
    n_height = 1 + jnp.maximum(a.height, b.height)

    real = nodes < cap
    l_in, r_in = ids[:, _LL] >= 0, ids[:, _RL] >= 0
    interior = real & (left >= 0)
    legal = jnp.stack([r_in, r_in, l_in, l_in, l_in & r_in, l_in & r_in], axis=1) & interior[:, None]

    return Scores(ids=ids, interior=interior, cur=cur, cand=cand, n_height=n_height,
                  cur_height=1 + jnp.maximum(part.height[:, _L], part.height[:, _R]),
                  legal=legal, parts=ext)


# ----------------------------------------------------------------------------------
# Decisions and application
# ----------------------------------------------------------------------------------


def _choose_greedy(cand, cur, legal, tol):
    """Hill climbing: the first move within ``tol`` of the least cost, if it improves."""
    improving = legal & (cand < (cur - tol)[:, None])
    least = jnp.min(jnp.where(improving, cand, jnp.inf), axis=1)
    near = improving & (cand <= (least + tol)[:, None])
    return jnp.where(jnp.any(improving, axis=1), jnp.argmax(near, axis=1).astype(jnp.int32), -1)


def _choose_annealing(cand, cur, legal, tol, temperature, draws):
    """Kensler's annealing rule: candidates in order against the best so far.

    ``xi < exp(-de / T)`` is evaluated as ``de < T E`` with ``E = -log(xi)`` drawn as an
    Exp(1) variate (:func:`jaxbvh.draws.annealing_draws`): no exponential in the
    sequential chain (six chained exponentials made XLA's compile time explode), and no
    logarithm the twin would have to repeat to the ulp.
    """
    hot = temperature > 0
    reach = jnp.where(hot, temperature * draws, -1)  # [W, 6]; -1: accept none
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


def _materialise(x):
    """``x`` [W], computed once: XLA's CPU fusion copies a cheap producer into every
    consumer kernel (an ``optimization_barrier`` does not stop it), but no consumer
    takes in a scatter (compile time only: the same values)."""
    return jnp.zeros_like(x).at[jnp.arange(x.shape[0])].set(x, unique_indices=True)


def _choose(s: Scores, nodes, min_gain, temperature, draws, annealing):
    """The move of each node ([W] int32, -1: none) by hill climbing or annealing, and
    the scores with ``cur`` and ``cand`` materialised (what the application reads)."""
    cur, cand, legal = s.cur, s.cand, s.legal
    tol = rounded(min_gain * jnp.abs(cur))  # never contracted into cur - tol
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
    choice = _materialise(jnp.where(s.interior, choice, -1))
    return choice, s._replace(cur=cur, cand=cand)


def _swap_slots(st, s: Scores, nodes, row, moved):
    """The links after each moved node's two slots swapped contents: ``(child, parent)``.
    ``row`` [W, 10]: each node's row of :data:`_MOVE_TABLE`."""
    cap = st.child.shape[0]
    family = jnp.stack([nodes, s.left, s.right], axis=1)  # node codes 0 = n, 1 = L, 2 = R
    a_node = jnp.where(moved, _pick(family, row[:, _A_NODE]), cap)
    b_node = jnp.where(moved, _pick(family, row[:, _B_NODE]), cap)
    a_side, b_side = row[:, _A_SIDE], row[:, _B_SIDE]
    # the slots' contents are ids the scoring already gathered; reading child again here
    # (or through a flat view) makes XLA copy the whole array for every window
    a_val = jnp.where(moved, _pick(s.ids, row[:, _A_PART]), -1)
    b_val = jnp.where(moved, _pick(s.ids, row[:, _B_PART]), -1)
    child = (st.child.at[a_node, a_side].set(b_val, mode="drop")
             .at[b_node, b_side].set(a_val, mode="drop"))
    parent = st.parent.at[jnp.where(moved, b_val, cap)].set(a_node, mode="drop")
    parent = parent.at[jnp.where(moved, a_val, cap)].set(b_node, mode="drop")
    return child, parent


def _update_parts(st, s: Scores, nodes, m, row, moved):
    """New boxes, costs and heights of the changed children and of ``n`` (``row``: as
    :func:`_swap_slots`).

    Returns ``(lo, hi, cost, height, l_at, r_at)``: the state's arrays updated, and the
    changed left and right children ([W] int32, ``N`` where unchanged).
    """
    cap = st.child.shape[0]
    oob = jnp.full_like(nodes, cap)
    interior_nodes = jnp.where(s.interior, nodes, cap)
    new_l = _Part(*(_pick(x, row[:, _NEW_L]) for x in s.parts))
    new_r = _Part(*(_pick(x, row[:, _NEW_R]) for x in s.parts))
    l_at = jnp.where(moved & (row[:, _CHANGE_L] > 0), s.left, oob)
    r_at = jnp.where(moved & (row[:, _CHANGE_R] > 0), s.right, oob)
    n_cost = jnp.where(moved, _pick(s.cand, m), s.cur)
    n_height = jnp.where(moved, _pick(s.n_height, m), s.cur_height)
    # materialise what the scatters write once: XLA would otherwise fuse its computation
    # into each scatter (compile time)
    new_l, new_r, l_at, r_at, n_cost, n_height = jax.lax.optimization_barrier(
        (new_l, new_r, l_at, r_at, n_cost, n_height))
    lo = st.lo.at[l_at].set(new_l.lo, mode="drop").at[r_at].set(new_r.lo, mode="drop")
    hi = st.hi.at[l_at].set(new_l.hi, mode="drop").at[r_at].set(new_r.hi, mode="drop")
    cost = (st.cost.at[l_at].set(new_l.cost, mode="drop").at[r_at].set(new_r.cost, mode="drop")
            .at[interior_nodes].set(n_cost, mode="drop"))
    height = (st.height.at[l_at].set(new_l.height, mode="drop")
              .at[r_at].set(new_r.height, mode="drop")
              .at[interior_nodes].set(n_height, mode="drop"))
    return lo, hi, cost, height, l_at, r_at


def _moves_per_chain(nodes, moved, cap, chains):
    """Moves made in each chain of the forest, [chains] int32."""
    if chains == 1:
        return jnp.sum(moved, dtype=jnp.int32)[None]
    # a one-hot sum: a scatter-add with this many collisions is slow on CPU
    chain = nodes // (cap // chains)
    return jnp.sum((chain[:, None] == jnp.arange(chains)) & moved[:, None], axis=0, dtype=jnp.int32)


def process_window(st, nodes, scale, ct, min_gain, temperature, draws, annealing, chains):
    """Score ``nodes`` (disjoint subtrees), pick a move for each, apply them all.

    Returns the new state, the moves made per chain [chains] (a forest of ``chains``
    equal-capacity trees, node ``k * (N / chains) + i`` being node ``i`` of tree ``k``)
    and the nodes each move changed ([W, 3]: the node and its changed children, ``N``
    where none).
    """
    cap = st.child.shape[0]
    choice, s = _choose(score(st, nodes, scale, ct), nodes, min_gain, temperature, draws, annealing)
    moved = choice >= 0
    m = jnp.maximum(choice, 0)
    row = jax.lax.optimization_barrier(jnp.asarray(_MOVE_TABLE, jnp.int32)[m])  # [W, 10], gathered once
    child, parent = _swap_slots(st, s, nodes, row, moved)
    lo, hi, cost, height, l_at, r_at = _update_parts(st, s, nodes, m, row, moved)
    new = st._replace(child=child, parent=parent, lo=lo, hi=hi, cost=cost, height=height)
    changed = jnp.stack([jnp.where(moved, nodes, cap), l_at, r_at], axis=1)
    return new, _moves_per_chain(nodes, moved, cap, chains), changed
