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

# The two slots each move swaps, as (which node, which side). Node codes: 0 = n, 1 = L, 2 = R.
_SLOT_A = ((0, 0), (0, 0), (0, 1), (0, 1), (1, 0), (1, 0))
_SLOT_B = ((2, 0), (2, 1), (1, 0), (1, 1), (2, 0), (2, 1))
_CHANGES_L = (False, False, True, True, True, True)
_CHANGES_R = (True, True, False, False, True, True)


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
    # products rounded alone (numerics.rounded): vmapped or not, one rounding
    weighted = (rounded(area_a * cost_a) + rounded(area_b * cost_b)) / jnp.where(positive, parent_area, 1)
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


class Scores(NamedTuple):
    """The six moves of a set of nodes ``n`` [W], scored (:func:`score`)."""

    left: Any        # [W] int32: L (N: none)
    right: Any       # [W] int32: R
    grand: Any       # (LL, LR, RL, RR): [W] int32 each (N: none)
    interior: Any    # [W] bool: n is a real interior node
    cur: Any         # [W]: C(n) now
    cand: Any        # [W, 6]: C(n) after each move
    n_height: Any    # list of 6 [W] int32: height of n after each move
    cur_height: Any  # [W] int32: height of n now
    legal: Any       # [W, 6] bool: the move exists at n
    new_left: Any    # list of 6 _Part: L's slot after each move (box, area, cost, height)
    new_right: Any   # list of 6 _Part: R's slot after each move


def score(st, nodes, scale, ct) -> Scores:
    """Scores of the six moves at ``nodes`` [W] (``N`` = no node), a :class:`Scores`.

    ``scale``: the power of two areas are measured with; ``ct``: the SAH traversal cost.
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

    return Scores(
        left=left, right=right, grand=(ll, lr, rl, rr), interior=interior, cur=cur,
        cand=jnp.stack([c for c, _ in n_after], axis=1),
        n_height=[h for _, h in n_after],
        cur_height=1 + jnp.maximum(L.height, R.height),
        legal=legal, new_left=new_left, new_right=new_right,
    )


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
    choice = jax.lax.optimization_barrier(jnp.where(s.interior, choice, -1))
    return choice, s._replace(cur=cur, cand=cand)


def _swap_slots(st, s: Scores, nodes, m, moved):
    """The links after each moved node's two slots swapped contents: ``(child, parent)``."""
    cap = st.child.shape[0]
    left, right = s.left, s.right
    family = (nodes, left, right)
    a_node = _select(m, [family[a] for a, _ in _SLOT_A])
    b_node = _select(m, [family[b] for b, _ in _SLOT_B])
    a_side = _select(m, [jnp.int32(side) for _, side in _SLOT_A])
    b_side = _select(m, [jnp.int32(side) for _, side in _SLOT_B])
    a_node = jnp.where(moved, a_node, cap)
    b_node = jnp.where(moved, b_node, cap)
    # the slots' contents are ids the scoring already gathered; reading child again here
    # (or through a flat view) makes XLA copy the whole array for every window
    ll, lr, rl, rr = s.grand
    content = {(0, 0): left, (0, 1): right, (1, 0): ll, (1, 1): lr, (2, 0): rl, (2, 1): rr}
    a_val = jnp.where(moved, _select(m, [content[slot] for slot in _SLOT_A]), -1)
    b_val = jnp.where(moved, _select(m, [content[slot] for slot in _SLOT_B]), -1)
    child = (st.child.at[a_node, a_side].set(b_val, mode="drop")
             .at[b_node, b_side].set(a_val, mode="drop"))
    parent = st.parent.at[jnp.where(moved, b_val, cap)].set(a_node, mode="drop")
    parent = parent.at[jnp.where(moved, a_val, cap)].set(b_node, mode="drop")
    return child, parent


def _update_parts(st, s: Scores, nodes, m, moved):
    """New boxes, costs and heights of the changed children and of ``n``.

    Returns ``(lo, hi, cost, height, l_at, r_at)``: the state's arrays updated, and the
    changed left and right children ([W] int32, ``N`` where unchanged).
    """
    cap = st.child.shape[0]
    oob = jnp.full_like(nodes, cap)
    interior_nodes = jnp.where(s.interior, nodes, cap)

    def pick(parts):
        return _Part(*(_select(m, list(f)) for f in zip(*parts)))

    new_l, new_r = pick(s.new_left), pick(s.new_right)
    l_changes = moved & _select(m, [jnp.bool_(x) for x in _CHANGES_L])
    r_changes = moved & _select(m, [jnp.bool_(x) for x in _CHANGES_R])
    l_at = jnp.where(l_changes, s.left, oob)
    r_at = jnp.where(r_changes, s.right, oob)
    lo = st.lo.at[l_at].set(new_l.lo, mode="drop").at[r_at].set(new_r.lo, mode="drop")
    hi = st.hi.at[l_at].set(new_l.hi, mode="drop").at[r_at].set(new_r.hi, mode="drop")
    n_cost = jnp.where(moved, _select(m, [s.cand[:, k] for k in range(6)]), s.cur)
    n_height = jnp.where(moved, _select(m, s.n_height), s.cur_height)
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
    child, parent = _swap_slots(st, s, nodes, m, moved)
    lo, hi, cost, height, l_at, r_at = _update_parts(st, s, nodes, m, moved)
    new = st._replace(child=child, parent=parent, lo=lo, hi=hi, cost=cost, height=height)
    changed = jnp.stack([jnp.where(moved, nodes, cap), l_at, r_at], axis=1)
    return new, _moves_per_chain(nodes, moved, cap, chains), changed
