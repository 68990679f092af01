"""The working tree of parallel reinsertion and the search of one iteration.

Part of :mod:`jaxbvh.optimize.reinsert`, whose docstring explains the gain of a move,
the bounded branch and bound search (Meister & Bittner 2018), the candidates of an
iteration and the exactness margin. :class:`State` is the working tree (links, boxes,
scaled areas); :func:`prepare` makes it from a BVH and :func:`to_tree` puts it back;
:func:`candidates` lists the nodes an iteration searches and :func:`search` finds the
best place of each, all walks at once in :func:`search_width` lanes.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.numerics import extent_scale, half_area, rounded, take_clipped
from jaxbvh.optimize.reinsert_rules import ALL_OCTAVES
from jaxbvh.tree.refit import refit_boxes


class State(NamedTuple):
    """The working tree of a reinsertion run (interior boxes kept tight)."""

    child: Any   # [N, 2] int32, -1 none
    parent: Any  # [N] int32, -1 none
    lo: Any      # [N, 3]
    hi: Any      # [N, 3]
    root: Any    # [] int32
    area: Any    # [N] scaled half-areas (0 for padding)


# ----------------------------------------------------------------------------------
# The working tree
# ----------------------------------------------------------------------------------


def scale_of(st: State):
    """The power of two areas are measured with (:func:`jaxbvh.numerics.extent_scale` of the root box)."""
    return extent_scale(st.lo[st.root], st.hi[st.root])


def prepare(tree) -> State:
    """The working state of ``tree`` (a JAX :class:`~jaxbvh.tree.layout.BVH`): interior
    boxes refitted tight, their scaled areas (traceable)."""
    child = jnp.stack([tree.left, tree.right], axis=1).astype(jnp.int32)
    lo, hi = refit_boxes(child, tree.lo, tree.hi)
    root = jnp.asarray(tree.root, jnp.int32)
    scale = extent_scale(lo[root], hi[root])
    return State(child, tree.parent.astype(jnp.int32), lo, hi, root, half_area(lo, hi, scale))


def to_tree(tree, st: State):
    """``tree`` with the links, boxes and root of the working state ``st``."""
    return tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent,
                        lo=st.lo, hi=st.hi, root=st.root)


def candidates(st: State, octaves, settled=None):
    """Real non-root nodes whose parent's area is at least ``2^-octaves`` of the root's,
    in id order: ``(ids [N] int32 (-1 past count), count [] int32)``; every real non-root
    node from :data:`~jaxbvh.optimize.reinsert_rules.ALL_OCTAVES` on. ``settled`` [N]
    bool (None: none): nodes left out, whose last search still stands (module docstring
    of :mod:`jaxbvh.optimize.reinsert`, step 1)."""
    cap = st.child.shape[0]
    valid = st.parent >= 0
    area_p = take_clipped(st.area, st.parent)
    threshold = jnp.ldexp(st.area[st.root], -jnp.minimum(octaves, ALL_OCTAVES))
    pick = valid & ((area_p >= threshold) | (octaves >= ALL_OCTAVES))
    if settled is not None:
        pick = pick & ~settled
    at = jnp.where(pick, jnp.cumsum(pick.astype(jnp.int32)) - 1, cap)
    ids = jnp.full(cap, -1, jnp.int32).at[at].set(jnp.arange(cap, dtype=jnp.int32), mode="drop")
    return ids, jnp.sum(pick, dtype=jnp.int32)


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
    red: Any       # running sum (docstring of jaxbvh.optimize.reinsert)
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


def _tables(st: State) -> _Tables:
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
    tol = rounded(min_gain * s.area_high)  # never contracted into best + tol (numerics.rounded)

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

#: the search narrows its lanes by this factor when the walks still running fit in fewer
#: lanes and no candidate is left to start (speed only; :func:`lane_widths`)
TAIL_SHRINK = 4
#: the narrowest lane count the search narrows to (below it a narrower copy of the walk
#: step costs more to compile than it saves)
MIN_TAIL_LANES = 64


def search_width(capacity: int) -> int:
    """Lanes of the search: nodes searched at once (a static size from the capacity)."""
    return int(min(capacity, max(1024, min(16384, capacity // 16))))


def lane_widths(capacity: int) -> tuple[int, ...]:
    """The lane counts of the search's phases (static): :func:`search_width`, then
    narrower by :data:`TAIL_SHRINK` while that is at least :data:`MIN_TAIL_LANES`.

    Why: every lane computes every step, running or not, so the cost of a search is its
    lane count times the steps of its longest chain of walks. Once every candidate has a
    lane, lanes finish one by one while the last walks run: on legocar's first
    iterations (1,852 candidates, walks of 38 steps on average and up to 132, 1,024
    lanes) 37 % of the lane-steps were walks, the rest lanes waiting for the longest
    walk. Moving the running walks into 256 and then 64 lanes halves the lane-steps there
    (and cuts them by a fifth when every node is searched); each walk takes the same
    steps in any lane, so the results are the same."""
    widths = [search_width(capacity)]
    while widths[-1] // TAIL_SHRINK >= MIN_TAIL_LANES:
        widths.append(widths[-1] // TAIL_SHRINK)
    return tuple(widths)


def _compact(t: _Tables, s: _Search, width: int) -> _Search:
    """The running lanes of ``s`` (at most ``width`` of them) moved into ``width`` lanes,
    in lane order; the others idle (finished lanes have handed in their results)."""
    running = ~s.done
    at = jnp.where(running, jnp.cumsum(running.astype(jnp.int32)) - 1, width)
    idle = _start_search(t, jnp.full(width, -1, jnp.int32))
    return jax.tree_util.tree_map(lambda n, o: n.at[at].set(o, mode="drop"), idle, s)


def search(st: State, ids, count, scale, max_steps, min_gain):
    """Best place of each candidate: ``(gain [N], out [N], lca [N])`` by node id.

    ``ids`` [N] int32: the candidates (:func:`candidates`), the first ``count`` of them
    searched (none the root). ``scale``: :func:`scale_of`; ``max_steps`` [] int32: the
    search bound; ``min_gain`` []: the relative margin (module docstring of
    :mod:`jaxbvh.optimize.reinsert`, Exactness). ``gain`` is in the state's scaled
    half-areas, ``lca`` the common ancestor of the node's parent and ``out``.
    The walks run in :func:`search_width` lanes; every :data:`REFILL_STEPS` steps, the
    lanes whose walk ended (at the root or after ``max_steps`` steps) hand in their
    result and take the next candidates, so the work follows the steps the walks take,
    not the longest walk times the node count. When every candidate has started and the
    walks still running fit in fewer lanes, they move there (:func:`lane_widths`).
    ``out = -1`` where no place gains more than the margin (and for nodes not searched).
    """
    cap = st.child.shape[0]
    widths = lane_widths(cap)
    dtype = st.lo.dtype
    t = _tables(st)
    first = jnp.where(jnp.arange(widths[0]) < count, ids[:widths[0]], -1)
    carry = (_start_search(t, first), jnp.int32(widths[0]),
             (jnp.zeros(cap, dtype), jnp.full(cap, -1, jnp.int32), jnp.full(cap, -1, jnp.int32)), jnp.int32(0))
    # body iterations of all phases: the first phase's candidates, then every later phase
    # ends within a walk's bound
    bound = (cap // widths[0] + 1 + len(widths)) * (max_steps // REFILL_STEPS + 1)

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
        fresh = jnp.where(free & (slot < count), take_clipped(ids, slot), -1)
        new = _start_search(t, fresh)
        s = jax.tree_util.tree_map(
            lambda n, o: jnp.where(free.reshape(free.shape + (1,) * (n.ndim - 1)), n, o), new, s)
        return s, nxt + jnp.sum(free, dtype=jnp.int32), results, i + 1

    for phase, width in enumerate(widths):
        narrower = widths[phase + 1] if phase + 1 < len(widths) else 0
        if phase:
            carry = (_compact(t, carry[0], width),) + carry[1:]

        def cond(c, narrower=narrower):
            s, nxt, _, i = c
            running = jnp.sum(~s.done, dtype=jnp.int32)
            # the tail: no candidate left to start, the running walks fit the next phase
            tail = (nxt >= count) & (running <= narrower)
            return (running > 0) & ~tail & (i <= bound)

        carry = jax.lax.while_loop(cond, body, carry)
    return carry[2]
