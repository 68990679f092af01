"""The one host driver every optimizer runs under: compiled chunks of steps, progress, a time budget.

:func:`run` takes any :class:`~jaxbvh.optimize.protocol.Optimizer`: ``init``, then
``step`` in a compiled ``while_loop`` (:func:`advance`) until the state is done, then
``result``; an optimizer with a host ``advance`` of its own (the pipeline: one compiled
loop per stage) runs through that instead (:func:`run_steps`). With no callback and no
budget the whole run is one call. With
``on_step(info)`` or ``time_budget`` it runs in *chunks* of steps (one step first, then
doubling while a chunk takes under :data:`CHUNK_SECONDS`, up to :data:`MAX_CHUNK`): the
host reads the progress after each chunk, calls ``on_step`` once per step with a
:class:`~jaxbvh.optimize.protocol.StepInfo`, and checks the budget. Chunks never change
the result: the state carries everything, so one call to the limit and many short ones
give the same tree (tested).

Time budget. ``time_budget`` (seconds) bounds the *search*: :func:`run` first makes the
start state (``init``) and compiles the loop of steps and ``result`` (or loads them from
the persistent cache, :mod:`jaxbvh.compile_cache`; nothing when this process compiled
them already), then starts the budget's clock. The search runs in chunks and stops at
the end of the chunk that crosses the budget (chunks grow only while short, so the
overshoot stays small), returning the state it reached: the best tree so far for every
optimizer (all of them only lower the SAH, except annealing, which keeps its best). So a
budget always buys its search: the first step always runs, however small the budget,
and a budget shorter than compiling no longer returns the start tree untouched. The
seconds spent before the clock started (init and compiling) are reported apart, as the
result's ``compile_seconds``; they are paid once per program and machine, since the
compiled programs are cached in memory and on disk. Nothing runs in a background
thread, so nothing is left compiling when the call returns, and a script exits as soon
as its last line is done. No host callback runs inside a compiled program, so every
compiled piece is cached.

Batches: the one batch driver. Every batch of trees runs through :func:`run_states`
(stacked trees: :func:`run_batch`, and through it :func:`jaxbvh.optimize.rotate.optimize_batch`;
meshes in capacity groups and chunks over devices: :func:`jaxbvh.batch.optimize`). Each
tree's state is made by ``init`` on the host and the states are stacked along a new
leading axis (:func:`init_batch`, :func:`stack_states`). :func:`run_rows` is the one
compiled program: ``"vmap"`` runs ``step`` vmapped in one ``while_loop`` until every
state is done (a done state is a fixed point of ``step``, ``keep_if_done``, so a tree
that has converged stops changing while the others go on), then ``result`` vmapped;
``"map"`` runs each row's own loop and ``result`` one row after another, the
single-tree program exactly (:mod:`jaxbvh.batch.rows`: which mode suits which device).
Either way each tree gets exactly its own single-tree result. Rows that only fill the
batch axis (to a batch-size bucket or a device multiple) are marked done before the
call (:func:`fill_rows`), so they run no step in either mode. A batch has no time
budget and no per-step callback: the whole batch is one call.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import on_device
from jaxbvh.optimize.protocol import OptimizeResult, OptimizerState, StepInfo
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.batching import unstack_trees

#: a chunk of steps grows (doubling, up to this many) while one takes under CHUNK_SECONDS
MAX_CHUNK = 256
#: the host learns of a step only at the end of its chunk, so a shorter chunk reports the
#: step that reaches a target sooner. Measured (pipeline, CPU seconds to tinybvh's
#: Optimize(200) SAH, chunks alternating in one process, loaded 2-core machine): 0.1 ->
#: 0.03 s gave legocar 0.78 -> 0.75 s and 0.77 -> 0.70 s (mean of 6 and 4 runs), drone
#: 2.05 -> 1.88 s (2 runs); the whole run's CPU time did not grow measurably (legocar 43
#: steps 1.64 -> 1.59 s; 0.02 s: +7 %).
CHUNK_SECONDS = 0.03


class TimeBudget:
    """``seconds`` of wall time from :meth:`start` (``None``: no limit)."""

    def __init__(self, seconds: float | None):
        if seconds is not None and not seconds > 0:
            raise ValueError(f"time_budget must be > 0 seconds, got {seconds}")
        self.seconds = seconds
        self.deadline = None

    def start(self) -> None:
        """Start the clock (:func:`run` calls this first thing; later calls do nothing)."""
        if self.seconds is not None and self.deadline is None:
            self.deadline = time.perf_counter() + self.seconds

    def left(self) -> float | None:
        """Seconds left (None: no limit; before :meth:`start`, the whole budget)."""
        if self.seconds is None:
            return None
        if self.deadline is None:
            return self.seconds
        return self.deadline - time.perf_counter()

    def spent(self) -> bool:
        """True once the clock has started and run past the budget."""
        left = self.left()
        return left is not None and self.deadline is not None and left <= 0


def _advance(step: Callable, state: OptimizerState, stop) -> OptimizerState:
    """``step`` until ``stop`` steps in all or the state is done (traceable)."""

    def cond(s):
        return ~s.progress.done & (s.progress.step < stop)

    return jax.lax.while_loop(cond, step, state)


#: ``advance(step, state, stop)``: the compiled loop of steps (one program per step
#: function and state shape)
advance = stored_jit(_advance, static_argnums=0)

_NO_STOP = int(np.iinfo(np.int32).max)


def run_steps(optimizer, state: OptimizerState, stop: int) -> OptimizerState:
    """``optimizer``'s steps on one state until it is done or ``stop`` steps in all: its
    own host ``advance`` where it has one (:class:`~jaxbvh.optimize.protocol.Optimizer`),
    else ``step`` in the compiled loop :data:`advance`."""
    stop = min(int(stop), _NO_STOP)
    if optimizer.advance is not None:
        return optimizer.advance(state, stop)
    return advance(optimizer.step, state, on_device(stop, np.int32))


@partial(stored_jit, static_argnums=0)
def finish(result: Callable, state: OptimizerState):
    return result(state)


def run(optimizer, tree, config=None, *, key=None, time_budget: float | None = None,
        on_step: Callable | None = None, state: OptimizerState | None = None):
    """Run ``optimizer`` on ``tree`` to the end; returns its ``OptimizeResult`` (NumPy arrays).

    ``config``: the optimizer's ``Config`` (None: defaults). ``key``: a ``jax.random``
    key for randomized methods (annealing). ``time_budget``: seconds (module docstring).
    ``on_step(info)``: called on the host after every step with a ``StepInfo``.
    ``state``: start from this state instead of ``init(tree, config, key)``.
    The result's ``trace`` lists every step's ``StepInfo`` when the run went in chunks,
    its ``compile_seconds`` the seconds before the search began (``init`` and
    compiling or loading the programs; about 0 once this process has them), ``seconds``
    those of the whole run and ``stop`` why it ended.
    """
    if on_step is not None and not callable(on_step):
        raise ValueError(f"on_step must be a function on_step(info), got {on_step!r}")
    budget = TimeBudget(time_budget)
    clock = time.perf_counter()
    trace = []
    if state is None:
        state = optimizer.init(tree, config, key)
    compile_loop(optimizer, state)
    compile_seconds = time.perf_counter() - clock
    budget.start()  # the search's clock: init and compiling are reported apart
    if on_step is None and time_budget is None:  # one call to the end
        state = run_steps(optimizer, state, _NO_STOP)
    else:
        state = drive(optimizer, state, budget=budget, on_step=on_step, trace=trace, clock=clock)
    out = jax.device_get(finish(optimizer.result, state))
    stop = "converged" if bool(out.converged) else "limit" if bool(state.progress.done) else "budget"
    return out.replace(trace=tuple(trace), compile_seconds=compile_seconds, stop=stop,
                       seconds=time.perf_counter() - clock)


def compile_loop(optimizer, state: OptimizerState) -> float:
    """Compile (or load from the caches) the loop of steps and ``result`` for ``state``'s
    shapes and settings, by running zero steps of them; returns the seconds it took,
    ``init`` excluded (about 0 when this process has compiled them already)."""
    started = time.perf_counter()
    jax.block_until_ready(run_steps(optimizer, state, 0))
    jax.block_until_ready(finish(optimizer.result, state))
    return time.perf_counter() - started


def drive(optimizer, state: OptimizerState, *, budget: TimeBudget, on_step: Callable | None = None,
          trace: list | None = None, clock: float | None = None) -> OptimizerState:
    """Chunks of steps until the state is done or the budget is spent (module docstring).

    Reports every step to ``on_step`` and appends its ``StepInfo`` to ``trace``.
    """
    clock = time.perf_counter() if clock is None else clock
    budget.start()  # no-op when the caller started it
    done_steps, chunk = int(state.progress.step), 1
    while True:
        started = time.perf_counter()
        state = run_steps(optimizer, state, done_steps + chunk)
        # whole (small) arrays to the host: slicing on the device would compile a program
        # per slice shape
        progress = jax.device_get(state.progress)
        now = int(progress.step)
        seconds = time.perf_counter() - clock
        for j in range(done_steps, min(now, progress.history.shape[0])):
            info = StepInfo(optimizer.name, optimizer.stages[int(progress.history_stage[j])], j,
                            float(progress.history[j]), int(progress.history_moves[j]), seconds)
            if trace is not None:
                trace.append(info)
            if on_step is not None:
                on_step(info)
        if bool(progress.done) or now < done_steps + chunk:
            return state
        if budget.spent():
            return state
        done_steps = now
        if time.perf_counter() - started < CHUNK_SECONDS:
            chunk = min(2 * chunk, MAX_CHUNK)


def stack_states(states) -> OptimizerState:
    """One state with a leading batch axis from states of one optimizer, config and capacity."""
    states = list(states)
    if not states:
        raise ValueError("stack_states: no states")
    if any(s.static != states[0].static for s in states):
        raise ValueError("stack_states: the states differ in their static settings (config or shapes)")
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *states)


def init_batch(optimizer, trees, config=None, keys=None) -> OptimizerState:
    """The states of ``optimizer`` for a batch of trees, stacked (module docstring).

    ``trees``: a :class:`~jaxbvh.tree.layout.BVH` whose arrays have a leading batch axis
    B (:func:`jaxbvh.tree.batching.stack_trees`). ``keys``: [B] ``jax.random`` keys (None:
    every tree gets ``init``'s default key).
    """
    singles = unstack_trees(trees)
    if keys is not None and len(keys) != len(singles):
        raise ValueError(f"init_batch: {len(singles)} trees but {len(keys)} keys")
    return stack_states(optimizer.init(tree, config, None if keys is None else keys[i])
                        for i, tree in enumerate(singles))


def fill_rows(states: OptimizerState, real) -> OptimizerState:
    """``states`` with every row where ``real`` (bool [B]) is False marked done, so that
    it runs no step (a filler row: its result is dropped by the caller)."""
    real = np.asarray(real, bool)
    if real.all():
        return states
    done = np.asarray(states.progress.done) | ~real
    return states.replace(progress=states.progress._replace(done=jnp.asarray(done)))


def run_rows(states: OptimizerState, *, step: Callable, result: Callable, mode: str = "vmap") -> OptimizeResult:
    """The batch program (traceable): every row's ``step`` until it is done, then its
    ``result``; ``mode`` ``"vmap"`` or ``"map"`` (module docstring). Every leaf of
    ``states`` and of the result has the batch axis first."""
    if mode == "vmap":  # one loop for all rows, until the last is done (done rows are fixed points)
        states = jax.lax.while_loop(lambda s: ~jnp.all(s.progress.done), jax.vmap(step), states)
        return jax.vmap(result)(states)
    if mode != "map":
        raise ValueError(f"run_rows: mode must be 'map' or 'vmap', got {mode!r}")

    def run_one(state):  # the single-tree run: its own loop, only the branches it takes
        return result(jax.lax.while_loop(lambda s: ~s.progress.done, step, state))

    return jax.lax.map(run_one, states)


#: :func:`run_rows` compiled for the arrays' own devices (one program per step function,
#: mode and state shape; stored, so a warm process loads it)
_run_rows = stored_jit(run_rows, static_argnames=("step", "result", "mode"))


def run_states(optimizer, states: OptimizerState, *, mode: str = "vmap", real=None, call=None) -> OptimizeResult:
    """The one batch driver: ``optimizer`` run on stacked ``states`` to the end
    (module docstring); returns the stacked ``OptimizeResult`` (JAX arrays, every row's
    exactly its tree's single-tree result; a filler row's is to be dropped).

    ``mode``: ``"vmap"`` or ``"map"``. ``real``: bool [B], False for a filler row
    (None: every row is real). ``call``: None (the program runs where the arrays are:
    one device, or sharded by ``jax.sharding`` along the batch axis), or a function
    ``call(run_rows, (states,), step=..., result=..., mode=...)`` that compiles and runs
    it (:func:`jaxbvh.batch.devices.on_devices` with its devices: the batch axis split
    over them, each device's loop its own).
    """
    states = states if real is None else fill_rows(states, real)
    if call is None:
        return _run_rows(states, step=optimizer.step, result=optimizer.result, mode=mode)
    return call(run_rows, (states,), step=optimizer.step, result=optimizer.result, mode=mode)


def run_batch(optimizer, trees, config=None, *, keys=None, mode: str = "vmap") -> OptimizeResult:
    """Run ``optimizer`` on a batch of stacked trees at once, to the end (:func:`run_states`).

    ``trees``, ``keys``: as :func:`init_batch`; the trees' arrays may be sharded over
    devices along the batch axis (``jax.sharding``): the states are then placed the same
    way, and the result is sharded so. ``mode``: as :func:`run_states` (``"vmap"``: the
    protocol's ``step`` vmapped). Returns the ``OptimizeResult`` of every tree (JAX
    arrays with a leading batch axis), each exactly the tree's own result.
    """
    states = init_batch(optimizer, trees, config, keys)
    sharding = getattr(trees.left, "sharding", None)
    if sharding is not None and len(sharding.device_set) > 1:
        states = jax.device_put(states, sharding)
    return run_states(optimizer, states, mode=mode)
