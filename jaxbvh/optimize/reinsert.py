"""Parallel reinsertion (Meister & Bittner 2018): move subtrees to where the SAH drops most.

The move
========
Reinserting node ``a`` (with its subtree; ``a`` is not the root) removes ``a``'s
parent ``p`` from the tree (``a``'s sibling ``s`` takes ``p``'s place) and puts ``p``
back above some node ``out``: ``p`` becomes the parent of ``a`` (on its old side) and
``out``, in ``out``'s old place. Leaves keep their primitives and boxes; only links and
interior boxes change. This is the insertion-based optimization of Bittner, Hapala &
Havran (2013) in the form of Meister & Bittner (2018): a single subtree is moved (not
the two children of a removed node), and every node searches its best place at once,
in the tree as it is, without removing anything first.

The gain
========
All interior boxes are first refitted to the union of their children (optimizers may
change interior boxes). The SAH of a tree whose boxes are tight is
``(Ct * sum of interior areas + Ci * sum over leaves of count * area) / area(root)``
(the identity ``S(n) C(n) = Ct S(n) + S_L C_L + S_R C_R`` of :mod:`jaxbvh.tree.cost`, which
holds for zero-area nodes too). A move keeps every leaf and the root's box, so it lowers
the SAH by ``Ct * gain / area(root)``, where ``gain`` is the drop in the sum of
interior (scaled half-) areas:

* ``+ S(p)``: ``p`` leaves its place;
* ``+ S(g) - S(g')`` for every ancestor ``g`` of ``p`` below the common ancestor of
  ``p`` and ``out`` (``g'``: ``g`` without ``a``, the union of the other subtrees below it);
* ``- S(a U out)``: ``p`` in its new place (when ``out`` is such an ancestor, ``out``
  itself shrinks first: ``+ S(out) - S(out')`` and ``p`` gets ``a U out'``);
* ``- (S(x U a) - S(x))`` for every ancestor ``x`` of ``out`` below the common ancestor.

With ``Ct = 0`` no move changes the SAH and the optimizer returns at once.

The search (bounded branch and bound)
=====================================
Meister & Bittner's traversal for one node ``a``: start at the sibling ``s`` with the
*highest node* ``p``; walk the subtree below the current highest node depth first
(left child first) with parent links and no stack, then climb: the highest node becomes
its parent and the walk enters the other child. Going down through ``x`` adds ``x``'s
growth ``S(x) - S(x U a)`` (<= 0) to a running sum ``red``; going back up removes it;
passing a highest node ``g != p`` adds its shrinkage ``S(g) - S(g')``, where ``g'`` is
the union of the boxes walked below it. Each visited node ``out`` below the highest
node is a candidate place with gain ``S(p) - S(a U out) + red``; each highest node
``g != p`` is one too, with gain ``S(p) + red + S(g) - S(g') - S(a U g')`` (Meister &
Bittner's code leaves out ``g``'s own shrinkage here; we count it). Branch and bound:
every place below ``x`` gains at most ``red(x) + S(p) - S(a)`` (the merged area is at
least ``S(a)`` and growths are <= 0), so the walk does not descend below ``x`` when
that bound is not better than the best so far. The walk ends when the root has been the
highest node, or after ``max_steps`` steps (one step: one node visited going down or
up), when the best place found so far is kept: the search is bounded.

One iteration
=============
1. Candidates: the real nodes but the root whose parent's area is at least ``2^-k`` of
   the root's (``k`` octaves; the removal of a large parent is the first term of the
   gain, and on our inputs the top few percent of nodes by parent area hold nearly all
   of the first iterations' gain). ``k`` starts where about ``first_fraction`` of the
   nodes are candidates and grows by one octave after an iteration that lowers the SAH
   by at most ``escalate`` (relative), by four after one that takes no move, until all
   nodes are candidates (coarse to fine; ``first_fraction = 1``: Meister & Bittner's
   every node, every iteration).
2. Search: the candidates' walks run vectorised in :func:`search_width` lanes of one
   ``while_loop`` (a work queue: every :data:`REFILL_STEPS` steps, lanes whose walk
   ended hand in their result and take the next candidate), over node data packed by
   rows, so the work follows the steps the walks take.
3. Conflicts: a move *locks* ``a``, ``s``, the paths from ``p`` and from ``out`` up to
   their common ancestor (both ends included) and the parents of ``p`` and ``out``
   (their child links change). The moves found (the first :func:`move_width` in id
   order) are ranked by gain, descending (:func:`rank_key`: gains within about 1% tie),
   ties by the id of ``a`` (smaller first), and taken greedily in rank order: a move is
   taken when it locks no node that a better taken move locks. On the device this runs
   in rounds: every remaining move that ranks first on all the nodes it locks is taken
   (a scatter-min of ranks, then a check), moves touching a taken move's nodes drop
   out, repeat, which gives exactly the greedy choice. Taken moves lock disjoint node
   sets, which makes them independent: the boxes each one reads are changed by none of
   the others, so each gains exactly what its search found, the SAH drops by their sum,
   and the order of applying them does not matter.
4. All taken moves are applied at once (scatters), then the boxes on each move's two
   changed paths are refitted bottom-up, all moves in lockstep, stopping below the
   common ancestor (whose box cannot change).

Iterations repeat until one over all nodes takes no move (the run has converged),
``max_iterations``, or ``time_budget``; every iteration lowers the SAH, so the last tree
is the best. The NumPy twin (:mod:`jaxbvh.optimize.reinsert_reference`) searches one
candidate at a time with the same steps, takes the moves greedily and applies them one
by one, in rank order.

The protocol
============
:data:`REINSERT` is an optimizer of :mod:`jaxbvh.optimize.protocol`: ``init`` refits the
boxes and finds the first octaves (:mod:`jaxbvh.optimize.reinsert_rules`), ``step`` is
one iteration, the widening of the candidates included (:func:`widen`: the octaves are
loop state, so a batch of trees widens each its own way), ``result`` the tree.
:func:`reinsert` runs it under the shared driver (:func:`jaxbvh.optimize.driver.run`).

Exactness
=========
As in :mod:`jaxbvh.optimize.rotate`, decisions must not hinge on the last bit (XLA fuses
multiply-adds, NumPy does not): a place counts as better than the best so far only when
its gain is larger by more than ``min_gain * S(h)``, ``h`` the current highest node (the
largest area the running sums involve), and the walk prunes when the bound is not larger
than best plus that margin, so a pruned place could never have been taken. ``min_gain``
defaults to ``64 * eps`` of the float type.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import Checked, ci_knob, ct_knob, integer, knob, min_gain_knob, real, split_axes_knob
from jaxbvh.numerics import extent_scale, half_area, none_to_oob, take_clipped
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.optimize.driver import run
from jaxbvh.optimize.protocol import (
    Optimizer,
    OptimizeResult,
    OptimizerState,
    check_config,
    check_tree,
    float_dtype,
    keep_if_done,
    make_result,
    new_progress,
    record,
)
from jaxbvh.optimize.reinsert_rules import (
    ALL_OCTAVES,
    FIRST_OCTAVES_TRIED,
    candidates_needed,
    move_width,
    octaves_holding,
)
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import to_jax
from jaxbvh.tree.refit import refit_boxes
from jaxbvh.tree.split_axes import apply_split_axes

DEFAULT_MAX_STEPS = 1024       # search steps per node and iteration (legocar needs < 200)
DEFAULT_MAX_ITERATIONS = 1000
DEFAULT_FIRST_FRACTION = 1 / 32
DEFAULT_ESCALATE = 1e-4


class _State(NamedTuple):
    child: Any   # [N, 2] int32, -1 none
    parent: Any  # [N] int32, -1 none
    lo: Any      # [N, 3]
    hi: Any      # [N, 3]
    root: Any    # [] int32
    area: Any    # [N] scaled half-areas (0 for padding)


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


def _areas(lo, hi, scale):
    return half_area(lo, hi, scale)


def _interior_sah(st: _State, prim_count, ct, ci):
    """SAH from the sums of areas (tight boxes; module docstring), a scalar."""
    interior = st.child[:, 0] >= 0
    leaf = prim_count > 0
    dtype = st.lo.dtype
    root_area = st.area[st.root]
    weighted = (ct * jnp.sum(jnp.where(interior, st.area, 0))
                + ci * jnp.sum(jnp.where(leaf, prim_count.astype(dtype) * st.area, 0)))
    flat = ct * jnp.sum(interior).astype(dtype) + ci * jnp.sum(prim_count).astype(dtype)
    return jnp.where(root_area > 0, weighted / jnp.where(root_area > 0, root_area, 1), flat)


# ----------------------------------------------------------------------------------
# The search, vectorised over all nodes
# ----------------------------------------------------------------------------------


class _Search(NamedTuple):
    """The search state of a set of lanes (each works on one node ``a`` at a time)."""

    a: Any         # the node being placed (-1: idle lane)
    p: Any         # its parent
    alo: Any       # its box
    ahi: Any
    area_p: Any    # S(p)
    base: Any      # S(p) - S(a): the bound's constant part
    steps: Any     # steps taken for a
    out: Any       # current node of the walk
    high: Any      # current highest node
    area_high: Any  # its area
    down: Any      # walking down (else up)
    red: Any       # running sum (module docstring)
    hlo: Any       # box of the highest node without a (union of the walked subtrees)
    hhi: Any
    best: Any
    best_out: Any
    best_lca: Any
    done: Any


class _Tables(NamedTuple):
    """Node data packed by rows, so that a walk step gathers whole rows."""

    box: Any    # [N, 8] float: lo (3), hi (3), area, 0
    links: Any  # [N, 4] int32: left, right, parent, 0


def _tables(st: _State) -> _Tables:
    cap = st.child.shape[0]
    dtype = st.lo.dtype
    box = jnp.concatenate([st.lo, st.hi, st.area[:, None], jnp.zeros((cap, 1), dtype)], axis=1)
    links = jnp.concatenate([st.child, st.parent[:, None], jnp.zeros((cap, 1), jnp.int32)], axis=1)
    return _Tables(box, links)


def _start_search(t: _Tables, a):
    """Search states for nodes ``a`` [W] (``-1``: an idle lane, done at once)."""
    dtype = t.box.dtype
    idle = a < 0
    row_a = take_clipped(t.box, a)
    p = jnp.where(idle, 0, take_clipped(t.links, a)[:, 2])
    links_p = take_clipped(t.links, p)
    area_p = take_clipped(t.box, p)[:, 6]
    width = a.shape[0]
    inf = jnp.full((width, 3), jnp.inf, dtype)
    zero = jnp.zeros(width, dtype)
    none = jnp.full(width, -1, jnp.int32)
    sibling = jnp.where(links_p[:, 0] == a, links_p[:, 1], links_p[:, 0])
    return _Search(a=a, p=p, alo=row_a[:, 0:3], ahi=row_a[:, 3:6], area_p=area_p,
                   base=area_p - row_a[:, 6], steps=jnp.zeros(width, jnp.int32), out=sibling,
                   high=p, area_high=area_p, down=jnp.ones(width, bool), red=zero, hlo=inf,
                   hhi=-inf, best=zero, best_out=none, best_lca=none, done=idle)


def _step(t: _Tables, s: _Search, scale, min_gain, max_steps) -> _Search:
    """One step of every lane's walk (lanes that are done keep their state)."""
    out = s.out
    row = take_clipped(t.box, out)
    olo, ohi, s_out = row[:, 0:3], row[:, 3:6], row[:, 6]
    links = take_clipped(t.links, out)

    def merged_area(lo_b, hi_b):
        return half_area(jnp.minimum(s.alo, lo_b), jnp.maximum(s.ahi, hi_b), scale)

    merged = merged_area(olo, ohi)
    tol = min_gain * s.area_high

    # going down: out is a candidate place; descend unless a leaf or pruned
    gain_d = s.area_p - merged + s.red
    take_d = gain_d > s.best + tol
    best_d = jnp.where(take_d, gain_d, s.best)
    red_d = s.red + (s_out - merged)
    stop = (links[:, 0] < 0) | (red_d + s.base <= best_d + tol)
    out_d = jnp.where(stop, out, links[:, 0])

    # going up: leave out's growth behind
    red_u = s.red - (s_out - merged)
    up = links[:, 2]
    up_links = take_clipped(t.links, up)
    at_high = up == s.high
    # below the highest node: the right sibling next, or further up
    from_left = up_links[:, 0] == out
    out_b = jnp.where(from_left, up_links[:, 1], up)
    # back at the highest node g (= up): g is a candidate (unless g is p), then climb
    hlo = jnp.minimum(s.hlo, olo)
    hhi = jnp.maximum(s.hhi, ohi)
    g = s.high
    not_p = g != s.p
    shrunk = half_area(hlo, hhi, scale)
    s_g = s.area_high
    gain_a = s.area_p + red_u + (s_g - shrunk) - merged_area(hlo, hhi)
    take_a = not_p & (gain_a > s.best + tol)
    red_a = jnp.where(not_p, red_u + (s_g - shrunk), red_u)
    top = up_links[:, 2]                       # parent of g (up_links are g's links here)
    finished = top < 0
    top_links = take_clipped(t.links, top)
    out_c = jnp.where(top_links[:, 0] == g, top_links[:, 1], top_links[:, 0])

    down, live = s.down, ~s.done
    climb = ~down & at_high
    steps = s.steps + 1
    new = s._replace(
        steps=steps,
        out=jnp.where(down, out_d, jnp.where(at_high, out_c, out_b)),
        high=jnp.where(climb, top, s.high),
        area_high=jnp.where(climb, take_clipped(t.box, top)[:, 6], s.area_high),
        down=jnp.where(down, ~stop, jnp.where(at_high, True, from_left)),
        red=jnp.where(down, red_d, jnp.where(at_high, red_a, red_u)),
        hlo=jnp.where(climb[:, None], hlo, s.hlo),
        hhi=jnp.where(climb[:, None], hhi, s.hhi),
        best=jnp.where(down, best_d, jnp.where(climb & take_a, gain_a, s.best)),
        best_out=jnp.where(down & take_d, out, jnp.where(climb & take_a, g, s.best_out)),
        best_lca=jnp.where(down & take_d, s.high, jnp.where(climb & take_a, g, s.best_lca)),
        done=(climb & finished) | (steps >= max_steps),
    )
    return jax.tree_util.tree_map(
        lambda n, o: jnp.where(live.reshape(live.shape + (1,) * (n.ndim - 1)), n, o), new, s)


#: walk steps between refills of finished lanes (speed only)
REFILL_STEPS = 8


def search_width(capacity: int) -> int:
    """Lanes of the search: nodes searched at once (a static size from the capacity)."""
    return int(min(capacity, max(1024, min(16384, capacity // 16))))


def _search(st: _State, candidates, count, scale, max_steps, min_gain):
    """Best place of each candidate: ``(gain [N], out [N], lca [N])`` by node id.

    ``candidates`` [N]: node ids, the first ``count`` of them searched (none the root).
    The walks run in :func:`search_width` lanes; every :data:`REFILL_STEPS` steps, the
    lanes whose walk ended (at the root or after ``max_steps`` steps) hand in their
    result and take the next candidates, so the work follows the steps the walks take,
    not the longest walk times the node count. ``out = -1`` where no place gains more
    than the margin (and for nodes not searched).
    """
    cap = st.child.shape[0]
    width = search_width(cap)
    dtype = st.lo.dtype
    t = _tables(st)
    first = jnp.where(jnp.arange(width) < count, candidates[:width], -1)
    init = _start_search(t, first)
    results = (jnp.zeros(cap, dtype), jnp.full(cap, -1, jnp.int32), jnp.full(cap, -1, jnp.int32))

    def cond(c):
        s, _, _, i = c
        return ~jnp.all(s.done) & (i <= (cap // width + 2) * (max_steps // REFILL_STEPS + 1))

    def body(c):
        s, nxt, results, i = c
        s = jax.lax.fori_loop(0, REFILL_STEPS, lambda _, s: _step(t, s, scale, min_gain, max_steps), s)
        # finished lanes hand in their result and take the next candidates
        free = s.done
        at = jnp.where(free & (s.a >= 0), s.a, cap)
        gain, out, lca = results
        results = (gain.at[at].set(s.best, mode="drop"), out.at[at].set(s.best_out, mode="drop"),
                   lca.at[at].set(s.best_lca, mode="drop"))
        slot = nxt + jnp.cumsum(free.astype(jnp.int32)) - 1
        fresh = jnp.where(free & (slot < count), take_clipped(candidates, slot), -1)
        new = _start_search(t, fresh)
        s = jax.tree_util.tree_map(
            lambda n, o: jnp.where(free.reshape(free.shape + (1,) * (n.ndim - 1)), n, o), new, s)
        return s, nxt + jnp.sum(free, dtype=jnp.int32), results, i + 1

    _, _, results, _ = jax.lax.while_loop(cond, body, (init, jnp.int32(width), results, jnp.int32(0)))
    return results


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


def _best(gain, out, width):
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


class _Moves(NamedTuple):
    """Moves as lanes, best first (lane index = rank): ``a`` (-1: idle lane), the nodes
    it touches and the ends of its paths."""

    a: Any
    p: Any
    s: Any
    g: Any      # parent of p (-1: p is the root)
    out: Any
    up: Any     # parent of out (-1: out is the root)
    lca: Any


def _moves(st: _State, a, out, lca) -> _Moves:
    live = a >= 0
    p = jnp.where(live, take_clipped(st.parent, a), -1)
    y = jnp.where(live, take_clipped(out, a), -1)
    return _Moves(a=a, p=p, s=jnp.where(live, _sibling(st.child, st.parent, a), -1),
                  g=jnp.where(live, take_clipped(st.parent, p), -1), out=y,
                  up=jnp.where(live, take_clipped(st.parent, y), -1),
                  lca=jnp.where(live, take_clipped(lca, a), -1))


def _select(st: _State, m: _Moves):
    """Which moves (lanes, best first) are taken: the greedy choice in rank order, in rounds.

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

    def claim(lanes):
        """Scatter-min of lane ranks over the nodes each lane in ``lanes`` locks."""
        lock = jnp.full(cap, none, jnp.int32)
        lock = lock.at[jnp.where(lanes[:, None], none_to_oob(extra, cap), cap)].min(
            jnp.broadcast_to(rank[:, None], extra.shape), mode="drop")

        def mark(lock, nodes, live):
            return lock.at[jnp.where(live, nodes, cap)].min(rank, mode="drop")

        lock = _walk(parent, m.p, m.lca, lanes, mark, lock, cap)
        return _walk(parent, m.out, m.lca, lanes, mark, lock, cap)

    def every(lanes, test):
        """Whether ``test(nodes, ranks)`` holds on every node each lane locks."""
        ok = lanes & jnp.all((extra < 0) | test(extra, rank[:, None]), axis=1)

        def check(ok, nodes, live):
            return ok & (~live | test(nodes, rank))

        ok = _walk(parent, m.p, m.lca, lanes, check, ok, cap)
        return _walk(parent, m.out, m.lca, lanes, check, ok, cap)

    def cond(c):
        return jnp.any(c[0]) & (c[3] <= width)

    def body(c):
        alive, taken, held, i = c
        lock = claim(alive)
        free = every(alive, lambda n, r: take_clipped(held, n) == none)
        win = every(alive & free, lambda n, r: take_clipped(lock, n) == r)
        held = jnp.minimum(held, claim(win))
        return alive & free & ~win, taken | win, held, i + 1

    _, taken, _, _ = jax.lax.while_loop(
        cond, body, (has, jnp.zeros(width, bool), jnp.full(cap, none, jnp.int32), jnp.int32(0)))
    return taken


def _apply(st: _State, m: _Moves, taken, scale):
    """Apply the taken moves at once, then refit their changed paths (module docstring)."""
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
    return _State(new_child, new_parent, lo, hi, root, _areas(lo, hi, scale))


# ----------------------------------------------------------------------------------
# One iteration
# ----------------------------------------------------------------------------------


def _scale_of(st: _State):
    return extent_scale(st.lo[st.root], st.hi[st.root])


def _prepare(tree) -> _State:
    """The working state of ``tree``: interior boxes refitted tight, their areas."""
    child = jnp.stack([tree.left, tree.right], axis=1).astype(jnp.int32)
    lo, hi = refit_boxes(child, tree.lo, tree.hi)
    root = jnp.asarray(tree.root, jnp.int32)
    scale = extent_scale(lo[root], hi[root])
    return _State(child, tree.parent.astype(jnp.int32), lo, hi, root, _areas(lo, hi, scale))


def _candidates(st: _State, octaves):
    """Real non-root nodes whose parent's area is at least ``2^-octaves`` of the root's,
    in id order: ``(ids [N] (-1 past count), count)``."""
    cap = st.child.shape[0]
    valid = st.parent >= 0
    area_p = take_clipped(st.area, st.parent)
    threshold = jnp.ldexp(st.area[st.root], -jnp.minimum(octaves, ALL_OCTAVES))
    pick = valid & ((area_p >= threshold) | (octaves >= ALL_OCTAVES))
    at = jnp.where(pick, jnp.cumsum(pick.astype(jnp.int32)) - 1, cap)
    ids = jnp.full(cap, -1, jnp.int32).at[at].set(jnp.arange(cap, dtype=jnp.int32), mode="drop")
    return ids, jnp.sum(pick, dtype=jnp.int32)


def _find(st: _State, octaves, max_steps, min_gain):
    """Search and select: ``(moves, taken, gain of each lane, candidates searched)``."""
    scale = _scale_of(st)
    candidates, count = _candidates(st, octaves)
    gain, out, lca = _search(st, candidates, count, scale, max_steps, min_gain)
    a = _best(gain, out, move_width(st.child.shape[0]))
    m = _moves(st, a, out, lca)
    return m, _select(st, m), jnp.where(a >= 0, take_clipped(gain, a), 0), count


def _iteration(st: _State, prim_count, ct, ci, octaves, max_steps, min_gain):
    """One iteration: ``(state, moves taken, total gain, SAH after, candidates searched)``."""
    m, taken, gain, count = _find(st, octaves, max_steps, min_gain)
    new = _apply(st, m, taken, _scale_of(st))
    moves = jnp.sum(taken, dtype=jnp.int32)
    return new, moves, jnp.sum(jnp.where(taken, gain, 0)), _interior_sah(new, prim_count, ct, ci), count


@jax.jit
def _moves_of(st: _State, octaves, max_steps, min_gain):
    """Search and selection of one iteration (for tests): ``(moves, taken, gains, count)``."""
    return _find(st, octaves, max_steps, min_gain)


def _to_tree(tree, st: _State):
    """``tree`` with the links, boxes and root of the working state ``st``."""
    return tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent,
                        lo=st.lo, hi=st.hi, root=st.root)


def widen(octaves, taken, count, nodes, before, after, escalate):
    """The octaves of the next iteration (module docstring, step 1; traceable).

    One more after an iteration that took moves but lowered the SAH (``before`` ->
    ``after``) by at most ``escalate`` (relative), four more after one that took none,
    every node from 64 octaves on; unchanged once every node (``count == nodes``) is
    searched or while the gains stay large. The comparison runs in the tree's float type
    (the host loop it replaces, and the twin, compare the same two SAH values in
    float64: they can differ only when the drop lies within rounding of the threshold).
    """
    small = (taken == 0) | (before - after <= escalate * before)
    grown = jnp.where(octaves < FIRST_OCTAVES_TRIED, octaves + jnp.where(taken > 0, 1, 4), ALL_OCTAVES)
    return jnp.where((count < nodes) & small, grown, octaves).astype(jnp.int32)


# ----------------------------------------------------------------------------------
# The optimizer protocol
# ----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    """Knobs of parallel reinsertion (Meister & Bittner 2018), with the defaults.

    ``max_iterations``: most iterations. ``max_steps``: the search bound, in steps per
    node and iteration. ``first_fraction``: about the share of nodes searched at first,
    those of largest parent area (1: every node, Meister & Bittner's schedule).
    ``escalate``: relative SAH drop at or below which the next iteration searches one
    more octave. ``ct``, ``ci``: SAH constants. ``min_gain``: relative margin a place
    must beat (None: ``64 * eps`` of the tree's float type). ``split_axes``: Kensler's
    final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`) in ``result``.
    """

    max_iterations: int = knob(DEFAULT_MAX_ITERATIONS, check=integer(0), metavar="N", help="most iterations")
    max_steps: int = knob(DEFAULT_MAX_STEPS, check=integer(1), metavar="S",
                          help="search steps per node and iteration")
    first_fraction: float = knob(DEFAULT_FIRST_FRACTION, check=real(above=0, maximum=1), metavar="F",
                                 help="about the share of nodes (largest parent area first) searched at "
                                      "first, growing to all; in (0, 1]")
    escalate: float = knob(DEFAULT_ESCALATE, check=real(0, finite=False), metavar="E",
                           help="relative SAH drop of an iteration at or below which one more octave of "
                                "nodes is searched")
    ct: float = ct_knob()
    ci: float = ci_knob()
    min_gain: float | None = min_gain_knob()
    split_axes: bool = split_axes_knob()


class Params(NamedTuple):
    """Settings passed as traced values (changing them does not recompile)."""

    ct: Any         # [] tree dtype: SAH cost of a traversal step
    ci: Any         # [] tree dtype: SAH cost of a primitive test
    min_gain: Any   # [] tree dtype: relative margin (module docstring, Exactness)
    escalate: Any   # [] tree dtype: relative drop that widens the candidates
    max_steps: Any  # [] int32: search steps per node and iteration
    need: Any       # [] int32: candidates of the first iteration (reinsert_rules.candidates_needed)
    split_axes: Any  # [] bool: Kensler's final pass in result() (traced: no program of its own)


class Inner(NamedTuple):
    """Reinsertion's own loop state."""

    tree: Any     # _State: links, boxes (interior ones tight), root, scaled areas
    octaves: Any  # [] int32: candidates' parent areas reach 2^-octaves of the root's
    nodes: Any    # [] int32: real nodes but the root (every one a candidate at ALL_OCTAVES)


def init(tree, config: Config | None = None, key=None) -> OptimizerState:
    """The state before the first iteration: boxes refitted tight, the first octaves.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity,
    leaves of any size). ``key``: unused (the method is deterministic).
    """
    del key
    check_tree(tree)
    config = check_config(config, Config, "reinsert")
    tree = to_jax(tree)
    dtype = float_dtype(tree)
    min_gain = default_min_gain(dtype) if config.min_gain is None else config.min_gain
    # the node count never changes while optimizing: the first candidates' count is
    # taken here, on the host (reinsert_rules)
    nodes = int(jnp.sum(tree.parent >= 0))
    params = Params(*(jnp.asarray(x, dtype) for x in (config.ct, config.ci, min_gain, config.escalate)),
                    max_steps=jnp.int32(config.max_steps),
                    need=jnp.int32(candidates_needed(config.first_fraction, nodes)),
                    split_axes=jnp.bool_(config.split_axes))
    limit = config.max_iterations if config.ct > 0 else 0  # with Ct = 0 no move changes the SAH
    return restart(params, tree, limit)


@jax.jit
def _start(tree, need) -> Inner:
    st = _prepare(tree)
    octaves = octaves_holding(st.area, st.parent, st.root, need, xp=jnp)
    return Inner(st, octaves, jnp.sum(st.parent >= 0, dtype=jnp.int32))


def restart(params: Params, tree, limit: int) -> OptimizerState:
    """The state of a fresh run on ``tree`` (a JAX BVH) with these settings (traceable:
    the pipeline starts each reinsertion stage with it). ``limit``: most iterations."""
    progress = new_progress(sah_of(tree, params.ct, params.ci), limit, float_dtype(tree))
    # every setting is traced (no static part): one compiled program for every config
    return OptimizerState(tree, progress, params, _start(tree, params.need), None)


def step(state: OptimizerState) -> OptimizerState:
    """One iteration: search the candidates, take the independent best moves, apply
    them; widen the candidates when the gain gets small (module docstring)."""
    p, inner, progress = state.params, state.inner, state.progress
    st, taken, _, sah, count = _iteration(inner.tree, state.tree.prim_count, p.ct, p.ci, inner.octaves,
                                          p.max_steps, p.min_gain)
    octaves = widen(inner.octaves, taken, count, inner.nodes, progress.sah, sah, p.escalate)
    progress = record(progress, sah, taken, converged=(taken == 0) & (count == inner.nodes))
    return keep_if_done(state, state.replace(inner=inner._replace(tree=st, octaves=octaves), progress=progress))


def result(state: OptimizerState) -> OptimizeResult:
    """The optimized tree (same capacity as the input) and the run's figures."""
    out = _to_tree(state.tree, state.inner.tree)
    out = jax.lax.cond(state.params.split_axes, apply_split_axes, lambda t: t, out)
    progress = state.progress._replace(sah=sah_of(out, state.params.ct, state.params.ci))
    return make_result(out, progress)


REINSERT = Optimizer("reinsert", Config, init, step, result, paper="Meister & Bittner 2018")


def reinsert(tree, *, time_budget: float | None = None, on_step: Callable | None = None,
             **config) -> OptimizeResult:
    """Parallel reinsertion until an iteration over all nodes takes no move (module docstring).

    ``config``: fields of :class:`Config` (e.g. ``first_fraction=1.0``, ``max_steps=64``).
    ``time_budget``, ``on_step(info)``: as :func:`jaxbvh.optimize.driver.run` (the run
    stops after an iteration with the tree so far: every iteration lowers the SAH).
    Returns an :class:`~jaxbvh.optimize.protocol.OptimizeResult` whose tree has the
    input's capacity (``steps``: iterations).
    """
    return run(REINSERT, tree, Config(**config), time_budget=time_budget, on_step=on_step)
