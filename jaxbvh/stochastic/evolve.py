"""A genetic algorithm over insertion orders (Ng & Trifonov 2003, §4), population-parallel.

Goldsmith and Salmon's insertion build (:mod:`jaxbvh.builders.insertion`) depends on the order
in which objects arrive. Ng and Trifonov search that order space with a genetic
algorithm on permutations (operators after Cassen, Michalewicz & Subramanian 1995):

* **fitness**: the Goldsmith–Salmon cost of the tree an order builds
  (:func:`jaxbvh.goldsmith_salmon_cost`, lower is fitter); the whole population is built
  in one batched call (:func:`jaxbvh.builders.insertion.insert_batch`);
* **selection**: slot 0 of the next population is the fittest individual (elitism: it
  is kept unchanged, so the best order seen so far is always in the population and the
  best cost never rises); each other slot ``i`` holds the winner of a tournament
  between two individuals drawn uniformly (with replacement) — the lower cost wins,
  the first drawn on a tie (duplicates are possible, as in the paper);
* **crossover** (order crossover, rate ``crossover``, default 0.7): slots ``(1, 2)``,
  ``(3, 4)``, ... are pairs of parents; a pair crosses with probability ``crossover``
  at a cut ``c`` drawn uniformly from ``1 .. n-1``: the first child is the first
  parent's prefix of length ``c`` followed by the remaining objects in the second
  parent's order, the second child the same with the parents' roles swapped, and the
  children replace their parents;
* **mutation** (swap mutation, rate ``mutation = F``, default 1/500): every individual
  but the elite makes up to ``S`` swaps of two distinct positions drawn uniformly, each
  one with probability ``F n / S``, in order — on average ``F n`` swaps, the paper's
  "about 1/500th of the length" (``S = max(1, ceil(4 F capacity))``,
  :func:`max_swaps`).

A generation applies selection, crossover and mutation to the current population and
prices the new one; the operators work on the whole population at once
(:func:`next_population`: gathers, a ``vmap`` of :func:`order_crossover`, and the
swaps as ``S`` batched exchanges). Generation 0 is ``P`` uniformly random orders; its
median cost is reported as ``random_median`` beside the GA's best (the paper's
comparison with "the average Goldsmith and Salmon case"). Ties between costs use the relative ``TIE_TOLERANCE`` of
:mod:`jaxbvh.builders.topdown` (within it, the first of a tournament pair wins and the lowest
slot is the elite), so the NumPy twin :mod:`jaxbvh.stochastic.evolve_reference`, fed the same
draws, makes the same choices.

Randomness. Every random number of generation ``g`` (1-based) comes from
:func:`generation_draws` with the key :func:`generation_key` ``(key, g)``; the initial
population from :func:`initial_population` with ``generation_key(key, 0)``. The same
key gives the same run, bit for bit, on one machine, and on one device or several.

Devices. With ``devices`` the population is split evenly over them and each device
builds its share of the trees (``jax.shard_map``); selection and the operators are
cheap and run on the gathered population. The results are the same as on one device
(tested with two host devices). Each device also returns its best tree, so the final
tree needs no rebuild unless a cost tie within the tolerance straddles two devices.

Layout. A population is int32 [P, capacity]: row ``i`` is an order of ``0 .. n-1``
followed by the padding ids ``n .. capacity-1`` (``capacity = capacity_bucket(n)``,
so meshes of similar size share compiled code); the operators never move padding.

The paper's empirical check — does the G&S cost predict what rays measure? — is
:func:`ray_costs`: the mean number of box and primitive tests per random ray (origins
uniform in the root box, directions uniform; :func:`jaxbvh.rays.measure.random_rays`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
import warnings
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders import insertion
from jaxbvh.configs import Checked, config_or_options, integer, knob, real
from jaxbvh.numerics import TIE_TOLERANCE
from jaxbvh.optimize.protocol import CompileClock, OptimizeResult, StepInfo, check_on_step
from jaxbvh.program_store import stored_jit
from jaxbvh.rays.measure import make_rays, trace


def _max_children(name, value):
    return insertion.check_max_children(value)  # the insertion build's rule; its message names max_children


@dataclasses.dataclass(frozen=True)
class EvolveConfig(Checked):
    """Knobs of the genetic algorithm (Ng & Trifonov 2003, §4; module docstring).

    ``population``: individuals P (>= 2; the paper's 50). ``generations``: G (>= 0; 0
    only prices random orders). ``crossover``: probability that a pair of parents
    crosses (the paper's 0.7). ``mutation``: expected swaps per individual and
    generation as a fraction of n (the paper's "about 1/500th of the length").
    ``max_children``: most children per node of the insertion build
    (:data:`jaxbvh.builders.insertion.DEFAULT_MAX_CHILDREN`). ``dtype``: float32 (None)
    or float64 (needs x64).
    """

    population: int = knob(50, check=integer(2), metavar="P", help="insertion orders per generation, >= 2")
    generations: int = knob(100, check=integer(0), metavar="G",
                            help="generations after the random first one, >= 0")
    crossover: float = knob(0.7, check=real(0, 1), metavar="R",
                            help="probability that a pair of parents crosses, in [0, 1]")
    mutation: float = knob(1 / 500, check=real(0, 1), metavar="F",
                           help="expected swaps per individual and generation as a fraction of the "
                                "primitives, in [0, 1] (the paper's 1/500)")
    max_children: int = knob(insertion.DEFAULT_MAX_CHILDREN, check=_max_children, metavar="K",
                             help="most children of a node, >= 2 (see jaxbvh.insertion)")
    dtype: Any = knob(None, help="float32 (None) or float64 (needs x64)")


class Draws(NamedTuple):
    """The random numbers of one generation (population P, pairs Q = (P - 1) // 2).

    ``first``, ``second``: [P-1] int32 tournament contestants for slots 1 .. P-1;
    ``cross``: [Q] bool, pair ``j`` (slots ``1 + 2j``, ``2 + 2j``) crosses;
    ``cut``: [Q] int32 crossover cut in ``1 .. n-1``;
    ``swap``: [P-1, S] bool, individual ``i + 1`` makes swap ``s``;
    ``swap_a``, ``swap_b``: [P-1, S] int32 the two (distinct) positions of that swap.
    """

    first: Any
    second: Any
    cross: Any
    cut: Any
    swap: Any
    swap_a: Any
    swap_b: Any


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvolveResult(OptimizeResult):
    """What :func:`evolve` returns (NumPy / Python values): the fields of every search
    (:class:`jaxbvh.optimize.protocol.OptimizeResult`) and the GA's own.

    Search fields: ``tree``: the best order's tree (:class:`~jaxbvh.tree.layout.WideBVH`,
    JAX arrays); ``sah`` (also ``cost``) = ``best``; ``sah_start`` = ``initial_best``; ``cost_name``:
    ``"gs"`` (Goldsmith and Salmon's cost); ``steps``: generations run, generation 0
    included (G + 1); ``history`` [G + 1]: the best cost of every generation (0 .. G);
    ``stop``: ``"limit"``; ``trace``: every generation's
    :class:`~jaxbvh.optimize.protocol.StepInfo`; ``seconds``: wall time of the whole run
    (compiling included), ``compile_seconds``: the part spent compiling.

    The GA's own: ``order`` [n]: the best order found; ``best``: its cost;
    ``initial_best``: the best cost of generation 0; ``random_median``: the median cost
    of generation 0 (P uniformly random orders); ``population`` [P, n], ``costs`` [P]:
    the last generation; ``elites`` [G + 1, n]: the best order of every generation
    (``keep_elites=True``), else None.
    """

    order: np.ndarray
    best: float
    initial_best: float
    random_median: float
    population: np.ndarray
    costs: np.ndarray
    elites: np.ndarray | None = None


def max_swaps(capacity: int, mutation: float) -> int:
    """``S``: swap slots per individual and generation for orders padded to ``capacity``.

    ``S = max(1, ceil(4 F capacity))``; each slot swaps with probability ``F n / S``
    (module docstring). Depending on the capacity, not on ``n``, it keeps the shapes
    (and so the compiled code) the same for all meshes of one capacity bucket.
    """
    return max(1, math.ceil(4 * mutation * capacity))


def generation_key(key, generation: int):
    """The key of ``generation`` (0: the initial population) in a run seeded with ``key``."""
    return jax.random.fold_in(key, generation)


@partial(stored_jit, static_argnames=("population", "capacity"))
def initial_population(key, population: int, n, capacity: int):
    """``population`` uniformly random orders of ``0 .. n-1``, padded: int32 [P, capacity].

    Each order sorts the ids by 31 random bits (ties, about ``n^2 / 2^32`` of them, by
    id); the padding ids sort last, in order.
    """
    ids = jnp.arange(capacity, dtype=jnp.uint32)

    def one(k):
        bits = jax.random.bits(k, (capacity,), jnp.uint32) >> 1
        return jnp.argsort(jnp.where(ids < n, bits, jnp.uint32(2**31)), stable=True).astype(jnp.int32)

    return jax.vmap(one)(jax.random.split(key, population))


@partial(stored_jit, static_argnames=("population", "swaps"))
def generation_draws(key, population: int, n, swaps: int, crossover, mutation) -> Draws:
    """The random numbers of one generation (:class:`Draws`) for orders of ``n`` objects;
    ``swaps`` is :func:`max_swaps`."""
    k_first, k_second, k_cross, k_cut, k_swap, k_a, k_b = jax.random.split(key, 7)
    others = population - 1
    pairs = others // 2
    n = jnp.asarray(n, jnp.int32)
    cut = jax.random.randint(k_cut, (pairs,), 1, jnp.maximum(n, 2), jnp.int32)
    a = jax.random.randint(k_a, (others, swaps), 0, n, jnp.int32)
    b = jax.random.randint(k_b, (others, swaps), 0, jnp.maximum(n - 1, 1), jnp.int32)
    b = b + (b >= a)  # distinct from a
    probability = jnp.asarray(mutation, jnp.float32) * n.astype(jnp.float32) / swaps
    swap = (jax.random.uniform(k_swap, (others, swaps)) < probability) & (n >= 2)
    return Draws(first=jax.random.randint(k_first, (others,), 0, population, jnp.int32),
                 second=jax.random.randint(k_second, (others,), 0, population, jnp.int32),
                 cross=(jax.random.uniform(k_cross, (pairs,)) < crossover) & (n >= 2),
                 cut=cut, swap=swap, swap_a=a, swap_b=jnp.where(swap, b, a))


# ----------------------------------------------------------------------------------
# Operators, vectorised over the population
# ----------------------------------------------------------------------------------


def elite_index(costs):
    """Lowest slot whose cost is within the tie tolerance of the least."""
    near = 1 + TIE_TOLERANCE
    return jnp.argmax(costs <= jnp.min(costs) * near).astype(jnp.int32)


def order_crossover(first, second, cut):
    """``first[:cut]`` then the rest of ``second`` in its order; orders [capacity]."""
    capacity = first.shape[0]
    ids = jnp.arange(capacity, dtype=jnp.int32)
    position_in_first = jnp.zeros(capacity, jnp.int32).at[first].set(ids)
    keep = position_in_first[second] >= cut
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1
    child = jnp.where(ids < cut, first, -1)
    return child.at[jnp.where(keep, cut + rank, capacity)].set(second, mode="drop")


@stored_jit
def next_population(population, costs, draws: Draws):
    """Selection with elitism, order crossover and swap mutation: int32 [P, capacity]."""
    near = 1 + TIE_TOLERANCE
    a, b = draws.first, draws.second
    winner = jnp.where(costs[b] * near < costs[a], b, a)
    pop = population[jnp.concatenate([elite_index(costs)[None], winner])]
    pairs = draws.cut.shape[0]
    if pairs:
        first, second = pop[1:1 + 2 * pairs:2], pop[2:2 + 2 * pairs:2]
        one = jax.vmap(order_crossover)(first, second, draws.cut)
        two = jax.vmap(order_crossover)(second, first, draws.cut)
        cross = draws.cross[:, None]
        pop = pop.at[1:1 + 2 * pairs:2].set(jnp.where(cross, one, first))
        pop = pop.at[2:2 + 2 * pairs:2].set(jnp.where(cross, two, second))
    rest = pop[1:]
    rows = jnp.arange(rest.shape[0])

    def swap(s, rest):
        i, j = draws.swap_a[:, s], draws.swap_b[:, s]  # i == j when the swap is off
        vi, vj = rest[rows, i], rest[rows, j]
        return rest.at[rows, i].set(vj).at[rows, j].set(vi)

    rest = jax.lax.fori_loop(0, draws.swap.shape[1], swap, rest)
    return pop.at[1:].set(rest)


# ----------------------------------------------------------------------------------
# Fitness: the whole population in one call, optionally split over devices
# ----------------------------------------------------------------------------------


def _mesh(devices, population: int):
    if devices is None:
        return None
    if isinstance(devices, int):
        if devices < 1 or devices > jax.device_count():
            raise ValueError(f"devices must be in 1 .. {jax.device_count()}, got {devices}")
        devices = jax.devices()[:devices]
    devices = list(devices)
    if population % len(devices):
        raise ValueError(f"population {population} does not split evenly over {len(devices)} devices")
    return jax.sharding.Mesh(np.array(devices), ("population",))


@partial(stored_jit, static_argnames=("max_children",))
def _costs_and_elite(lo, hi, orders, n, scale, *, max_children: int):
    trees, costs = insertion.insert_batch(lo, hi, orders, n, scale, max_children=max_children)
    elite = elite_index(costs)
    return costs, insertion.tree_at(trees, elite), elite


@functools.lru_cache(maxsize=None)
def _sharded_costs_and_elites(mesh, max_children: int):
    spec, whole = jax.sharding.PartitionSpec("population"), jax.sharding.PartitionSpec()

    def local(lo, hi, orders, n, scale):
        costs, tree, elite = _costs_and_elite(lo, hi, orders, n, scale, max_children=max_children)
        return costs, jax.tree_util.tree_map(lambda a: a[None], tree), elite[None]

    return jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(whole, whole, spec, whole, whole),
                                 out_specs=spec, check_vma=False))


def population_costs(lo, hi, orders, n, scale, *, max_children: int, mesh=None):
    """``(costs, elite tree)``: the G&S costs [P] of the trees of ``orders`` [P, capacity]
    (boxes prepared by :func:`jaxbvh.builders.insertion.prepare`), built in one batched call
    (split over ``mesh`` if given), and the tree of :func:`elite_index` ``(costs)``.

    Split over devices, each device returns its own elite; the global elite is one of
    them unless a tie within the tolerance straddles two devices, and then (None) the
    caller builds it again.
    """
    if mesh is None:
        costs, tree, _ = _costs_and_elite(lo, hi, orders, n, scale, max_children=max_children)
        return costs, tree
    costs, trees, local = _sharded_costs_and_elites(mesh, max_children)(lo, hi, orders, n, scale)
    size = orders.shape[0] // mesh.size
    elite = int(elite_index(costs))
    device = elite // size
    if device * size + int(local[device]) != elite:
        return costs, None
    return costs, insertion.tree_at(trees, device)


# ----------------------------------------------------------------------------------
# The driver
# ----------------------------------------------------------------------------------


def evolve(key, prim_lo, prim_hi, config: EvolveConfig | None = None, *, devices=None,
           on_step: Callable[[StepInfo], None] | None = None,
           on_generation: Callable[[int, float], None] | None = None,
           keep_elites: bool = False, **options) -> EvolveResult:
    """Search insertion orders of ``prim_lo``, ``prim_hi`` [n, 3] with the genetic algorithm.

    Args:
      key: ``jax.random`` key; the same key gives the same run.
      config: an :class:`EvolveConfig` (its knobs and defaults: population, generations,
        crossover, mutation, max_children, dtype); or None and
      options: those knobs as keywords.
      devices: None (one device), a number of devices, or a list of devices to split
        the population over (P must be a multiple of their number).
      on_step: the optimizers' progress callback (:func:`jaxbvh.optimize.optimize`):
        called as ``on_step(info)`` after each generation (``info.step`` = g = 0 .. G)
        with a :class:`~jaxbvh.optimize.protocol.StepInfo` (``sah``: the best G&S cost
        of that generation, ``moves``: 0, ``seconds``: since the run started).
      on_generation: deprecated (use ``on_step``): called as ``on_generation(g,
        best_cost)`` after each generation.
      keep_elites: also return the best order of every generation (``elites``).

    Returns:
      :class:`EvolveResult`.
    """
    config = config_or_options(config, options, EvolveConfig)
    check_on_step(on_step)
    if on_generation is not None:
        warnings.warn("evolve(on_generation=...) is deprecated: use on_step(info), the optimizers' callback",
                      DeprecationWarning, stacklevel=2)
    with CompileClock() as clock:
        result = _evolve(key, prim_lo, prim_hi, config, devices, on_step, on_generation, keep_elites)
    return result.replace(compile_seconds=clock.seconds)


def _evolve(key, prim_lo, prim_hi, config: EvolveConfig, devices, on_step, on_generation,
            keep_elites: bool) -> EvolveResult:
    """:func:`evolve` without its compile clock."""
    population, generations = config.population, config.generations
    crossover, mutation, k = config.crossover, config.mutation, config.max_children
    start = time.perf_counter()
    lo, hi, n_dev, scale = insertion.prepare(prim_lo, prim_hi, dtype=config.dtype)
    n, capacity = int(n_dev), int(lo.shape[0])
    mesh = _mesh(devices, population)

    def fitness(orders):
        return population_costs(lo, hi, orders, n_dev, scale, max_children=k, mesh=mesh)

    swaps = max_swaps(capacity, mutation)
    trace = []

    def report(g: int, best: float) -> None:
        info = StepInfo("evolve", "evolve", g, best, 0, time.perf_counter() - start)
        trace.append(info)
        if on_step is not None:
            on_step(info)
        if on_generation is not None:
            on_generation(g, best)

    pop = initial_population(generation_key(key, 0), population, n, capacity)
    costs, elite_tree = fitness(pop)
    history = [float(jnp.min(costs))]
    elites = [np.asarray(pop[elite_index(costs), :n])] if keep_elites else None
    random_median = float(np.median(np.asarray(costs)))
    report(0, history[0])
    for g in range(1, generations + 1):
        draws = generation_draws(generation_key(key, g), population, n, swaps, crossover, mutation)
        pop = next_population(pop, costs, draws)
        costs, elite_tree = fitness(pop)
        history.append(float(jnp.min(costs)))
        if keep_elites:
            elites.append(np.asarray(pop[elite_index(costs), :n]))
        report(g, history[-1])
    best_slot = int(elite_index(costs))
    order = np.asarray(pop[best_slot, :n])
    if elite_tree is None:  # a tie across devices: build it again
        trees, _ = insertion.insert_batch(lo, hi, pop[best_slot][None], n_dev, scale, max_children=k)
        elite_tree = insertion.tree_at(trees, 0)
    jax.block_until_ready(elite_tree)
    best = float(costs[best_slot])
    return EvolveResult(tree=elite_tree, sah=best, sah_start=history[0], cost_name="gs", steps=generations + 1,
                        history=np.asarray(history), converged=False, stop="limit", trace=tuple(trace),
                        order=order, best=best, initial_best=history[0],
                        random_median=random_median, population=np.asarray(pop)[:, :n], costs=np.asarray(costs),
                        elites=np.stack(elites) if keep_elites else None,
                        seconds=time.perf_counter() - start)


# ----------------------------------------------------------------------------------
# The empirical check: rays against the G&S cost
# ----------------------------------------------------------------------------------


def ray_costs(key, trees, triangles, *, rays: int = 10000, mode: str = "any", batch: int = 256) -> np.ndarray:
    """Mean box + primitive tests per ray for each tree, all traced with the same rays.

    ``trees``: a list of trees over ``triangles`` [T, 3, 3] (their frame); ``rays``
    random rays (origins uniform in the first tree's root box, directions uniform) from
    ``key``; ``mode``: ``"any"`` (shadow rays, as in the paper) or ``"closest"``.
    Returns float64 [len(trees)].
    """

    trees = list(trees)
    origin, direction = make_rays(key, "random", trees[0], triangles, rays)
    out = []
    for tree in trees:  # the walk's fixed stack: one compiled program for every tree of a capacity
        hits = trace(tree, triangles, origin, direction, mode=mode, batch=batch)
        out.append(float(np.mean(hits.box_tests.astype(np.float64) + hits.prim_tests)))
    return np.asarray(out)
