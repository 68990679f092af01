"""Treelet restructuring (Karras & Aila 2013): SAH-optimal topology of small treelets.

Treelets
========
The *treelet* of an interior node ``r`` is grown from ``r``'s two children: while it has
fewer than ``n`` leaves (default 7, as in the paper), the treelet leaf of largest surface
area that is an interior node of the tree is replaced by its two children (the first in
the treelet's leaf list among those within ``min_gain`` of the largest area; the new
children take the expanded leaf's slot and the next free one). Its *interior* nodes are ``r`` and the expanded nodes, ``k - 1`` of them
for ``k`` leaves; subtrees below the treelet leaves are left alone. Fewer leaves are
taken when the subtree has no more interior nodes to expand.

Optimal topology (dynamic programming over subsets)
===================================================
With ``c(x) = S(x) C(x)`` (area-weighted cost; ``S`` the scaled half-area, ``C`` the
node cost of :mod:`jaxbvh.tree.cost`), an interior node costs ``c(x) = Ct S(x) + c(L) +
c(R)`` (this holds for zero-area nodes too). The best binary tree over a set ``L`` of
treelet leaves (a bitmask over the ``k`` leaves) therefore costs

    ``c*(L) = Ct S(union of L) + min over splits (P, L \\ P) of c*(P) + c*(L \\ P)``

with ``c*({x}) = c(x)``. Sets are solved in order of size; the splits of ``L`` are the
proper subsets ``P`` that contain ``L``'s lowest leaf, in increasing bitmask order (each
unordered split once: ``2^(|L|-1) - 1`` of them, 966 for all sets of 7 leaves), and the
first split within ``min_gain * c*`` of the least is taken. The topology is rebuilt
top-down from the chosen splits, reusing the treelet's interior node ids in the order
the sets are reached breadth first (``r`` keeps the whole set, so its parent link does
not change); the subset containing the lowest leaf goes left. A treelet is restructured
only when ``c*`` is below its current cost by more than ``min_gain`` (relative), so no
move is made on rounding noise (the same rule as :mod:`jaxbvh.optimize.rotate`; ``min_gain``
defaults to ``64 * eps``). Leaves keep their primitives and boxes; interior boxes are
unions of their leaves' boxes (all interior boxes are refitted tight first).

Rounds
======
One *pass* visits every interior node once, as a treelet root, in order of height
(longest path to a leaf) measured when the pass starts, lowest first (nodes of height 1
root two-leaf treelets, whose one topology is the current one: they are passed over,
:data:`SKIPPED_HEIGHT`, speed only; the twin solves them and finds nothing): nodes of one
height have disjoint subtrees, hence disjoint treelets, and are solved together (the
DP vmapped over every treelet of a window of nodes); by the time a node is solved, every
node below it has been (restructuring only permutes ids inside a subtree). A pass solves
only the *fresh* nodes (``Inner.fresh``, speed only): every node before the first pass,
then the nodes a changed treelet rewrote and their ancestors; any other node was solved
with the subtree it still has and found no change, which solving it again would find too
(fresh before legocar's second pass: 3,338 of its 5,297 interior nodes; its third: 1,465).
:func:`resume` carries this over a reinsertion stage in the pipeline: a node stays
settled when no move rewrote a link in its subtree. Passes repeat
until one restructures nothing, ``max_passes`` (the paper uses 3), or ``time_budget``.
The NumPy twin (:mod:`jaxbvh.optimize.treelet_reference`) solves the same treelets one at a time,
in the same order, by the same recursion.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import Checked, ci_knob, ct_knob, integer, knob, min_gain_knob, optional, sizes, split_axes_knob
from jaxbvh.numerics import extent_scale, half_area, on_device, rounded, take_clipped
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
from jaxbvh.optimize.reinsert import start_sah
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import to_jax
from jaxbvh.tree.refit import refit_boxes
from jaxbvh.tree import windows as level_windows
from jaxbvh.tree.split_axes import apply_split_axes

DEFAULT_LEAVES = 7
MAX_LEAVES = 10        # 2^n subsets and 3^n splits: beyond this the DP is too large
DEFAULT_MAX_PASSES = 8
DEFAULT_WINDOWS = None  # treelets solved at once: by capacity (window_sizes)
#: windows of a tree of fewer nodes than SMALL_WINDOWS_FROM, and of one of more
WINDOWS_SMALL_TREE, WINDOWS_LARGE_TREE = (256,), (256, 16)
SMALL_WINDOWS_FROM = 4096
#: a pass solves the treelets of nodes above this height only: a node of height 1 (two leaf
#: children) roots a two-leaf treelet, whose one topology is the current one (speed only,
#: never the result; a pass over legocar solved 5,297 treelets, 1,976 of them of two leaves)
SKIPPED_HEIGHT = 1




# ----------------------------------------------------------------------------------
# Static tables of sets and splits
# ----------------------------------------------------------------------------------


def splits(mask: int) -> list[int]:
    """The splits of a set (bitmask): proper subsets holding its lowest member, increasing."""
    low = mask & -mask
    return [p for p in range(1, mask) if p & mask == p and p & low]


@lru_cache(maxsize=None)
def tables(n: int):
    """Host tables for treelets of up to ``n`` leaves.

    ``members`` [2^n, n] bool; ``popcount`` [2^n]; ``single`` [2^n] (index of the one
    member, -1 otherwise); ``sizes``: for each set size ``s >= 2`` a pair ``(sets [m],
    parts [m, 2^(s-1) - 1])`` of bitmasks.
    """
    count = 1 << n
    members = np.array([[(m >> j) & 1 for j in range(n)] for m in range(count)], bool)
    popcount = members.sum(axis=1).astype(np.int32)
    single = np.full(count, -1, np.int32)
    for j in range(n):
        single[1 << j] = j
    sizes = []
    for s in range(2, n + 1):
        sets = np.array([m for m in range(count) if popcount[m] == s], np.int32)
        parts = np.array([splits(int(m)) for m in sets], np.int32)
        sizes.append((sets, parts))
    return members, popcount, single, tuple(sizes)


# ----------------------------------------------------------------------------------
# One treelet (vmapped over a window)
# ----------------------------------------------------------------------------------


class _State(NamedTuple):
    child: Any   # [N, 2] int32
    parent: Any  # [N] int32
    lo: Any      # [N, 3]
    hi: Any      # [N, 3]
    cost: Any    # [N] area-weighted cost c(x) = S(x) C(x)
    area: Any    # [N] scaled half-area



def _form(st: _State, root, n, min_gain):
    """Leaves [n] (-1 past ``k``), interior nodes [n-1] (-1 past ``k-1``) and ``k``."""
    kids = take_clipped(st.child, root)
    leaves = jnp.full(n, -1, jnp.int32).at[0].set(kids[0]).at[1].set(kids[1])
    inner = jnp.full(n - 1, -1, jnp.int32).at[0].set(root)
    def grow_one(_, carry):
        leaves, inner, k = carry
        present = leaves >= 0
        expandable = present & (take_clipped(st.child, leaves)[:, 0] >= 0)
        areas = jnp.where(expandable, take_clipped(st.area, leaves), -jnp.inf)
        largest = jnp.max(areas)
        j = jnp.argmax(expandable & (areas >= largest - rounded(min_gain * jnp.abs(largest))))
        grow = expandable[j]
        x = leaves[j]
        xk = take_clipped(st.child, x)
        leaves = jnp.where(grow, leaves.at[j].set(xk[0]).at[k].set(xk[1], mode="drop"), leaves)
        inner = jnp.where(grow, inner.at[k - 1].set(x, mode="drop"), inner)
        return leaves, inner, k + grow.astype(jnp.int32)

    leaves, inner, k = jax.lax.fori_loop(0, n - 2, grow_one, (leaves, inner, jnp.int32(2)))
    return leaves, inner, k


def _solve(st: _State, root, scale, ct, min_gain, n):
    """Form and solve the treelet of ``root``; returns what to write back."""
    # products that feed an add pass numerics.rounded: one rounding in every program (vmapped too)
    members, popcount, single, sizes = tables(n)
    count = 1 << n
    leaves, inner, k = _form(st, root, n, min_gain)
    present = leaves >= 0
    leaf_lo = jnp.where(present[:, None], take_clipped(st.lo, leaves), jnp.inf)
    leaf_hi = jnp.where(present[:, None], take_clipped(st.hi, leaves), -jnp.inf)
    member = jnp.asarray(members)[:, :, None]                          # [2^n, n, 1]
    set_lo = jnp.min(jnp.where(member, leaf_lo[None], jnp.inf), axis=1)   # [2^n, 3]
    set_hi = jnp.max(jnp.where(member, leaf_hi[None], -jnp.inf), axis=1)
    set_area = half_area(set_lo, set_hi, scale)
    leaf_cost = jnp.where(present, take_clipped(st.cost, leaves), 0)
    cost = jnp.zeros(count, st.cost.dtype).at[1 << np.arange(n)].set(leaf_cost)
    part = jnp.zeros(count, jnp.int32)
    for sets, parts in sizes:
        total = cost[parts] + cost[sets[:, None] ^ parts]                # [m, splits]
        least = jnp.min(total, axis=1)
        near = total <= (least + rounded(min_gain * jnp.abs(least)))[:, None]
        pick = jnp.argmax(near, axis=1)
        cost = cost.at[sets].set(rounded(ct * set_area[sets]) + least)
        part = part.at[sets].set(jnp.take_along_axis(jnp.asarray(parts), pick[:, None], axis=1)[:, 0])
    full = (jnp.int32(1) << k) - 1
    kids = take_clipped(st.child, root)
    current = rounded(ct * take_clipped(st.area, root)) + take_clipped(st.cost, kids[0]) + take_clipped(st.cost, kids[1])
    best = cost[full]
    change = best < current - rounded(min_gain * jnp.abs(current))

    # rebuild breadth first: queue position i holds the set of interior node inner[i]
    popcount = jnp.asarray(popcount)
    single = jnp.asarray(single)
    def place(i, carry):
        queue, nxt, new_child = carry
        active = i < k - 1
        s = queue[i]
        p = part[s]
        ids = []
        for m in (p, s ^ p):
            one = popcount[m] == 1
            ids.append(jnp.where(one, leaves[jnp.maximum(single[m], 0)], inner[jnp.minimum(nxt, n - 2)]))
            push = active & ~one
            queue = jnp.where(push, queue.at[jnp.minimum(nxt, n - 2)].set(m), queue)
            nxt = nxt + push.astype(jnp.int32)
        return queue, nxt, new_child.at[i].set(jnp.stack(ids))

    queue, _, new_child = jax.lax.fori_loop(
        0, n - 1, place, (jnp.zeros(n - 1, jnp.int32).at[0].set(full), jnp.int32(1),
                          jnp.zeros((n - 1, 2), jnp.int32)))
    new = (new_child, set_lo[queue], set_hi[queue], cost[queue], set_area[queue])
    return change, inner, k, new, current


def _process(st: _State, roots, scale, ct, min_gain, n):
    """Solve the treelets of ``roots`` [W] (``N``: none; disjoint) and write them back."""
    cap = st.child.shape[0]
    live = roots < cap
    change, inner, k, new, current = jax.vmap(
        lambda r: _solve(st, r, scale, ct, min_gain, n))(roots)
    new_child, new_lo, new_hi, new_cost, new_area = new
    change = change & live
    slot = jnp.arange(n - 1)[None, :] < (k - 1)[:, None]               # [W, n-1]
    write = change[:, None] & slot
    at = jnp.where(write, inner, cap)
    child = st.child.at[at].set(new_child, mode="drop")
    kid_at = jnp.where(write[..., None], new_child, cap)
    parent = st.parent.at[kid_at].set(jnp.broadcast_to(inner[..., None], kid_at.shape), mode="drop")
    lo = st.lo.at[at].set(new_lo, mode="drop")
    hi = st.hi.at[at].set(new_hi, mode="drop")
    cost = st.cost.at[at].set(new_cost, mode="drop")
    area = st.area.at[at].set(new_area, mode="drop")
    # an unchanged root still takes the cost of its (improved) children
    cost = cost.at[jnp.where(live & ~change, roots, cap)].set(current, mode="drop")
    return _State(child, parent, lo, hi, cost, area), jnp.sum(change, dtype=jnp.int32), at


# ----------------------------------------------------------------------------------
# Passes
# ----------------------------------------------------------------------------------


def _to_fixpoint(update, start, cap: int):
    """``update`` applied to ``start`` until it changes nothing: at most ``cap + 1``
    sweeps (a bound: a walk up or down a tree of ``cap`` nodes settles within ``cap``)."""

    def cond(c):
        return c[1] & (c[2] <= cap)

    def body(c):
        x, _, i = c
        new = update(x)
        return new, jnp.any(new != x), i + 1

    out, _, _ = jax.lax.while_loop(cond, body, (start, jnp.bool_(True), jnp.int32(0)))
    return out


def _heights(child):
    """Height of every node [N] (leaves and padding 0), by sweeps (at most N + 1)."""
    interior = child[:, 0] >= 0
    return _to_fixpoint(
        lambda h: jnp.where(interior, 1 + jnp.maximum(take_clipped(h, child[:, 0]), take_clipped(h, child[:, 1])), 0),
        jnp.zeros(child.shape[0], jnp.int32), child.shape[0])


def _costs(child, area, prim_count, ct, ci):
    """Area-weighted costs ``c(x)`` of every node [N] by bottom-up sweeps."""
    cap = child.shape[0]
    interior = child[:, 0] >= 0
    leaf = ci * prim_count.astype(area.dtype) * area

    def cond(c):
        return c[1] & (c[2] <= cap)

    def body(c):
        cost, _, i = c
        new = jnp.where(interior, rounded(ct * area) + take_clipped(cost, child[:, 0]) + take_clipped(cost, child[:, 1]), leaf)
        return new, jnp.any(new != cost), i + 1

    cost, _, _ = jax.lax.while_loop(cond, body, (leaf, jnp.bool_(True), jnp.int32(0)))
    return cost


def window_sizes(capacity: int, windows=None) -> tuple:
    """The windows of a pass over a tree of ``capacity`` nodes (speed only, never the
    result): ``windows`` when given, else :data:`WINDOWS_LARGE_TREE` from
    :data:`SMALL_WINDOWS_FROM` nodes on and :data:`WINDOWS_SMALL_TREE` below.

    Every height of the pass takes at least one window, and the top heights hold a few
    nodes each: with windows of 256 alone, legocar's first pass (5,297 interior nodes,
    20 heights, 15 of them under 256 nodes) solved 9,216 treelets for 5,297 roots and
    took 125 ms; with a window of 16 for what is left of each height, 74 ms (CPU, min
    of 5; drone 0.29 -> 0.23 s). Each size is one more compiled copy of the dynamic
    programme (compiling a 512-node tree's pass took 2x as long with three sizes), so
    small trees, which pass quickly anyway, keep one.
    """
    if windows is not None:
        return tuple(windows)
    return WINDOWS_LARGE_TREE if capacity >= SMALL_WINDOWS_FROM else WINDOWS_SMALL_TREE


def _above(marked, child):
    """``marked`` [N] bool and every ancestor of a marked node, by sweeps (at most N + 1)."""
    interior = child[:, 0] >= 0
    return _to_fixpoint(
        lambda m: m | (interior & (take_clipped(m, child[:, 0]) | take_clipped(m, child[:, 1]))),
        marked, child.shape[0])


def _pass(st: _State, fresh, scale, ct, min_gain, *, n, windows):
    """One bottom-up pass over the fresh interior nodes (module docstring, Passes);
    returns the state, the treelets changed and the nodes fresh for the next pass."""
    cap = st.child.shape[0]
    big = jnp.int32(2 ** 31 - 1)
    height = _heights(st.child)
    # a node whose children are both leaves (height 1) roots a treelet of two leaves, which
    # has one topology: solving it never changes anything, so it is not solved (37 % of
    # legocar's interior nodes; SKIPPED_HEIGHT); nor is a node that is not fresh
    solved = (height > SKIPPED_HEIGHT) & fresh
    height = jnp.where(solved, height, big)
    order = jnp.argsort(height, stable=True).astype(jnp.int32)
    keys = height[order]
    count = jnp.sum(solved, dtype=jnp.int32)
    widths = tuple(sorted({min(w, cap) for w in windows}, reverse=True))
    order = jnp.concatenate([order, jnp.full(widths[0], cap, jnp.int32)])

    def visit(carry, start, valid):
        st, changed, rewritten = carry
        roots = jnp.where(valid, jax.lax.dynamic_slice(order, (start,), (valid.shape[0],)), cap)
        st, made, at = _process(st, roots, scale, ct, min_gain, n)
        return st, changed + made, rewritten.at[at].set(True, mode="drop")

    st, changed, rewritten = level_windows.by_runs(
        visit, (st, jnp.int32(0), jnp.zeros(cap, bool)), keys, count, widths)
    # fresh for the next pass: the nodes a changed treelet rewrote and their ancestors in the
    # new tree; every other node was solved (now or before) with the subtree it has, found
    # no change and would find none again (Passes)
    return st, changed, _above(rewritten, st.child)


class Params(NamedTuple):
    """Settings passed as traced values (changing them does not recompile)."""

    ct: Any          # [] tree dtype: SAH cost of a traversal step
    ci: Any          # [] tree dtype: SAH cost of a primitive test
    min_gain: Any    # [] tree dtype: relative margin (module docstring)
    split_axes: Any  # [] bool: Kensler's final pass in result() (traced: no program of its own)


class Static(NamedTuple):
    """Settings that fix the compiled program."""

    leaves: int         # treelet size n
    windows: tuple      # treelets solved at once (speed only; window_sizes)


class Inner(NamedTuple):
    """Treelet restructuring's own loop state: the tree's links and boxes, kept tight."""

    tree: Any   # _State: child, parent, lo, hi, area-weighted cost, area
    scale: Any  # [] the area scale of the root box
    fresh: Any  # [N] bool: solve this node's treelet in the next pass (module docstring, Passes)


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    """Knobs of treelet restructuring (Karras & Aila 2013), with the paper's defaults.

    ``leaves``: treelet size ``n`` (2 .. :data:`MAX_LEAVES`; the paper's 7; each size
    compiles its own program). ``max_passes``: most passes (the paper uses 3; 8 lets the
    last gains in). ``ct``, ``ci``: SAH constants. ``min_gain``: relative margin a
    change must beat (None: ``64 * eps`` of the tree's float type,
    :func:`jaxbvh.numerics.min_gain`). ``split_axes``: Kensler's final pass
    (:func:`jaxbvh.tree.split_axes.assign_split_axes`) in ``result`` (a traced setting:
    no program of its own). ``windows``: treelets solved at once (speed only, never the
    result; None: by the tree's capacity, :func:`window_sizes`).
    """

    leaves: int = knob(DEFAULT_LEAVES, check=integer(2, MAX_LEAVES), metavar="N",
                       help="treelet size: leaves of a treelet (each size compiles its own program)")
    max_passes: int = knob(DEFAULT_MAX_PASSES, check=integer(0), metavar="P", help="most passes")
    ct: float = ct_knob()
    ci: float = ci_knob()
    min_gain: float | None = min_gain_knob()
    split_axes: bool = split_axes_knob()
    windows: tuple | None = knob(DEFAULT_WINDOWS, check=optional(sizes),
                                 help="treelets solved at once (speed only; none: by the tree's capacity)")


@stored_jit
def _prepare(tree, ct, ci) -> Inner:
    child = jnp.stack([tree.left, tree.right], axis=1).astype(jnp.int32)
    lo, hi = refit_boxes(child, tree.lo, tree.hi)
    scale = extent_scale(lo[tree.root], hi[tree.root])
    area = half_area(lo, hi, scale)
    cost = _costs(child, area, tree.prim_count, ct, ci)
    fresh = jnp.ones(child.shape[0], bool)  # nothing solved yet
    return Inner(_State(child, tree.parent.astype(jnp.int32), lo, hi, cost, area), scale, fresh)


def _sah(st: _State, root, prim_count, ct, ci):
    """SAH from the area-weighted cost of the root."""
    root_area = st.area[root]
    dtype = st.lo.dtype
    flat = rounded(ct * jnp.sum(st.child[:, 0] >= 0).astype(dtype)) + rounded(ci * jnp.sum(prim_count).astype(dtype))
    return jnp.where(root_area > 0, st.cost[root] / jnp.where(root_area > 0, root_area, 1), flat)


def init(tree, config: Config | None = None, key=None, *, sah_start=None) -> OptimizerState:
    """The state before the first pass: boxes refitted tight, costs of every node.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity,
    leaves of any size). ``key``: unused (the method is deterministic). ``sah_start``:
    the tree's SAH with the config's ``ct``, ``ci`` when the caller has it (the pipeline:
    computing it takes a sweep per level), else computed here.
    """
    del key
    check_tree(tree)
    config = check_config(config, Config, "treelet")
    dtype = float_dtype(tree)
    if dtype not in (np.float32, np.float64):
        # float16 (as a user's arrays may be) made every pass restructure one treelet and
        # the next undo it (its areas round the DP's gain away): passes ran to max_passes,
        # each slow in emulated float16, and never converged. Tree files are widened on load
        raise ValueError(f"treelet restructuring needs float32 or float64 boxes, got {dtype}: "
                         "widen them (float16 to float32 is exact)")
    tree = to_jax(tree)
    min_gain = default_min_gain(dtype) if config.min_gain is None else config.min_gain
    params = Params(*(on_device(x, dtype) for x in (config.ct, config.ci, min_gain)),
                    split_axes=on_device(config.split_axes, bool))
    inner = _prepare(tree, params.ct, params.ci)
    limit = config.max_passes if config.leaves > 2 else 0  # two-leaf treelets cannot change
    sah_start = start_sah(tree, config.ct, config.ci) if sah_start is None else sah_start
    progress = new_progress(sah_start, limit, dtype)
    return OptimizerState(tree, progress, params, inner,
                          Static(int(config.leaves), window_sizes(tree.left.shape[0], config.windows)))


def resume(previous: OptimizerState, tree, config: Config | None = None) -> OptimizerState:
    """:func:`init` on ``tree``, a tree made from ``previous``'s latest tree by moves that
    keep node ids (reinsertion), with the nodes whose subtree no move changed left as
    ``previous`` had them: not solved again until a pass changes their subtree (module
    docstring, Passes). Traceable (the pipeline starts each round's treelets with it);
    ``previous``: a state of this optimizer on a tree of the same capacity and leaves."""
    state = init(tree, config)
    old, child = previous.inner, state.inner.tree.child
    moved = jnp.any(child != old.tree.child, axis=1)  # a move rewrote its links
    return state.replace(inner=state.inner._replace(fresh=_above(old.fresh | moved, child)))


def step(state: OptimizerState) -> OptimizerState:
    """One pass over every interior node, lowest first (module docstring)."""
    p, static, inner = state.params, state.static, state.inner
    st, changed, fresh = _pass(inner.tree, inner.fresh, inner.scale, p.ct, p.min_gain, n=static.leaves,
                               windows=static.windows)
    sah = _sah(st, state.tree.root, state.tree.prim_count, p.ct, p.ci)
    progress = record(state.progress, sah, changed, converged=changed == 0)
    return keep_if_done(state, state.replace(inner=inner._replace(tree=st, fresh=fresh), progress=progress))


def tree_of(state: OptimizerState):
    """The state's tree (same capacity as the input), without :func:`result`'s split-axis
    pass and SAH (traceable; what the pipeline hands to its next stage)."""
    st = state.inner.tree
    return state.tree.replace(left=st.child[:, 0], right=st.child[:, 1], parent=st.parent, lo=st.lo, hi=st.hi)


def result(state: OptimizerState) -> OptimizeResult:
    """The restructured tree (same capacity as the input) and the run's figures."""
    out = tree_of(state)
    out = jax.lax.cond(state.params.split_axes, apply_split_axes, lambda t: t, out)
    progress = state.progress._replace(sah=sah_of(out, state.params.ct, state.params.ci))
    return make_result(out, progress)


TREELET = Optimizer("treelet", Config, init, step, result, paper="Karras & Aila 2013")


class Treelet(NamedTuple):
    """One treelet, formed and solved alone (:func:`solve`); ``k`` leaves, ``n`` = ``Config.leaves``."""

    improves: Any  # [] bool: the best topology beats the current one by more than min_gain (a pass rewrites it)
    inner: Any     # [n - 1] int32: its interior nodes, the root first, in the order formed (-1 past k - 1)
    leaves: Any    # [] int32: k, its leaf count
    best: Any      # [] least area-weighted cost c* over every binary tree of its leaves
    current: Any   # [] area-weighted cost of its present topology


@stored_jit
def solve(state: OptimizerState, root) -> Treelet:
    """Form and solve the treelet of ``root`` (an interior node) in ``state``, writing nothing back.

    The unit of work of a pass (module docstring: formation and the dynamic programme over
    subsets), open to tests and study. ``state``: from :func:`init` or :func:`step`; its
    ``Config.leaves``, ``ct`` and ``min_gain`` apply; costs are area-weighted in the state's
    area scale (that of the root box). Returns a :class:`Treelet`.
    """
    p, inner = state.params, state.inner
    improves, ids, k, new, current = _solve(inner.tree, jnp.asarray(root, jnp.int32), inner.scale, p.ct,
                                            p.min_gain, state.static.leaves)
    return Treelet(improves, ids, k, new[3][0], current)


def restructure(tree, *, time_budget: float | None = None, on_step: Callable | None = None,
                **config) -> OptimizeResult:
    """Treelet restructuring, pass after pass, until a pass changes nothing (module docstring).

    ``config``: fields of :class:`Config` (e.g. ``leaves=7``, ``max_passes=8``).
    ``time_budget``, ``on_step(info)``: as :func:`jaxbvh.optimize.driver.run` (the run
    stops after a pass with the tree so far: every pass lowers the SAH).
    """
    return run(TREELET, tree, Config(**config), time_budget=time_budget, on_step=on_step)
