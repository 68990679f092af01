"""NumPy twin of :mod:`jaxbvh.stochastic.evolve`, written the slow, literal way (Ng & Trifonov 2003, §4).

One individual at a time, with Python lists: the elite, then one tournament per slot,
then order crossover pair by pair, then each individual's swaps one after another.
The random numbers are the JAX version's (:func:`jaxbvh.stochastic.evolve.generation_draws`), so
both give the same populations generation by generation; fitness is the reference
insertion build (:mod:`jaxbvh.builders.insertion_reference`) priced by the reference cost.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.builders import insertion_reference as ref_insertion
from jaxbvh.numerics import TIE_TOLERANCE
from jaxbvh.tree import cost_reference as ref_cost


def order_crossover(first, second, cut: int) -> list[int]:
    """``first[:cut]``, then the objects of ``second`` not yet taken, in ``second``'s order."""
    child = list(first[:cut])
    taken = set(child)
    child += [x for x in second if x not in taken]
    return child


def next_population(population, costs, draws) -> list[list[int]]:
    """Selection with elitism, order crossover and swap mutation (:mod:`jaxbvh.stochastic.evolve`).

    ``population``: P orders (lists or arrays of length n); ``costs``: their costs;
    ``draws``: a :class:`jaxbvh.stochastic.evolve.Draws` (arrays are read as NumPy; padded
    positions are never drawn).
    """
    near = 1 + TIE_TOLERANCE
    costs = [float(c) for c in costs]
    least = min(costs)
    elite = next(i for i, c in enumerate(costs) if c <= least * near)
    new = [list(population[elite])]
    first, second = np.asarray(draws.first), np.asarray(draws.second)
    for a, b in zip(first.tolist(), second.tolist()):
        new.append(list(population[b] if costs[b] * near < costs[a] else population[a]))
    for j, (cross, cut) in enumerate(zip(np.asarray(draws.cross).tolist(), np.asarray(draws.cut).tolist())):
        if cross:
            one, two = new[1 + 2 * j], new[2 + 2 * j]
            new[1 + 2 * j], new[2 + 2 * j] = order_crossover(one, two, cut), order_crossover(two, one, cut)
    swap, a, b = np.asarray(draws.swap), np.asarray(draws.swap_a), np.asarray(draws.swap_b)
    for i in range(1, len(new)):
        for s in range(swap.shape[1]):
            if swap[i - 1, s]:
                x, y = int(a[i - 1, s]), int(b[i - 1, s])
                new[i][x], new[i][y] = new[i][y], new[i][x]
    return new


def fitness(prim_lo, prim_hi, order, *, max_children: int) -> float:
    """The G&S cost of the reference insertion tree of ``order``."""
    tree = ref_insertion.build(prim_lo, prim_hi, order, max_children=max_children)
    return ref_cost.goldsmith_salmon_cost(tree)


def evolve(prim_lo, prim_hi, population, draws_per_generation, *, max_children: int):
    """Run the algorithm from the initial ``population`` (P orders of length n) with the
    given draws (one :class:`jaxbvh.stochastic.evolve.Draws` per generation).

    Returns ``(populations, costs)``: lists with one entry per generation 0 .. G.
    """
    pop = [list(np.asarray(o)) for o in population]
    costs = [fitness(prim_lo, prim_hi, o, max_children=max_children) for o in pop]
    populations, all_costs = [pop], [costs]
    for draws in draws_per_generation:
        pop = next_population(pop, costs, draws)
        costs = [fitness(prim_lo, prim_hi, o, max_children=max_children) for o in pop]
        populations.append(pop)
        all_costs.append(costs)
    return populations, all_costs
