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

* **Hill climbing** (:func:`hill_climb`, :data:`HILL_CLIMB`): apply the move of least cost if it lowers
  ``C(n)``; repeat passes until one makes no move.
* **Simulated annealing** (:func:`anneal`, :data:`ANNEAL`): candidates in the fixed order above are
  compared with the best found so far (initially "no move"); a better one always becomes
  the best, a worse one when a uniform ``xi`` falls below ``exp(-de / T)`` (``de`` the
  difference in ``C(n)``; never when ``T == 0``), tested as ``de < T E`` with the Exp(1)
  variate ``E = -log(xi)``; the best is applied. One draw per
  (pass, node, candidate), drawn by :func:`jaxbvh.draws.annealing_draws` and indexed by node id.
  The temperature of pass ``i`` is ``schedule(i)``, any optax-style schedule or a name
  of :data:`jaxbvh.optimize.schedules.SCHEDULES` (default Kensler's ramped sine,
  :func:`jaxbvh.optimize.schedules.kensler_schedule`); after ``steps`` passes the tree is
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

After optimizing, :func:`~jaxbvh.tree.split_axes.assign_split_axes` (Kensler's final
pass) gives every interior node the axis along which its children are separated most
(overlap least) and orders the children along it, for front-to-back traversal.

On the optimizer protocol
=========================
Both methods are optimizers of :mod:`jaxbvh.optimize.protocol`: :data:`HILL_CLIMB`
(``"hc"``, :class:`HillClimbConfig`) and :data:`ANNEAL` (``"sa"``, :class:`AnnealConfig`).
Their ``init`` differ (:func:`init_hill_climb`, :func:`init_anneal`); they share one
:func:`step` (one pass, of every chain) and one :func:`result` (the best chain). The
state's ``inner`` (:class:`Inner`) is the forest and each chain's figures; ``params``
(:class:`Params`) the costs, the margin and Kensler's schedule numbers, traced, so
changing them does not recompile; ``static`` (:class:`Static`) the modes and work sizes.
A step leaves a done state unchanged, so :func:`optimize_batch` is ``step`` vmapped over
a batch of trees until all are done. :func:`hill_climb` and :func:`anneal` are thin
wrappers over :func:`jaxbvh.optimize.driver.run` (chunks, ``on_step``, time budget).

The machinery sits beside this module: :mod:`jaxbvh.optimize.rotate_moves` (the six
moves of a window of nodes: scoring, choice, application) and
:mod:`jaxbvh.optimize.rotate_passes` (one pass: heights, windows, the queue; the forest).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import (
    Checked,
    ci_knob,
    ct_knob,
    integer,
    knob,
    min_gain_knob,
    optional,
    real,
    sizes,
    split_axes_knob,
)
from jaxbvh.draws import annealing_draws
from jaxbvh.numerics import extent_scale, on_device, rounded
from jaxbvh.numerics import min_gain as default_min_gain
from jaxbvh.optimize.driver import run, run_batch
from jaxbvh.optimize.protocol import (
    Optimizer,
    OptimizeResult,
    OptimizerState,
    check_config,
    check_tree,
    float_dtype,
    history_length,
    keep_if_done,
    make_result,
    new_progress,
    record,
)
from jaxbvh.optimize.rotate_moves import MOVES, State, score
from jaxbvh.optimize.rotate_passes import chain_of, forest_of, initial_state, run_pass, to_tree, tree_part
from jaxbvh.optimize.schedules import DEFAULT_HOTTEST, KENSLER_PERIOD, KENSLER_STEPS, SCHEDULES, kensler_temperature
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import to_jax
from jaxbvh.tree.split_axes import apply_split_axes

__all__ = [
    "MOVES", "DEFAULT_WINDOWS", "ANNEAL_WINDOWS", "DEFAULT_FRONTIER", "DEFAULT_HOTTEST", "score_moves",
    "HillClimbConfig", "AnnealConfig", "Params", "Static", "Inner", "init_hill_climb", "init_anneal",
    "step", "result", "HILL_CLIMB", "ANNEAL", "hill_climb", "anneal", "optimize_batch",
]

# Window sizes (speed only). Each size is one more compiled copy of the window step
# (~1.5 s of compile), so hill climbing (few passes) uses one; annealing (hundreds of
# passes) adds a narrow one for the sparse upper heights (2x faster on legocar), and a
# forest of K chains starts K times wider.
DEFAULT_WINDOWS = (512,)
ANNEAL_WINDOWS = (512, 64)
DEFAULT_FRONTIER = 131072  # queue of changed nodes; more in one pass: visit every node


def score_moves(tree, ct=1.0, ci=1.0):
    """Cost of every node before and after each of the six moves (one jitted call).

    Returns ``(current [N], after [N, 6], legal [N, 6])``: ``current`` is ``C(n)``,
    ``after[n, m]`` what ``C(n)`` becomes after move ``m`` (:data:`MOVES`), ``legal``
    whether the move exists there. Leaves and padding have no legal move.
    """
    return _score_moves(to_jax(tree), ct, ci)


@stored_jit
def _score_moves(tree, ct, ci):
    scale, st = initial_state(tree, ct, ci)
    s = score(st, jnp.arange(tree.left.shape[0]), scale, jnp.asarray(ct, tree.lo.dtype))
    return s.cur, s.cand, s.legal


# ----------------------------------------------------------------------------------
# The optimizer protocol: configs, state, init / step / result
# ----------------------------------------------------------------------------------


def _schedule(name, value):
    """A schedule: a name of :data:`SCHEDULES` or a function ``step -> temperature``."""
    if isinstance(value, str):
        if value not in SCHEDULES:
            raise ValueError(f"{name} must be one of {', '.join(SCHEDULES)} or a function "
                             f"step -> temperature, got {value!r}")
    elif not callable(value):
        raise ValueError(f"{name} must be a function step -> temperature, got {value!r}")
    return value


def _max_passes(help: str):
    return knob(1000, check=integer(1), metavar="P", help=help)


def _frontier():
    return knob(DEFAULT_FRONTIER, check=integer(1), help="queue of changed nodes (speed only)")


@dataclasses.dataclass(frozen=True)
class HillClimbConfig(Checked):
    """Knobs of Kensler's hill climbing (module docstring), with the defaults.

    ``ct``, ``ci``: SAH constants. ``max_passes``: stop after this many passes even if
    not converged. ``min_gain``: relative margin a move must beat (None: ``64 * eps`` of
    the tree's float type, :func:`jaxbvh.numerics.min_gain`). ``split_axes``: Kensler's
    final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`) in ``result``.
    ``windows``, ``frontier``: work sizes (speed only, never the result; each window
    size is one more compiled copy of the window step).
    """

    ct: float = ct_knob()
    ci: float = ci_knob()
    max_passes: int = _max_passes("most passes (stop even if not converged)")
    min_gain: float | None = min_gain_knob()
    split_axes: bool = split_axes_knob()
    windows: tuple = knob(DEFAULT_WINDOWS, check=sizes, help="window sizes (speed only)")
    frontier: int = _frontier()


@dataclasses.dataclass(frozen=True)
class AnnealConfig(Checked):
    """Knobs of Kensler's simulated annealing (module docstring), with the defaults.

    ``schedule``: the temperature of each pass: a name from
    :data:`jaxbvh.optimize.schedules.SCHEDULES` (made with ``steps``, ``hottest``,
    ``period``) or any optax-style function ``step -> T``. The default, ``"kensler"``,
    is Kensler's ramped sine with ``steps``, ``period``, ``hottest`` passed as traced
    values (changing them does not recompile; another schedule compiles once per
    function object). ``steps``: passes ``0 .. steps-1`` follow the schedule (Kensler's
    N = 1250); then passes at ``T = 0`` follow, at most ``max_quench``, until one makes
    no move. ``hottest``: peak temperature in units of the node cost ``C(n)``
    (:data:`jaxbvh.optimize.schedules.DEFAULT_HOTTEST`, 0.15, not the paper's 1.5, which
    is far too hot on this cost). ``period``: the sine's period f in passes (50).
    ``chains``: independent chains (keys ``jax.random.split(key, chains)``) run as one
    forest; the best is returned. ``keep_best``: return the tree of least SAH seen after
    any pass (else the last). ``windows``: None picks :data:`ANNEAL_WINDOWS` (one chain)
    or a K times wider first window (a forest). Others as :class:`HillClimbConfig`.
    """

    schedule: str | Callable = knob("kensler", check=_schedule, choices=tuple(SCHEDULES),
                                    help="temperature of each pass (a name; the library also takes "
                                         "any function step -> T)")
    steps: int = knob(KENSLER_STEPS, check=integer(0), metavar="N",
                      help="passes that follow the schedule (Kensler's N)")
    hottest: float = knob(DEFAULT_HOTTEST, check=real(0, finite=False), metavar="H",
                          help="peak temperature, in units of the node cost")
    period: int = knob(KENSLER_PERIOD, check=integer(1), metavar="F",
                       help="period of Kensler's sine, in passes")
    chains: int = knob(1, check=integer(1), metavar="K", help="independent chains, run as one forest")
    keep_best: bool = knob(True, help="return the tree of least SAH seen (else the last)")
    max_quench: int = _max_passes("most passes at T = 0 after the schedule")
    ct: float = ct_knob()
    ci: float = ci_knob()
    min_gain: float | None = min_gain_knob()
    split_axes: bool = split_axes_knob()
    windows: tuple | None = knob(None, check=optional(sizes),
                                 help="window sizes (speed only; none: chosen by the chains)")
    frontier: int = _frontier()


class Params(NamedTuple):
    """Settings passed as traced values (changing them does not recompile)."""

    ct: Any        # [] tree dtype: SAH cost of a traversal step
    ci: Any        # [] tree dtype: SAH cost of a primitive test
    min_gain: Any  # [] tree dtype: relative margin a move must beat (module docstring)
    steps: Any     # [] int32: passes that follow the schedule (0 for hill climbing)
    period: Any    # [] float32: Kensler's period f (default schedule only)
    hottest: Any   # [] float32: Kensler's peak temperature h (default schedule only)


class Static(NamedTuple):
    """Settings that fix the compiled program (pytree metadata of the state)."""

    annealing: bool   # simulated annealing (else hill climbing)
    schedule: Any     # step -> T; None: Kensler's, from params (traced)
    keep_best: bool   # result() gives the tree of least SAH seen (annealing)
    chains: int       # K chains, run as one forest
    windows: tuple    # window sizes (speed only)
    frontier: int     # queue of changed nodes (speed only)
    split_axes: bool  # Kensler's final pass in result()


class Inner(NamedTuple):
    """The rotations' own loop state: K chains as one forest, and each chain's figures.

    ``H`` is the history length of the state's :class:`~jaxbvh.optimize.protocol.Progress`
    (which holds the figures of all chains together: least SAH, moves summed).
    """

    forest: Any         # State of the forest: links, boxes, costs, heights, queue
    keys: Any           # [K] jax.random keys of the chains (annealing); None for hill climbing
    done: Any           # [K] bool: the chain converged (a pass at T = 0 made no move)
    passes: Any         # [K] int32: passes the chain ran (up to the one that converged)
    moves: Any          # [K] int32: moves the chain applied in all
    history: Any        # [K, H] SAH of the chain's tree after each pass, NaN after its last
    history_moves: Any  # [K, H] int32: the chain's moves in each pass
    best: Any           # keep_best: ([K] least SAH seen, State links and boxes at it); else None


def _temperature(i, params: Params, dtype, static: Static):
    """Temperature of pass ``i`` (traced): the schedule's, clamped at 0, and 0 from ``steps`` on."""
    if not static.annealing:
        return jnp.zeros((), dtype)
    if static.schedule is None:
        t = kensler_temperature(i, jnp.maximum(params.steps, 1), params.period, params.hottest)
    else:
        t = static.schedule(i)
    return jnp.where(i < params.steps, jnp.maximum(jnp.asarray(t, dtype), 0), 0)


def _draws(keys, i, temperature, cap: int, dtype):
    """The Exp(1) draws of pass ``i`` for the forest [K N, 6] (ones when cold: none is read)."""
    chains = keys.shape[0]

    def hot():
        rows = jax.vmap(lambda k: annealing_draws(k, i, cap, dtype))(keys)
        return rows.reshape(chains * cap, 6)

    return jax.lax.cond(temperature > 0, hot, lambda: jnp.ones((chains * cap, 6), dtype))


def _keep_best(best, cost, forest: State, cap: int):
    """``best`` after a pass that left chain roots at ``cost`` [K]: each chain whose SAH
    fell below its least so far keeps its links and boxes."""
    best_cost, best_st = best
    chains = cost.shape[0]
    better = cost < best_cost
    keep = better[jnp.arange(chains * cap, dtype=jnp.int32) // cap]

    def update():
        def pick(new, old):
            return jnp.where(keep.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
        return jax.tree_util.tree_map(pick, tree_part(forest), best_st)

    return jnp.where(better, cost, best_cost), jax.lax.cond(jnp.any(better), update, lambda: best_st)


@partial(stored_jit, static_argnames=("chains", "frontier", "keep_best", "history"))
def _start(tree, params: Params, keys, *, chains, frontier, keep_best, history):
    """The inner state before the first pass (K = ``chains`` copies as one forest) and
    the input's SAH (``C`` of the root)."""
    dtype = tree.lo.dtype
    _, one = initial_state(tree, params.ct, params.ci)
    cap = one.child.shape[0]
    st = forest_of(one, chains)
    # the first pass visits every node: a queue that overflowed
    queue_size = min(frontier, chains * cap)
    st = st._replace(queue=jnp.full(queue_size, chains * cap, jnp.int32),
                     queued=jnp.int32(queue_size + 1))
    start_cost = one.cost[tree.root]
    none = jnp.zeros(chains, jnp.int32)
    best = (jnp.full(chains, start_cost), tree_part(st)) if keep_best else None
    inner = Inner(st, keys, jnp.zeros(chains, bool), none, none,
                  jnp.full((chains, history), jnp.nan, dtype), jnp.zeros((chains, history), jnp.int32),
                  best)
    return inner, start_cost


def _init_state(tree, config, keys, static: Static, *, limit: int, steps: int = 0,
                period: float = KENSLER_PERIOD, hottest: float = DEFAULT_HOTTEST) -> OptimizerState:
    """The state of either method before its first pass (host code; ``config`` checked;
    ``steps``, ``period``, ``hottest``: the schedule's numbers, unused by hill climbing)."""
    check_tree(tree)
    tree = to_jax(tree)
    dtype = float_dtype(tree)
    min_gain = default_min_gain(dtype) if config.min_gain is None else config.min_gain
    params = Params(on_device(config.ct, dtype), on_device(config.ci, dtype), on_device(min_gain, dtype),
                    on_device(steps, np.int32), on_device(period, np.float32), on_device(hottest, np.float32))
    inner, start_cost = _start(tree, params, keys, chains=static.chains, frontier=static.frontier,
                               keep_best=static.keep_best, history=history_length(limit))
    return OptimizerState(tree, new_progress(start_cost, limit, dtype), params, inner, static)


def init_hill_climb(tree, config: HillClimbConfig | None = None, key=None) -> OptimizerState:
    """Hill climbing's state before the first pass.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity).
    ``config``: a :class:`HillClimbConfig` (None: the defaults). ``key``: unused (the
    method is deterministic).
    """
    del key
    config = check_config(config, HillClimbConfig, "hc")
    static = Static(annealing=False, schedule=None, keep_best=False, chains=1, windows=config.windows,
                    frontier=int(config.frontier), split_axes=bool(config.split_axes))
    return _init_state(tree, config, None, static, limit=config.max_passes)


def init_anneal(tree, config: AnnealConfig | None = None, key=None) -> OptimizerState:
    """Annealing's state before the first pass: K chains of the tree as one forest.

    ``tree``: as :func:`init_hill_climb`. ``config``: an :class:`AnnealConfig` (None:
    the defaults). ``key``: a ``jax.random`` key (None: ``jax.random.key(0)``); chain
    ``k`` draws from ``jax.random.split(key, K)[k]`` (one chain: ``key`` itself).
    """
    config = check_config(config, AnnealConfig, "sa")
    key = jax.random.key(0) if key is None else key
    chains = int(config.chains)
    keys = key[None] if chains == 1 else jax.random.split(key, chains)
    windows = config.windows
    if windows is None:
        windows = ANNEAL_WINDOWS if chains == 1 else (DEFAULT_WINDOWS[0] * chains,) + DEFAULT_WINDOWS
    schedule = config.schedule
    if isinstance(schedule, str):  # Kensler's: traced from params; others made once (cached)
        schedule = None if schedule == "kensler" else SCHEDULES[schedule](
            max(int(config.steps), 1), float(config.hottest), int(config.period))
    static = Static(annealing=True, schedule=schedule, keep_best=bool(config.keep_best), chains=chains,
                    windows=windows, frontier=int(config.frontier), split_axes=bool(config.split_axes))
    return _init_state(tree, config, keys, static, limit=config.steps + config.max_quench,
                       steps=int(config.steps), period=config.period, hottest=config.hottest)


def step(state: OptimizerState) -> OptimizerState:
    """One pass over every chain's tree (hill climbing or annealing, as the state says).

    A chain is done after a pass at ``T = 0`` that makes no move; it then makes no move
    in later passes either, so each chain's result is exactly what it gives alone. The
    progress records the least SAH over the running chains and the moves of all of them
    (``sah``: the least over all chains of what ``result`` would return).
    """
    tree, params, static, inner = state.tree, state.params, state.static, state.inner
    dtype = tree.lo.dtype
    cap = tree.left.shape[0]
    i = state.progress.step
    t = _temperature(i, params, dtype, static)
    draws = _draws(inner.keys, i, t, cap, dtype) if static.annealing else None
    collect = _temperature(i + 1, params, dtype, static) <= 0
    scale = extent_scale(tree.lo[tree.root], tree.hi[tree.root])
    forest, moves = run_pass(inner.forest, inner.forest.child[:, 0] >= 0, scale, params.ct, params.min_gain,
                          t, draws, collect, annealing=static.annealing, windows=static.windows,
                          chains=static.chains)
    cost = forest.cost[tree.root + cap * jnp.arange(static.chains, dtype=jnp.int32)]
    running = ~inner.done
    cold = (i + 1 >= params.steps) if static.annealing else jnp.bool_(True)
    best = _keep_best(inner.best, cost, forest, cap) if static.keep_best else None
    inner = Inner(forest, inner.keys, inner.done | ((moves == 0) & cold), inner.passes + running,
                  inner.moves + moves, inner.history.at[:, i].set(jnp.where(running, cost, jnp.nan), mode="drop"),
                  inner.history_moves.at[:, i].set(jnp.where(running, moves, 0), mode="drop"), best)
    progress = record(state.progress, jnp.min(jnp.where(running, cost, jnp.inf)), jnp.sum(moves, dtype=jnp.int32),
                      converged=jnp.all(inner.done))
    progress = progress._replace(sah=jnp.min(best[0] if static.keep_best else cost))
    return keep_if_done(state, state.replace(inner=inner, progress=progress))


def result(state: OptimizerState) -> OptimizeResult:
    """The best chain's tree (same capacity as the input) and its figures.

    The best chain is the first whose final SAH is within ``min_gain`` (relative) of
    the least (the margin of the module docstring).

    ``steps``, ``moves``, ``converged``, ``history``, ``history_moves`` are the best
    chain's; ``chain_sah`` [K] every chain's final SAH when K > 1 (else None).
    ``sah``: the SAH of the returned tree (``keep_best``: the least seen).
    """
    tree, static, inner = state.tree, state.static, state.inner
    chains, cap = static.chains, tree.left.shape[0]
    if static.keep_best:
        final_cost, st = inner.best
    else:
        st = inner.forest
        final_cost = st.cost[tree.root + cap * jnp.arange(chains, dtype=jnp.int32)]
    # the first chain within the margin of the least: an ulp of noise in the costs (another
    # fusion, e.g. under vmap) must not pick another chain
    least = jnp.min(final_cost)
    k = jnp.argmax(final_cost <= least + rounded(state.params.min_gain * jnp.abs(least))).astype(jnp.int32)
    out = to_tree(tree, chain_of(st, k, chains))
    if static.split_axes:
        out = apply_split_axes(out)
    progress = state.progress._replace(
        step=inner.passes[k], moves=inner.moves[k], converged=inner.done[k], sah=final_cost[k],
        history=inner.history[k], history_moves=inner.history_moves[k])
    return make_result(out, progress, final_cost if chains > 1 else None)


HILL_CLIMB = Optimizer("hc", HillClimbConfig, init_hill_climb, step, result,
                       paper="Kensler 2008 (tree rotations, hill climbing)")
ANNEAL = Optimizer("sa", AnnealConfig, init_anneal, step, result,
                   paper="Kensler 2008 (tree rotations, simulated annealing)")


# ----------------------------------------------------------------------------------
# Convenience entry points
# ----------------------------------------------------------------------------------


def hill_climb(tree, *, time_budget: float | None = None, on_step: Callable | None = None,
               **config) -> OptimizeResult:
    """Kensler's hill climbing: passes of the best improving move per node until none.

    ``tree``: a :class:`~jaxbvh.tree.layout.BVH` (NumPy or JAX arrays, any capacity).
    ``config``: fields of :class:`HillClimbConfig` (e.g. ``max_passes``, ``ct``,
    ``split_axes``). ``time_budget``, ``on_step(info)``: as
    :func:`jaxbvh.optimize.driver.run` (without them the run is one compiled call; with
    them it goes in chunks of passes, giving the same tree). The tree is identical, pass
    by pass, to :func:`jaxbvh.optimize.rotate_reference.hill_climb`.
    """
    return run(HILL_CLIMB, tree, HillClimbConfig(**config), time_budget=time_budget, on_step=on_step)


def anneal(key, tree, *, time_budget: float | None = None, on_step: Callable | None = None,
           **config) -> OptimizeResult:
    """Kensler's simulated annealing of tree rotations.

    ``key``: a ``jax.random`` key. ``tree``: as :func:`hill_climb`. ``config``: fields
    of :class:`AnnealConfig` (e.g. ``schedule``, any optax schedule or a name of
    :data:`jaxbvh.optimize.schedules.SCHEDULES`; ``steps``, ``hottest``, ``period``,
    ``chains``). ``time_budget``, ``on_step(info)``: as :func:`hill_climb` (a budget
    stops the schedule early: pair it with ``keep_best``). With K chains the result is
    the best chain's, and ``chain_sah`` lists all K (each chain's result is exactly
    what it gives alone).
    """
    return run(ANNEAL, tree, AnnealConfig(**config), key=key, time_budget=time_budget, on_step=on_step)


def optimize_batch(trees, keys=None, *, method: str = "hc", **config) -> OptimizeResult:
    """Optimize a batch of trees at once: the protocol's ``step`` vmapped over the batch
    (:func:`jaxbvh.optimize.driver.run_batch`, the one batch driver).

    ``trees``: a :class:`~jaxbvh.tree.layout.BVH` whose arrays have a leading batch axis B
    (:func:`jaxbvh.tree.batching.stack_trees`); the arrays may be sharded over devices
    along it (``jax.sharding``), and the result is sharded the same way. ``method``:
    ``"hc"`` or ``"sa"``; ``config``: fields of its Config (:class:`HillClimbConfig`,
    :class:`AnnealConfig`). ``keys``: [B] keys for ``"sa"``. Every field of the result
    gains a leading axis; each tree stops when it is done (its state is then a fixed
    point of ``step``), so each gets exactly its own single-tree result.
    """
    check_tree(trees, "trees")
    optimizers = {"hc": HILL_CLIMB, "sa": ANNEAL}
    if method not in optimizers:
        raise ValueError(f"method must be 'hc' or 'sa', got {method!r}")
    optimizer = optimizers[method]
    if method == "sa" and keys is None:
        raise ValueError("optimize_batch: method 'sa' needs keys (one per tree)")
    return run_batch(optimizer, trees, optimizer.Config(**config), keys=keys)
