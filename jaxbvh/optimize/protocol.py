"""The optimizer protocol: every optimizer is three pure functions over one state pytree.

An optimizer (:class:`Optimizer`; all of them in :data:`jaxbvh.optimize.OPTIMIZERS`) is

* ``Config``: a frozen dataclass of its knobs, with the papers' defaults;
* ``init(tree, config=None, key=None) -> OptimizerState``: the state before the first
  step (host code allowed: checks, first settings);
* ``step(state) -> OptimizerState``: one pass or iteration; pure, jittable, and
  vmappable over a leading batch axis of states of one capacity. A state that is
  :attr:`Progress.done` comes back unchanged, so in a batch a tree that has converged
  stops changing while the others go on;
* ``result(state) -> OptimizeResult``: the optimized tree and the run's figures
  (traceable, so a batch of states gives a batch of results).

One host driver (:mod:`jaxbvh.optimize.driver`) runs any of them: chunks of steps in
one compiled loop, progress callbacks, a time budget.

The state
=========
:class:`OptimizerState` has the same five parts for every method:

=============  ======================================================================
field          meaning
=============  ======================================================================
``tree``       the input :class:`~jaxbvh.tree.layout.BVH` (JAX arrays): the fields an
               optimizer does not change (primitives, leaves) come from it
``progress``   :class:`Progress`: steps, SAH, moves, history, stopping flags
``params``     settings passed as traced values (costs, margins, schedule numbers):
               changing them does not recompile
``inner``      the method's own loop state (a NamedTuple, documented by the method)
``static``     hashable settings that fix shapes and modes (pytree metadata: part of
               the compiled program's identity, equal across a batch)
=============  ======================================================================
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.numerics import on_device
from jaxbvh.tree.layout import BVH, capacity_bucket


class Progress(NamedTuple):
    """The figures every optimizer keeps current (shapes: ``[]`` scalars, ``[H]`` history)."""

    step: Any           # int32 []: steps (passes or iterations) run so far
    limit: Any          # int32 []: most steps (the config's step limit)
    done: Any           # bool []: the run is over (converged or at the limit); step() keeps it
    converged: Any      # bool []: over because a step changed nothing (rather than the limit)
    sah: Any            # float []: SAH of the tree result() returns (annealing: the best kept)
    sah_start: Any      # float []: SAH of the input tree
    moves: Any          # int32 []: moves applied in all (rotations, reinsertions, treelets)
    stage: Any          # int32 []: index into Optimizer.stages of the current stage
    history: Any        # float [H]: SAH after each step, NaN past ``step``
    history_moves: Any  # int32 [H]: moves of each step
    history_stage: Any  # int32 [H]: stage of each step


def new_progress(sah_start, limit: int, dtype) -> Progress:
    """Progress before the first step; history length ``H`` = capacity bucket of ``limit``."""
    length = history_length(limit)
    sah_start = jnp.asarray(sah_start, dtype)
    zero = on_device(0, np.int32)  # numbers cast on the host: no conversion programs
    return Progress(step=zero, limit=on_device(limit, np.int32), done=on_device(limit <= 0, bool),
                    converged=on_device(False, bool), sah=sah_start, sah_start=sah_start, moves=zero,
                    stage=zero, history=on_device(np.full(length, np.nan), dtype),
                    history_moves=on_device(np.zeros(length), np.int32),
                    history_stage=on_device(np.zeros(length), np.int32))


def history_length(limit: int) -> int:
    """Entries of the history arrays for a step limit (a capacity bucket: few shapes)."""
    return capacity_bucket(max(int(limit), 1))


def record(progress: Progress, sah, moves, converged) -> Progress:
    """``progress`` after one more step that reached ``sah`` with ``moves`` moves;
    ``converged``: that step changed nothing (so the run is over)."""
    i = progress.step
    moves = jnp.asarray(moves, jnp.int32)
    sah = jnp.asarray(sah, progress.history.dtype)
    step = i + 1
    return progress._replace(
        step=step, sah=sah, moves=progress.moves + moves, converged=jnp.asarray(converged, bool),
        done=jnp.asarray(converged, bool) | (step >= progress.limit),
        history=progress.history.at[i].set(sah, mode="drop"),
        history_moves=progress.history_moves.at[i].set(moves, mode="drop"),
        history_stage=progress.history_stage.at[i].set(progress.stage, mode="drop"))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class OptimizerState:
    """The state of any optimizer between steps (layout: module docstring)."""

    tree: Any
    progress: Progress
    params: Any
    inner: Any
    static: Any = dataclasses.field(default=None, metadata=dict(static=True))

    def replace(self, **changes) -> "OptimizerState":
        """A copy with the given parts replaced."""
        return dataclasses.replace(self, **changes)


def keep_if_done(old: OptimizerState, new: OptimizerState) -> OptimizerState:
    """``new``, or ``old`` unchanged where ``old`` was already done (every step ends with
    this, so a finished state is a fixed point of ``step``, also inside a batch)."""
    done = old.progress.done
    return jax.tree_util.tree_map(lambda n, o: jnp.where(done, o, n), new, old)


#: why a run ended: ``"converged"`` (a step changed nothing), ``"limit"`` (its steps,
#: trials or generations were all run), ``"budget"`` (its time budget was spent)
STOP_REASONS = ("converged", "limit", "budget")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, kw_only=True)
class OptimizeResult:
    """What every optimizer and every search returns: one type, one set of conventions.

    The optimizers (``result(state)``, :func:`jaxbvh.optimize.optimize`) fill every
    field; the searches that are not step functions over one tree (GRASP, the GA,
    re-braiding: their results subclass this one, below) leave the per-move fields None.

    ``tree``: the tree found (optimizers: a :class:`~jaxbvh.tree.layout.BVH` of the
    input's capacity). ``sah``, ``sah_start``: its cost and the start's, measured by
    ``cost_name``: ``"sah"`` for the optimizers (``ct``, ``ci`` of the config); a search
    may price by another cost (``"nt"``, ``"gs"``: :mod:`jaxbvh.tree.cost`), or by none
    (None, re-braiding) as :class:`StepInfo`'s ``sah`` does. ``steps``: steps run (a
    pass or an iteration of an optimizer; GRASP: trials; the GA: generations, generation
    0 included; re-braiding: stages). ``converged``: the run ended because a step changed
    nothing (not at a step limit or a time budget); ``stop``: why it ended, one of
    :data:`STOP_REASONS` (None from ``result`` alone). ``history`` [H]: the cost after each
    step (NaN past ``steps``, or where nothing is priced; GRASP and the GA: the best so far).
    ``moves``: moves applied in all (rotations, reinsertions, restructured treelets);
    ``history_moves`` [H]: moves of each step; ``history_stage`` [H]: the stage of each
    step (index into the optimizer's ``stages``: the pipeline's are ``("treelet",
    "reinsert")``): None for the searches. ``chain_sah`` [K]: for annealing with K chains,
    every chain's final SAH (the other fields describe the best chain); None otherwise.
    ``trace``: the :class:`StepInfo` of every step as ``on_step`` got them, on the host
    (empty from ``result`` alone). ``seconds``: wall seconds of the whole run;
    ``compile_seconds``: wall seconds spent before the search began (``init`` and
    compiling the programs, or loading them from the persistent cache; about 0 when this
    process had them already; a search counts its tracing and compiling); a time budget
    counts the search only. Both None from ``result`` alone.
    Arrays are JAX arrays from ``result``, NumPy from :func:`jaxbvh.optimize.optimize`.
    """

    tree: Any
    sah: Any
    sah_start: Any
    steps: Any
    converged: Any
    history: Any
    moves: Any = None
    history_moves: Any = None
    history_stage: Any = None
    chain_sah: Any = None
    cost_name: str | None = dataclasses.field(default="sah", metadata=dict(static=True))
    stop: str | None = dataclasses.field(default=None, metadata=dict(static=True))
    trace: tuple = dataclasses.field(default=(), metadata=dict(static=True))
    seconds: float | None = dataclasses.field(default=None, metadata=dict(static=True))
    compile_seconds: float | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def cost(self):
        """``sah`` under the name searches gave it (the cost measured by ``cost_name``)."""
        return self.sah

    @property
    def cost_start(self):
        """``sah_start`` under the name searches gave it."""
        return self.sah_start

    def replace(self, **changes) -> "OptimizeResult":
        """A copy with the given fields replaced."""
        return dataclasses.replace(self, **changes)


def make_result(tree, progress: Progress, chain_sah=None) -> OptimizeResult:
    """The :class:`OptimizeResult` of an optimized ``tree`` and its ``progress``."""
    return OptimizeResult(tree=tree, sah=progress.sah, sah_start=progress.sah_start, steps=progress.step,
                          moves=progress.moves, converged=progress.converged, history=progress.history,
                          history_moves=progress.history_moves, history_stage=progress.history_stage,
                          chain_sah=chain_sah)


class StepInfo(NamedTuple):
    """What the driver tells ``on_step(info)`` after every step (host values)."""

    method: str    # the optimizer's name
    stage: str     # the stage of this step (the method itself unless it has several)
    step: int      # index of the step, from 0
    sah: float     # SAH after it
    moves: int     # moves it made
    seconds: float  # wall time since the run started (including compiling)


@dataclasses.dataclass(frozen=True)
class Optimizer:
    """One optimizer: ``Config`` and the three functions of the protocol (module docstring).

    ``stages``: names of the stages its steps belong to (``(name,)`` for one).
    ``paper``: where the method comes from. ``advance``: None (the driver runs ``step``
    in one compiled ``while_loop``), or a host function ``advance(state, stop) -> state``
    that the driver calls instead for one tree: it runs steps until the state is done or
    ``stop`` (an int) steps in all, exactly as that loop of ``step`` would (the same
    state), through programs of its own (the pipeline: one loop per stage, shared with
    that stage's optimizer, instead of one program holding both stages); given ``stop``
    at or below the steps already run, it runs none but compiles (or loads) every
    program it could run. Batches (:func:`~jaxbvh.optimize.driver.run_rows`) run ``step`` row by row,
    mapped or vmapped, never ``advance``.
    """

    name: str
    Config: type
    init: Callable
    step: Callable
    result: Callable
    stages: tuple = ()
    paper: str = ""
    advance: Callable | None = None

    def __post_init__(self):
        if not self.stages:
            object.__setattr__(self, "stages", (self.name,))


def check_tree(tree, name: str = "tree") -> None:
    """Raise ``ValueError`` unless ``tree`` is a binary :class:`~jaxbvh.tree.layout.BVH`."""
    if not isinstance(tree, BVH):
        raise ValueError(f"{name} must be a binary jaxbvh.BVH, got {type(tree).__name__}")


def check_config(config, Config: type, name: str):
    """``config`` (None: the defaults) as a ``Config``; ``ValueError`` for another type."""
    if config is None:
        return Config()
    if not isinstance(config, Config):
        raise ValueError(f"{name}: config must be a {Config.__qualname__}, got {type(config).__name__}")
    return config


def check_costs(ct, ci) -> None:
    """Raise ``ValueError`` unless the SAH constants are >= 0 (and not NaN)."""
    if not ct >= 0 or not ci >= 0:
        raise ValueError(f"ct and ci must be >= 0, got ct={ct}, ci={ci}")


def float_dtype(tree) -> np.dtype:
    """The tree's box dtype (float32 or float64)."""
    return np.dtype(tree.lo.dtype)


# ----------------------------------------------------------------------------------
# Searches that are not step functions over one tree (GRASP, the GA, re-braiding)
# ----------------------------------------------------------------------------------
#
# GRASP (jaxbvh.stochastic.grasp), the genetic algorithm (jaxbvh.stochastic.evolve) and
# re-braiding (jaxbvh.twolevel) build many trees or a two-level tree, not one tree step
# by step, so they do not run under the driver; they report the way it does: the
# optimizers' result type (their results subclass OptimizeResult, adding their own
# fields) and the driver's callback, on_step(info) with a StepInfo after every step.

#: the name the searches' result type had; the same type as :class:`OptimizeResult`
SearchResult = OptimizeResult


def check_on_step(on_step) -> None:
    """Raise ``ValueError`` unless ``on_step`` is None or a function ``on_step(info)``."""
    if on_step is not None and not callable(on_step):
        raise ValueError(f"on_step must be a function on_step(info), got {on_step!r}")


#: the compile events jax.monitoring reports (tracing, lowering, compiling)
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
_clocks: list = []  # the open CompileClocks (one listener serves them all)
_listening = False


def _on_event(event: str, seconds: float, **_) -> None:
    if event in COMPILE_EVENTS:
        for clock in _clocks:
            clock.seconds += seconds
            clock.events[event] = clock.events.get(event, 0) + 1


class CompileClock:
    """Seconds JAX spends tracing and compiling while the ``with`` block runs (every
    thread of the process counts), and how many of each :data:`COMPILE_EVENTS`.

    ``with CompileClock() as clock: ...`` then ``clock.seconds``, ``clock.events``.
    """

    def __init__(self):
        self.seconds = 0.0
        self.events: dict = {}

    def __enter__(self) -> "CompileClock":
        global _listening
        if not _listening:  # one listener for the process; never removed (it only adds)
            jax.monitoring.register_event_duration_secs_listener(_on_event)
            _listening = True
        _clocks.append(self)
        return self

    def __exit__(self, *exc) -> None:
        _clocks.remove(self)

    @property
    def traces(self) -> int:
        """Functions traced (a retrace counts again)."""
        return self.events.get(COMPILE_EVENTS[0], 0)
