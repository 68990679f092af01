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
(the identity ``S(n) C(n) = Ct S(n) + S_L C_L + S_R C_R`` of :mod:`jaxbvh.cost`, which
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
1. Every real node but the root searches at once: the traversal is vectorised over
   all nodes as lanes of one ``while_loop``, one step per lane per loop step.
2. Conflicts: a move *locks* ``a``, ``s``, the paths from ``p`` and from ``out`` up to
   their common ancestor (both ends included) and the parents of ``p`` and ``out``
   (their child links change). Moves are ranked by gain (descending), ties by the id
   of ``a`` (smaller first); a move is taken when it ranks first on every node it locks
   (a scatter-min of ranks, then a check). Taken moves lock disjoint node sets, which
   makes them independent: the boxes each one reads are changed by none of the others,
   so each gains exactly what its search found and the order of applying them does not
   matter.
3. All taken moves are applied at once (scatters), then the boxes on each move's two
   changed paths are refitted bottom-up, all moves in lockstep, stopping below the
   common ancestor (whose box cannot change).

Iterations repeat until one takes no move, ``max_iterations``, or ``time_budget``.
The NumPy twin (:mod:`jaxbvh.reference.reinsert`) searches one node at a time with the
same steps and applies the taken moves one by one, in rank order.

Exactness
=========
As in :mod:`jaxbvh.rotate`, decisions must not hinge on the last bit (XLA fuses
multiply-adds, NumPy does not): a place counts as better than the best so far only when
its gain is larger by more than ``min_gain * S(h)``, ``h`` the current highest node (the
largest area the running sums involve), and the walk prunes when the bound is not larger
than best plus that margin, so a pruned place could never have been taken. ``min_gain``
defaults to ``64 * eps`` of the float type.
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.cost import extent_scale, half_area
from jaxbvh.tree import BVH, to_jax

DEFAULT_MAX_STEPS = 1024       # search steps per node and iteration (legocar needs < 200)
DEFAULT_MAX_ITERATIONS = 1000


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ReinsertResult:
    """What :func:`reinsert` returns.

    ``tree``: the optimized :class:`~jaxbvh.tree.BVH` (same capacity as the input).
    ``sah``: its SAH; ``sah_start``: the input's. ``iterations``: iterations run (the
    last one took no move when the optimizer converged). ``moves``: moves applied in
    all. ``history``: SAH after each iteration (NumPy, length ``iterations``).
    """

    tree: Any
    sah: Any
    sah_start: Any
    iterations: Any
    moves: Any
    history: Any


class _State(NamedTuple):
    child: Any   # [N, 2] int32, -1 none
    parent: Any  # [N] int32, -1 none
    lo: Any      # [N, 3]
    hi: Any      # [N, 3]
    root: Any    # [] int32
    area: Any    # [N] scaled half-areas (0 for padding)


RANK_BITS = 8  # low mantissa bits of a gain ignored when moves are ranked


def rank_key(gain):
    """Integer key that orders positive gains, blind to their last :data:`RANK_BITS` bits.

    Works on JAX and NumPy arrays (float32 -> int32, float64 -> int64 keys; a float64
    key is returned by NumPy or by JAX with x64 on).
    """
    if isinstance(gain, np.ndarray) or np.isscalar(gain):
        gain = np.asarray(gain)
        ints = gain.view(np.int32 if gain.dtype == np.float32 else np.int64)
        return ints >> RANK_BITS
    ints = jax.lax.bitcast_convert_type(gain, jnp.int32 if gain.dtype == jnp.float32 else jnp.int64)
    return ints >> RANK_BITS


def default_min_gain(dtype) -> float:
    """Relative margin a better place must beat: ``64 * eps`` of ``dtype``."""
    return float(64 * np.finfo(np.dtype(dtype)).eps)


# ----------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------


def _take(arr, idx):
    """``arr[idx]`` with ids clipped into range (callers mask lanes that had none)."""
    return jnp.take(arr, jnp.clip(idx, 0, arr.shape[0] - 1), axis=0, mode="clip")


def _oob(idx, cap):
    """``-1`` ("none") as the out-of-range id ``cap`` (for ``mode="drop"`` scatters)."""
    return jnp.where(idx < 0, cap, idx)


def _sibling(child, parent, n):
    up = _take(parent, n)
    kids = _take(child, up)
    return jnp.where(kids[..., 0] == n, kids[..., 1], kids[..., 0])


def _refit(child, lo, hi):
    """Every interior box set to the union of its children's (bottom-up sweeps).

    A sweep sets every interior box from its children's; it stops when nothing changes
    (height + 1 sweeps), at most ``N + 1`` sweeps.
    """
    cap = child.shape[0]
    interior = child[:, 0] >= 0
    left, right = child[:, 0], child[:, 1]

    def sweep(lo, hi):
        new_lo = jnp.where(interior[:, None], jnp.minimum(_take(lo, left), _take(lo, right)), lo)
        new_hi = jnp.where(interior[:, None], jnp.maximum(_take(hi, left), _take(hi, right)), hi)
        return new_lo, new_hi

    def cond(c):
        return c[2] & (c[3] <= cap)

    def body(c):
        lo, hi, _, i = c
        new_lo, new_hi = sweep(lo, hi)
        changed = jnp.any(new_lo != lo) | jnp.any(new_hi != hi)
        return new_lo, new_hi, changed, i + 1

    lo, hi, _, _ = jax.lax.while_loop(cond, body, (lo, hi, jnp.bool_(True), jnp.int32(0)))
    return lo, hi


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
    out: Any
    high: Any
    down: Any
    red: Any
    hlo: Any
    hhi: Any
    best: Any
    best_out: Any
    best_lca: Any
    done: Any


def _search(st: _State, scale, max_steps, min_gain):
    """Best place of every node: ``(gain [N], out [N], lca [N])``; ``out = -1``: none."""
    cap = st.child.shape[0]
    dtype = st.lo.dtype
    child, parent, lo, hi, area = st.child, st.parent, st.lo, st.hi, st.area
    left = child[:, 0]
    a = jnp.arange(cap, dtype=jnp.int32)
    valid = parent >= 0  # real nodes but the root (padding has no parent either)
    p = jnp.where(valid, parent, 0)
    alo, ahi = lo, hi
    area_p = _take(area, p)
    base = area_p - area
    start = _sibling(child, parent, a)
    start = jnp.where(valid, start, 0)
    inf = jnp.full((cap, 3), jnp.inf, dtype)
    zero = jnp.zeros(cap, dtype)
    init = _Search(out=start, high=p, down=jnp.ones(cap, bool), red=zero, hlo=inf, hhi=-inf,
                   best=zero, best_out=jnp.full(cap, -1, jnp.int32),
                   best_lca=jnp.full(cap, -1, jnp.int32), done=~valid)

    def merged_area(lo_b, hi_b):
        return half_area(jnp.minimum(alo, lo_b), jnp.maximum(ahi, hi_b), scale)

    def step(s: _Search) -> _Search:
        out = s.out
        olo, ohi = _take(lo, out), _take(hi, out)
        s_out = _take(area, out)
        merged = merged_area(olo, ohi)
        tol = min_gain * _take(area, s.high)
        kids = _take(child, out)

        # going down: out is a candidate place; descend unless a leaf or pruned
        gain_d = area_p - merged + s.red
        take_d = gain_d > s.best + tol
        best_d = jnp.where(take_d, gain_d, s.best)
        red_d = s.red + (s_out - merged)
        stop = (kids[:, 0] < 0) | (red_d + base <= best_d + tol)
        out_d = jnp.where(stop, out, kids[:, 0])

        # going up: leave out's growth behind
        red_u = s.red - (s_out - merged)
        up = _take(parent, out)
        up_kids = _take(child, up)
        at_high = up == s.high
        # below the highest node: the right sibling next, or further up
        from_left = up_kids[:, 0] == out
        out_b = jnp.where(from_left, up_kids[:, 1], up)
        # back at the highest node g: g is a candidate (unless g is p), then climb
        hlo = jnp.minimum(s.hlo, olo)
        hhi = jnp.maximum(s.hhi, ohi)
        g = s.high
        not_p = g != p
        shrunk = half_area(hlo, hhi, scale)
        s_g = _take(area, g)
        gain_a = area_p + red_u + (s_g - shrunk) - merged_area(hlo, hhi)
        take_a = not_p & (gain_a > s.best + tol)
        red_a = jnp.where(not_p, red_u + (s_g - shrunk), red_u)
        top = _take(parent, g)
        finished = top < 0
        top_kids = _take(child, top)
        out_c = jnp.where(top_kids[:, 0] == g, top_kids[:, 1], top_kids[:, 0])

        down, live = s.down, ~s.done
        climb = ~down & at_high
        new = _Search(
            out=jnp.where(down, out_d, jnp.where(at_high, out_c, out_b)),
            high=jnp.where(climb, top, s.high),
            down=jnp.where(down, ~stop, jnp.where(at_high, True, from_left)),
            red=jnp.where(down, red_d, jnp.where(at_high, red_a, red_u)),
            hlo=jnp.where(climb[:, None], hlo, s.hlo),
            hhi=jnp.where(climb[:, None], hhi, s.hhi),
            best=jnp.where(down, best_d, jnp.where(climb & take_a, gain_a, s.best)),
            best_out=jnp.where(down & take_d, out, jnp.where(climb & take_a, g, s.best_out)),
            best_lca=jnp.where(down & take_d, s.high, jnp.where(climb & take_a, g, s.best_lca)),
            done=climb & finished,
        )
        # lanes already done keep their state
        return jax.tree_util.tree_map(
            lambda n, o: jnp.where(live.reshape(live.shape + (1,) * (n.ndim - 1)), n, o), new, s)

    def cond(c):
        s, i = c
        return (i < max_steps) & ~jnp.all(s.done)

    def body(c):
        s, i = c
        return step(s), i + 1

    s, _ = jax.lax.while_loop(cond, body, (init, jnp.int32(0)))
    return s.best, s.best_out, s.best_lca


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
        cur = jnp.where(live, _take(parent, cur), cur)
        return carry, cur, live, i + 1

    carry, _, _, _ = jax.lax.while_loop(cond, body, (carry, starts, active, jnp.int32(0)))
    return carry


def _select(st: _State, gain, out, lca):
    """Which moves are taken (bool [N]): ranked first on every node they lock."""
    cap = st.child.shape[0]
    parent = st.parent
    ids = jnp.arange(cap, dtype=jnp.int32)
    has = out >= 0
    key = jnp.where(has, -rank_key(gain), jnp.iinfo(jnp.int32).max)
    _, _, order = jax.lax.sort((key, ids, ids), num_keys=2)
    rank = jnp.zeros(cap, jnp.int32).at[order].set(ids)
    p = jnp.where(has, parent, 0)
    extra = jnp.stack([ids, _sibling(st.child, parent, ids), _take(parent, p),
                       _take(parent, jnp.maximum(out, 0))], axis=1)  # [N, 4]
    extra = jnp.where(has[:, None], extra, -1)
    none = jnp.int32(cap)
    lock = jnp.full(cap, none, jnp.int32)
    lock = lock.at[_oob(extra, cap)].min(jnp.broadcast_to(rank[:, None], extra.shape), mode="drop")

    def claim(lock, nodes, live):
        return lock.at[jnp.where(live, nodes, cap)].min(rank, mode="drop")

    lock = _walk(parent, p, lca, has, claim, lock, cap)
    lock = _walk(parent, jnp.maximum(out, 0), lca, has, claim, lock, cap)

    def check(ok, nodes, live):
        return ok & (~live | (_take(lock, nodes) == rank))

    ok = has & jnp.all((extra < 0) | (_take(lock, extra) == rank[:, None]), axis=1)
    ok = _walk(parent, p, lca, has, check, ok, cap)
    ok = _walk(parent, jnp.maximum(out, 0), lca, has, check, ok, cap)
    return ok


def _apply(st: _State, taken, out, lca, scale):
    """Apply the taken moves at once, then refit their changed paths (module docstring)."""
    cap = st.child.shape[0]
    child, parent = st.child, st.parent
    a = jnp.arange(cap, dtype=jnp.int32)
    p = jnp.where(taken, parent, 0)
    s = _sibling(child, parent, a)
    g = _take(parent, p)
    y = jnp.maximum(out, 0)
    up = _take(parent, y)
    side_s = jnp.where(_take(child, p)[:, 0] == a, 1, 0)
    side_p = jnp.where(_take(child, g)[:, 0] == p, 0, 1)
    side_y = jnp.where(_take(child, up)[:, 0] == y, 0, 1)

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
            kids = _take(new_child, cur)
            box_lo = jnp.minimum(_take(lo, kids[:, 0]), _take(lo, kids[:, 1]))
            box_hi = jnp.maximum(_take(hi, kids[:, 0]), _take(hi, kids[:, 1]))
            lo = lo.at[jnp.where(live, cur, cap)].set(box_lo, mode="drop")
            hi = hi.at[jnp.where(live, cur, cap)].set(box_hi, mode="drop")
        nxt1 = _take(new_parent, cur1)
        nxt2 = _take(new_parent, cur2)
        live1 = live1 & (nxt1 != stop1) & (nxt1 >= 0) & (i < cap)
        live2 = live2 & (nxt2 != stop2) & (nxt2 >= 0) & (i < cap)
        return lo, hi, jnp.where(live1, nxt1, cur1), jnp.where(live2, nxt2, cur2), live1, live2, i + 1

    lo, hi, *_ = jax.lax.while_loop(cond, body, (st.lo, st.hi, start1, start2, live1, live2,
                                                 jnp.int32(0)))
    return _State(new_child, new_parent, lo, hi, root, _areas(lo, hi, scale))


# ----------------------------------------------------------------------------------
# Jitted pieces and the driver
# ----------------------------------------------------------------------------------


def _scale_of(st: _State):
    return extent_scale(st.lo[st.root], st.hi[st.root])


@jax.jit
def _prepare(tree):
    child = jnp.stack([tree.left, tree.right], axis=1).astype(jnp.int32)
    lo, hi = _refit(child, tree.lo, tree.hi)
    root = jnp.asarray(tree.root, jnp.int32)
    scale = extent_scale(lo[root], hi[root])
    return _State(child, tree.parent.astype(jnp.int32), lo, hi, root, _areas(lo, hi, scale))


@jax.jit
def _iteration(st: _State, prim_count, ct, ci, max_steps, min_gain):
    """One iteration: ``(state, moves taken, total gain, SAH after)``."""
    scale = _scale_of(st)
    gain, out, lca = _search(st, scale, max_steps, min_gain)
    taken = _select(st, gain, out, lca)
    new = _apply(st, taken, out, lca, scale)
    moves = jnp.sum(taken, dtype=jnp.int32)
    return new, moves, jnp.sum(jnp.where(taken, gain, 0)), _interior_sah(new, prim_count, ct, ci)


@jax.jit
def _moves_of(st: _State, max_steps, min_gain):
    """The search and the selection of one iteration (for tests): ``(gain, out, lca, taken)``."""
    scale = _scale_of(st)
    gain, out, lca = _search(st, scale, max_steps, min_gain)
    return gain, out, lca, _select(st, gain, out, lca)


@jax.jit
def _to_tree(tree, st: _State):
    return tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent,
                        lo=st.lo, hi=st.hi, root=st.root)


def _check_tree(tree):
    if not isinstance(tree, BVH):
        raise ValueError(f"tree must be a binary jaxbvh.BVH, got {type(tree).__name__}")


def reinsert(tree, *, ct: float = 1.0, ci: float = 1.0,
             max_iterations: int = DEFAULT_MAX_ITERATIONS, max_steps: int = DEFAULT_MAX_STEPS,
             min_gain: float | None = None, split_axes: bool = True,
             on_iteration: Callable | None = None,
             time_budget: float | None = None) -> ReinsertResult:
    """Parallel reinsertion until an iteration takes no move (module docstring).

    ``tree``: a :class:`~jaxbvh.tree.BVH` (NumPy or JAX arrays, any capacity; leaves of
    any size). ``max_iterations``: most iterations. ``max_steps``: the search bound, in
    steps per node and iteration. ``min_gain``: relative margin (module docstring).
    ``split_axes``: run :func:`jaxbvh.rotate.assign_split_axes` at the end.
    ``on_iteration(i, sah, moves)``: called on the host after every iteration (progress).
    ``time_budget``: seconds after which to stop (at the end of an iteration) with the
    tree so far (the best so far: every iteration lowers the SAH); the clock starts after
    the first iteration, which also compiles. Returns a :class:`ReinsertResult` whose
    tree has the input's capacity.
    """
    from jaxbvh.cost import sah as sah_of
    from jaxbvh.rotate import assign_split_axes

    _check_tree(tree)
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0, got {max_iterations}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if not ct >= 0 or not ci >= 0:
        raise ValueError(f"ct and ci must be >= 0, got ct={ct}, ci={ci}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if on_iteration is not None and not callable(on_iteration):
        raise ValueError(f"on_iteration must be a function (iteration, sah, moves), got {on_iteration!r}")
    tree = to_jax(tree)
    dtype = np.dtype(tree.lo.dtype)
    min_gain = default_min_gain(dtype) if min_gain is None else float(min_gain)
    if not min_gain >= 0:
        raise ValueError(f"min_gain must be >= 0, got {min_gain}")
    sah_start = sah_of(tree, ct, ci)
    st = _prepare(tree)
    history, moves, deadline = [], 0, None
    args = (jnp.asarray(ct, dtype), jnp.asarray(ci, dtype), jnp.int32(max_steps),
            jnp.asarray(min_gain, dtype))
    for i in range(max_iterations if ct > 0 else 0):
        st, taken, _, sah = _iteration(st, tree.prim_count, *args)
        taken, sah = int(taken), float(sah)
        history.append(sah)
        moves += taken
        if on_iteration is not None:
            on_iteration(i, sah, taken)
        if taken == 0:
            break
        if time_budget is not None:
            if deadline is None:
                deadline = time.perf_counter() + time_budget
            elif time.perf_counter() > deadline:
                break
    out = _to_tree(tree, st)
    if split_axes:
        out = assign_split_axes(out)
    return ReinsertResult(out, sah_of(out, ct, ci), sah_start, len(history), moves,
                          np.asarray(history, dtype))
