"""Tree rotations (jaxbvh.rotate) against the sequential NumPy twin and the invariants.

Random trees are padded to one capacity so every jitted function compiles once. Both
methods are optimizers of the protocol (HILL_CLIMB, ANNEAL: init / step / result) run by
the shared driver; the tests use the public step.
"""

from __future__ import annotations

import functools
import logging
import os
import subprocess
import sys
import textwrap

import helpers
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import REPO, SHARED_DATA, assert_same_costs, random_tree
from hypothesis import example, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.draws import annealing_draws
from jaxbvh.numerics import min_gain
from jaxbvh.optimize import driver, rotate, rotate_passes
from jaxbvh.optimize import rotate_reference as ref
from jaxbvh.optimize.rotate import ANNEAL, HILL_CLIMB, AnnealConfig, HillClimbConfig
from jaxbvh.optimize.schedules import EXPONENTIAL_FINAL, constant_schedule, kensler_schedule
from jaxbvh.testing.plugin import examples

NODES, PRIMS = 128, 64  # one capacity for all random trees



# rotations move subtrees, never primitives: every array is compared, the leaves' too
assert_same_tree = functools.partial(helpers.assert_same_tree, fields=(
    "left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "prim_index", "axis", "root"))


def check_result(result, prim_lo, prim_hi):
    """Valid tree, reported SAH equals jaxbvh.sah of the tree, never worse than the start."""
    jaxbvh.validate(result.tree, prim_lo, prim_hi)
    sah = float(jaxbvh.sah(jaxbvh.to_jax(result.tree)))
    assert float(result.sah) == pytest.approx(sah, rel=1e-5)
    return sah


trees = st.builds(lambda seed, n, leaf, grid: (seed, n, leaf, grid),
                  st.integers(0, 2**31), st.integers(1, 40), st.integers(1, 3),
                  st.sampled_from(["random", "grid"]))


# ----------------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------------


def _apply_move(tree, n, move):
    """Move ``move`` at node ``n`` done by hand (NumPy) from its name in
    :data:`rotate.MOVES` (``"A<->B"``: swap the contents of slots A and B), boxes recomputed."""
    t = jaxbvh.to_numpy(tree)
    child = np.stack([t.left, t.right], 1).copy()
    parent, lo, hi = t.parent.copy(), t.lo.copy(), t.hi.copy()
    L, R = child[n]
    slots = {"L": (n, 0), "R": (n, 1), "LL": (L, 0), "LR": (L, 1), "RL": (R, 0), "RR": (R, 1)}
    (na, a_side), (nb, b_side) = (slots[name] for name in rotate.MOVES[move].split("<->"))
    x, y = child[na, a_side], child[nb, b_side]
    child[na, a_side], child[nb, b_side] = y, x
    parent[y], parent[x] = na, nb
    for node in (L, R):
        lo[node] = np.minimum(lo[child[node, 0]], lo[child[node, 1]]) if child[node, 0] >= 0 else lo[node]
        hi[node] = np.maximum(hi[child[node, 0]], hi[child[node, 1]]) if child[node, 0] >= 0 else hi[node]
    return t.replace(left=child[:, 0].copy(), right=child[:, 1].copy(), parent=parent, lo=lo, hi=hi)


@settings(max_examples=examples(10))
@given(trees)
def test_score_moves_matches_cost_of_moved_tree(case):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    current, after, legal = (np.asarray(a) for a in rotate.score_moves(tree))
    costs = np.asarray(jaxbvh.node_costs(jaxbvh.to_jax(tree)))
    real = np.asarray(tree.left) >= 0
    np.testing.assert_allclose(current[real], costs[real], rtol=1e-5)
    assert not legal[~real].any()
    for node in np.flatnonzero(real)[:6]:
        for move in np.flatnonzero(legal[node]):
            moved = _apply_move(tree, node, move)
            jaxbvh.validate(moved, plo, phi)
            new_cost = np.asarray(jaxbvh.node_costs(jaxbvh.to_jax(moved)))
            assert after[node, move] == pytest.approx(new_cost[node], rel=1e-5)
            # the move's sign on C(n) is its sign on the whole tree's SAH
            d_local = new_cost[node] - costs[node]
            d_tree = new_cost[int(tree.root)] - costs[int(tree.root)]
            if abs(d_local) > 1e-4 * costs[node]:
                assert np.sign(d_local) == np.sign(d_tree)


# ----------------------------------------------------------------------------------
# Hill climbing equals the sequential reference, pass by pass
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(15))
@given(trees)
def test_hill_climb_equals_reference_pass_by_pass(case):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    full = rotate.hill_climb(tree, split_axes=False)
    expected, info = ref.hill_climb(tree)
    assert int(full.steps) == info["passes"] and int(full.moves) == info["moves"]
    assert bool(full.converged) == (info["passes"] < 1000)
    assert_same_tree(full.tree, expected)
    np.testing.assert_allclose(np.asarray(full.history)[: info["passes"]], info["history"], rtol=1e-5)
    assert np.isnan(np.asarray(full.history)[info["passes"]:]).all()
    for passes in range(1, min(info["passes"], 3) + 1):
        part = rotate.hill_climb(tree, max_passes=passes, split_axes=False)
        assert_same_tree(part.tree, ref.hill_climb(tree, max_passes=passes)[0])
    sah = check_result(full, plo, phi)
    assert sah <= float(full.sah_start) * (1 + 1e-6)


@pytest.mark.skipif(not (SHARED_DATA / "trees").exists(), reason=f"shared data not found at {SHARED_DATA}")
def test_hill_climb_equals_reference_on_a_real_tree():
    tree, _ = jaxbvh.load(SHARED_DATA / "trees" / "legocar_binned_ref.npz")
    result = rotate.hill_climb(tree, split_axes=False, max_passes=3)
    expected, info = ref.hill_climb(tree, max_passes=3)
    assert_same_tree(result.tree, expected)
    assert float(result.sah) == pytest.approx(info["sah"], rel=1e-5)
    assert float(result.sah) < float(result.sah_start)
    jaxbvh.validate(result.tree)
    leaf = np.asarray(tree.prim_count) > 0  # leaf boxes are the primitives' boxes we know
    assert np.array_equal(np.asarray(result.tree.lo)[leaf], tree.lo[leaf])


def test_work_sizes_do_not_change_the_result(monkeypatch):
    tree, plo, phi = random_tree(7, 40, 2)
    a = rotate.hill_climb(tree, windows=(1,), frontier=1)   # queue always overflows
    c = rotate.hill_climb(tree)                             # queue and ancestor list fit
    assert_same_tree(a.tree, c.tree)
    check_result(c, plo, phi)
    # the short-queue walk (normally 4096 wide) next to the full-width one
    monkeypatch.setattr(rotate_passes, "SMALL_QUEUE", 3)
    d = rotate.hill_climb(tree, windows=(2, 5), frontier=5)
    assert_same_tree(d.tree, c.tree)
    assert int(d.steps) == int(c.steps) and int(d.moves) == int(c.moves)
    key = jax.random.key(5)
    e = rotate.anneal(key, tree, steps=12, period=6, frontier=7)
    monkeypatch.setattr(rotate_passes, "SMALL_QUEUE", 4096)
    f = rotate.anneal(key, tree, steps=12, period=6, frontier=1)
    assert_same_tree(e.tree, f.tree)


def test_progress_reports_every_pass_and_chunks_change_nothing(monkeypatch):
    """With ``on_step`` the driver runs in chunks of passes; chunk sizes never change the result."""
    tree, plo, phi = random_tree(11, 50, 2)
    key = jax.random.key(3)
    runs = {
        "hc": lambda **kw: rotate.hill_climb(tree, **kw),
        "sa": lambda **kw: rotate.anneal(key, tree, steps=10, period=5, **kw),
        "sa chains": lambda **kw: rotate.anneal(key, tree, steps=10, period=5, chains=3, **kw),
    }
    for name, run in runs.items():
        whole = run()
        for max_chunk in (1, 3, driver.MAX_CHUNK):
            monkeypatch.setattr(driver, "MAX_CHUNK", max_chunk)
            log = []
            chunked = run(on_step=log.append)
            assert_same_tree(chunked.tree, whole.tree)
            check_result(chunked, plo, phi)
            assert int(chunked.steps) == int(whole.steps) and int(chunked.moves) == int(whole.moves)
            assert float(chunked.sah) == float(whole.sah), name
            np.testing.assert_array_equal(chunked.history, whole.history)
            if whole.chain_sah is not None:
                np.testing.assert_array_equal(np.asarray(chunked.chain_sah), np.asarray(whole.chain_sah))
            # one report per pass, in order, that agrees with the history
            assert [info.step for info in log] == list(range(len(log)))
            assert {(info.method, info.stage) for info in log} == {(name[:2],) * 2}
            assert len(log) >= int(whole.steps) and tuple(log) == chunked.trace
            if name != "sa chains":  # several chains: the least SAH and all chains' moves
                assert len(log) == int(whole.steps)
                history = np.asarray(whole.history)[: int(whole.steps)]
                np.testing.assert_array_equal([info.sah for info in log], history)
                assert sum(info.moves for info in log) == int(whole.moves)
                np.testing.assert_array_equal([info.moves for info in log],
                                              np.asarray(whole.history_moves)[: int(whole.steps)])


def test_time_budget_stops_early_with_a_valid_tree():
    tree, plo, phi = random_tree(12, 60, 1)
    full = rotate.anneal(jax.random.key(1), tree, steps=400, period=20)
    short = rotate.anneal(jax.random.key(1), tree, steps=400, period=20, time_budget=1e-9)
    check_result(short, plo, phi)  # compiling comes before the budget: the first chunk runs
    assert int(short.steps) == 1 < int(full.steps) and short.compile_seconds >= 0
    assert float(short.sah) <= float(short.sah_start) * (1 + 1e-6)  # keep_best: never worse
    hc = rotate.hill_climb(tree, time_budget=60.0)  # a budget it does not reach: the same tree
    assert_same_tree(hc.tree, rotate.hill_climb(tree).tree)
    with pytest.raises(ValueError, match="time_budget"):
        rotate.hill_climb(tree, time_budget=0)


def test_no_recompile_for_trees_of_one_capacity_and_traced_settings(caplog):
    """Other trees of one capacity, and other costs, margins, pass limits (in one history
    bucket) and Kensler numbers (steps, period, hottest) reuse every compiled program."""
    tree = random_tree(1, 20)[0]
    rotate.hill_climb(tree)
    rotate.anneal(jax.random.key(0), tree, steps=8, period=4)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        for seed in range(2, 4):
            tree = random_tree(seed, 30, 2)[0]
            rotate.hill_climb(tree, ct=0.5 * seed, ci=2.0, min_gain=1e-5 * seed, max_passes=900 + seed)
            rotate.anneal(jax.random.key(seed), tree, steps=8 + seed, period=3 + seed, hottest=0.1 * seed,
                          ct=0.5 * seed, max_quench=990)
    compiled = [r.getMessage() for r in caplog.records if "ompil" in r.getMessage()]
    assert not compiled


def test_leaf_root_and_tiny_trees():
    for n in (1, 2, 3):
        tree, plo, phi = random_tree(n, n)
        result = rotate.hill_climb(tree)
        check_result(result, plo, phi)
        if n <= 2:
            assert int(result.moves) == 0  # no grandchildren, no moves
        assert int(rotate.anneal(jax.random.key(0), tree, steps=4).moves) >= 0


def test_bad_arguments_raise_value_error():
    tree = random_tree(0, 5)[0]
    with pytest.raises(ValueError):
        rotate.hill_climb(tree, max_passes=0)
    with pytest.raises(ValueError):
        rotate.anneal(jax.random.key(0), tree, chains=0)
    with pytest.raises(ValueError):
        rotate.hill_climb(tree, ct=-1.0)
    with pytest.raises(ValueError):
        rotate.hill_climb(jaxbvh.from_interchange({**jaxbvh.to_interchange(tree),
                                                   "child": np.full((9, 3), -1, np.int32)}))
    for knob, value in [("schedule", "warm"), ("schedule", 3.0), ("steps", -1), ("period", 0),
                        ("hottest", -0.1), ("max_quench", 0), ("min_gain", -1.0), ("windows", ()),
                        ("frontier", 0)]:
        with pytest.raises(ValueError, match=knob):
            AnnealConfig(**{knob: value})
    with pytest.raises(ValueError, match="config"):
        HILL_CLIMB.init(tree, AnnealConfig())


def test_configs_keep_the_documented_defaults():
    assert HillClimbConfig() == HillClimbConfig(ct=1.0, ci=1.0, max_passes=1000, min_gain=None,
                                                split_axes=True, windows=rotate.DEFAULT_WINDOWS,
                                                frontier=rotate.DEFAULT_FRONTIER)
    assert AnnealConfig() == AnnealConfig(schedule="kensler", steps=1250, hottest=rotate.DEFAULT_HOTTEST,
                                          period=50, chains=1, keep_best=True, max_quench=1000,
                                          ct=1.0, ci=1.0, min_gain=None, split_axes=True, windows=None,
                                          frontier=rotate.DEFAULT_FRONTIER)
    assert (HILL_CLIMB.name, ANNEAL.name) == ("hc", "sa")
    assert (HILL_CLIMB.Config, ANNEAL.Config) == (HillClimbConfig, AnnealConfig)


# ----------------------------------------------------------------------------------
# Simulated annealing
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(15))
@given(trees, st.integers(0, 2**31), st.booleans())
@example((117371, 9, 1, "grid"), 0, False)  # exact ties at T = 1e-7 once split JAX from NumPy
def test_anneal_equals_reference_fed_the_same_draws(case, key_seed, keep_best):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    key = jax.random.key(key_seed)
    steps, period, hottest = 24, 8, 1.5
    result = rotate.anneal(key, tree, steps=steps, period=period, hottest=hottest,
                           keep_best=keep_best, split_axes=False)
    expected, info = ref.anneal(tree, lambda i: np.asarray(annealing_draws(key, i, NODES)),
                                kensler_schedule(steps, period, hottest), steps, keep_best=keep_best)
    assert int(result.steps) == info["passes"] and int(result.moves) == info["moves"]
    assert_same_tree(result.tree, expected)
    np.testing.assert_allclose(np.asarray(result.history)[: info["passes"]], info["history"], rtol=1e-5)
    sah = check_result(result, plo, phi)
    if keep_best:
        assert sah <= float(result.sah_start) * (1 + 1e-6)
        assert sah <= np.nanmin(np.asarray(result.history)) * (1 + 1e-6)


# (schedule for anneal, the same temperatures for the twin), made once: a schedule is
# static, so every new function object compiles the run again. The names of SCHEDULES
# are made from the run's steps and hottest: they are the optax schedules beside them.
STEPS, HOTTEST = 16, 0.4
OPTAX_SCHEDULES = {
    "cosine": ("cosine", optax.cosine_decay_schedule(HOTTEST, STEPS)),
    "exponential": ("exponential", optax.exponential_decay(HOTTEST, STEPS, EXPONENTIAL_FINAL)),
    "join kensler, cosine": (optax.join_schedules(
        [kensler_schedule(STEPS // 2, 4, 4 * HOTTEST), optax.cosine_decay_schedule(HOTTEST, STEPS // 2)],
        [STEPS // 2]),) * 2,
    "linear": (optax.linear_schedule(HOTTEST, 0.0, STEPS),) * 2,
}


@pytest.mark.parametrize("name", list(OPTAX_SCHEDULES))
@settings(max_examples=examples(5))
@given(case=trees, key_seed=st.integers(0, 2**31))
def test_anneal_with_optax_schedules_equals_reference(name, case, key_seed):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    key = jax.random.key(key_seed)
    schedule, twin_schedule = OPTAX_SCHEDULES[name]
    result = rotate.anneal(key, tree, schedule=schedule, steps=STEPS, hottest=HOTTEST, split_axes=False)
    expected, info = ref.anneal(tree, lambda i: np.asarray(annealing_draws(key, i, NODES)),
                                twin_schedule, STEPS)
    assert int(result.steps) == info["passes"] and int(result.moves) == info["moves"]
    assert_same_tree(result.tree, expected)
    np.testing.assert_allclose(np.asarray(result.history)[: info["passes"]], info["history"], rtol=1e-5)
    check_result(result, plo, phi)


def test_float64_trees_stay_float64_and_equal_the_reference():
    """x64 mode: boxes and costs stay float64 (an optax schedule's float64 too), links
    int32, and both methods still equal the twin."""
    with jax.enable_x64(True):
        tree, plo, phi = random_tree(4, 30, 2, dtype=np.float64)
        hc = rotate.hill_climb(tree, ct=0.3, split_axes=False)
        expected, info = ref.hill_climb(tree, ct=0.3)
        assert_same_tree(hc.tree, expected)
        assert int(hc.steps) == info["passes"]
        key = jax.random.key(1)
        schedule = optax.cosine_decay_schedule(0.4, 16)
        sa = rotate.anneal(key, tree, schedule=schedule, steps=16, split_axes=False)
        expected, info = ref.anneal(tree, lambda i: np.asarray(annealing_draws(key, i, NODES, np.float64)),
                                    schedule, 16)
        assert_same_tree(sa.tree, expected)
        assert int(sa.steps) == info["passes"]
        for out in (hc, sa):
            assert np.asarray(out.tree.lo).dtype == np.float64 and np.asarray(out.sah).dtype == np.float64
            assert np.asarray(out.tree.left).dtype == np.int32
            jaxbvh.validate(out.tree, plo, phi)


def test_kensler_schedule_composes_under_optax_join():
    """Kensler's schedule as a piece of an optax composition: followed by a constant 0 it
    is the default run; a composition that starts later shifts it (other trees)."""
    tree, plo, phi = random_tree(8, 40, 1)
    key = jax.random.key(2)
    steps, period, hottest = 12, 6, 0.5
    kensler = kensler_schedule(steps, period, hottest)
    joined = optax.join_schedules([kensler, optax.constant_schedule(0.0)], boundaries=[steps])
    default = rotate.anneal(key, tree, steps=steps, period=period, hottest=hottest)
    composed = rotate.anneal(key, tree, schedule=joined, steps=steps)
    assert_same_tree(composed.tree, default.tree)
    assert_same_costs(composed.history, default.history)
    assert int(composed.steps) == int(default.steps) and int(composed.moves) == int(default.moves)
    # kensler second: cold for 5 passes, then its ramped sine shifted by 5
    late = optax.join_schedules([optax.constant_schedule(0.0), kensler], boundaries=[5])
    shifted = rotate.anneal(key, tree, schedule=late, steps=steps + 5, split_axes=False)
    expected, info = ref.anneal(tree, lambda i: np.asarray(annealing_draws(key, i, NODES)),
                                lambda i: kensler(i - 5) if i >= 5 else 0.0, steps + 5)
    assert_same_tree(shifted.tree, expected)
    assert int(shifted.steps) == info["passes"]
    check_result(shifted, plo, phi)


def test_cold_annealing_is_greedy_descent():
    tree, plo, phi = random_tree(11, 40, 1)
    cold = rotate.anneal(jax.random.key(0), tree, schedule=constant_schedule(0.0), steps=5)
    hc = rotate.hill_climb(tree)
    check_result(cold, plo, phi)
    # the first-better rule and the best-move rule may reach different local minima,
    # but a cold run never makes the tree worse and converges
    assert float(cold.sah) <= float(cold.sah_start) * (1 + 1e-6)
    assert int(cold.steps) < 5 + 1000 and int(hc.steps) < 1000 and bool(cold.converged)


def test_chains_return_the_best_chain():
    tree, plo, phi = random_tree(21, 40, 1)
    key = jax.random.key(3)
    many = rotate.anneal(key, tree, steps=16, period=8, chains=3)
    singles = [rotate.anneal(k, tree, steps=16, period=8) for k in jax.random.split(key, 3)]
    sahs = np.array([float(r.sah) for r in singles], np.float32)
    np.testing.assert_allclose(np.asarray(many.chain_sah), sahs, rtol=1e-6)
    # the best: the first chain within the margin of the least (ulps must not choose)
    best = int(np.argmax(sahs <= sahs.min() * (1 + min_gain(np.float32))))
    assert_same_tree(many.tree, singles[best].tree)
    # the other fields describe the best chain
    for field in ("steps", "moves", "converged", "history_moves"):
        np.testing.assert_array_equal(getattr(many, field), getattr(singles[best], field), err_msg=field)
    assert_same_costs(many.history, singles[best].history)
    check_result(many, plo, phi)


def test_batch_of_trees_equals_one_by_one():
    cases = [random_tree(s, n, 2) for s, n in ((1, 10), (2, 33), (3, 25))]
    batch = jaxbvh.tree.stack_trees([t for t, _, _ in cases])
    out = rotate.optimize_batch(batch)
    for (tree, plo, phi), got in zip(cases, jaxbvh.tree.unstack_trees(out.tree)):
        assert_same_tree(got, rotate.hill_climb(tree).tree)
        jaxbvh.validate(got, plo, phi)
    keys = jax.random.split(jax.random.key(0), 3)
    out = rotate.optimize_batch(batch, keys, method="sa", steps=8, period=4)
    for (tree, _, _), key, got in zip(cases, keys, jaxbvh.tree.unstack_trees(out.tree)):
        assert_same_tree(got, rotate.anneal(key, tree, steps=8, period=4).tree)


def json_ready(a):
    """An array of the state as NumPy (keys as their data)."""
    return np.asarray(jax.random.key_data(a) if jnp.issubdtype(a.dtype, jax.dtypes.prng_key) else a)


@pytest.mark.parametrize("optimizer, config", [
    (HILL_CLIMB, HillClimbConfig()),
    (ANNEAL, AnnealConfig(steps=10, period=4, hottest=0.5, chains=2)),
], ids=["hc", "sa"])
def test_vmapped_step_gives_each_tree_its_own_result(optimizer, config):
    """The protocol's step, vmapped over two different trees of one capacity: each tree
    stops when it is done (a done state is a fixed point), and each gets exactly its
    single-tree result, node for node."""
    cases = [random_tree(4, 12, 2), random_tree(9, 45, 1, "grid")]
    batch = jaxbvh.tree.stack_trees([t for t, _, _ in cases])
    keys = jax.random.split(jax.random.key(7), 2)
    states = jax.vmap(lambda tree, key: optimizer.init(tree, config, key))(jaxbvh.to_jax(batch), keys)
    step = jax.jit(jax.vmap(optimizer.step))
    while not bool(np.all(states.progress.done)):
        states = step(states)
    again = step(states)  # done states do not change
    for a, b in zip(jax.tree_util.tree_leaves(states), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(json_ready(a), json_ready(b))
    results = jax.vmap(optimizer.result)(states)
    steps = []
    for k, ((tree, plo, phi), got) in enumerate(zip(cases, jaxbvh.tree.unstack_trees(results.tree))):
        alone = driver.run(optimizer, tree, config, key=keys[k])
        assert_same_tree(got, alone.tree)
        jaxbvh.validate(got, plo, phi)
        for field in ("steps", "moves", "converged", "history_moves"):
            np.testing.assert_array_equal(np.asarray(getattr(results, field))[k], getattr(alone, field))
        # costs are summed in another fusion under vmap: the last bit may differ
        for field in ("sah", "sah_start", "history", "chain_sah"):
            if getattr(alone, field) is not None:
                np.testing.assert_allclose(np.asarray(getattr(results, field))[k], getattr(alone, field),
                                           rtol=1e-6, err_msg=field)
        steps.append(int(alone.steps))
    assert steps[0] != steps[1]  # the trees stop at different passes


# ----------------------------------------------------------------------------------
# Split axes
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(10))
@given(trees)
def test_split_axes_match_reference_and_keep_cost(case):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    out = jaxbvh.tree.assign_split_axes(tree)
    assert_same_tree(out, ref.assign_split_axes(tree))
    jaxbvh.validate(out, plo, phi)
    t = jaxbvh.to_numpy(out)
    interior = t.left >= 0
    assert ((t.axis >= 0) == interior).all()
    a, b, k = t.left[interior], t.right[interior], t.axis[interior]
    rows = np.arange(a.size)
    centre_a, centre_b = (t.lo[a] + t.hi[a])[rows, k], (t.lo[b] + t.hi[b])[rows, k]
    assert (centre_a <= centre_b).all()  # lower child on the left
    assert float(jaxbvh.sah(jaxbvh.to_jax(out))) == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(tree))), rel=1e-6)


# ----------------------------------------------------------------------------------
# Devices (a subprocess: XLA flags must be set before jax starts)
# ----------------------------------------------------------------------------------

_SUBPROCESS = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    sys.path.insert(0, {repo!r}); sys.path.insert(0, {tests!r})
    from helpers import random_tree
    import jaxbvh
    from jaxbvh.optimize import rotate
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    cases = [random_tree(s, 40, 1, "grid" if s % 2 == 0 else "random") for s in range(4)]
    batch = jaxbvh.tree.stack_trees([t for t, _, _ in cases])
    out = {{"devices": jax.device_count()}}
    if jax.device_count() >= 2:
        mesh = Mesh(np.array(jax.devices()[:2]), ("batch",))
        batch = jax.device_put(batch, NamedSharding(mesh, P("batch")))
        keys = jax.device_put(jax.random.split(jax.random.key(1), 4), NamedSharding(mesh, P("batch")))
        res = rotate.optimize_batch(batch, keys, method="sa", steps=8, period=4)
        out["sharded_devices"] = len(res.tree.left.sharding.device_set)
        out["sa"] = np.asarray(res.tree.left).tolist()
        res = rotate.optimize_batch(batch)
    else:
        res = rotate.optimize_batch(batch)
    out["hc"] = np.asarray(res.tree.left).tolist()
    out["passes"] = np.asarray(res.steps).tolist()
    print("RESULT" + json.dumps(out))
""")


def _run_subprocess(flags: str) -> dict:
    import json

    code = _SUBPROCESS.format(repo=str(REPO), tests=str(REPO / "tests"))
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {flags}", "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [l for l in proc.stdout.splitlines() if l.startswith("RESULT")][-1]
    return json.loads(line[len("RESULT"):])


def test_sharded_batch_on_two_cpu_devices_equals_one_device():
    """The batch sharded over 2 fake CPU devices (a subprocess) gives this process's trees."""
    two = _run_subprocess("--xla_force_host_platform_device_count=2")
    assert two["devices"] == 2 and two["sharded_devices"] == 2
    cases = [random_tree(s, 40, 1, "grid" if s % 2 == 0 else "random") for s in range(4)]
    here = rotate.optimize_batch(jaxbvh.tree.stack_trees([t for t, _, _ in cases]))
    assert np.asarray(here.tree.left).tolist() == two["hc"]
    assert np.asarray(here.steps).tolist() == two["passes"]
    keys = jax.random.split(jax.random.key(1), 4)
    sa = rotate.optimize_batch(jaxbvh.tree.stack_trees([t for t, _, _ in cases]), keys, method="sa",
                               steps=8, period=4)
    assert np.asarray(sa.tree.left).tolist() == two["sa"]


# ----------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------


def test_cli_optimize_tree_file(tmp_path):
    from jaxbvh.cli import make_parser

    tree, plo, phi = random_tree(5, 30, 2)
    src, out = tmp_path / "in.npz", tmp_path / "out.npz"
    jaxbvh.save(src, tree)
    parser, modules = make_parser()
    for method in ("hc", "sa"):
        args = parser.parse_args(["optimize", str(src), "--method", method, "--steps", "8",
                                  "--chains", "2", "--json", "-o", str(out)])
        result = modules["optimize"].run(args)
        assert result["valid"] and result["after"]["sah"] <= result["before"]["sah"] * (1 + 1e-6)
        saved, _ = jaxbvh.load(out)
        jaxbvh.validate(saved, plo, phi)
        assert float(jaxbvh.sah(jaxbvh.to_jax(saved))) == pytest.approx(result["after"]["sah"], rel=1e-6)
    with pytest.raises(ValueError):
        modules["optimize"].run(parser.parse_args(["optimize", str(src), "--hottest", "-1"]))
