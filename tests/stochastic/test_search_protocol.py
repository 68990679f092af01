"""GRASP and the GA report as the optimizers do (their results subclass jaxbvh.optimize.protocol.OptimizeResult).

For each: the result has the optimizer result's fields, consistent with each other and
with what ``on_step`` got (one StepInfo per step, in order); a second run on other
inputs of the same shapes traces and compiles nothing (no retrace); what the search
batches (GRASP: trials packed into forests; the GA: a population priced in one call)
equals the same work done one item at a time (the loop). Small inputs keep it quick.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

import jaxbvh
from jaxbvh.optimize.protocol import STOP_REASONS, CompileClock, OptimizeResult, SearchResult, StepInfo
from jaxbvh.stochastic import evolve, grasp
from jaxbvh.stochastic import evolve_reference as evolve_ref

N = 20  # primitives: every input below has this many (one capacity: one compiled program each)
#: forests of at most 48 primitives (a full chunk each run below: one forest capacity)
GRASP_OPTIONS = dict(trials=8, noise=0.5, rcl="axes", chunk_prims=48)
GA_OPTIONS = dict(population=6, generations=3, mutation=0.1)


def random_boxes(seed: int, n: int = N):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 1, (n, 3))
    half = rng.uniform(0, 0.2, (n, 3))
    return (centre - half).astype(np.float32), (centre + half).astype(np.float32)


def run_grasp(seed, on_step=None):
    return grasp.grasp(jax.random.key(seed), *random_boxes(seed), on_step=on_step, **GRASP_OPTIONS)


def run_ga(seed, on_step=None):
    return evolve.evolve(jax.random.key(seed), *random_boxes(seed), on_step=on_step, **GA_OPTIONS)


RUNS = {"grasp": run_grasp, "evolve": run_ga}


def test_the_result_type_is_the_optimizers():
    # one result type: a search's result is an OptimizeResult with fields of its own added
    assert SearchResult is OptimizeResult  # the older name
    own = {f.name for f in dataclasses.fields(OptimizeResult)}
    for result_type in (grasp.GraspResult, evolve.EvolveResult):
        assert issubclass(result_type, OptimizeResult)
        assert own <= {f.name for f in dataclasses.fields(result_type)}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_result_and_callback(name):
    infos = []
    result = RUNS[name](1, on_step=infos.append)
    assert isinstance(result, OptimizeResult) and result.cost == result.sah and result.cost_start == result.sah_start
    # on_step got every step once, in order, as the result's trace holds them
    assert all(isinstance(i, StepInfo) for i in infos) and tuple(infos) == result.trace
    assert [i.step for i in infos] == list(range(result.steps)) and {i.method for i in infos} == {name}
    seconds = [i.seconds for i in infos]
    assert seconds == sorted(seconds) and seconds[-1] <= result.seconds
    # the history is the best so far: never rising, its end the result's cost
    history = np.asarray(result.history)
    assert history.shape == (result.steps,) and [i.sah for i in infos] == history.tolist()
    assert (np.diff(history) <= 0).all() and result.cost == history[-1]
    assert result.stop in STOP_REASONS and result.stop == "limit" and not result.converged
    assert 0 <= result.compile_seconds <= result.seconds
    if name == "grasp":
        assert result.steps == GRASP_OPTIONS["trials"] and result.cost_name == "nt"
        # the start is the greedy tree, which no trial need beat: the trials' best is the cost
        assert result.cost_start == result.base and result.cost == result.objectives.min()
        assert result.cost == pytest.approx(float(jaxbvh.ng_trifonov_cost(result.tree)), rel=1e-5)
    else:
        assert result.steps == GA_OPTIONS["generations"] + 1 and result.cost_name == "gs"
        assert result.cost <= result.cost_start == history[0]  # the elite survives
        assert result.cost == pytest.approx(float(jaxbvh.goldsmith_salmon_cost(result.tree)), rel=1e-6)


@pytest.mark.parametrize("name", sorted(RUNS))
def test_no_retrace_for_inputs_of_the_same_shapes(name):
    first = RUNS[name](2)  # compiles what this process had not yet
    with CompileClock() as clock:
        second = RUNS[name](3)  # other boxes, another key, the same shapes
    assert clock.traces == 0 and clock.seconds == 0.0, clock.events
    assert second.compile_seconds == 0.0
    assert not np.array_equal(np.asarray(first.history), np.asarray(second.history))  # really other inputs


def test_grasp_forest_capacity_does_not_follow_the_draws():
    # at the default chunk a run's forest capacity once followed the primitives its key
    # made it rebuild (seed 2: 53, capacity 96; seed 4: 34, capacity 48), so a new key
    # compiled a new forest build; now it follows the shapes and knobs only
    options = dict(trials=3, noise=0.3)
    grasp.grasp(jax.random.key(2), *random_boxes(2), **options)
    with CompileClock() as clock:
        grasp.grasp(jax.random.key(4), *random_boxes(4), **options)
    assert clock.traces == 0 and clock.seconds == 0.0, clock.events


def test_grasp_forests_equal_each_trial_built_alone():
    # the batch: the trials' rebuilt subtrees, packed into forests; the loop: every
    # trial's whole tree built alone (randomized_build), priced by the library's cost
    lo, hi = random_boxes(4)
    result = grasp.grasp(jax.random.key(4), lo, hi, **GRASP_OPTIONS)
    alone = [float(jaxbvh.ng_trifonov_cost(grasp.randomized_build(
        jax.random.key(4), lo, hi, trial=t, noise=result.noise, rcl=result.rcl))) for t in range(result.steps)]
    np.testing.assert_allclose(result.objectives, alone, rtol=1e-5)
    assert result.objectives.min() < result.base or result.rebuilt.sum() > 0  # the trials did deviate


def test_ga_population_priced_at_once_equals_each_order_alone():
    # the batch: a generation's trees built and priced in one call; the loop: the NumPy
    # twin builds and prices every order by itself
    lo, hi = random_boxes(5)
    result = evolve.evolve(jax.random.key(5), lo, hi, **GA_OPTIONS)
    k = evolve.EvolveConfig().max_children
    alone = [evolve_ref.fitness(lo, hi, order, max_children=k) for order in result.population]
    np.testing.assert_allclose(result.costs, alone, rtol=1e-5)
    assert len(set(map(tuple, result.population.tolist()))) > 1  # several different orders
