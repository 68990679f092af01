"""GRASP: randomized full-sweep builds, best of many trials (Ng & Trifonov 2003, §3.4).

The algorithm
=============
Ng & Trifonov treat the full-sweep SAH builder (Müller & Fellner; ``jaxbvh.build(method=
"sweep")``, one primitive per leaf) as a greedy constructive search and randomize it the
GRASP way: at some nodes the split is drawn from a *restricted candidate list* (RCL)
instead of always being the best one; many trees are built and the one with the lowest
objective is kept. A trial builds one tree:

* every node first finds the greedy split (least ``A_L N_L + A_R N_R``, the sweep
  builder's tie rule), then with probability ``noise`` *deviates* from it;
* ``rcl="axes"`` (the paper's first method): a deviating node takes the best split of
  one of the two other axes, each with probability 1/2;
* ``rcl=k`` (cardinality RCL, the paper's Figure 1): a deviating node takes one of the
  ``k - 1`` next-best splits over all three axes, uniformly (fewer when the node has fewer
  than ``k`` candidates; ``k = 1`` never deviates).

``noise`` is the probability of *not* taking the greedy split, as the paper defines its
noise setting ("different probabilities of not picking the point with the best heuristic
value"), so a tree of ``n`` primitives (``n - 1`` interior nodes) deviates ``noise (n -
1)`` times on average: ``deviations = noise (n - 1)`` is the scale-free form. Table 3's
"random pick among the three axes' best points" is ``rcl="axes"`` with ``noise = 2/3``;
reading "pick uniformly among the ``k`` best, the best included, with probability ``p``"
for the cardinality RCL gives ``noise = p (k - 1) / k`` here. The exact rule, ties
included, is in :mod:`jaxbvh.builders.topdown` (randomized split choice), whose level-synchronous
engine builds every tree here (nothing is copied).

The objective (``objective="nt"``, the paper's) is the total surface area of the interior
boxes over the root's (:func:`jaxbvh.tree.cost.ng_trifonov_cost`); ``objective="sah"`` keeps
the tree of least SAH (``Ct = Ci = 1``) instead. Among equal objectives the lowest trial
number wins.

Randomness
==========
Node ``[start, start + count)`` of trial ``t`` draws its two uniforms from
:func:`jaxbvh.draws.split_uniforms` ``(key, t, start, count)``: keyed by the node's run of
primitive positions (root ``[0, n)``, left child ``[start, start + N_L)``, right child
the rest), not drawn in sequence. So a trial's tree does not depend on how many trials
run or in which order nodes are built: the level-synchronous engine equals the recursive
:mod:`jaxbvh.stochastic.grasp_reference` node for node, and the best of the first 10 trials of a
100-trial run is the best of a 10-trial run with the same key. The first uniform decides
the deviation (``u0 < noise``), the second the alternative.

Only deviating subtrees are built
=================================
Until a node deviates, a trial builds exactly the greedy tree: a node whose ancestors all
took the greedy split holds the same primitives, has the same run (so the same draws) and
finds the same greedy split. A trial's tree is therefore the greedy tree with the
subtrees under its *topmost deviating nodes* (deviating, no deviating ancestor) rebuilt.
:func:`grasp` builds the greedy tree once, draws ``u0`` for all of its interior nodes in
every trial, and builds only those subtrees, each as one tree of a forest
(:func:`jaxbvh.builders.topdown.randomized_forest`: its own trial number, its nodes named as in the
whole tree). Trees of many trials are packed into one forest, up to
:data:`CHUNK_PRIMS` primitives per call (memory bound), every call padded to one capacity
that depends on the scene's capacity, the trials and the noise only (``_run_capacity``: one
compile for every key and every scene of one capacity). A trial's objective is the greedy
tree's with the rebuilt subtrees' contributions swapped in (in float64 on the host; both
objectives are sums over nodes: the interior areas for ``"nt"``, each subtree's SAH
weighted by the area ratios down to it for ``"sah"``). With ``deviations`` per tree the
rebuilt subtrees hold about ``deviations x depth`` primitives, so a trial costs a small
fraction of a build; at high noise the root deviates and the whole tree is rebuilt. The
best trial's tree is built whole at the end (:func:`randomized_build`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders.configs import SweepConfig
from jaxbvh.builders.dispatch import build
from jaxbvh.builders.inputs import prepare
from jaxbvh.builders.topdown import RandomSplits, randomized_forest
from jaxbvh.configs import Checked, config_or_options, integer, knob, one_of, optional, real
from jaxbvh.draws import split_uniforms
from jaxbvh.numerics import half_area
from jaxbvh.optimize.protocol import CompileClock, OptimizeResult, StepInfo, check_on_step
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import capacity_bucket, concat_ranges, to_numpy
from jaxbvh.tree.walks import levels as tree_levels

OBJECTIVES = ("nt", "sah")

# Default noise, as expected deviations per tree: noise = DEFAULT_DEVIATIONS / (n - 1).
# The noise must shrink with the mesh: noise acts per node, and every deviation from the
# greedy split costs a little on average, so at a fixed noise big meshes only get worse
# (bunny, 69k triangles: best of 100 at noise 0.01 is 0.06% above greedy, every trial
# worse; the paper's 0.1 is 0.4-0.7% worse on the 6k-triangle meshes). Measured
# (bench/results/stochastic.md; rcl "axes", 100 trials, D = 1, 2, 3, 5, 10, 20, 30
# deviations per tree, seeds 0-2 on six shared meshes of 5.8k-20k triangles, seed 0 on
# bunny): D = 2 ... 10 put the best of 100 below greedy in every run (D = 1 missed once),
# D = 10 with the most trials below greedy on average (6.4 of 100; 2-18 per run); at
# D >= 20 spot, teapot and fandisk runs find nothing better. Gains are small: 0.002%
# (spot) to 0.8% (legocar) at D = 10, up to 1.4% (legocar, D ~ 330).
DEFAULT_DEVIATIONS = 10.0

# Most primitives in one forest call: the memory bound. Measured 1.4 KB of peak memory per
# forest slot (spot, noise 1: 44 trials in 262,144 slots, +350 MB), and a forest pads to
# at most twice its primitives, so a call stays under ~1.5 GB.
CHUNK_PRIMS = 1 << 19
_DRAWS_PER_CALL = 1 << 22  # u0 draws per call when screening the greedy tree's nodes


@dataclasses.dataclass(frozen=True, kw_only=True)
class GraspResult(OptimizeResult):
    """What :func:`grasp` returns: the fields of every search
    (:class:`jaxbvh.optimize.protocol.OptimizeResult`) and GRASP's own.

    Search fields: ``tree``: the best trial's :class:`~jaxbvh.tree.layout.BVH` (JAX
    arrays, one primitive per leaf); ``sah`` (also ``cost``) = ``objective``; ``sah_start`` = ``base``;
    ``cost_name`` = ``name``; ``steps``: trials run; ``history`` float64 [trials]: the
    best objective of the first ``t + 1`` trials; ``stop``: ``"limit"`` (every trial
    ran); ``trace``: every trial's :class:`~jaxbvh.optimize.protocol.StepInfo`;
    ``seconds``, ``compile_seconds``: the run's wall seconds and those spent compiling.

    GRASP's own: ``objective``: the best objective; ``objectives``: float64 NumPy
    [trials], every trial's objective in trial order; ``best_trial``: its trial number;
    ``base``: the objective of the greedy sweep tree (``noise = 0``); ``noise``: the noise
    used; ``rcl``: ``"axes"`` or ``k``; ``name``: the objective's name; ``rebuilt``: int64
    [trials], primitives under each trial's rebuilt subtrees (the work it cost).
    """

    objective: float
    objectives: np.ndarray
    best_trial: int
    base: float
    noise: float
    rcl: Any
    name: str
    rebuilt: np.ndarray

    def best_of(self, trials: int) -> float:
        """Best objective among the first ``trials`` trials (what a shorter run finds)."""
        return float(np.min(self.objectives[:trials]))


def check_rcl(rcl):
    """``rcl`` as ``"axes"`` or an int ``k >= 1``; ``ValueError`` naming the problem otherwise."""
    if isinstance(rcl, str) and rcl != "axes":
        if not rcl.strip().lstrip("+").isdigit():
            raise ValueError(f"rcl must be 'axes' or a list length k >= 1, got {rcl!r}")
        rcl = int(rcl)
    if rcl == "axes":
        return rcl
    if isinstance(rcl, (bool, float)) or not isinstance(rcl, (int, np.integer)) or rcl < 1:
        raise ValueError(f"rcl must be 'axes' or a list length k >= 1, got {rcl!r}")
    return int(rcl)


@dataclasses.dataclass(frozen=True)
class GraspConfig(Checked):
    """Knobs of a GRASP run (Ng & Trifonov 2003, §3.4; module docstring).

    ``trials``: randomized trees built (>= 1). ``noise``: the per-node probability of
    deviating from the greedy split, in [0, 1]; or ``deviations``: the expected
    deviations per tree (``noise = deviations / (n - 1)``); with neither,
    :data:`DEFAULT_DEVIATIONS`. ``rcl``: ``"axes"`` (the paper's first method) or a list
    length ``k >= 1``. ``objective``: ``"nt"`` (Ng & Trifonov's interior area) or
    ``"sah"``. ``chunk_prims``: most primitives per forest call (None:
    :data:`CHUNK_PRIMS`; a subtree larger than that gets a call of its own). ``pad``,
    ``dtype``: as for :class:`jaxbvh.builders.configs.SweepConfig`.
    """

    trials: int = knob(100, check=integer(1), metavar="T", help="randomized trees to build, >= 1")
    noise: float | None = knob(None, check=optional(real(0, 1)), type=float, metavar="P",
                               help="probability in [0, 1] that a node deviates from the greedy split")
    deviations: float | None = knob(None, check=optional(real(0)), type=float, metavar="D",
                                    help="instead of noise: expected deviations per tree, "
                                         "noise = D / (n - 1)")
    rcl: Any = knob("axes", check=lambda name, value: check_rcl(value), metavar="axes|K",
                    help="candidates of a deviation: 'axes' (the other axes' best splits, the paper's "
                         "first method) or K (the K - 1 next-best splits)")
    objective: str = knob("nt", check=one_of(OBJECTIVES), choices=OBJECTIVES,
                          help="nt: total interior box area / root area (the paper's); sah: SAH")
    chunk_prims: int | None = knob(None, check=optional(integer(1)), type=int,
                                   help="most primitives per forest call (memory bound)")
    pad: bool = knob(True, help="pad arrays to a capacity bucket (fewer recompiles)")
    dtype: Any = knob(None, help="float32 (None) or float64 (needs x64)")

    def _check_together(self):
        if self.noise is not None and self.deviations is not None:
            raise ValueError("give noise or deviations, not both")


def resolve_noise(n: int, noise=None, deviations=None) -> float:
    """The per-node noise for ``n`` primitives from ``noise`` or ``deviations`` (one of them).

    ``deviations``: expected deviations per tree, ``noise = deviations / (n - 1)`` capped
    at 1 (0 for one primitive). Neither given: :data:`DEFAULT_DEVIATIONS`. Raises
    ``ValueError`` (:class:`GraspConfig`'s checks) for both given, noise outside [0, 1],
    or negative deviations.
    """
    config = GraspConfig(noise=noise, deviations=deviations)
    if config.noise is not None:
        return config.noise
    deviations = DEFAULT_DEVIATIONS if config.deviations is None else config.deviations
    return min(1.0, deviations / (n - 1)) if n > 1 else 0.0


def _mode(rcl):
    return ("axes", 0) if rcl == "axes" else ("list", int(rcl))


#: :func:`jaxbvh.builders.topdown.randomized_forest`, compiled: every forest of a run and
#: every :func:`randomized_build` go through it (one program per capacity and RCL mode)
build_forest = stored_jit(randomized_forest, static_argnames=("rcl",))


def randomized_build(key, prim_lo, prim_hi, *, trial: int = 0, noise: float, rcl="axes", pad: bool = True,
                     dtype=None):
    """Trial ``trial`` of a GRASP run keyed ``key``: its whole randomized full-sweep tree.

    Args:
      key: the run's ``jax.random`` key.
      prim_lo, prim_hi: [n, 3] primitive boxes (as for :func:`jaxbvh.builders.topdown`).
      trial: the trial number, >= 0.
      noise: probability in [0, 1] that a node deviates from the greedy split.
      rcl: ``"axes"`` or a list length ``k >= 1`` (module docstring).
      pad, dtype: as for :func:`jaxbvh.builders.topdown`.

    Returns:
      A :class:`~jaxbvh.tree.layout.BVH` (one primitive per leaf, nodes level by level, root 0).
    """
    mode, k = _mode(check_rcl(rcl))
    trial = integer(0)("trial", trial)
    noise = resolve_noise(2, noise=noise)  # checks it
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, dtype=dtype)
    cap = lo.shape[0]
    zeros = jnp.zeros(cap, jnp.int32)
    splits = RandomSplits(key, zeros, zeros.at[0].set(trial), zeros, jnp.float32(noise), jnp.int32(k))
    tree, _ = build_forest(lo, hi, n, scale, splits, rcl=mode)
    return tree


# ----------------------------------------------------------------------------------
# Host-side bookkeeping over a tree: runs, subtree sums, SAH weights (float64)
# ----------------------------------------------------------------------------------


def _areas(lo, hi):
    """Half-areas [n] float64 of the boxes ``lo``, ``hi`` [n, 3] (host)."""
    return half_area(np.asarray(lo, np.float64), np.asarray(hi, np.float64))


def _subtree_sums(t, levels, area):
    """Per node: primitives under it, interior area below and at it, SAH ``C`` (float64)."""
    left, right = t.left.astype(np.int64), t.right.astype(np.int64)
    count = np.where(t.prim_count > 0, t.prim_count, 0).astype(np.int64)
    interior_area = np.zeros(left.shape[0])
    cost = np.where(t.prim_count > 0, t.prim_count.astype(np.float64), 0.0)  # Ci N, Ci = 1
    for ids in reversed(levels):
        inner = ids[left[ids] >= 0]
        a, b = left[inner], right[inner]
        count[inner] = count[a] + count[b]
        interior_area[inner] = area[inner] + interior_area[a] + interior_area[b]
        own = area[inner]
        weighted = (area[a] * cost[a] + area[b] * cost[b]) / np.where(own > 0, own, 1.0)
        cost[inner] = 1.0 + np.where(own > 0, weighted, cost[a] + cost[b])  # Ct = 1
    return count, interior_area, cost


@dataclasses.dataclass(frozen=True)
class _Greedy:
    """The greedy tree as seen by the trials: its interior nodes' runs and contributions."""

    prim_index: np.ndarray  # [n] primitive of each position
    start: np.ndarray       # [m] run of each interior node, sorted by (start, -count)
    count: np.ndarray
    contribution: np.ndarray  # [m] what the node's subtree adds to the objective
    weight: np.ndarray        # [m] its weight in the objective (sah: area ratios down to it)
    base: float               # the objective
    root_area: float


def _greedy(tree, objective) -> _Greedy:
    t = to_numpy(tree)
    root = int(t.root)
    levels = tree_levels(np.stack([t.left, t.right], axis=1).astype(np.int64), [root])
    area = _areas(t.lo, t.hi)
    count, interior_area, cost = _subtree_sums(t, levels, area)
    start = np.zeros_like(count)
    weight = np.zeros(count.shape[0])
    weight[root] = 1.0
    for ids in levels:
        inner = ids[t.left[ids] >= 0]
        a, b = t.left[inner], t.right[inner]
        start[a], start[b] = start[inner], start[inner] + count[a]
        own = area[inner]
        for c in (a, b):
            weight[c] = weight[inner] * np.where(own > 0, area[c] / np.where(own > 0, own, 1.0), 1.0)
    inner = np.flatnonzero(t.left >= 0)
    inner = inner[np.lexsort((-count[inner], start[inner]))]
    if objective == "nt":
        root_area = area[root]
        # zero root area: the objective counts interior nodes, the same for every tree
        scale = 1.0 / root_area if root_area > 0 else 0.0
        contribution, base = interior_area[inner] * scale, interior_area[root] * scale
        if root_area <= 0:
            base = float(inner.size)
        weight_inner = np.ones(inner.size)
    else:
        contribution, base, weight_inner = cost[inner], cost[root], weight[inner]
    return _Greedy(prim_index=np.asarray(t.prim_index), start=start[inner], count=count[inner],
                   contribution=contribution, weight=weight_inner, base=float(base), root_area=float(area[root]))


@stored_jit
def _first_uniforms(key, trials, start, count):
    """u0 [T, m] of the greedy tree's interior nodes in trials ``trials`` [T]."""
    t = jnp.broadcast_to(trials[:, None], (trials.shape[0], start.shape[0]))
    return split_uniforms(key, t, jnp.broadcast_to(start, t.shape), jnp.broadcast_to(count, t.shape))[..., 0]


def _topmost(deviate, start, count):
    """Indices of the topmost deviating nodes (runs sorted by (start, -count), laminar)."""
    idx = np.flatnonzero(deviate)
    if idx.size == 0:
        return idx
    end = start[idx] + count[idx]
    covered = np.concatenate([[-1], np.maximum.accumulate(end)[:-1]])  # furthest end so far
    return idx[start[idx] >= covered]


def _forest_values(forest, tree_of, groups, objective, root_area):
    """Per tree of the forest: its contribution to the objective (float64 [groups])."""
    t = to_numpy(forest)
    area = _areas(t.lo, t.hi)
    tree_of = np.asarray(tree_of)
    if objective == "nt":
        inner = t.left >= 0
        sums = np.bincount(tree_of[inner], weights=area[inner], minlength=groups)[:groups]
        return sums / root_area if root_area > 0 else np.zeros(groups)
    levels = tree_levels(np.stack([t.left, t.right], axis=1).astype(np.int64), np.arange(groups))
    _, _, cost = _subtree_sums(t, levels, area)
    return cost[:groups]


def _run_capacity(trials: int, noise: float, base: int, chunk_prims: int) -> int:
    """The forest capacity of a run, from its shapes and knobs only (not the key's draws
    nor the scene's boxes), so that every run of one capacity ``base``, ``trials`` and
    ``noise`` shares one compiled forest build (no retrace).

    In a balanced tree of ``base`` primitives every level holds them all and a node is a
    topmost deviating node with probability ``noise (1 - noise)^depth``, so a trial
    rebuilds about ``base (1 - (1 - noise)^log2(base))`` primitives. The capacity holds
    1.25 times that for all trials (a run above it makes one more call), at least
    ``base`` (any one subtree fits) and at most ``chunk_prims``, rounded up to ``base``
    x a power of two. (On spot, 100 trials at the default noise: 24,576 slots; the keys
    0-3 rebuild 9.6k-15.7k primitives.)
    """
    expected = trials * base * (1.0 - (1.0 - noise) ** math.log2(base))
    return _forest_capacity(max(1, min(math.ceil(1.25 * expected), chunk_prims)), base)


def _forest_capacity(total: int, base: int) -> int:
    """Capacity of a forest of ``total`` primitives: ``base`` (the scene's) times a power of two.

    Few shapes (compiles) per scene, at most half of the slots padding; the smallest is
    also the capacity of :func:`randomized_build`.
    """
    return base << max(0, math.ceil(math.log2(total / base))) if total > base else base


@dataclasses.dataclass(frozen=True)
class _Run:
    """What every forest call of a GRASP run shares."""

    key: Any          # the run's jax.random key
    lo: np.ndarray    # [n, 3] the prepared primitive boxes (cast; real primitives only)
    hi: np.ndarray    # [n, 3]
    scale: Any        # the scene's area scale (jaxbvh.builders.inputs.prepare)
    base: int         # the scene's capacity: a forest holds base x a power of two slots
    capacity: int     # the run's forest capacity (_run_capacity: the same for every key and scene)
    pad: bool         # pad forests to a capacity (else exactly their primitives)
    noise: float      # per-node deviation probability
    k: int            # list length of the cardinality RCL (0: rcl "axes")
    mode: str         # "axes" or "list" (static for the engine)
    objective: str    # "nt" or "sah"
    greedy: _Greedy   # the greedy tree the trials deviate from


def _deviating_subtrees(key, greedy: _Greedy, trials: int, noise: float, mode: str, k: int):
    """The topmost deviating nodes of every trial: ``[(trial, index into greedy's
    interior nodes)]``, by trial, then by run start."""
    can_deviate = greedy.start.size > 0 and noise > 0 and (mode == "axes" or k >= 2)
    subs = []
    # draw in blocks of a few shapes: trials and nodes padded to capacity buckets
    m = greedy.start.size
    padded = capacity_bucket(m)
    per_call = capacity_bucket(min(trials, max(1, _DRAWS_PER_CALL // padded)))
    start = jnp.zeros(padded, jnp.int32).at[:m].set(jnp.asarray(greedy.start, jnp.int32))
    count = jnp.zeros(padded, jnp.int32).at[:m].set(jnp.asarray(greedy.count, jnp.int32))
    for first in range(0, trials if can_deviate else 0, per_call):
        numbers = np.arange(first, first + per_call)
        u0 = np.asarray(_first_uniforms(key, jnp.asarray(numbers, jnp.int32), start, count))[:, :m]
        deviate = u0 < np.float32(noise)
        for row, t in enumerate(numbers[numbers < trials]):
            subs += [(int(t), int(i)) for i in _topmost(deviate[row], greedy.start, greedy.count)]
    return subs


def _batches(subs, count, chunk_prims: int):
    """``subs`` in order, cut into batches of at most ``chunk_prims`` primitives
    (``count[i]``: those under subtree ``i``; a larger subtree makes a batch alone)."""
    batch, size = [], 0
    for t, i in subs:
        c = int(count[i])
        if batch and size + c > chunk_prims:
            yield batch
            batch, size = [], 0
        batch.append((t, i))
        size += c
    if batch:
        yield batch


def _rebuild(run: _Run, batch):
    """Build one forest of the subtrees ``batch`` [(trial, node)] and price them.

    Returns ``(trial of each subtree, change of its trial's objective, its primitives)``,
    NumPy arrays [len(batch)].
    """
    greedy = run.greedy
    nodes = np.array([i for _, i in batch])
    owner = np.array([t for t, _ in batch])
    starts, counts = greedy.start[nodes], greedy.count[nodes]
    groups = np.repeat(np.arange(len(batch)), counts)
    ids = greedy.prim_index[concat_ranges(starts, counts)]
    ids = ids[np.lexsort((ids, groups))]  # each group's primitives by id: the tie order
    total = ids.size
    cap = max(run.capacity, _forest_capacity(total, run.base)) if run.pad else total
    lo_f = np.full((cap, 3), np.inf, run.lo.dtype)
    hi_f = np.full((cap, 3), -np.inf, run.lo.dtype)
    lo_f[:total], hi_f[:total] = run.lo[ids], run.hi[ids]
    per_group = np.zeros(cap, np.int32)
    trial_of, shift = per_group.copy(), per_group.copy()
    group = np.full(cap, 0, np.int32)
    group[:total] = groups
    trial_of[: len(batch)] = owner
    shift[: len(batch)] = starts - (np.cumsum(counts) - counts)
    splits = RandomSplits(run.key, jnp.asarray(group), jnp.asarray(trial_of), jnp.asarray(shift),
                          jnp.float32(run.noise), jnp.int32(run.k))
    forest, tree_of = build_forest(jnp.asarray(lo_f), jnp.asarray(hi_f), jnp.int32(total), run.scale, splits,
                                   rcl=run.mode)
    values = _forest_values(forest, tree_of, len(batch), run.objective, greedy.root_area)
    return owner, greedy.weight[nodes] * (values - greedy.contribution[nodes]), counts


def grasp(key, prim_lo, prim_hi, config: GraspConfig | None = None, *,
          on_step: Callable[[StepInfo], None] | None = None,
          on_chunk: Callable[[int, float], None] | None = None, **options) -> GraspResult:
    """Best of ``config.trials`` randomized full-sweep builds (module docstring).

    Args:
      key: ``jax.random`` key of the run.
      prim_lo, prim_hi: [n, 3] primitive boxes (as for :func:`jaxbvh.build`).
      config: a :class:`GraspConfig` (its knobs and defaults); or None and
      options: its knobs as keywords (``trials``, ``noise`` or ``deviations``, ``rcl``,
        ``objective``, ``chunk_prims``, ``pad``, ``dtype``).
      on_step: the optimizers' progress callback (:func:`jaxbvh.optimize.optimize`):
        called as ``on_step(info)`` once per trial, in trial order, with a
        :class:`~jaxbvh.optimize.protocol.StepInfo` (``step``: the trial, ``sah``: the
        best objective so far, ``moves``: primitives the trial rebuilt, ``seconds``:
        since the run started), as soon as the forest call that finishes it returns.
      on_chunk: deprecated (use ``on_step``): called after each forest call with
        (trials done, best objective among them; ``base`` while none is done), and once
        at the end with (trials, best).

    Returns:
      A :class:`GraspResult`; its tree is the best trial's (lowest objective, then lowest
      trial number), built whole.
    """
    config = config_or_options(config, options, GraspConfig)
    check_on_step(on_step)
    if on_chunk is not None:
        warnings.warn("grasp(on_chunk=...) is deprecated: use on_step(info), the optimizers' callback",
                      DeprecationWarning, stacklevel=2)
    with CompileClock() as clock:
        started = time.perf_counter()
        result = _grasp(key, prim_lo, prim_hi, config, on_step, on_chunk, started)
        jax.block_until_ready(result.tree)
        seconds = time.perf_counter() - started
    return result.replace(seconds=seconds, compile_seconds=clock.seconds)


def _grasp(key, prim_lo, prim_hi, config: GraspConfig, on_step, on_chunk, started: float) -> GraspResult:
    """:func:`grasp` without its clocks (``started``: when the run began, for ``StepInfo.seconds``)."""
    trials, objective, rcl, pad, dtype = config.trials, config.objective, config.rcl, config.pad, config.dtype
    mode, k = _mode(rcl)
    chunk_prims = CHUNK_PRIMS if config.chunk_prims is None else config.chunk_prims
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, dtype=dtype)
    n = int(n)
    noise = resolve_noise(n, config.noise, config.deviations)

    # the greedy tree GRASP perturbs: the sweep build with one primitive per leaf, as the
    # randomized builds make (not the builders' default leaves)
    greedy = _greedy(build(prim_lo, prim_hi, SweepConfig(pad=pad, dtype=dtype, max_leaf=1)), objective)
    objectives = np.full(trials, greedy.base)
    rebuilt = np.zeros(trials, np.int64)
    subs = _deviating_subtrees(key, greedy, trials, noise, mode, k)
    # one forest capacity for every run of this scene and knobs, whatever the key (one
    # compile); padded forests are cut to fit it (a subtree alone always fits: <= base)
    capacity = _run_capacity(trials, noise, lo.shape[0], chunk_prims)
    run = _Run(key=key, lo=np.asarray(lo)[:n], hi=np.asarray(hi)[:n], scale=scale, base=lo.shape[0],
               capacity=capacity, pad=pad, noise=noise, k=k, mode=mode, objective=objective, greedy=greedy)
    batches = list(_batches(subs, greedy.count, min(chunk_prims, capacity) if pad else chunk_prims))
    trace: list[StepInfo] = []

    def report(done: int) -> None:
        """StepInfo of trials ``len(trace) .. done - 1`` (all finished) to ``on_step``."""
        seconds = time.perf_counter() - started
        best = trace[-1].sah if trace else math.inf
        for t in range(len(trace), done):
            best = min(best, float(objectives[t]))
            info = StepInfo("grasp", "grasp", t, best, int(rebuilt[t]), seconds)
            trace.append(info)
            if on_step is not None:
                on_step(info)

    for number, batch in enumerate(batches):
        owner, change, counts = _rebuild(run, batch)
        np.add.at(objectives, owner, change)
        np.add.at(rebuilt, owner, counts)
        done = batch[-1][0]  # trials before the batch's last one are finished
        report(done)
        if on_chunk is not None and number < len(batches) - 1:
            on_chunk(done, float(np.min(objectives[:done])) if done else greedy.base)
    report(trials)
    best = int(np.argmin(objectives))
    if on_chunk is not None:
        on_chunk(trials, float(objectives[best]))
    tree = randomized_build(key, prim_lo, prim_hi, trial=best, noise=noise, rcl=rcl, pad=pad, dtype=dtype)
    return GraspResult(tree=tree, sah=float(objectives[best]), sah_start=greedy.base, cost_name=objective,
                       steps=trials, history=np.minimum.accumulate(objectives), converged=False, stop="limit",
                       trace=tuple(trace), objective=float(objectives[best]), objectives=objectives,
                       best_trial=best, base=greedy.base, noise=noise, rcl=rcl, name=objective, rebuilt=rebuilt)
