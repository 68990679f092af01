"""One entry point for every tree optimizer, and the default pipeline that combines them.

Methods (:data:`METHODS`):

* ``"hc"`` — Kensler's rotations, hill climbing (:func:`jaxbvh.optimize.rotate.hill_climb`);
* ``"sa"`` — Kensler's rotations, simulated annealing (:func:`jaxbvh.optimize.rotate.anneal`);
* ``"reinsert"`` — parallel reinsertion (Meister & Bittner 2018, :mod:`jaxbvh.optimize.reinsert`);
* ``"treelet"`` — treelet restructuring (Karras & Aila 2013, :mod:`jaxbvh.optimize.treelet`);
* ``"pipeline"`` — rounds of treelet restructuring (:data:`PIPELINE_TREELET_PASSES`
  passes) followed by reinsertion (from the largest parent areas in the first round, from
  every node in later ones, where the gains left are spread thin), until a round lowers
  the SAH by less than
  ``round_gain`` (relative, default :data:`PIPELINE_ROUND_GAIN`) or after
  :data:`PIPELINE_MAX_ROUNDS` rounds. The two move sets are complementary: reinsertion
  moves whole subtrees anywhere in the tree, treelets rearrange up to 7 neighbouring
  subtrees optimally; each stops where the other still finds gains, and together they
  end below either alone (``bench/bench_optimize.py``; rotations add nothing after
  treelets, whose 7-leaf optimum includes every rotation at their root). Starting with
  treelets gave the lower SAH on the tinybvh trees.

Every method takes ``time_budget`` (seconds, compiling apart: the clock starts after
the first pass or iteration, which compiles; in the pipeline, later stages compile inside
the budget unless their programs are cached) and returns the best tree so far when it runs out; all of
them only lower the SAH except annealing, which keeps its best tree. Every result is a
:class:`OptimizeResult`. The pipeline is a composition of the optimizers above, each
held equal to its NumPy twin, so it has no twin of its own.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import numpy as np

from jaxbvh.optimize import reinsert, rotate, treelet
from jaxbvh.tree.cost import sah as sah_of
from jaxbvh.tree.layout import BVH, to_jax, to_numpy
from jaxbvh.tree.split_axes import assign_split_axes

METHODS = ("hc", "sa", "reinsert", "treelet", "pipeline")
PIPELINE_TREELET_PASSES = 2
PIPELINE_ROUND_GAIN = 1e-3
PIPELINE_MAX_ROUNDS = 8


@dataclasses.dataclass(frozen=True)
class OptimizeResult:
    """What :func:`optimize` returns.

    ``tree``: the optimized :class:`~jaxbvh.tree.layout.BVH` (NumPy, same capacity as the
    input). ``sah``, ``sah_start``: SAH after and before. ``steps``: passes or
    iterations run in all. ``moves``: moves (rotations, reinsertions, restructured
    treelets) applied. ``trace``: ``[(stage, step, sah, moves), ...]`` after every step
    of every stage (for curves; stage is the method of that step). ``chain_sah``: for
    annealing with several chains, every chain's SAH.
    """

    tree: Any
    sah: float
    sah_start: float
    steps: int
    moves: int
    trace: list
    chain_sah: Any = None


def _run(method, tree, *, key, ct, ci, time_budget, report, options):
    """One optimizer; returns ``(tree, steps, moves, chain_sah)`` (JAX tree)."""

    if method == "hc":
        out = rotate.hill_climb(tree, ct=ct, ci=ci, split_axes=False, time_budget=time_budget,
                                on_pass=lambda i, sah, moves, _t: report("hc", i, sah, moves),
                                **options)
        return out.tree, int(out.passes), int(out.moves), None
    if method == "sa":
        import jax

        out = rotate.anneal(jax.random.key(0) if key is None else key, tree, ct=ct, ci=ci,
                            split_axes=False, time_budget=time_budget,
                            on_pass=lambda i, sah, moves, _t: report("sa", i, sah, moves),
                            **options)
        return out.tree, int(out.passes), int(out.moves), out.chain_sah
    if method == "reinsert":
        out = reinsert.reinsert(tree, ct=ct, ci=ci, split_axes=False, time_budget=time_budget,
                                on_iteration=lambda i, sah, moves: report("reinsert", i, sah, moves),
                                **options)
        return out.tree, int(out.iterations), int(out.moves), None
    out = treelet.restructure(tree, ct=ct, ci=ci, split_axes=False, time_budget=time_budget,
                              on_step=lambda info: report("treelet", info.step, info.sah, info.moves),
                              **options)
    return to_jax(out.tree), int(out.steps), int(out.moves), None


def optimize(tree, method: str = "pipeline", *, key=None, ct: float = 1.0, ci: float = 1.0,
             time_budget: float | None = None, split_axes: bool = True,
             on_step: Callable | None = None, round_gain: float = PIPELINE_ROUND_GAIN,
             max_rounds: int = PIPELINE_MAX_ROUNDS, **options) -> OptimizeResult:
    """Optimize ``tree`` with ``method`` (one of :data:`METHODS`, module docstring).

    ``key``: ``jax.random`` key for ``"sa"`` (default ``key(0)``). ``time_budget``:
    seconds for the whole run (module docstring). ``split_axes``: Kensler's final pass
    (:func:`jaxbvh.optimize.rotate.assign_split_axes`) at the end. ``on_step(stage, step, sah,
    moves)``: called on the host after every pass or iteration. ``options``: passed to
    the optimizer (e.g. ``steps``/``chains`` for ``"sa"``, ``first_fraction`` for
    ``"reinsert"``, ``leaves`` for ``"treelet"``; for ``"pipeline"`` keys
    ``reinsert=dict(...)`` and ``treelet=dict(...)``). ``round_gain``, ``max_rounds``:
    the pipeline's stopping rule.
    """
    import jax

    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not isinstance(tree, BVH):
        raise ValueError(f"tree must be a binary jaxbvh.BVH, got {type(tree).__name__}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if not round_gain >= 0 or max_rounds < 1:
        raise ValueError(f"round_gain must be >= 0 and max_rounds >= 1, got {round_gain}, {max_rounds}")
    tree = to_jax(tree)
    trace = []
    clock = {}

    def report(stage, step, sah, moves):
        if not trace and time_budget is not None:  # the first step compiled: start the clock
            clock["deadline"] = time.perf_counter() + time_budget
        trace.append((stage, int(step), float(sah), int(moves)))
        if on_step is not None:
            on_step(stage, int(step), float(sah), int(moves))

    sah_start = float(sah_of(tree, ct, ci))
    common = dict(key=key, ct=ct, ci=ci, report=report)
    chain_sah = None
    if method != "pipeline":
        tree, steps, moves, chain_sah = _run(method, tree, time_budget=time_budget, options=options,
                                             **common)
    else:
        unknown = set(options) - {"reinsert", "treelet"}
        if unknown:
            raise ValueError(f"pipeline options are reinsert=dict(...) and treelet=dict(...), "
                             f"got {', '.join(sorted(unknown))}")
        stages = {"treelet": {"max_passes": PIPELINE_TREELET_PASSES, **options.get("treelet", {})},
                  "reinsert": dict(options.get("reinsert", {}))}
        steps = moves = 0
        sah = sah_start
        for round_ in range(max_rounds):
            if round_ == 1:  # the big moves are made: search every node from the start
                stages["reinsert"] = {**stages["reinsert"], "first_fraction": 1.0}
            before = sah
            for stage in ("treelet", "reinsert"):
                deadline = clock.get("deadline")
                left = time_budget if deadline is None else deadline - time.perf_counter()
                if left is not None and left <= 0:
                    break
                tree, n, m, _ = _run(stage, tree, time_budget=left, options=stages[stage], **common)
                steps, moves = steps + n, moves + m
                sah = trace[-1][2] if trace else sah
            deadline = clock.get("deadline")
            if before - sah < round_gain * before or (
                    deadline is not None and time.perf_counter() >= deadline):
                break
    if split_axes:
        tree = assign_split_axes(tree)
    tree = to_numpy(jax.block_until_ready(tree))
    return OptimizeResult(tree, float(sah_of(to_jax(tree), ct, ci)), sah_start, steps, moves, trace,
                          None if chain_sah is None else np.asarray(chain_sah))
