"""The pipeline: rounds of treelet restructuring and parallel reinsertion, as one optimizer.

Rounds
======
A round is a *treelet stage*, passes of treelet restructuring (Karras & Aila 2013,
:mod:`jaxbvh.optimize.treelet`; ``treelet_passes``, default 2, or fewer when a pass
restructures nothing; the first round may have its own ``first_treelet_passes``), then
a *reinsertion stage*, parallel reinsertion (Meister & Bittner 2018,
:mod:`jaxbvh.optimize.reinsert`) until an iteration over all nodes takes
no move (or its ``max_iterations``). The first round's reinsertion starts from the nodes
of largest parent area (``first_fraction`` of the reinsertion config, 1/8) and widens
octave by octave, until it would widen candidates that are ``widen_until`` (0.45) of
the nodes or more: there it hands over to the next round's treelets (an iteration over
half the nodes costs nearly what one over all does); later rounds search every node
from the start, since the gains left are spread thin. Rounds repeat until one lowers the SAH by less than ``round_gain``
(relative, default 1e-3; the run has then *converged*) or after ``max_rounds`` (8).

The two move sets are complementary: reinsertion moves whole subtrees anywhere in the
tree, treelets rearrange up to 7 neighbouring subtrees optimally; each stops where the
other still finds gains, and together they end below either alone
(``bench/bench_optimize.py``; rotations add nothing after treelets, whose 7-leaf optimum
includes every rotation at their root). Starting with treelets gave the lower SAH on the
tinybvh trees.

Leaves
======
The stages move subtrees and never look inside a leaf; the run ends with the exact
bottom-up merge (``max_leaf``, :mod:`jaxbvh.optimize.leaves`), so leaves can only grow.
Given the primitives' boxes (``init(..., prims=(lo, hi))``, :func:`pipeline`), :func:`init`
first splits every leaf of several primitives into one-primitive leaves
(:mod:`jaxbvh.optimize.split`): the stages then move single primitives and the merge
decides every leaf afresh, so leaves change both ways. Measured
(``bench/results/leaves.md``, split section): lower on every bench input for trees of the
sweep builder (the same tree as building with ``max_leaf`` 1), mixed after spatial splits
(SBVH: lower on the small meshes, higher on legocar and the interior), so it is the
caller's choice; a tree alone (no primitive boxes) keeps its leaves until the merge.

On the protocol
===============
:data:`PIPELINE` is an optimizer of :mod:`jaxbvh.optimize.protocol` whose stages are
``("treelet", "reinsert")``. Its loop state holds one state of each stage's optimizer;
one ``step`` is one step of the current stage (a treelet pass or a reinsertion
iteration, chosen by ``lax.cond`` on the stage counter), recorded with its stage in the
history. When that stage's state is done, the next stage starts (traced, inside the same
step) from its tree: the links and boxes go on from one stage to the next, and a stage
that has nothing to do (two-leaf treelets, ``ct = 0``) is passed over at once; a later
round's treelet stage starts with :func:`jaxbvh.optimize.treelet.resume`, so the treelets
the last stage found optimal and no reinsertion move changed are not solved again (speed
only: the same trees). A round
ends when its reinsertion stage is done. For one tree the driver does not compile that
``step`` (both stages in one program, the largest the library had): :func:`advance` runs
each stage in its own optimizer's compiled loop and hands over on the host, reaching the
same state (tested); batches vmap ``step``. Each stage is held equal to its NumPy twin, and
the pipeline equal to the stages chained by hand (``tests/optimize/test_optimize.py``), so it has
no twin of its own.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import Checked, ci_knob, config_of, ct_knob, integer, knob, max_leaf_knob, optional, real, split_axes_knob
from jaxbvh.numerics import on_device
from jaxbvh.optimize import reinsert, treelet
from jaxbvh.optimize.driver import advance as driver_advance
from jaxbvh.optimize.driver import run
from jaxbvh.optimize.leaves import merge_leaves
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
from jaxbvh.optimize.reinsert_rules import candidates_needed
from jaxbvh.optimize.split import split_leaves
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import capacity_bucket, pad_to, to_jax
from jaxbvh.tree.split_axes import apply_split_axes

DEFAULT_TREELET_PASSES = 2
DEFAULT_FIRST_TREELET_PASSES = None
DEFAULT_ROUND_GAIN = 1e-3
DEFAULT_MAX_ROUNDS = 8
#: the first round's reinsertion hands over to the treelets instead of widening its
#: candidates once they are this share of the nodes (reinsert.Config.widen_until). Past
#: about half the nodes an iteration costs nearly what a later round's iteration over
#: every node does, while a treelet pass gains as much as several of them. Measured on
#: legocar (pipeline under the driver, CPU seconds to tinybvh's Optimize(200) SAH, the
#: same process): none 0.81 - 0.94 s (26 steps); 0.35: 0.81 - 0.93 (23 steps); 0.45:
#: 0.62 - 0.80 (24 steps); 0.6: 1.01 - 1.08 (26 steps); drone reaches it before its first
#: handover (unchanged, and ends lower in a 6 s budget: 12.731 against 12.744).
DEFAULT_WIDEN_UNTIL = 0.45

#: the stages, in the order of a round (``progress.stage`` and ``history_stage`` index it)
STAGES = ("treelet", "reinsert")
TREELETS, REINSERTION = 0, 1


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    """Knobs of the pipeline (module docstring), with the defaults.

    ``round_gain``: a round that lowers the SAH by less than this (relative) is the
    last. ``max_rounds``: most rounds. ``treelet_passes``: most treelet passes per
    round; ``first_treelet_passes``: those of the first round (None: ``treelet_passes``;
    0: the run starts with reinsertion; measured in ``docs/time-to-quality.md``). ``treelet``: the treelet stage's :class:`jaxbvh.optimize.treelet.Config`
    (or a dict of its fields); ``reinsert``: the reinsertion stage's
    :class:`jaxbvh.optimize.reinsert.Config` (or a dict), whose ``first_fraction``
    applies to the first round (later rounds search every node) and whose
    ``max_iterations`` bounds each stage. ``ct``, ``ci``: SAH constants of both stages.
    ``split_axes``: Kensler's final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`)
    in ``result``. ``widen_until``: the first round's reinsertion ends at a widening of
    candidates that are this share of the nodes or more (None: it widens to every node;
    later rounds search every node and never widen). The pipeline's ``ct``, ``ci``,
    ``treelet_passes``, ``widen_until`` replace those of the stage configs (as stored
    here), and the stages never assign split axes themselves. ``max_leaf``: ``result``
    merges every subtree of at most this many primitives into one leaf where that lowers
    the SAH (:mod:`jaxbvh.optimize.leaves`, exact; before the split-axis pass; 1: no
    merge), so the run ends with the leaves the scene needs whatever leaves it started with.
    """

    round_gain: float = knob(DEFAULT_ROUND_GAIN, check=real(0, finite=False), metavar="G",
                             help="the last round is the first that lowers the SAH by less than this "
                                  "(relative)")
    max_rounds: int = knob(DEFAULT_MAX_ROUNDS, check=integer(1), metavar="R",
                           help="most rounds of treelets and reinsertion")
    treelet_passes: int = knob(DEFAULT_TREELET_PASSES, check=integer(0), metavar="P",
                               help="most treelet passes per round")
    first_treelet_passes: int | None = knob(DEFAULT_FIRST_TREELET_PASSES, check=optional(integer(0)), type=int,
                                            metavar="P", help="most treelet passes of the first round (0: it "
                                                              "starts with reinsertion; none: treelet_passes)")
    treelet: treelet.Config = knob(treelet.Config(), check=config_of(treelet.Config),
                                   help="the treelet stage's Config")
    reinsert: reinsert.Config = knob(reinsert.Config(), check=config_of(reinsert.Config),
                                     help="the reinsertion stage's Config")
    widen_until: float | None = knob(DEFAULT_WIDEN_UNTIL, check=optional(real(above=0, maximum=1)), type=float,
                                     metavar="F", help="the first round's reinsertion hands over to the treelets "
                                                       "at a widening of candidates this share of the nodes or "
                                                       "more (none: it widens to every node)")
    ct: float = ct_knob()
    ci: float = ci_knob()
    split_axes: bool = split_axes_knob()
    max_leaf: int = max_leaf_knob()

    def _check_together(self):
        # the stored stage configs are what runs: the pipeline's costs and passes, no
        # split-axis pass of their own
        common = dict(ct=self.ct, ci=self.ci, split_axes=False)
        object.__setattr__(self, "treelet", self.treelet.replace(**common, max_passes=self.treelet_passes))
        object.__setattr__(self, "reinsert", self.reinsert.replace(**common, widen_until=self.widen_until))


class Params(NamedTuple):
    """Settings passed as traced values (changing them does not recompile)."""

    ct: Any          # [] tree dtype: SAH cost of a traversal step
    ci: Any          # [] tree dtype: SAH cost of a primitive test
    round_gain: Any  # [] tree dtype: relative gain below which a round is the last
    max_rounds: Any  # [] int32: most rounds
    need_first: Any  # [] int32: first candidates of the first round's reinsertion
    need_later: Any  # [] int32: the same in later rounds (every node)
    split_axes: Any  # [] bool: Kensler's final pass in result()
    max_leaf: Any    # [] int32: the final leaf merge's largest leaf (1: none)


class Static(NamedTuple):
    """Settings that fix the compiled program."""

    treelet: Any          # treelet.Config of the treelet stages (hashable)
    reinsert_limit: int   # most iterations of a reinsertion stage


class Inner(NamedTuple):
    """The pipeline's loop state: one state per stage, the round's figures."""

    treelet: Any     # OptimizerState of the treelet stage (current while stage == 0)
    reinsert: Any    # OptimizerState of the reinsertion stage (current while stage == 1)
    stage: Any       # [] int32: the current stage (index into STAGES)
    round: Any       # [] int32: the current round, from 0
    round_start: Any  # [] tree dtype: SAH when the current round began


# ----------------------------------------------------------------------------------
# From one stage to the next
# ----------------------------------------------------------------------------------


def _start_reinsertion(inner: Inner, params: Params, static: Static) -> Inner:
    """The reinsertion stage, started from the treelet stage's tree."""
    # the stages' configs never assign split axes (Config): their trees as result() gives them
    tree = treelet.tree_of(inner.treelet)
    sub = inner.reinsert
    need = jnp.where(inner.round == 0, params.need_first, params.need_later)
    sub = reinsert.restart(sub.params._replace(need=need), tree, static.reinsert_limit)
    return inner._replace(reinsert=sub, stage=jnp.int32(REINSERTION))


def _start_round(inner: Inner, sah, static: Static) -> Inner:
    """The next round's treelet stage, started from the reinsertion stage's tree."""
    tree = reinsert.tree_of(inner.reinsert)
    # traceable: it reads nothing on the host; the treelets that the last treelet stage
    # found optimal and that no reinsertion move changed are not solved again
    sub = treelet.resume(inner.treelet, tree, static.treelet)
    return inner._replace(treelet=sub, stage=jnp.int32(TREELETS), round=inner.round + 1,
                          round_start=jnp.asarray(sah, inner.round_start.dtype))


def _stage_done(inner: Inner):
    return jnp.where(inner.stage == TREELETS, inner.treelet.progress.done, inner.reinsert.progress.done)


def _settle(inner: Inner, sah, params: Params, static: Static):
    """Start the next stage while the current one is done: ``(inner, finished,
    converged)``; ``finished``: the last round is over (``converged``: by the round
    gain rule, not by ``max_rounds``). ``sah``: the SAH of the latest step."""

    def after_treelets(inner):
        return _start_reinsertion(inner, params, static), jnp.bool_(False), jnp.bool_(False)

    def after_round(inner):
        before = inner.round_start
        small = before - sah < params.round_gain * before
        last = small | (inner.round + 1 >= params.max_rounds)
        inner = jax.lax.cond(last, lambda i: i, lambda i: _start_round(i, sah, static), inner)
        return inner, last, small

    def cond(carry):
        inner, finished, _ = carry
        return _stage_done(inner) & ~finished

    def body(carry):
        inner, _, _ = carry
        return jax.lax.cond(inner.stage == TREELETS, after_treelets, after_round, inner)

    return jax.lax.while_loop(cond, body, (inner, jnp.bool_(False), jnp.bool_(False)))


def _settled(state: OptimizerState) -> OptimizerState:
    """``state`` with the next stage started while the current one is done (``step``'s
    last part; at ``init``, it passes over stages with nothing to do)."""
    inner, finished, converged = _settle(state.inner, state.progress.sah, state.params, state.static)
    progress = state.progress._replace(done=state.progress.done | finished, converged=converged,
                                       stage=inner.stage)
    return state.replace(inner=inner, progress=progress)


#: :func:`_settled` as one program: at ``init``, and after each stage run on the host
_settle_at_init = stored_jit(_settled)


# ----------------------------------------------------------------------------------
# The optimizer protocol
# ----------------------------------------------------------------------------------


def _split(tree, prims):
    """``tree`` with every leaf split (:func:`init`), in a capacity that holds the split."""
    counts = np.asarray(tree.prim_count)
    need = 2 * int(counts[np.asarray(tree.left) < 0].sum()) - 1  # one leaf per reference
    if tree.left.shape[0] < need:
        tree = pad_to(tree, capacity_bucket(need), tree.prim_index.shape[0])
    prim_lo, prim_hi = (jnp.asarray(p) for p in prims)
    split, _ = split_leaves(to_jax(tree), prim_lo, prim_hi)  # no overflow: the capacity fits
    return split


def init(tree, config: Config | None = None, key=None, *, prims=None) -> OptimizerState:
    """The state before the first step: both stages' states, the first one current.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity,
    leaves of any size). ``key``: unused (the method is deterministic). ``prims``: the
    primitives' boxes ``(lo, hi)`` [n, 3] that ``prim_index`` names, or None; given,
    every leaf of several primitives is first split into one-primitive leaves
    (:func:`jaxbvh.optimize.split.split_leaves`), so that the stages move single
    primitives and the final merge (``max_leaf``) makes the leaves. A tree of ``P``
    references then needs ``2P - 1`` nodes: a smaller capacity (a compact or loaded
    tree) grows to :func:`~jaxbvh.tree.layout.capacity_bucket` of that, and so does the
    result's.
    """
    del key
    check_tree(tree)
    config = check_config(config, Config, "pipeline")
    if prims is not None:
        tree = _split(tree, prims)
    tree = to_jax(tree)
    dtype = float_dtype(tree)
    # one SAH for the three progress records (each stage's config has the pipeline's ct, ci)
    sah_start = reinsert.start_sah(tree, config.ct, config.ci)
    treelets = treelet.init(tree, config.treelet, sah_start=sah_start)
    if config.first_treelet_passes is not None:
        # the first round's own pass limit (traced: the same program as later rounds')
        first = min(config.first_treelet_passes, int(treelets.progress.limit))
        treelets = treelets.replace(progress=treelets.progress._replace(
            limit=on_device(first, np.int32), done=treelets.progress.done | (first <= 0)))
    reinsertion = reinsert.init(tree, config.reinsert, sah_start=sah_start)  # its params and settings; restarted later
    nodes = int(np.count_nonzero(np.asarray(tree.parent) >= 0))  # on the host: no program
    # numbers cast on the host (numerics.on_device): no conversion programs
    params = Params(ct=on_device(config.ct, dtype), ci=on_device(config.ci, dtype),
                    round_gain=on_device(config.round_gain, dtype), max_rounds=on_device(config.max_rounds, np.int32),
                    need_first=reinsertion.params.need, need_later=on_device(candidates_needed(1.0, nodes), np.int32),
                    split_axes=on_device(config.split_axes, bool), max_leaf=on_device(config.max_leaf, np.int32))
    treelet_limit, reinsert_limit = int(treelets.progress.limit), int(reinsertion.progress.limit)
    progress = new_progress(sah_start, config.max_rounds * (treelet_limit + reinsert_limit), dtype)
    inner = Inner(treelets, reinsertion, on_device(TREELETS, np.int32), on_device(0, np.int32), progress.sah_start)
    static = Static(config.treelet, reinsert_limit)
    return _settle_at_init(OptimizerState(tree, progress, params, inner, static))


def step(state: OptimizerState) -> OptimizerState:
    """One step of the current stage (a treelet pass or a reinsertion iteration), then
    the next stage or round if that stage is done (module docstring)."""
    inner, params, static = state.inner, state.params, state.static

    def treelet_pass(inner):
        sub = treelet.step(inner.treelet)
        return inner._replace(treelet=sub), sub.progress.sah, sub.progress.moves - inner.treelet.progress.moves

    def reinsert_iteration(inner):
        sub = reinsert.step(inner.reinsert)
        return inner._replace(reinsert=sub), sub.progress.sah, sub.progress.moves - inner.reinsert.progress.moves

    new, sah, moves = jax.lax.cond(inner.stage == TREELETS, treelet_pass, reinsert_iteration, inner)
    progress = record(state.progress._replace(stage=inner.stage), sah, moves, converged=False)
    new, finished, converged = _settle(new, progress.sah, params, static)
    progress = progress._replace(done=progress.done | finished, converged=converged, stage=new.stage)
    return keep_if_done(state, state.replace(inner=new, progress=progress))


# ----------------------------------------------------------------------------------
# The host loop over stages (what the driver runs for one tree)
# ----------------------------------------------------------------------------------
#
# Why: ``step`` holds both stages' steps and every hand-over in one program, the
# largest the library compiled (9,239 StableHLO ops on spot: about the treelet loop's
# plus the reinsertion loop's; bench/results/opt_program_anatomy.md). On the host, each
# stage runs in its own optimizer's compiled loop (driver.advance of treelet.step or
# reinsert.step: the same programs as those optimizers', where shapes agree), and one
# small program per stage records the steps it ran and starts the next stage. A stage
# is one to tens of passes, so the host steps in between cost nothing measurable; the
# state after any number of steps is the one the loop of ``step`` reaches (tested).


@partial(stored_jit, static_argnums=3)
def _absorb(state: OptimizerState, sub: OptimizerState, first, stage: int) -> OptimizerState:
    """``state`` after its current stage (``stage``) ran from its step ``first`` to the
    state ``sub``: each of those steps recorded as :func:`step` records it (the next
    stage is started apart, by :data:`_settle_at_init`: one program for both stages)."""
    progress = state.progress
    done_steps = sub.progress.step - first  # steps the stage ran
    at = jnp.arange(sub.progress.history.shape[0], dtype=jnp.int32)
    ran = (at >= first) & (at < sub.progress.step)
    # the stage's j-th step is the pipeline's (step + j - first)-th; the rest dropped
    to = jnp.where(ran, progress.step + at - first, progress.history.shape[0])
    step_moves = jnp.where(ran, sub.progress.history_moves, 0)
    steps = progress.step + done_steps
    recorded = progress._replace(
        step=steps, stage=jnp.int32(stage), sah=sub.progress.sah.astype(progress.sah.dtype),
        moves=progress.moves + jnp.sum(step_moves, dtype=jnp.int32), converged=jnp.bool_(False),
        done=steps >= progress.limit,
        history=progress.history.at[to].set(sub.progress.history.astype(progress.history.dtype), mode="drop"),
        history_moves=progress.history_moves.at[to].set(sub.progress.history_moves, mode="drop"),
        history_stage=progress.history_stage.at[to].set(jnp.int32(stage), mode="drop"))
    progress = jax.tree_util.tree_map(lambda new, old: jnp.where(done_steps > 0, new, old), recorded, progress)
    return state.replace(inner=state.inner._replace(**{STAGES[stage]: sub}), progress=progress)


_STAGE_OPTIMIZERS = {TREELETS: treelet.TREELET, REINSERTION: reinsert.REINSERT}


def advance(state: OptimizerState, stop: int) -> OptimizerState:
    """Steps until the state is done or ``stop`` steps in all, stage by stage on the host
    (the loop of :func:`step` gives the same state); ``stop`` at or below the steps run:
    none, but every program compiled (:class:`~jaxbvh.optimize.protocol.Optimizer`)."""

    def position(state):  # one read from the device per stage
        p, inner = state.progress, state.inner
        return (int(x) for x in jax.device_get((p.step, p.done, p.stage, p.limit, inner.treelet.progress.step,
                                                 inner.reinsert.progress.step)))

    steps, done, stage, limit, *firsts = position(state)
    if stop <= steps:  # compile (or load) both stages' loops and their hand-overs
        for index, name in enumerate(STAGES):
            sub = getattr(state.inner, name)
            first = on_device(firsts[index], np.int32)
            ran = driver_advance(_STAGE_OPTIMIZERS[index].step, sub, first)
            jax.block_until_ready(_absorb(state, ran, first, index))
        jax.block_until_ready(_settle_at_init(state))
        return state
    while not done and steps < stop:
        sub = getattr(state.inner, STAGES[stage])
        first = firsts[stage]
        # as many stage steps as the pipeline has left (its own limit included)
        sub_stop = first + min(stop, limit) - steps
        ran = driver_advance(_STAGE_OPTIMIZERS[stage].step, sub, on_device(sub_stop, np.int32))
        state = _settle_at_init(_absorb(state, ran, on_device(first, np.int32), stage))
        steps, done, stage, limit, *firsts = position(state)
    return state


def result(state: OptimizerState) -> OptimizeResult:
    """The optimized tree (same capacity as the input), its leaves merged where that
    pays (``max_leaf``), and the run's figures.

    The current stage's state holds the latest tree (a stage that has just started
    holds the tree the previous one ended with).
    """
    inner = state.inner
    out = jax.lax.cond(inner.stage == TREELETS, lambda i: treelet.tree_of(i.treelet),
                       lambda i: reinsert.tree_of(i.reinsert), inner)
    out = merge_leaves(out, state.params.max_leaf, state.params.ct, state.params.ci)
    out = jax.lax.cond(state.params.split_axes, apply_split_axes, lambda t: t, out)
    progress = state.progress._replace(sah=sah_of(out, state.params.ct, state.params.ci))
    return make_result(out, progress)


PIPELINE = Optimizer("pipeline", Config, init, step, result, stages=STAGES,
                     paper="Karras & Aila 2013 and Meister & Bittner 2018, in rounds", advance=advance)


def pipeline(tree, *, prims=None, time_budget: float | None = None, on_step: Callable | None = None,
             **config) -> OptimizeResult:
    """Rounds of treelets and reinsertion until a round gains little (module docstring).

    ``prims``: the primitives' boxes ``(lo, hi)``, to split the leaves first
    (:func:`init`). ``config``: fields of :class:`Config` (``treelet``, ``reinsert``:
    stage configs or dicts of their fields). ``time_budget``, ``on_step(info)``: as
    :func:`jaxbvh.optimize.driver.run` (``info.stage`` names the stage of each step).
    """
    config = Config(**config)
    state = init(tree, config, prims=prims) if prims is not None else None
    return run(PIPELINE, tree, config, time_budget=time_budget, on_step=on_step, state=state)
