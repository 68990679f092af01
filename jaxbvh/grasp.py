"""GRASP: randomized full-sweep builds, best of many trials (Ng & Trifonov 2003, §3.4).

The algorithm
=============
Ng & Trifonov treat the full-sweep SAH builder (Müller & Fellner; ``jaxbvh.build(method=
"sweep")``, one primitive per leaf) as a greedy constructive search and randomize it the
GRASP way: at every node the split is drawn from a *restricted candidate list* (RCL)
instead of always taking the best one, many trees are built, and the one with the
lowest objective is kept. A trial builds one tree:

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
included, is in :mod:`jaxbvh.build` (randomized split choice), whose level-synchronous
engine builds the trials (nothing is copied here).

The objective (``objective="nt"``, the paper's) is the total surface area of the interior
boxes over the root's (:func:`jaxbvh.cost.ng_trifonov_cost`); ``objective="sah"`` keeps
the tree of least SAH (``Ct = Ci = 1``) instead. Among equal objectives the lowest trial
number wins.

Randomness
==========
Trial ``t`` uses the key ``fold_in(key, t)`` (:func:`trial_key`), so a trial's tree does
not depend on how many trials run or how they are chunked, and the best of the first 10
trials of a 100-trial run is the best of a 10-trial run with the same key. Inside a
trial every node draws its two uniforms from :func:`jaxbvh.build.split_uniforms`, keyed by
the node's run of primitive positions ``[start, start + count)`` (root ``[0, n)``, left
child ``[start, start + N_L)``, right child the rest); draws are not sequential, so the
level-synchronous build equals the recursive one in :mod:`jaxbvh.reference.grasp` fed the
same key, node for node. The first uniform decides the deviation (``u0 < noise``), the
second the alternative.

Trials run as one vmapped call per chunk of trials (chunk size bounded by memory,
:data:`CHUNK_BYTES`); only each chunk's best tree leaves the device. ``noise = 0`` gives
the sweep builder's tree in every trial.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.build import build, engine_inputs, randomized_sweep
from jaxbvh.cost import ng_trifonov_cost, sah

OBJECTIVES = ("nt", "sah")

# Default noise, as expected deviations per tree (noise = DEFAULT_DEVIATIONS / (n - 1)).
# Placeholder until the sweep in bench/bench_stochastic.py is run.
DEFAULT_DEVIATIONS = 10.0

# Memory one chunk of trials may use (bytes); a trial needs about _BYTES_PER_SLOT per
# primitive slot of the padded capacity (measured: peak resident memory of one chunk).
CHUNK_BYTES = 1 << 30
_BYTES_PER_SLOT = 1024


@dataclasses.dataclass(frozen=True)
class GraspResult:
    """What :func:`grasp` returns.

    ``tree``: the best trial's :class:`~jaxbvh.tree.BVH` (JAX arrays, one primitive per
    leaf); ``objective``: its objective; ``objectives``: float64 NumPy [trials], every
    trial's objective in trial order; ``best_trial``: its trial number; ``base``: the
    objective of the greedy sweep tree (``noise = 0``); ``noise``: the noise used;
    ``rcl``: ``"axes"`` or ``k``; ``name``: the objective's name.
    """

    tree: Any
    objective: float
    objectives: np.ndarray
    best_trial: int
    base: float
    noise: float
    rcl: Any
    name: str

    def best_of(self, trials: int) -> float:
        """Best objective among the first ``trials`` trials (what a shorter run finds)."""
        return float(np.min(self.objectives[:trials]))


def trial_key(key, trial):
    """The key of trial number ``trial``: ``fold_in(key, trial)`` (int, or int array [T] -> [T] keys)."""
    trial = jnp.asarray(trial, jnp.uint32)
    if trial.ndim == 0:
        return jax.random.fold_in(key, trial)
    return jax.vmap(lambda t: jax.random.fold_in(key, t))(trial)


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


def resolve_noise(n: int, noise=None, deviations=None) -> float:
    """The per-node noise for ``n`` primitives from ``noise`` or ``deviations`` (one of them).

    ``deviations``: expected deviations per tree, ``noise = deviations / (n - 1)`` capped
    at 1 (0 for one primitive). Neither given: :data:`DEFAULT_DEVIATIONS`. Raises
    ``ValueError`` for both given, noise outside [0, 1], or negative deviations.
    """
    if noise is not None and deviations is not None:
        raise ValueError("give noise or deviations, not both")
    if noise is not None:
        noise = float(noise)
        if not 0.0 <= noise <= 1.0:
            raise ValueError(f"noise must be in [0, 1], got {noise}")
        return noise
    deviations = DEFAULT_DEVIATIONS if deviations is None else float(deviations)
    if not deviations >= 0.0 or math.isinf(deviations):
        raise ValueError(f"deviations must be a finite number >= 0, got {deviations}")
    return min(1.0, deviations / (n - 1)) if n > 1 else 0.0


def _mode(rcl):
    return ("axes", 0) if rcl == "axes" else ("list", int(rcl))


def _objective(tree, name):
    return ng_trifonov_cost(tree) if name == "nt" else sah(tree)


def randomized_build(key, prim_lo, prim_hi, *, noise: float, rcl="axes", pad: bool = True, dtype=None):
    """One GRASP trial: the randomized full-sweep tree for the trial key ``key``.

    Args:
      key: the trial's ``jax.random`` key (:func:`trial_key` of the run's key).
      prim_lo, prim_hi: [n, 3] primitive boxes (as for :func:`jaxbvh.build`).
      noise: probability in [0, 1] that a node deviates from the greedy split.
      rcl: ``"axes"`` or a list length ``k >= 1`` (module docstring).
      pad, dtype: as for :func:`jaxbvh.build`.

    Returns:
      A :class:`~jaxbvh.tree.BVH` (one primitive per leaf, nodes level by level).
    """
    mode, k = _mode(check_rcl(rcl))
    noise = resolve_noise(2, noise=noise)  # checks it
    lo, hi, n, scale = engine_inputs(prim_lo, prim_hi, pad=pad, dtype=dtype)
    return _one_trial(lo, hi, n, scale, key, jnp.float32(noise), jnp.int32(k), rcl=mode)


_one_trial = jax.jit(randomized_sweep, static_argnames=("rcl",))


@partial(jax.jit, static_argnames=("mode", "objective"))
def _chunk(keys, real, lo, hi, n, scale, noise, k, *, mode, objective):
    """Build ``keys`` [C] trials at once; returns (the best real trial's tree, objectives [C])."""
    def trial(key):
        tree = randomized_sweep(lo, hi, n, scale, key, noise, k, rcl=mode)
        return tree, _objective(tree, objective)

    trees, values = jax.vmap(trial)(keys)
    best = jnp.argmin(jnp.where(real, values, jnp.inf))  # first of equal values
    return jax.tree_util.tree_map(lambda x: x[best], trees), values


def chunk_size(capacity: int, trials: int) -> int:
    """Trials per vmapped call: as many as :data:`CHUNK_BYTES` allows, spread evenly."""
    most = max(1, CHUNK_BYTES // (_BYTES_PER_SLOT * max(capacity, 1)))
    chunks = -(-trials // most)
    return -(-trials // chunks)


def grasp(key, prim_lo, prim_hi, *, trials: int = 100, noise=None, deviations=None, rcl="axes",
          objective: str = "nt", chunk: int | None = None, pad: bool = True, dtype=None,
          on_chunk: Callable[[int, float], None] | None = None) -> GraspResult:
    """Best of ``trials`` randomized full-sweep builds (module docstring).

    Args:
      key: ``jax.random`` key of the run; trial ``t`` uses :func:`trial_key` ``(key, t)``.
      prim_lo, prim_hi: [n, 3] primitive boxes (as for :func:`jaxbvh.build`).
      trials: number of trees built, >= 1.
      noise: per-node probability of deviating, in [0, 1]; or
      deviations: expected deviations per tree (``noise = deviations / (n - 1)``); with
        neither, :data:`DEFAULT_DEVIATIONS`.
      rcl: ``"axes"`` (default, the paper's first method) or a list length ``k >= 1``.
      objective: ``"nt"`` (Ng & Trifonov's interior area, default) or ``"sah"``.
      chunk: trials per vmapped call (default: :func:`chunk_size`, bounded by memory).
      pad, dtype: as for :func:`jaxbvh.build`.
      on_chunk: called after each chunk with (trials done, best objective so far).

    Returns:
      A :class:`GraspResult`; its tree is the best trial's (lowest objective, then lowest
      trial number).
    """
    if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 1:
        raise ValueError(f"trials must be an integer >= 1, got {trials!r}")
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    rcl = check_rcl(rcl)
    mode, k = _mode(rcl)
    lo, hi, n, scale = engine_inputs(prim_lo, prim_hi, pad=pad, dtype=dtype)
    noise = resolve_noise(int(n), noise, deviations)
    if chunk is None:
        chunk = chunk_size(lo.shape[0], trials)
    elif isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"chunk must be an integer >= 1, got {chunk!r}")
    chunk = min(int(chunk), trials)

    base_tree = build(prim_lo, prim_hi, method="sweep", pad=pad, dtype=dtype)
    base = float(_objective(base_tree, objective))

    objectives = np.empty(trials, np.float64)
    best_tree, best_value, best_trial = None, math.inf, -1
    for first in range(0, trials, chunk):
        numbers = np.arange(first, first + chunk)
        tree, values = _chunk(trial_key(key, numbers), jnp.asarray(numbers < trials), lo, hi, n, scale,
                              jnp.float32(noise), jnp.int32(k), mode=mode, objective=objective)
        values = np.asarray(values, np.float64)[: trials - first]
        objectives[first: first + values.size] = values
        i = int(np.argmin(values))
        if values[i] < best_value:
            best_tree, best_value, best_trial = tree, float(values[i]), first + i
        if on_chunk is not None:
            on_chunk(first + values.size, best_value)
    return GraspResult(tree=best_tree, objective=best_value, objectives=objectives, best_trial=best_trial,
                       base=base, noise=noise, rcl=rcl, name=objective)
