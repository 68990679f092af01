"""The moves of one reinsertion iteration: ranking, conflicts, application.

Part of :mod:`jaxbvh.optimize.reinsert`, whose docstring explains the move, its lock
set and the greedy choice in rank order (steps 3 and 4 of an iteration). :func:`find`
searches the candidates (:mod:`jaxbvh.optimize.reinsert_search`) and chooses the moves
to take; :func:`apply` applies them at once and refits their paths; :func:`iteration`
is both, with the SAH after.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import half_area, none_to_oob, ordered_sum, rounded, take_clipped
from jaxbvh.optimize.reinsert_rules import move_width
from jaxbvh.optimize.reinsert_search import State, candidates, scale_of, search

#: mantissa bits of a gain that rank moves: gains within about 1% of each other tie
RANK_MANTISSA = 7


def rank_key(gain):
    """Integer key that orders positive gains by their exponent and first
    :data:`RANK_MANTISSA` mantissa bits (about 1%): closer gains tie, and then the
    smaller id ranks first. Mirror-image moves (``a`` beside ``b`` and ``b`` beside
    ``a``) gain the same in exact arithmetic but come out several ulps apart, differently
    in XLA and in NumPy; a coarse key makes them tie in both.

    Works on JAX and NumPy arrays (float32 -> int32, float64 -> int64 keys; a float64
    key needs x64 in JAX, which float64 trees have).
    """
    if isinstance(gain, np.ndarray) or np.isscalar(gain):
        gain = np.asarray(gain)
        f32 = gain.dtype == np.float32
        ints = gain.view(np.int32 if f32 else np.int64)
    else:
        f32 = gain.dtype == jnp.float32
        ints = jax.lax.bitcast_convert_type(gain, jnp.int32 if f32 else jnp.int64)
    return ints >> ((23 if f32 else 52) - RANK_MANTISSA)


# ----------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------


def _sibling(child, parent, n):
    up = take_clipped(parent, n)
    kids = take_clipped(child, up)
    return jnp.where(kids[..., 0] == n, kids[..., 1], kids[..., 0])


def interior_sah(st: State, prim_count, ct, ci):
    """SAH of the working tree from its sums of areas (tight boxes; the identity in the
    docstring of :mod:`jaxbvh.optimize.reinsert`), a scalar of the boxes' dtype.
    ``prim_count`` [N] int32: the tree's leaf sizes; ``ct``, ``ci``: SAH constants."""
    interior = st.child[:, 0] >= 0
    leaf = prim_count > 0
    dtype = st.lo.dtype
    root_area = st.area[st.root]
    # fixed-order sums of rounded products (numerics: a vmapped step decides alike)
    weighted = (rounded(ct * ordered_sum(jnp.where(interior, st.area, 0)))
                + rounded(ci * ordered_sum(jnp.where(leaf, rounded(prim_count.astype(dtype) * st.area), 0))))
    flat = rounded(ct * jnp.sum(interior).astype(dtype)) + rounded(ci * jnp.sum(prim_count).astype(dtype))
    return jnp.where(root_area > 0, weighted / jnp.where(root_area > 0, root_area, 1), flat)


# ----------------------------------------------------------------------------------
# Conflicts, moves, refit
# ----------------------------------------------------------------------------------


def _walk(parent, starts, tops, active, fn, carry, cap):
    """Walk up from ``starts`` to ``tops`` (inclusive) in lockstep, ``carry = fn(carry,
    nodes, live)`` at every step (``nodes``: the current node of each lane)."""

    def cond(c):
        _, _, live, i = c
        return jnp.any(live) & (i <= cap)

    def body(c):
        carry, cur, live, i = c
        carry = fn(carry, cur, live)
        live = live & (cur != tops)
        cur = jnp.where(live, take_clipped(parent, cur), cur)
        return carry, cur, live, i + 1

    carry, _, _, _ = jax.lax.while_loop(cond, body, (carry, starts, active, jnp.int32(0)))
    return carry


def best(gain, out, width):
    """Up to ``width`` of the moves found, best first: node ids [width] (``-1``: none).

    The moves found are taken in id order (the first ``width`` of them when there are
    more), then ranked by :func:`rank_key` of their gain, descending, ties by id.
    """
    cap = out.shape[0]
    has = out >= 0
    at = jnp.where(has, jnp.cumsum(has.astype(jnp.int32)) - 1, width)
    a = jnp.full(width, -1, jnp.int32).at[at].set(jnp.arange(cap, dtype=jnp.int32), mode="drop")
    key = jnp.where(a >= 0, -rank_key(take_clipped(gain, a)), jnp.iinfo(jnp.int32).max)
    big = jnp.int32(cap)
    _, _, a = jax.lax.sort((key, jnp.where(a >= 0, a, big), a), num_keys=2)
    return a


class Moves(NamedTuple):
    """Moves as lanes, best first (lane index = rank): ``a`` (-1: idle lane), the nodes
    it touches and the ends of its paths."""

    a: Any      # [W] int32: the node moved, with its subtree (-1: idle lane)
    p: Any      # [W] int32: its parent, which moves with it
    s: Any      # [W] int32: its sibling, which takes p's place
    g: Any      # [W] int32: parent of p (-1: p is the root)
    out: Any    # [W] int32: the place: p goes above it
    up: Any     # [W] int32: parent of out (-1: out is the root)
    lca: Any    # [W] int32: common ancestor of p and out (top of both paths)


def moves(st: State, a, out, lca) -> Moves:
    """The moves of nodes ``a`` [W] (``-1``: idle lane) as lanes, from the search's
    results by node id: ``out`` [N] the place, ``lca`` [N] the common ancestor."""
    live = a >= 0
    p = jnp.where(live, take_clipped(st.parent, a), -1)
    y = jnp.where(live, take_clipped(out, a), -1)
    return Moves(a=a, p=p, s=jnp.where(live, _sibling(st.child, st.parent, a), -1),
                 g=jnp.where(live, take_clipped(st.parent, p), -1), out=y,
                 up=jnp.where(live, take_clipped(st.parent, y), -1),
                 lca=jnp.where(live, take_clipped(lca, a), -1))


def select(st: State, m: Moves):
    """Which moves (lanes, best first) are taken, bool [W]: the greedy choice in rank
    order, in rounds.

    Round after round, every remaining move that ranks first on every node it locks
    (among the remaining moves) is taken, and moves that lock a node of a taken move
    drop out. The result is the sequential greedy choice (best rank first, a move taken
    when it shares no locked node with one taken before): the first-ranked remaining
    move always wins, and a move wins in a round exactly when every better move that
    shares a node with it has dropped out.
    """
    cap = st.child.shape[0]
    parent = st.parent
    width = m.a.shape[0]
    has = m.a >= 0
    rank = jnp.arange(width, dtype=jnp.int32)
    extra = jnp.stack([m.a, m.s, m.g, m.up], axis=1)  # [W, 4], -1: none
    none = jnp.int32(width)

    def claim(lock, held, lanes, winners):
        """Scatter-min of lane ranks over the nodes each lane locks: into ``lock`` for
        ``lanes``, into ``held`` for ``winners`` (one walk up both paths for both)."""
        def at(chosen, nodes):
            return jnp.where(chosen, nodes, cap)

        lock = lock.at[at(lanes[:, None], none_to_oob(extra, cap))].min(
            jnp.broadcast_to(rank[:, None], extra.shape), mode="drop")
        held = held.at[at(winners[:, None], none_to_oob(extra, cap))].min(
            jnp.broadcast_to(rank[:, None], extra.shape), mode="drop")

        def mark(arrays, nodes, live):
            lock, held = arrays
            return (lock.at[at(live & lanes, nodes)].min(rank, mode="drop"),
                    held.at[at(live & winners, nodes)].min(rank, mode="drop"))

        arrays = _walk(parent, m.p, m.lca, lanes | winners, mark, (lock, held), cap)
        return _walk(parent, m.out, m.lca, lanes | winners, mark, arrays, cap)

    def check(lanes, lock, held):
        """Per lane of ``lanes``: no node it locks is ``held`` (``free``), and it ranks
        first on every one in ``lock`` (``first``); one walk up both paths for both."""
        def tests(nodes, ranks):
            return take_clipped(held, nodes) == none, take_clipped(lock, nodes) == ranks

        no_held, ranks_first = tests(extra, rank[:, None])
        free = lanes & jnp.all((extra < 0) | no_held, axis=1)
        first = lanes & jnp.all((extra < 0) | ranks_first, axis=1)

        def test(flags, nodes, live):
            no_held, ranks_first = tests(nodes, rank)
            return flags[0] & (~live | no_held), flags[1] & (~live | ranks_first)

        flags = _walk(parent, m.p, m.lca, lanes, test, (free, first), cap)
        return _walk(parent, m.out, m.lca, lanes, test, flags, cap)

    def cond(c):
        return jnp.any(c[0]) & (c[4] <= width)

    def body(c):
        alive, taken, held, won, i = c
        # the last round's winners are held before this round's tests (its claims of
        # them ride on this round's walk)
        lock, held = claim(jnp.full(cap, none, jnp.int32), held, alive, won)
        free, first = check(alive, lock, held)
        win = free & first
        return alive & free & ~win, taken | win, held, win, i + 1

    _, taken, _, _, _ = jax.lax.while_loop(
        cond, body, (has, jnp.zeros(width, bool), jnp.full(cap, none, jnp.int32), jnp.zeros(width, bool),
                     jnp.int32(0)))
    return taken


def apply(st: State, m: Moves, taken, scale) -> State:
    """Apply the ``taken`` moves (bool [W]) at once, then refit their changed paths
    (docstring of :mod:`jaxbvh.optimize.reinsert`, step 4); ``scale``: that of ``st``."""
    cap = st.child.shape[0]
    child, parent = st.child, st.parent
    a, p, s, g, y, up, lca = m.a, m.p, m.s, m.g, m.out, m.up, m.lca
    side_s = jnp.where(take_clipped(child, p)[:, 0] == a, 1, 0)
    side_p = jnp.where(take_clipped(child, g)[:, 0] == p, 0, 1)
    side_y = jnp.where(take_clipped(child, up)[:, 0] == y, 0, 1)

    def at(nodes, ok):
        return jnp.where(taken & ok, nodes, cap)

    new_child = child.at[at(g, g >= 0), side_p].set(s, mode="drop")
    new_child = new_child.at[at(up, up >= 0), side_y].set(p, mode="drop")
    new_child = new_child.at[at(p, True), side_s].set(y, mode="drop")
    new_parent = parent.at[at(s, True)].set(g, mode="drop")
    new_parent = new_parent.at[at(p, True)].set(up, mode="drop")
    new_parent = new_parent.at[at(y, True)].set(p, mode="drop")
    root = jnp.max(jnp.where(taken & (g < 0), s, jnp.where(taken & (up < 0), p, -1)))
    root = jnp.where(root >= 0, root, st.root)

    # refit: chain 1 from g (ancestors of p that shrink), chain 2 from p (p and the
    # ancestors of out that grow); each stops below the node whose box cannot change
    case_i = lca == p       # out inside s's subtree: only chain 2, up to s
    case_ii = y == lca      # out is an ancestor: only chain 1, through p above out
    start1 = jnp.where(case_i, -1, g)
    stop1 = jnp.where(case_ii, up, lca)
    start2 = jnp.where(case_ii, -1, p)
    stop2 = jnp.where(case_i, g, lca)
    live1 = taken & (start1 >= 0) & (start1 != stop1)
    live2 = taken & (start2 >= 0)

    def cond(c):
        return jnp.any(c[4]) | jnp.any(c[5])

    def body(c):
        lo, hi, cur1, cur2, live1, live2, i = c
        for cur, live in ((cur1, live1), (cur2, live2)):
            kids = take_clipped(new_child, cur)
            box_lo = jnp.minimum(take_clipped(lo, kids[:, 0]), take_clipped(lo, kids[:, 1]))
            box_hi = jnp.maximum(take_clipped(hi, kids[:, 0]), take_clipped(hi, kids[:, 1]))
            lo = lo.at[jnp.where(live, cur, cap)].set(box_lo, mode="drop")
            hi = hi.at[jnp.where(live, cur, cap)].set(box_hi, mode="drop")
        nxt1 = take_clipped(new_parent, cur1)
        nxt2 = take_clipped(new_parent, cur2)
        live1 = live1 & (nxt1 != stop1) & (nxt1 >= 0) & (i < cap)
        live2 = live2 & (nxt2 != stop2) & (nxt2 >= 0) & (i < cap)
        return lo, hi, jnp.where(live1, nxt1, cur1), jnp.where(live2, nxt2, cur2), live1, live2, i + 1

    lo, hi, *_ = jax.lax.while_loop(cond, body, (st.lo, st.hi, start1, start2, live1, live2,
                                                 jnp.int32(0)))
    return State(new_child, new_parent, lo, hi, root, half_area(lo, hi, scale))


def touched(st: State, m: Moves, taken, new_parent):
    """Nodes whose last search an iteration's moves may have changed, bool [N]: the
    nodes the ``taken`` moves lock (in ``st``, before the moves) and their children
    after the moves (``new_parent``: the links after; module docstring of
    :mod:`jaxbvh.optimize.reinsert`, step 1)."""
    cap = st.child.shape[0]
    extra = jnp.stack([m.a, m.s, m.g, m.up], axis=1)
    marks = jnp.zeros(cap, bool).at[jnp.where(taken[:, None], none_to_oob(extra, cap), cap)].set(
        True, mode="drop")

    def mark(marks, nodes, live):
        return marks.at[jnp.where(live, nodes, cap)].set(True, mode="drop")

    marks = _walk(st.parent, m.p, m.lca, taken, mark, marks, cap)
    marks = _walk(st.parent, m.out, m.lca, taken, mark, marks, cap)
    return marks | ((new_parent >= 0) & take_clipped(marks, new_parent))


# ----------------------------------------------------------------------------------
# One iteration
# ----------------------------------------------------------------------------------


def find(st: State, octaves, max_steps, min_gain, settled=None):
    """Search and selection of one iteration: ``(moves, taken, gains, count, idle)``.

    ``octaves`` [] int32 and ``settled`` [N] bool (None: none): the candidates
    (:func:`~jaxbvh.optimize.reinsert_search.candidates`); ``max_steps`` [] int32,
    ``min_gain`` []: as for :func:`~jaxbvh.optimize.reinsert_search.search`.
    Returns the :class:`Moves` found (best first, :func:`~jaxbvh.optimize.reinsert_rules.move_width`
    lanes), which of them are taken (bool [W]), each lane's gain ([W], 0 for idle lanes),
    the number of candidates searched ([] int32) and which nodes were searched and
    found no move (bool [N]). Traceable.
    """
    found, count, idle = _search(st, octaves, max_steps, min_gain, settled)
    m, taken, gains = _choose(st, found, move_width(st.child.shape[0]))
    return m, taken, gains, count, idle


def _search(st: State, octaves, max_steps, min_gain, settled):
    """:func:`find`'s search: ``((gain, out, lca) [N] each, count, idle [N] bool)``."""
    ids, count = candidates(st, octaves, settled)
    gain, out, lca = search(st, ids, count, scale_of(st), max_steps, min_gain)
    cap = st.child.shape[0]
    searched = jnp.zeros(cap, bool).at[none_to_oob(ids, cap)].set(True, mode="drop")
    return (gain, out, lca), count, searched & (out < 0)


def _choose(st: State, found, width: int):
    """:func:`find`'s choice in ``width`` lanes: ``(moves, taken [W] bool, gains [W])``."""
    gain, out, lca = found
    a = best(gain, out, width)
    m = moves(st, a, out, lca)
    return m, select(st, m), jnp.where(a >= 0, take_clipped(gain, a), 0)


#: the moves of an iteration are chosen and applied in this many times fewer lanes while
#: the moves found fit there (speed only; :func:`move_lanes`)
MOVE_SHRINK = 4
#: the fewest lanes the moves are narrowed to
MIN_MOVE_LANES = 256


def move_lanes(capacity: int) -> tuple[int, ...]:
    """The lane counts an iteration may choose and apply its moves in (static):
    :func:`~jaxbvh.optimize.reinsert_rules.move_width`, then narrower by
    :data:`MOVE_SHRINK` while that is at least :data:`MIN_MOVE_LANES`.

    Why: ranking, :func:`select` (rounds of walks up every lane's paths) and
    :func:`apply` work on every lane, found or idle, and an iteration finds far fewer
    moves than the width (legocar: at most about 700 for 4,096 lanes, 18 - 210 in the
    first round). An iteration runs them in the narrowest of these that holds every move
    found; the first ``found`` lanes are the same moves in the same ranks and the other
    lanes are idle in every width, so the same moves are taken (speed only)."""
    widths = [move_width(capacity)]
    while widths[-1] // MOVE_SHRINK >= MIN_MOVE_LANES:
        widths.append(widths[-1] // MOVE_SHRINK)
    return tuple(widths)


def iteration(st: State, prim_count, ct, ci, octaves, max_steps, min_gain, settled=None):
    """One iteration: ``(state, moves taken, total gain, SAH after, candidates searched,
    settled after)``.

    :func:`find`'s search and choice, then :func:`apply` (the choice and the moves in
    the narrowest of :func:`move_lanes` that holds the moves found: the same moves as
    :func:`find` takes); ``prim_count`` [N] int32, ``ct``, ``ci``: the SAH of the new
    state (:func:`interior_sah`). The gain is in scaled half-areas (the SAH drops by
    ``ct * gain / area(root)``). ``settled`` [N] bool (None: none): nodes not searched,
    whose last search stands; after: those and the nodes searched without a move, less
    the nodes the moves touched (:func:`touched`). Traceable.
    """
    found, count, idle = _search(st, octaves, max_steps, min_gain, settled)

    def in_lanes(width):
        def run(_):
            m, taken, gains = _choose(st, found, width)
            new = apply(st, m, taken, scale_of(st))
            total = ordered_sum(jnp.where(taken, gains, 0))  # one order, vmapped or not
            return new, jnp.sum(taken, dtype=jnp.int32), total, touched(st, m, taken, new.parent)
        return run

    widths = move_lanes(st.child.shape[0])
    if len(widths) == 1:
        new, made, total, marks = in_lanes(widths[0])(None)
    else:
        moves_found = jnp.sum(found[1] >= 0, dtype=jnp.int32)
        # 0: every lane; k: the k-th narrower width, the narrowest that holds the moves found
        which = sum((moves_found <= w).astype(jnp.int32) for w in widths[1:])
        new, made, total, marks = jax.lax.switch(which, [in_lanes(w) for w in widths], None)
    settled = idle if settled is None else settled | idle
    return new, made, total, interior_sah(new, prim_count, ct, ci), count, settled & ~marks
