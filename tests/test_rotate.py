"""Tree rotations (jaxbvh.rotate) against the sequential NumPy twin and the invariants.

Random trees are padded to one capacity so every jitted function compiles once.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_tree
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.optimize import rotate
from jaxbvh.optimize import rotate_reference as ref
from jaxbvh.optimize.schedules import constant_schedule, kensler_schedule

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NODES, PRIMS = 128, 64  # one capacity for all random trees
REPO = Path(__file__).resolve().parents[1]
SETTINGS = dict(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])



def assert_same_tree(a, b):
    a, b = jaxbvh.to_numpy(a), jaxbvh.to_numpy(b)
    for field in ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "prim_index", "axis"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert int(a.root) == int(b.root)


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
    """Move ``move`` at node ``n`` done by hand (NumPy), boxes recomputed."""
    t = jaxbvh.to_numpy(tree)
    child = np.stack([t.left, t.right], 1).copy()
    parent, lo, hi = t.parent.copy(), t.lo.copy(), t.hi.copy()
    L, R = child[n]
    a_code, a_side = rotate._SLOT_A[move]
    b_code, b_side = rotate._SLOT_B[move]
    fam = (n, L, R)
    (na, nb) = fam[a_code], fam[b_code]
    x, y = child[na, a_side], child[nb, b_side]
    child[na, a_side], child[nb, b_side] = y, x
    parent[y], parent[x] = na, nb
    for node in (L, R):
        lo[node] = np.minimum(lo[child[node, 0]], lo[child[node, 1]]) if child[node, 0] >= 0 else lo[node]
        hi[node] = np.maximum(hi[child[node, 0]], hi[child[node, 1]]) if child[node, 0] >= 0 else hi[node]
    return t.replace(left=child[:, 0].copy(), right=child[:, 1].copy(), parent=parent, lo=lo, hi=hi)


@settings(max_examples=10, deadline=None)
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


@settings(**SETTINGS)
@given(trees)
def test_hill_climb_equals_reference_pass_by_pass(case):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    full = rotate.hill_climb(tree, split_axes=False)
    expected, info = ref.hill_climb(tree)
    assert int(full.passes) == info["passes"] and int(full.moves) == info["moves"]
    assert_same_tree(full.tree, expected)
    np.testing.assert_allclose(np.asarray(full.history)[: info["passes"]], info["history"], rtol=1e-5)
    assert np.isnan(np.asarray(full.history)[info["passes"]:]).all()
    for passes in range(1, min(info["passes"], 3) + 1):
        part = rotate.hill_climb(tree, max_passes=passes, split_axes=False)
        assert_same_tree(part.tree, ref.hill_climb(tree, max_passes=passes)[0])
    sah = check_result(full, plo, phi)
    assert sah <= float(full.sah_start) * (1 + 1e-6)


@pytest.mark.skipif(not (DATA / "trees").exists(), reason=f"shared data not found at {DATA}")
def test_hill_climb_equals_reference_on_a_real_tree():
    tree, _ = jaxbvh.load(DATA / "trees" / "legocar_binned_ref.npz")
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
    b = rotate.hill_climb(tree, windows=(3,), frontier=4)
    c = rotate.hill_climb(tree)                             # queue and ancestor list fit
    assert_same_tree(a.tree, c.tree)
    assert_same_tree(b.tree, c.tree)
    check_result(c, plo, phi)
    # the short-queue walk (normally 4096 wide) next to the full-width one
    monkeypatch.setattr(rotate, "_SMALL_QUEUE", 3)
    for frontier in (5, 7):
        d = rotate.hill_climb(tree, windows=(2, 5), frontier=frontier)
        assert_same_tree(d.tree, c.tree)
        assert int(d.passes) == int(c.passes) and int(d.moves) == int(c.moves)
    key = jax.random.key(5)
    e = rotate.anneal(key, tree, steps=12, period=6, frontier=7)
    monkeypatch.setattr(rotate, "_SMALL_QUEUE", 4096)
    f = rotate.anneal(key, tree, steps=12, period=6, frontier=1)
    assert_same_tree(e.tree, f.tree)


def test_progress_reports_every_pass_and_chunks_change_nothing(monkeypatch):
    """With ``on_pass`` the run goes in chunks of passes; chunk sizes never change the result."""
    tree, plo, phi = random_tree(11, 50, 2)
    key = jax.random.key(3)
    runs = {
        "hc": lambda **kw: rotate.hill_climb(tree, **kw),
        "sa": lambda **kw: rotate.anneal(key, tree, steps=10, period=5, **kw),
        "sa chains": lambda **kw: rotate.anneal(key, tree, steps=10, period=5, chains=3, **kw),
    }
    for name, run in runs.items():
        whole = run()
        for max_chunk in (1, 3, rotate.MAX_CHUNK):
            monkeypatch.setattr(rotate, "MAX_CHUNK", max_chunk)
            log = []
            chunked = run(on_pass=lambda i, sah, moves, t: log.append((i, float(sah), int(moves), float(t))))
            assert_same_tree(chunked.tree, whole.tree)
            check_result(chunked, plo, phi)
            assert int(chunked.passes) == int(whole.passes) and int(chunked.moves) == int(whole.moves)
            assert float(chunked.sah) == float(whole.sah), name
            if whole.chain_sah is not None:
                np.testing.assert_array_equal(np.asarray(chunked.chain_sah), np.asarray(whole.chain_sah))
            # one report per pass, in order, that agrees with the history
            assert [i for i, *_ in log] == list(range(len(log)))
            assert len(log) >= int(whole.passes)
            if name != "sa chains":
                history = np.asarray(whole.history)[: int(whole.passes)]
                np.testing.assert_array_equal([sah for _, sah, _, _ in log], history)
                assert sum(moves for _, _, moves, _ in log) == int(whole.moves)
            assert all(t == 0 for *_, t in log[10:]) and (name == "hc" or any(t > 0 for *_, t in log))


def test_time_budget_stops_early_with_a_valid_tree():
    tree, plo, phi = random_tree(12, 60, 1)
    full = rotate.anneal(jax.random.key(1), tree, steps=400, period=20)
    short = rotate.anneal(jax.random.key(1), tree, steps=400, period=20, time_budget=1e-9)
    check_result(short, plo, phi)
    assert 1 <= int(short.passes) < int(full.passes)  # the first chunk (one pass), then the budget
    assert float(short.sah) <= float(short.sah_start) * (1 + 1e-6)  # keep_best: never worse
    hc = rotate.hill_climb(tree, time_budget=60.0)  # a budget it does not reach: the same tree
    assert_same_tree(hc.tree, rotate.hill_climb(tree).tree)
    with pytest.raises(ValueError, match="time_budget"):
        rotate.hill_climb(tree, time_budget=0)


def test_no_retrace_for_trees_of_one_capacity():
    rotate.hill_climb(random_tree(1, 20)[0])
    before = rotate._run_one._cache_size()
    for seed in range(2, 5):
        rotate.hill_climb(random_tree(seed, 30, 2)[0])
    assert rotate._run_one._cache_size() == before


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


# ----------------------------------------------------------------------------------
# Simulated annealing
# ----------------------------------------------------------------------------------


@settings(**{**SETTINGS, "max_examples": 15})
@given(trees, st.integers(0, 2**31), st.booleans())
@example((117371, 9, 1, "grid"), 0, False)  # exact ties at T = 1e-7 once split JAX from NumPy
def test_anneal_equals_reference_fed_the_same_draws(case, key_seed, keep_best):
    seed, n, leaf, grid = case
    tree, plo, phi = random_tree(seed, n, leaf, grid)
    key = jax.random.key(key_seed)
    steps, period, hottest = 24, 8, 1.5
    result = rotate.anneal(key, tree, steps=steps, period=period, hottest=hottest,
                           keep_best=keep_best, split_axes=False)
    expected, info = ref.anneal(tree, lambda i: np.asarray(rotate.annealing_draws(key, i, NODES)),
                                kensler_schedule(steps, period, hottest), steps, keep_best=keep_best)
    assert int(result.passes) == info["passes"] and int(result.moves) == info["moves"]
    assert_same_tree(result.tree, expected)
    np.testing.assert_allclose(np.asarray(result.history)[: info["passes"]], info["history"], rtol=1e-5)
    sah = check_result(result, plo, phi)
    if keep_best:
        assert sah <= float(result.sah_start) * (1 + 1e-6)
        assert sah <= np.nanmin(np.asarray(result.history)) * (1 + 1e-6)


def test_anneal_accepts_optax_schedules():
    optax = pytest.importorskip("optax")
    tree, plo, phi = random_tree(3, 30, 2)
    key = jax.random.key(5)
    schedule = optax.linear_schedule(1.0, 0.0, 10)
    result = rotate.anneal(key, tree, schedule=schedule, steps=10, split_axes=False)
    expected, info = ref.anneal(tree, lambda i: np.asarray(rotate.annealing_draws(key, i, NODES)),
                                schedule, 10)
    assert_same_tree(result.tree, expected)
    check_result(result, plo, phi)


def test_cold_annealing_is_greedy_descent():
    tree, plo, phi = random_tree(11, 40, 1)
    cold = rotate.anneal(jax.random.key(0), tree, schedule=constant_schedule(0.0), steps=5)
    hc = rotate.hill_climb(tree)
    check_result(cold, plo, phi)
    # the first-better rule and the best-move rule may reach different local minima,
    # but a cold run never makes the tree worse and converges
    assert float(cold.sah) <= float(cold.sah_start) * (1 + 1e-6)
    assert int(cold.passes) < 5 + 1000 and int(hc.passes) < 1000


def test_kensler_schedule_values():
    s = kensler_schedule(1250, 50, 1.5)
    i = np.arange(0, 1300)
    expected = np.maximum(0, -np.sin(2 * np.pi * i / 50)) * np.maximum(0, 1250 - i) * 1.5 / 1250
    got = np.array([float(s(k)) for k in (0, 10, 25, 37, 40, 600, 1249, 1260)])
    np.testing.assert_allclose(got, expected[[0, 10, 25, 37, 40, 600, 1249, 1260]], atol=1e-5)
    assert float(s(0)) == 0.0 and float(s(1260)) == 0.0  # starts cold, ends cold
    assert float(s(25)) == 0.0 and float(s(50 * 7 + 25)) == 0.0  # exactly cold at sin(pi)
    assert float(jax.jit(s)(jnp.int32(37))) == pytest.approx(expected[37], rel=1e-5)
    assert kensler_schedule(1250, 50, 1.5) is s  # same function object: jit caches hit
    with pytest.raises(ValueError):
        kensler_schedule(0)


def test_chains_return_the_best_chain():
    tree, plo, phi = random_tree(21, 40, 1)
    key = jax.random.key(3)
    many = rotate.anneal(key, tree, steps=16, period=8, chains=3)
    singles = [rotate.anneal(k, tree, steps=16, period=8) for k in jax.random.split(key, 3)]
    np.testing.assert_allclose(np.asarray(many.chain_sah), [float(r.sah) for r in singles], rtol=1e-6)
    best = int(np.argmin([float(r.sah) for r in singles]))
    assert_same_tree(many.tree, singles[best].tree)
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


# ----------------------------------------------------------------------------------
# Split axes
# ----------------------------------------------------------------------------------


@settings(max_examples=10, deadline=None)
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
# Devices and threads (subprocesses: XLA flags must be set before jax starts)
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
    out["passes"] = np.asarray(res.passes).tolist()
    print("RESULT" + json.dumps(out))
""")


def _run_subprocess(flags: str) -> dict:
    import json

    code = _SUBPROCESS.format(repo=str(REPO), tests=str(REPO / "tests"))
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [l for l in proc.stdout.splitlines() if l.startswith("RESULT")][-1]
    return json.loads(line[len("RESULT"):])


def test_sharded_batch_on_two_cpu_devices_and_one_thread_agree():
    two = _run_subprocess("--xla_force_host_platform_device_count=2")
    one = _run_subprocess("--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    assert two["devices"] == 2 and two["sharded_devices"] == 2
    assert one["devices"] == 1
    # the same trees on two devices and on one thread (convergence is not thread-dependent)
    assert two["hc"] == one["hc"] and two["passes"] == one["passes"]
    cases = [random_tree(s, 40, 1, "grid" if s % 2 == 0 else "random") for s in range(4)]
    here = rotate.optimize_batch(jaxbvh.tree.stack_trees([t for t, _, _ in cases]))
    assert np.asarray(here.tree.left).tolist() == two["hc"]
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
        args = parser.parse_args(["optimize", str(src), "--method", method, "--iterations", "8",
                                  "--chains", "2", "--json", "-o", str(out)])
        result = modules["optimize"].run(args)
        assert result["valid"] and result["after"]["sah"] <= result["before"]["sah"] * (1 + 1e-6)
        saved, _ = jaxbvh.load(out)
        jaxbvh.validate(saved, plo, phi)
        assert float(jaxbvh.sah(jaxbvh.to_jax(saved))) == pytest.approx(result["after"]["sah"], rel=1e-6)
    with pytest.raises(ValueError):
        modules["optimize"].run(parser.parse_args(["optimize", str(src), "--hottest", "-1"]))
