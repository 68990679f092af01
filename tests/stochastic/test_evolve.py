"""Genetic algorithm over insertion orders (jaxbvh.evolve): the NumPy twin, the operators,
the run's bookkeeping, devices, the empirical check and the ``jaxbvh evolve`` command.

Random cases use 17 .. 24 primitives (one capacity bucket) and a population of 8, so the
jitted functions compile once.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import REPO, run_cli
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.builders import insertion
from jaxbvh.builders import insertion_reference as ref_insertion
from jaxbvh.stochastic import evolve
from jaxbvh.stochastic import evolve_reference as ref
from jaxbvh.testing.plugin import examples

P = 8


def boxes(seed, n):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    if seed % 3 == 0:
        lo = np.round(lo * 2) / 2  # shared corners: many tied costs
    hi = lo + (rng.uniform(0, 0.5, (n, 3)) * (rng.random((n, 1)) < 0.9)).astype(np.float32)
    return lo, hi


def draws_of(key, n, generations, crossover, mutation, population=P):
    swaps = evolve.max_swaps(jaxbvh.capacity_bucket(n), mutation)
    return [evolve.generation_draws(evolve.generation_key(key, g), population, n, swaps, crossover, mutation)
            for g in range(1, generations + 1)]


# ----------------------------------------------------------------------------------
# The twin
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(6))
@given(seed=st.integers(0, 2**31), n=st.integers(17, 24), crossover=st.sampled_from([0.7, 1.0]),
       mutation=st.sampled_from([0.002, 0.1]))
def test_run_equals_reference_generation_by_generation(seed, n, crossover, mutation):
    lo, hi = boxes(seed, n)
    key = jax.random.key(seed)
    generations = 3
    result = evolve.evolve(key, lo, hi, population=P, generations=generations, crossover=crossover,
                           mutation=mutation)
    capacity = jaxbvh.capacity_bucket(n)
    start = np.asarray(evolve.initial_population(evolve.generation_key(key, 0), P, n, capacity))[:, :n]
    populations, costs = ref.evolve(lo, hi, start, draws_of(key, n, generations, crossover, mutation),
                                    max_children=evolve.EvolveConfig().max_children)
    np.testing.assert_array_equal(np.asarray(populations[-1]), result.population)
    np.testing.assert_allclose(costs[-1], result.costs, rtol=1e-5)
    np.testing.assert_allclose([min(c) for c in costs], result.history, rtol=1e-5)
    assert result.random_median == pytest.approx(float(np.median(costs[0])), rel=1e-5)


# ----------------------------------------------------------------------------------
# Operators
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(30))
@given(seed=st.integers(0, 2**31), n=st.integers(2, 24), cut=st.integers(1, 23))
def test_order_crossover_is_the_papers(seed, n, cut):
    cut = min(cut, n - 1)
    rng = np.random.default_rng(seed)
    capacity = 24
    first, second = (insertion.pad_order(rng.permutation(n), capacity) for _ in range(2))
    child = np.asarray(evolve.order_crossover(jnp.asarray(first), jnp.asarray(second), cut))
    assert child[:n].tolist() == ref.order_crossover(first[:n].tolist(), second[:n].tolist(), cut)
    assert (child[:cut] == first[:cut]).all()
    assert sorted(child[:n].tolist()) == list(range(n))
    rest = [x for x in second[:n] if x not in set(first[:cut].tolist())]
    assert child[cut:n].tolist() == rest  # the second parent's order
    assert (child[n:] == np.arange(n, capacity)).all()  # padding untouched


@settings(max_examples=examples(15))
@given(seed=st.integers(0, 2**31), n=st.integers(17, 24))
def test_next_population_keeps_the_elite_and_makes_permutations(seed, n):
    key = jax.random.key(seed)
    capacity = jaxbvh.capacity_bucket(n)
    pop = evolve.initial_population(key, P, n, capacity)
    costs = jnp.asarray(np.random.default_rng(seed).permutation(P).astype(np.float32))
    draws = draws_of(key, n, 1, 0.7, 0.2)[0]
    new = np.asarray(evolve.next_population(pop, costs, draws))
    assert (new[0] == np.asarray(pop)[int(np.argmin(costs))]).all()  # the elite, untouched
    for row in new:
        assert sorted(row[:n].tolist()) == list(range(n))
        assert (row[n:] == np.arange(n, capacity)).all()
    # without crossover or mutation every other slot is its tournament's winner
    quiet = draws_of(key, n, 1, 0.0, 0.0)[0]
    new = np.asarray(evolve.next_population(pop, costs, quiet))
    a, b = np.asarray(quiet.first), np.asarray(quiet.second)
    winners = np.where(np.asarray(costs)[b] < np.asarray(costs)[a], b, a)
    assert (new[1:] == np.asarray(pop)[winners]).all()


def test_mutation_makes_the_expected_number_of_swaps():
    n, rate, population = 1000, 0.01, 41
    swaps = evolve.max_swaps(1024, rate)
    counts = []
    for g in range(20):
        draws = evolve.generation_draws(jax.random.key(g), population, n, swaps, 0.7, rate)
        made = np.asarray(draws.swap)
        assert (np.asarray(draws.swap_a)[made] != np.asarray(draws.swap_b)[made]).all()
        counts.append(made.sum(axis=1))
    counts = np.concatenate(counts)
    # Binomial(S, rate n / S) per individual: mean rate n = 10, sd < sqrt(10)
    assert abs(counts.mean() - rate * n) < 5 * np.sqrt(rate * n / counts.size)
    pairs = []
    for g in range(200):
        pairs.append(np.asarray(evolve.generation_draws(jax.random.key(g), population, n, swaps, 0.7, rate).cross))
    assert np.mean(pairs) == pytest.approx(0.7, abs=0.03)


# ----------------------------------------------------------------------------------
# A run
# ----------------------------------------------------------------------------------


def test_run_bookkeeping_and_reproducibility():
    lo, hi = boxes(4, 20)
    seen = []
    result = evolve.evolve(jax.random.key(3), lo, hi, population=P, generations=6, mutation=0.1,
                           on_step=seen.append, keep_elites=True)
    assert tuple(seen) == result.trace and [i.step for i in seen] == list(range(7))
    assert [i.sah for i in seen] == result.history.tolist() and result.steps == 7
    assert result.cost == result.best and result.cost_start == result.initial_best and result.stop == "limit"
    assert 0 <= result.compile_seconds <= result.seconds
    assert (np.diff(result.history) <= 0).all()  # the elite survives
    assert result.best == result.history[-1] == pytest.approx(result.costs.min())
    assert result.initial_best == result.history[0] and result.best <= result.random_median
    assert sorted(result.order.tolist()) == list(range(20))
    assert result.elites.shape == (7, 20) and (result.elites[-1] == result.order).all()
    k = evolve.EvolveConfig().max_children  # the run's (default) node width
    np.testing.assert_allclose([ref.fitness(lo, hi, e, max_children=k) for e in result.elites], result.history,
                               rtol=1e-5)
    jaxbvh.validate(result.tree, lo, hi)
    assert float(jaxbvh.goldsmith_salmon_cost(result.tree)) == pytest.approx(result.best, rel=1e-6)
    rebuilt = ref_insertion.build(lo, hi, result.order, max_children=k)
    np.testing.assert_array_equal(np.asarray(result.tree.child)[:39], rebuilt.child)
    again = evolve.evolve(jax.random.key(3), lo, hi, population=P, generations=6, mutation=0.1)
    np.testing.assert_array_equal(again.population, result.population)
    config = evolve.EvolveConfig(population=P, generations=6, mutation=0.1)  # the same run from a Config
    np.testing.assert_array_equal(evolve.evolve(jax.random.key(3), lo, hi, config).population, result.population)
    with pytest.raises(TypeError, match="not both"):
        evolve.evolve(jax.random.key(3), lo, hi, config, generations=1)
    other = evolve.evolve(jax.random.key(4), lo, hi, population=P, generations=6, mutation=0.1)
    assert not np.array_equal(other.population, result.population)


def test_zero_generations_price_random_orders():
    lo, hi = boxes(5, 18)
    result = evolve.evolve(jax.random.key(0), lo, hi, population=P, generations=0)
    assert result.history.shape == (1,) and result.best == result.initial_best == result.costs.min()
    assert result.random_median == pytest.approx(float(np.median(result.costs)))


def test_bad_options_are_refused():
    lo, hi = boxes(0, 18)
    key = jax.random.key(0)
    for kwargs, fragment in (({"population": 1}, "population"), ({"generations": -1}, "generations"),
                             ({"crossover": 1.5}, "crossover"), ({"mutation": -0.1}, "mutation"),
                             ({"max_children": 1}, "max_children"), ({"devices": 2, "population": 7}, "devices")):
        with pytest.raises(ValueError, match=fragment):
            evolve.evolve(key, lo, hi, **{"generations": 1, **kwargs})


# ----------------------------------------------------------------------------------
# Devices (a subprocess: XLA flags must be set before jax starts)
# ----------------------------------------------------------------------------------

_SUBPROCESS = textwrap.dedent("""
    import json, sys
    sys.path[:0] = [{repo!r}, {tests!r}, {here!r}]
    import jax, numpy as np
    from jaxbvh.stochastic import evolve
    from test_evolve import boxes
    lo, hi = boxes(6, 21)
    r = evolve.evolve(jax.random.key(2), lo, hi, population=8, generations=4, mutation=0.1, devices=2)
    print("RESULT" + json.dumps({{"devices": jax.device_count(), "history": r.history.tolist(),
                                  "population": r.population.tolist(), "child": np.asarray(r.tree.child).tolist()}}))
""")


def test_population_split_over_two_devices_gives_the_same_run():
    code = _SUBPROCESS.format(repo=str(REPO), tests=str(REPO / "tests"), here=str(Path(__file__).resolve().parent))
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
           "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads([line for line in proc.stdout.splitlines() if line.startswith("RESULT")][-1][6:])
    assert out["devices"] == 2
    lo, hi = boxes(6, 21)
    here = evolve.evolve(jax.random.key(2), lo, hi, population=8, generations=4, mutation=0.1)  # one device
    assert jax.device_count() == 1
    assert here.history.tolist() == out["history"]
    assert here.population.tolist() == out["population"]
    assert np.asarray(here.tree.child).tolist() == out["child"]


# ----------------------------------------------------------------------------------
# The empirical check
# ----------------------------------------------------------------------------------


def test_ray_costs_use_the_same_rays_for_every_tree():
    from jaxbvh.io import bundled_mesh_path, load_mesh

    mesh = load_mesh(bundled_mesh_path())
    lo, hi = mesh.local_boxes()
    keep = np.sort(np.argsort(((lo + hi) / 2)[:, 1])[:200])
    lo, hi, tri = lo[keep], hi[keep], mesh.local_triangles()[keep]
    orders = np.stack([np.random.default_rng(s).permutation(200) for s in range(2)])
    trees, costs = insertion.build_batch(lo, hi, orders)
    trees = [insertion.tree_at(trees, i) for i in range(2)]
    for tree in trees:  # a piece of a real mesh (wide traversal itself: tests/rays/test_rays.py)
        jaxbvh.validate(tree, lo, hi)
    key = jax.random.key(1)
    measured = evolve.ray_costs(key, trees + trees[:1], tri, rays=300)
    assert measured[0] == measured[2]  # same tree, same rays
    assert (measured >= 1).all() and np.isfinite(measured).all()
    from jaxbvh.rays import make_rays, trace
    origin, direction = make_rays(key, "random", trees[1], tri, 300)
    hits = trace(trees[1], tri, origin, direction, mode="any")
    assert measured[1] == pytest.approx(np.mean(hits.box_tests + hits.prim_tests))


# ----------------------------------------------------------------------------------
# The command
# ----------------------------------------------------------------------------------


def grid_obj(path: Path, n: int = 3) -> Path:
    """A bumpy n x n grid of 2 n^2 triangles."""
    rng = np.random.default_rng(0)
    lines = [f"v {i} {j} {rng.random()!r}" for i in range(n + 1) for j in range(n + 1)]
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            lines += [f"f {a + 1} {b + 1} {c + 1}", f"f {a + 1} {c + 1} {d + 1}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_cli_evolve_json_and_saved_tree(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 3)  # 18 triangles
    out = tmp_path / "best.npz"
    status, stdout, err = run_cli(capsys, "evolve", mesh, "--population", P, "--generations", 3, "--seed", 5,
                                  "--mutation", 0.1, "-o", out, "--json")
    assert status == 0, err
    lines = stdout.strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    for key in ("initial_best", "best", "random_median", "generations", "population", "history", "seconds"):
        assert key in result
    assert result["population"] == P and result["generations"] == 3 and len(result["history"]) == 4
    assert 0 <= result["compile_seconds"] <= result["seconds"] and result["stop"] == "limit"
    assert result["best"] <= result["initial_best"] and result["best"] == result["history"][-1]
    assert result["valid"] is True and result["tree"]["goldsmith_salmon"] == pytest.approx(result["best"])
    saved, frame = jaxbvh.load(out)
    loaded = jaxbvh.load_mesh(mesh)
    jaxbvh.validate(saved, *loaded.local_boxes())
    assert float(jaxbvh.goldsmith_salmon_cost(jaxbvh.to_jax(saved))) == pytest.approx(result["best"], rel=1e-6)


@pytest.mark.parametrize("option, value, fragment", [
    ("--population", 1, "--population"), ("--generations", -1, "--generations"),
    ("--crossover", 1.5, "--crossover"), ("--mutation", -0.5, "--mutation"),
    ("--max-children", 1, "--max-children")])
def test_cli_bad_options_are_one_line_errors(capsys, tmp_path, option, value, fragment):
    mesh = grid_obj(tmp_path / "grid.obj", 1)
    status, out, err = run_cli(capsys, "evolve", mesh, option, value)
    assert status == 2 and out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxbvh: error: ") and fragment in lines[0]


def test_cli_empty_mesh_and_tree_input_are_one_line_errors(capsys, tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\n")
    for path in (empty, tmp_path / "tree.npz"):
        status, out, err = run_cli(capsys, "evolve", path)
        assert status == 2 and out == "" and len(err.strip().splitlines()) == 1, err
        assert err.startswith("jaxbvh: error: ")
