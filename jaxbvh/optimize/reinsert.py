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
   by at most ``escalate`` (relative; by default 8 over the node count,
   :func:`~jaxbvh.optimize.reinsert_rules.escalate_for`: an iteration's relative drop
   shrinks with the tree's size), and every node is a candidate after one that
   takes no move (the big parents have no move left: what gain remains is spread over
   the small nodes; widening by a few octaves at a time spent a dozen empty
   iterations of growing cost on legocar before reaching them) (coarse to fine;
   ``first_fraction = 1``: Meister & Bittner's every node, every iteration). The default, 1/8
   (:data:`~jaxbvh.optimize.reinsert_rules.DEFAULT_FIRST_FRACTION`), reached tinybvh's
   optimizer SAH soonest: fewer candidates find moves that mostly lock each other near
   the root, more spend the first iterations on small gains. With ``settle`` (off by
   default), a candidate is also skipped while *settled*: its last search found no
   move and no taken move has touched it since (touched: the nodes a move locks, step
   3, and their children after the move); after an iteration over every octave that
   takes no move, every node is searched again, so a run still ends only when an
   iteration over all nodes takes no move. On legocar the skipped nodes held moves
   that the full search finds: fewer moves per iteration, tinybvh's optimizer SAH
   reached later (``docs/time-to-quality.md``), so it is not the default.
2. Search: the candidates' walks run vectorised in
   :func:`~jaxbvh.optimize.reinsert_search.search_width` lanes of one ``while_loop`` (a
   work queue: every :data:`~jaxbvh.optimize.reinsert_search.REFILL_STEPS` steps, lanes
   whose walk ended hand in their result and take the next candidate), over node data
   packed by rows, so the work follows the steps the walks take; once every candidate
   has started, the walks still running move into fewer lanes
   (:func:`~jaxbvh.optimize.reinsert_search.lane_widths`: speed only).
3. Conflicts: a move *locks* ``a``, ``s``, the paths from ``p`` and from ``out`` up to
   their common ancestor (both ends included) and the parents of ``p`` and ``out``
   (their child links change). The moves found (the first
   :func:`~jaxbvh.optimize.reinsert_rules.move_width` in id order) are ranked by gain,
   descending (:func:`rank_key`: gains within about 1% tie),
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
   common ancestor (whose box cannot change). Steps 3 and 4 run in the narrowest of
   :func:`~jaxbvh.optimize.reinsert_moves.move_lanes` that holds the moves found
   (speed only: the same moves in the same ranks).

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

The machinery sits beside this module: :mod:`jaxbvh.optimize.reinsert_search` (the
working tree, the candidates and the search, steps 1-2) and
:mod:`jaxbvh.optimize.reinsert_moves` (ranking, conflicts and application, steps 3-4,
and :func:`~jaxbvh.optimize.reinsert_moves.iteration`, one whole iteration);
:mod:`jaxbvh.optimize.reinsert_rules` holds the host rules the twin shares.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import Checked, ci_knob, ct_knob, integer, knob, min_gain_knob, optional, real, split_axes_knob
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.numerics import on_device
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
from jaxbvh.optimize.reinsert_moves import RANK_MANTISSA, iteration, rank_key  # noqa: F401 (public here)
from jaxbvh.optimize.reinsert_rules import (  # noqa: F401 (DEFAULT_FIRST_FRACTION public here)
    ALL_OCTAVES,
    DEFAULT_ESCALATE,
    DEFAULT_FIRST_FRACTION,
    FIRST_OCTAVES_TRIED,
    candidates_needed,
    escalate_for,
    octaves_holding,
    widening_stop,
)
from jaxbvh.optimize.reinsert_search import prepare, to_tree
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import to_jax
from jaxbvh.tree.split_axes import apply_split_axes

DEFAULT_MAX_STEPS = 1024       # search steps per node and iteration (legocar needs < 200)
DEFAULT_MAX_ITERATIONS = 1000
DEFAULT_SETTLE = False  # measured: reached tinybvh's SAH later on legocar (module docstring)
DEFAULT_WIDEN_UNTIL = None  # widen as the rule says until every node is searched


# ----------------------------------------------------------------------------------
# The candidates of the next iteration
# ----------------------------------------------------------------------------------


def widen(octaves, taken, count, nodes, before, after, escalate):
    """The octaves of the next iteration (module docstring, step 1; traceable).

    One more after an iteration that took moves but lowered the SAH (``before`` ->
    ``after``) by at most ``escalate`` (relative), every node after one that took none
    and from 64 octaves on; unchanged once every node (``count == nodes``) is
    searched or while the gains stay large. The comparison runs in the tree's float type
    (the host loop it replaces, and the twin, compare the same two SAH values in
    float64: they can differ only when the drop lies within rounding of the threshold).
    """
    small = (taken == 0) | (before - after <= escalate * before)
    grown = jnp.where((taken > 0) & (octaves < FIRST_OCTAVES_TRIED), octaves + 1, ALL_OCTAVES)
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
    more octave (None: :data:`~jaxbvh.optimize.reinsert_rules.ESCALATE_NODES` over the
    node count, :func:`~jaxbvh.optimize.reinsert_rules.escalate_for`). ``settle``: skip the settled nodes (module docstring, step 1).
    ``widen_until``: the run ends after an iteration that would widen the candidates
    when that iteration searched at least this share of the nodes (None: never; the
    pipeline's first round hands over to the treelets there, :mod:`jaxbvh.optimize.pipeline`).
    ``ct``, ``ci``: SAH constants. ``min_gain``: relative margin a place must beat (None: ``64 * eps`` of the tree's float type). ``split_axes``: Kensler's
    final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`) in ``result``.
    """

    max_iterations: int = knob(DEFAULT_MAX_ITERATIONS, check=integer(0), metavar="N", help="most iterations")
    max_steps: int = knob(DEFAULT_MAX_STEPS, check=integer(1), metavar="S",
                          help="search steps per node and iteration")
    first_fraction: float = knob(DEFAULT_FIRST_FRACTION, check=real(above=0, maximum=1), metavar="F",
                                 help="about the share of nodes (largest parent area first) searched at "
                                      "first, growing to all; in (0, 1]")
    escalate: float | None = knob(DEFAULT_ESCALATE, check=optional(real(0, finite=False)), type=float,
                                  metavar="E", help="relative SAH drop of an iteration at or below which one "
                                                    "more octave of nodes is searched (none: 8 / nodes)")
    settle: bool = knob(DEFAULT_SETTLE, help="search again only the nodes whose last search found a move "
                                             "or that a move touched since (every node before stopping)")
    widen_until: float | None = knob(DEFAULT_WIDEN_UNTIL, check=optional(real(above=0, maximum=1)), type=float,
                                     metavar="F", help="the run ends at an iteration that would widen the "
                                                       "candidates when they are this share of the nodes or "
                                                       "more (none: never)")
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
    settle: Any     # [] bool: skip settled nodes (module docstring, step 1; traced)
    widen_until: Any  # [] int32: a widening after an iteration over this many candidates or more ends the run


class Inner(NamedTuple):
    """Reinsertion's own loop state."""

    tree: Any     # reinsert_search.State: links, boxes (interior ones tight), root, scaled areas
    octaves: Any  # [] int32: candidates' parent areas reach 2^-octaves of the root's
    nodes: Any    # [] int32: real nodes but the root (every one a candidate at ALL_OCTAVES)
    settled: Any  # [N] bool: last search found no move and no move touched the node since


def init(tree, config: Config | None = None, key=None, *, sah_start=None) -> OptimizerState:
    """The state before the first iteration: boxes refitted tight, the first octaves.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity,
    leaves of any size). ``key``: unused (the method is deterministic). ``sah_start``:
    the tree's SAH with the config's ``ct``, ``ci`` when the caller has it (the pipeline),
    else computed here.
    """
    del key
    check_tree(tree)
    config = check_config(config, Config, "reinsert")
    tree = to_jax(tree)
    dtype = float_dtype(tree)
    min_gain = default_min_gain(dtype) if config.min_gain is None else config.min_gain
    # the node count never changes while optimizing: the first candidates' count is
    # taken here, on the host (reinsert_rules)
    # on the host: an eager jnp sum would compile two small programs
    nodes = int(np.count_nonzero(np.asarray(tree.parent) >= 0))
    escalate = escalate_for(nodes, config.escalate)
    params = Params(*(on_device(x, dtype) for x in (config.ct, config.ci, min_gain, escalate)),
                    max_steps=on_device(config.max_steps, np.int32),
                    need=on_device(candidates_needed(config.first_fraction, nodes), np.int32),
                    split_axes=on_device(config.split_axes, bool), settle=on_device(config.settle, bool),
                    widen_until=on_device(widening_stop(config.widen_until, nodes), np.int32))
    limit = config.max_iterations if config.ct > 0 else 0  # with Ct = 0 no move changes the SAH
    return restart(params, tree, limit, sah_start)


#: ``sah_of(tree, ct, ci)`` as one compiled program (called eagerly, its indexing of the
#: node costs would compile five more small ones); what the optimizers' ``init`` use
start_sah = stored_jit(sah_of)


@stored_jit
def _start(tree, need) -> Inner:
    st = prepare(tree)
    octaves = octaves_holding(st.area, st.parent, st.root, need, xp=jnp)
    return Inner(st, octaves, jnp.sum(st.parent >= 0, dtype=jnp.int32), jnp.zeros(st.parent.shape, bool))


def restart(params: Params, tree, limit: int, sah_start=None) -> OptimizerState:
    """The state of a fresh run on ``tree`` (a JAX BVH) with these settings (traceable:
    the pipeline starts each reinsertion stage with it). ``limit``: most iterations.
    ``sah_start``: the tree's SAH with ``params.ct``, ``params.ci`` (None: computed here)."""
    sah_start = start_sah(tree, params.ct, params.ci) if sah_start is None else sah_start
    progress = new_progress(sah_start, limit, float_dtype(tree))
    # every setting is traced (no static part): one compiled program for every config
    return OptimizerState(tree, progress, params, _start(tree, params.need), None)


def step(state: OptimizerState) -> OptimizerState:
    """One iteration: search the candidates, take the independent best moves, apply
    them; widen the candidates when the gain gets small (module docstring)."""
    p, inner, progress = state.params, state.inner, state.progress
    st, taken, _, sah, count, settled = iteration(inner.tree, state.tree.prim_count, p.ct, p.ci, inner.octaves,
                                                   p.max_steps, p.min_gain, inner.settled & p.settle)
    octaves = widen(inner.octaves, taken, count, inner.nodes, progress.sah, sah, p.escalate)
    # no move among the unsettled nodes of every octave: search every node again
    settled = settled & ~((taken == 0) & (inner.octaves >= ALL_OCTAVES))
    progress = record(progress, sah, taken, converged=(taken == 0) & (count == inner.nodes))
    # widen_until: the run ends here, with this iteration's tree, instead of widening
    progress = progress._replace(done=progress.done | ((octaves != inner.octaves) & (count >= p.widen_until)))
    inner = inner._replace(tree=st, octaves=octaves, settled=settled)
    return keep_if_done(state, state.replace(inner=inner, progress=progress))


def tree_of(state: OptimizerState):
    """The state's tree (same capacity as the input), without :func:`result`'s split-axis
    pass and SAH (traceable; what the pipeline hands to its next stage)."""
    return to_tree(state.tree, state.inner.tree)


def result(state: OptimizerState) -> OptimizeResult:
    """The optimized tree (same capacity as the input) and the run's figures."""
    out = tree_of(state)
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
