"""GRASP (jaxbvh.grasp): equal to the NumPy twin fed the same draws, noise 0 = sweep builder,
deviation rate = noise, best-of-trials bookkeeping, the CLI verb, clear errors.

Compiles dominate the run time, so inputs stay in one capacity bucket (17-24 primitives,
capacity 24; float64 13-16, capacity 16) and the trial chunks in a few sizes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_one_line_error, canonical, grid_obj, local_boxes, run_cli, run_json
from hypothesis import example, given, settings
from hypothesis import strategies as st
from strategies import box_sets, triangle_soups

import jaxbvh
from jaxbvh import numerics
from jaxbvh.stochastic import grasp
from jaxbvh.stochastic import grasp_reference as ref
from jaxbvh.testing.plugin import examples

RCLS = st.sampled_from(["axes", 1, 2, 3, 5, 20])
CHUNK = 96  # forests of at most 96 primitives: capacities 24, 48, 96 only (few compiles)


def random_boxes(seed: int, n: int):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 1, (n, 3))
    half = rng.uniform(0, 0.2, (n, 3))
    return (centre - half).astype(np.float32), (centre + half).astype(np.float32)


# ----------------------------------------------------------------------------------
# One trial against the NumPy twin
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(15))
@given(data=box_sets(min_size=17, max_size=24), rcl=RCLS, noise=st.sampled_from([0.2, 0.5, 1.0]),
       seed=st.integers(0, 2**31 - 1), trial=st.integers(0, 10**6))
@example(data=random_boxes(3, 24), rcl=20, noise=1.0, seed=0, trial=0)  # deep ranks of big lists
def test_trial_equals_reference_fed_the_same_draws(data, rcl, noise, seed, trial):
    lo, hi = data
    key = jax.random.key(seed)
    got = grasp.randomized_build(key, lo, hi, trial=trial, noise=noise, rcl=rcl)
    jaxbvh.validate(got, lo, hi)
    t = jaxbvh.to_numpy(got)
    assert t.prim_count.max() == 1  # one primitive per leaf, as the paper builds
    want = ref.randomized_build(key, lo, hi, trial=trial, noise=noise, rcl=rcl)
    jaxbvh.validate(want, lo, hi)
    assert canonical(got) == canonical(want)


@settings(max_examples=examples(12))
@given(tri=triangle_soups(min_size=17, max_size=24), rcl=RCLS, noise=st.sampled_from([0.3, 1.0]), seed=st.integers(0, 99))
def test_trial_equals_reference_on_extreme_soups(tri, rcl, noise, seed):
    lo, hi = local_boxes(tri)
    key = jax.random.key(seed)
    got = grasp.randomized_build(key, lo, hi, noise=noise, rcl=rcl)
    jaxbvh.validate(got, lo, hi)
    assert canonical(got) == canonical(ref.randomized_build(key, lo, hi, noise=noise, rcl=rcl))


@settings(max_examples=examples(6))
@given(data=box_sets(min_size=13, max_size=16), rcl=st.sampled_from(["axes", 4]), seed=st.integers(0, 99))
def test_float64_trial_equals_reference(data, rcl, seed):
    with jax.enable_x64(True):
        lo, hi = (a.astype(np.float64) for a in data)
        key = jax.random.key(seed)
        got = grasp.randomized_build(key, lo, hi, noise=0.5, rcl=rcl, dtype=np.float64)
        assert got.lo.dtype == np.float64
        jaxbvh.validate(got, lo, hi)
        assert canonical(got) == canonical(ref.randomized_build(key, lo, hi, noise=0.5, rcl=rcl))
        # the best of a few trials, forests of at most one tree's capacity (no new compile)
        result = grasp.grasp(key, lo, hi, trials=3, noise=0.5, rcl=rcl, dtype=np.float64, chunk_prims=16)
        assert result.tree.lo.dtype == np.float64
        whole = [float(jaxbvh.ng_trifonov_cost(grasp.randomized_build(key, lo, hi, trial=t, noise=0.5, rcl=rcl,
                                                                      dtype=np.float64))) for t in range(3)]
        np.testing.assert_allclose(result.objectives, whole, rtol=1e-12)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(min_size=17, max_size=24), rcl=RCLS, seed=st.integers(0, 99))
def test_noise_zero_is_the_sweep_builder(tri, rcl, seed):
    lo, hi = local_boxes(tri)
    got = grasp.randomized_build(jax.random.key(seed), lo, hi, noise=0.0, rcl=rcl)
    sweep = jaxbvh.build(lo, hi, method="sweep", max_leaf=1)  # GRASP perturbs the one-primitive-per-leaf sweep
    for field in ("left", "right", "parent", "axis", "prim_start", "prim_count", "prim_index", "lo", "hi"):
        np.testing.assert_array_equal(getattr(got, field), getattr(sweep, field), err_msg=field)


def test_list_of_one_never_deviates():
    lo, hi = random_boxes(0, 24)
    got = grasp.randomized_build(jax.random.key(1), lo, hi, noise=1.0, rcl=1)
    assert canonical(got) == canonical(jaxbvh.build(lo, hi, max_leaf=1))


def test_every_node_deviates_at_noise_one():
    """At noise 1 with rcl 'axes' every interior node takes another axis than the greedy one."""
    lo, hi = random_boxes(5, 22)
    got = jaxbvh.to_numpy(grasp.randomized_build(jax.random.key(2), lo, hi, noise=1.0, rcl="axes"))
    want = ref.randomized_build(jax.random.key(2), lo, hi, noise=1.0, rcl="axes")
    assert canonical(got) == canonical(want)
    # the root's split axis differs from the greedy tree's
    assert int(got.axis[0]) != int(jaxbvh.to_numpy(jaxbvh.build(lo, hi, max_leaf=1)).axis[0])


@pytest.mark.parametrize("rcl", ["axes", 5])
def test_deviation_rate_is_the_noise(rcl):
    """noise = the probability that a node does not take its greedy split (split axis or sides)."""
    lo, hi = random_boxes(11, 24)
    scale = lo.dtype.type(numerics.scene_scale(lo, hi))
    centre = np.float32(0.5) * lo + np.float32(0.5) * hi
    noise, trials = 0.25, 30
    deviations = []
    for t in range(trials):
        tree = jaxbvh.to_numpy(grasp.randomized_build(jax.random.key(3), lo, hi, trial=t, noise=noise, rcl=rcl))
        prims = _prims_under(tree)
        count = 0
        for node in np.flatnonzero(tree.left >= 0):
            greedy = ref.tie_winner(ref.sweep_candidates(np.sort(prims[node]), lo, hi, centre, scale))
            taken = (int(tree.axis[node]), set(prims[int(tree.left[node])].tolist()))
            count += taken != (greedy[2], set(greedy[3].tolist()))
        deviations.append(count)
    expected = noise * 23  # n - 1 interior nodes; std of the mean ~ 0.38
    assert abs(np.mean(deviations) - expected) < 1.2, deviations


def _prims_under(t):
    """Primitive ids under every node of a one-primitive-per-leaf tree (dict node -> array)."""
    out = {}

    def rec(node):
        if t.prim_count[node] > 0:
            out[node] = t.prim_index[t.prim_start[node]: t.prim_start[node] + t.prim_count[node]]
        else:
            out[node] = np.concatenate([rec(int(t.left[node])), rec(int(t.right[node]))])
        return out[node]

    rec(int(t.root))
    return out


# ----------------------------------------------------------------------------------
# Best of many trials
# ----------------------------------------------------------------------------------


@pytest.mark.parametrize("objective", grasp.OBJECTIVES)
def test_best_of_trials_is_the_best_trial(objective):
    lo, hi = random_boxes(7, 24)
    key = jax.random.key(4)
    result = grasp.grasp(key, lo, hi, trials=7, noise=0.3, rcl="axes", objective=objective, chunk_prims=CHUNK)
    jaxbvh.validate(result.tree, lo, hi)
    measure = jaxbvh.ng_trifonov_cost if objective == "nt" else jaxbvh.sah
    trees = [grasp.randomized_build(key, lo, hi, trial=t, noise=0.3) for t in range(7)]
    values = np.array([float(measure(t)) for t in trees])
    np.testing.assert_allclose(result.objectives, values, rtol=1e-6)
    assert result.best_trial == int(np.argmin(result.objectives))
    assert canonical(result.tree) == canonical(trees[result.best_trial])
    assert result.objective == pytest.approx(float(measure(result.tree)), rel=1e-6)
    assert result.base == pytest.approx(float(measure(jaxbvh.build(lo, hi, max_leaf=1))), rel=1e-6)
    # the NumPy twin finds the same trees and (in float64) the same objectives
    ref_tree, ref_values, ref_best = ref.grasp(key, lo, hi, trials=7, noise=0.3, objective=objective)
    np.testing.assert_allclose(result.objectives, ref_values, rtol=1e-5)
    assert canonical(ref_tree) == canonical(trees[ref_best])


def test_chunking_and_trial_count_do_not_change_trials():
    lo, hi = random_boxes(8, 21)
    key = jax.random.key(5)
    runs = [grasp.grasp(key, lo, hi, trials=t, noise=0.4, rcl=3, chunk_prims=c) for t, c in ((6, CHUNK), (6, 10), (3, 1))]
    np.testing.assert_array_equal(runs[1].objectives, runs[0].objectives)
    assert canonical(runs[1].tree) == canonical(runs[0].tree)
    np.testing.assert_array_equal(runs[2].objectives, runs[0].objectives[:3])
    assert runs[2].objective == runs[0].best_of(3)


def test_progress_reports_every_trial_and_the_best_so_far():
    # what the CLI's progress bar shows: on_step(info) once per trial, in order, as soon
    # as the forest call that finishes it returns, with the best objective so far
    lo, hi = random_boxes(8, 21)
    infos = []
    result = grasp.grasp(jax.random.key(5), lo, hi, trials=6, noise=0.4, rcl=3, chunk_prims=10,
                         on_step=infos.append)
    assert tuple(infos) == result.trace
    assert [i.step for i in infos] == list(range(6)) and {i.method for i in infos} == {"grasp"}
    np.testing.assert_array_equal([i.sah for i in infos], np.minimum.accumulate(result.objectives))
    np.testing.assert_array_equal([i.moves for i in infos], result.rebuilt)
    seconds = [i.seconds for i in infos]
    assert seconds == sorted(seconds) and len(set(seconds)) >= 2  # reported after several forest calls
    assert result.steps == 6 and result.stop == "limit" and not result.converged
    assert result.cost == result.objective == result.history[-1] and result.cost_start == result.base
    assert 0 <= result.compile_seconds <= result.seconds


def test_the_deprecated_chunk_callback_still_reports():
    lo, hi = random_boxes(8, 21)
    calls = []
    with pytest.warns(DeprecationWarning, match="on_step"):
        result = grasp.grasp(jax.random.key(5), lo, hi, trials=6, noise=0.4, rcl=3, chunk_prims=10,
                             on_chunk=lambda done, best: calls.append((done, best)))
    assert len(calls) >= 3  # several chunks of at most 10 primitives, and the final report
    done = [d for d, _ in calls]
    assert done == sorted(done) and 0 <= done[0] and done[-1] == 6
    assert calls[-1][1] == result.objective
    for d, best in calls:  # trials before `done` are finished: their best is final
        assert best == (float(np.min(result.objectives[:d])) if d else result.base)


def test_same_key_same_tree_bit_for_bit():
    lo, hi = random_boxes(9, 24)
    a = grasp.grasp(jax.random.key(6), lo, hi, trials=3, noise=0.2, chunk_prims=CHUNK)
    b = grasp.grasp(jax.random.key(6), lo, hi, trials=3, noise=0.2, chunk_prims=CHUNK)
    for x, y in zip(jax.tree_util.tree_leaves(a.tree), jax.tree_util.tree_leaves(b.tree)):
        np.testing.assert_array_equal(x, y)
    c = grasp.grasp(jax.random.key(7), lo, hi, trials=3, noise=0.2, chunk_prims=CHUNK)
    assert not np.array_equal(a.objectives, c.objectives)


@pytest.mark.parametrize("objective", grasp.OBJECTIVES)
@pytest.mark.parametrize("noise, rcl", [(0.05, "axes"), (0.3, 4), (1.0, "axes")])
def test_rebuilding_deviating_subtrees_gives_the_whole_trees_objectives(objective, noise, rcl):
    """Objectives from swapping in rebuilt subtrees = those of the whole trials' trees."""
    lo, hi = random_boxes(14, 24)
    key = jax.random.key(8)
    result = grasp.grasp(key, lo, hi, trials=12, noise=noise, rcl=rcl, objective=objective, chunk_prims=CHUNK)
    measure = jaxbvh.ng_trifonov_cost if objective == "nt" else jaxbvh.sah
    whole = [float(measure(grasp.randomized_build(key, lo, hi, trial=t, noise=noise, rcl=rcl))) for t in range(12)]
    np.testing.assert_allclose(result.objectives, whole, rtol=2e-6)
    if noise == 1.0:
        assert np.all(result.rebuilt == 24)  # the root deviates: every trial is built whole
    else:
        assert np.all(result.rebuilt < 24 * 12)


def test_forest_trees_equal_whole_trials():
    """A forest of copies of the scene, each its own trial: every tree is that trial's."""
    import importlib

    engine = importlib.import_module("jaxbvh.builders.topdown")
    lo, hi = random_boxes(15, 10)
    trials = np.array([4, 0, 9], np.int32)
    copies = len(trials)
    cap = 48  # a capacity grasp's forests use too (24 x 2)
    lo_f = np.full((cap, 3), np.inf, np.float32)
    hi_f = np.full((cap, 3), -np.inf, np.float32)
    lo_f[:30], hi_f[:30] = np.tile(lo, (copies, 1)), np.tile(hi, (copies, 1))
    group = np.zeros(cap, np.int32)
    group[:30] = np.repeat(np.arange(copies), 10)
    per_group = np.zeros(cap, np.int32)
    trial, shift = per_group.copy(), per_group.copy()
    trial[:copies] = trials
    shift[:copies] = -10 * np.arange(copies)  # name every tree's runs from 0
    key = jax.random.key(11)
    splits = engine.RandomSplits(key, jnp.asarray(group), jnp.asarray(trial), jnp.asarray(shift),
                                 jnp.float32(0.5), jnp.int32(3))
    scale = jnp.float32(numerics.scene_scale(lo, hi))
    forest, tree_of = engine.randomized_forest(jnp.asarray(lo_f), jnp.asarray(hi_f), jnp.int32(30), scale,
                                               splits, rcl="list")
    forest, tree_of = jaxbvh.to_numpy(forest), np.asarray(tree_of)
    for g, t in enumerate(trials):
        one = forest.replace(root=np.int32(g), prim_index=np.where(forest.prim_index >= 0, forest.prim_index % 10, -1))
        assert canonical(one) == canonical(grasp.randomized_build(key, lo, hi, trial=int(t), noise=0.5, rcl=3))
        assert np.all(tree_of[jaxbvh.tree.depth(one) >= 0] == g)
    assert np.all(tree_of[np.asarray(forest.left) < 0][np.asarray(forest.prim_count)[np.asarray(forest.left) < 0] == 0]
                  == -1)  # unused slots


def test_noise_zero_trials_all_equal_the_base():
    lo, hi = random_boxes(10, 24)
    result = grasp.grasp(jax.random.key(0), lo, hi, trials=3, noise=0.0, rcl=5)
    assert np.all(result.objectives == result.base)
    assert result.best_trial == 0


def test_noise_list_length_and_trial_do_not_recompile():
    lo, hi = random_boxes(12, 23)
    grasp.grasp(jax.random.key(0), lo, hi, trials=2, noise=1.0, rcl=3, chunk_prims=CHUNK)
    start = grasp.build_forest._cache_size()
    grasp.grasp(jax.random.key(1), lo, hi, trials=2, noise=1.0, rcl=9, chunk_prims=CHUNK)
    grasp.grasp(jax.random.key(2), *random_boxes(13, 18), trials=2, deviations=100.0, rcl=2, chunk_prims=CHUNK)
    grasp.randomized_build(jax.random.key(3), lo, hi, trial=5, noise=0.2, rcl=4)
    assert grasp.build_forest._cache_size() == start


def test_deviations_set_the_noise():
    assert grasp.resolve_noise(101, deviations=5) == pytest.approx(0.05)
    assert grasp.resolve_noise(101, noise=0.3) == 0.3
    assert grasp.resolve_noise(3, deviations=10) == 1.0  # capped
    assert grasp.resolve_noise(1, deviations=10) == 0.0  # no interior node
    assert grasp.resolve_noise(1001) == pytest.approx(grasp.DEFAULT_DEVIATIONS / 1000)


def test_one_primitive():
    lo = np.zeros((1, 3), np.float32)
    result = grasp.grasp(jax.random.key(0), lo, lo + 1, trials=2, noise=1.0)
    jaxbvh.validate(result.tree, lo, lo + 1)
    assert result.objective == result.base == 0.0


def test_a_config_is_the_keyword_form():
    lo, hi = random_boxes(8, 21)  # as test_chunking_and_trial_count_do_not_change_trials: compiled programs shared
    config = grasp.GraspConfig(trials=6, noise=0.4, rcl="3", objective="sah", chunk_prims=CHUNK)
    assert config.rcl == 3  # normalised as check_rcl does
    by_config = grasp.grasp(jax.random.key(5), lo, hi, config)
    by_keywords = grasp.grasp(jax.random.key(5), lo, hi, trials=6, noise=0.4, rcl=3, objective="sah",
                              chunk_prims=CHUNK)
    np.testing.assert_array_equal(by_config.objectives, by_keywords.objectives)
    assert canonical(by_config.tree) == canonical(by_keywords.tree)
    with pytest.raises(TypeError, match="not both"):
        grasp.grasp(jax.random.key(5), lo, hi, config, trials=2)


@pytest.mark.parametrize("kwargs, message", [
    (dict(trials=0), "trials"),
    (dict(trials=2.5), "trials"),
    (dict(noise=-0.1), "noise"),
    (dict(noise=1.5), "noise"),
    (dict(noise=float("nan")), "noise"),
    (dict(noise=0.1, deviations=2), "not both"),
    (dict(deviations=-1), "deviations"),
    (dict(rcl="ring"), "rcl"),
    (dict(rcl=0), "rcl"),
    (dict(rcl=2.0), "rcl"),
    (dict(objective="volume"), "objective"),
    (dict(chunk_prims=0), "chunk_prims"),
])
def test_bad_options_get_clear_errors(kwargs, message):
    lo, hi = random_boxes(0, 4)
    with pytest.raises(ValueError, match=message):
        grasp.grasp(jax.random.key(0), lo, hi, **kwargs)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3)), "no primitives"),
    (np.array([[0, 0, 0], [np.nan, 0, 0]]), "NaN"),
])
def test_bad_boxes_get_clear_errors(bad, message):
    with pytest.raises(ValueError, match=message):
        grasp.grasp(jax.random.key(0), bad, bad)


# ----------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------


def test_cli_grasp(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 3)
    out = tmp_path / "best.npz"
    result = run_json(capsys, "grasp", mesh, "--trials", 12, "--noise", 0.3, "--rcl", 3, "--seed", 2, "-o", out)
    for key in ("base", "best", "best_of_10", "trials", "noise", "rcl", "sah", "seconds"):
        assert key in result, key
    assert result["trials"] == 12 and result["noise"] == 0.3 and result["rcl"] == 3
    assert 0 <= result["compile_seconds"] <= result["seconds"] and result["stop"] == "limit"
    assert result["best"] <= result["best_of_10"] and result["valid"] is True
    assert result["deviations"] == pytest.approx(0.3 * 17)
    tree, frame = jaxbvh.load(out)
    assert not frame.is_identity
    assert float(jaxbvh.ng_trifonov_cost(tree)) == pytest.approx(result["best"], rel=1e-5)
    assert float(jaxbvh.sah(tree)) == pytest.approx(result["sah"], rel=1e-5)
    stats = run_json(capsys, "stats", out, "--mesh", mesh)
    assert stats["valid"] is True and stats["leaf_size_max"] == 1
    # the library call with the same seed finds the same best
    lo, hi = jaxbvh.load_mesh(mesh).local_boxes()
    again = grasp.grasp(jax.random.key(2), lo, hi, trials=12, noise=0.3, rcl=3)
    assert again.objective == pytest.approx(result["best"], rel=1e-6)
    assert again.best_of(10) == pytest.approx(result["best_of_10"], rel=1e-6)


def test_cli_grasp_defaults_and_sah(capsys, tmp_path):
    mesh = grid_obj(tmp_path / "grid.obj", 3)
    result = run_json(capsys, "grasp", mesh, "--trials", 3, "--objective", "sah", "--deviations", 2)
    assert result["rcl"] == "axes" and result["objective"] == "sah"
    assert result["best_of_10"] is None  # fewer than 10 trials
    assert result["noise"] == pytest.approx(2 / 17)
    assert result["best"] == pytest.approx(result["sah"], rel=1e-6)
    default = run_json(capsys, "grasp", mesh, "--trials", 3)
    assert default["deviations"] == pytest.approx(min(grasp.DEFAULT_DEVIATIONS, 17))


@pytest.mark.parametrize("argv, fragment", [
    (["--trials", "0"], "--trials"),
    (["--noise", "1.5"], "--noise"),
    (["--noise", "-0.1"], "--noise"),
    (["--noise", "0.1", "--deviations", "2"], "not both"),
    (["--deviations", "-3"], "--deviations"),
    (["--rcl", "0"], "--rcl"),
    (["--rcl", "many"], "--rcl"),
])
def test_cli_bad_options(capsys, tmp_path, argv, fragment):
    mesh = grid_obj(tmp_path / "grid.obj", 1)
    assert_one_line_error(*run_cli(capsys, "grasp", mesh, *argv), fragment)


def test_cli_bad_inputs(capsys, tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    assert_one_line_error(*run_cli(capsys, "grasp", empty), "no faces")
    tree = tmp_path / "t.npz"
    tree.write_bytes(b"")
    assert_one_line_error(*run_cli(capsys, "grasp", tree), "tree file")
