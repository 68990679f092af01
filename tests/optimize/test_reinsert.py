"""Parallel reinsertion (jaxbvh.optimize.reinsert) against its NumPy twin and the invariants.

Random tree_cases are padded to one capacity so every jitted function compiles once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import NODES, SHARED_DATA, assert_same_tree, check_result, random_tree, tree_cases
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh import numerics
from jaxbvh.optimize import driver, reinsert, reinsert_moves, reinsert_rules, reinsert_search
from jaxbvh.optimize import reinsert_reference as ref
from jaxbvh.testing.plugin import examples

MIN_GAIN = numerics.min_gain(np.float32)
ITERATION = jax.jit(reinsert_moves.iteration)
FIND = jax.jit(reinsert_moves.find)
PREPARE = jax.jit(reinsert_search.prepare)


def _search_all(tree, max_steps):
    s = PREPARE(jaxbvh.to_jax(tree))
    ids, count = reinsert_search.candidates(s, jnp.int32(reinsert.ALL_OCTAVES))
    out = jax.jit(reinsert_search.search)(s, ids, count, reinsert_search.scale_of(s), jnp.int32(max_steps),
                                          jnp.float32(MIN_GAIN))
    return s, [np.asarray(x) for x in out]


# ----------------------------------------------------------------------------------
# The first candidates
# ----------------------------------------------------------------------------------


OCTAVES = jax.jit(lambda area, parent, root, need: reinsert_rules.octaves_holding(area, parent, root, need, xp=jnp))


@settings(max_examples=examples(15))
@given(st.lists(st.tuples(st.integers(-1, NODES - 1), st.integers(-40, 2), st.sampled_from([0.0, 1.0, 1.7])),
                min_size=1, max_size=NODES),
       st.integers(0, NODES - 1), st.sampled_from([1 / 32, 0.2, 0.5, 1.0, 1e-9]))
def test_first_octaves_traced_equal_the_host_rule(rows, root, first_fraction):
    """The octaves a run starts with, taken inside a traced program (the pipeline's
    reinsertion stages), equal the host rule of the twin, literally: the fewest octaves
    whose parent areas hold ceil(first_fraction * nodes) nodes."""
    parent = np.full(NODES, -1, np.int32)
    area = np.zeros(NODES, np.float32)
    for i, (up, exponent, mantissa) in enumerate(rows):
        parent[i], area[i] = up, np.ldexp(np.float32(mantissa), exponent)
    root = min(root, len(rows) - 1)
    nodes = int(np.sum(parent >= 0))
    expected = reinsert_rules.ALL_OCTAVES
    if first_fraction < 1 and area[root] > 0 and nodes:
        need = int(np.ceil(first_fraction * nodes))
        for octaves in range(64):
            if np.sum(area[parent[parent >= 0]] >= np.ldexp(area[root], -octaves)) >= need:
                expected = octaves
                break
    assert reinsert_rules.first_octaves(area, parent, root, first_fraction) == expected
    need = reinsert_rules.candidates_needed(first_fraction, nodes)
    assert int(OCTAVES(area, parent, jnp.int32(root), jnp.int32(need))) == expected


WIDEN = jax.jit(reinsert.widen)


@settings(max_examples=examples(15))
@given(st.integers(0, 70), st.integers(0, 5), st.integers(1, 100), st.integers(0, 100),
       st.floats(1.0, 100.0), st.sampled_from([0.0, 1e-5, 1e-3]))
def test_widening_after_an_iteration(octaves, taken, count, nodes, before, drop):
    """The octaves after an iteration: one more after a small gain with moves, every node
    after one without a move (or from 64 octaves on), none more while gains are large or
    every node is searched already. (Drops well away from ``escalate``: the rule compares
    in the tree's float type.)"""
    escalate = 1e-4
    after = before * (1 - drop)
    got = int(WIDEN(jnp.int32(octaves), jnp.int32(taken), jnp.int32(count), jnp.int32(nodes),
                    jnp.float32(before), jnp.float32(after), jnp.float32(escalate)))
    small = taken == 0 or before - after <= escalate * before
    if count >= nodes or not small:
        assert got == octaves
    elif taken == 0 or octaves >= reinsert_rules.FIRST_OCTAVES_TRIED:
        assert got == reinsert.ALL_OCTAVES
    else:
        assert got == octaves + 1

# ----------------------------------------------------------------------------------
# The search
# ----------------------------------------------------------------------------------


@given(tree_cases, st.sampled_from([1, 3, 8, 1024]))
def test_search_equals_reference_node_by_node(case, max_steps):
    """Every node's best place, gain and common ancestor, also when the step bound cuts
    the walk short."""
    tree, _, _ = random_tree(*case)
    s, (gain, out, lca) = _search_all(tree, max_steps)
    t = ref.Tree(tree)
    np.testing.assert_array_equal(t.lo, np.asarray(s.lo))  # the same refit
    for a in range(NODES):
        if t.parent[a] < 0:
            assert out[a] == -1
            continue
        g, o, l, steps = ref.search(t, a, max_steps, MIN_GAIN)
        assert steps <= max_steps
        assert (out[a], lca[a]) == (o, l), a
        if o >= 0:
            assert gain[a] == pytest.approx(float(g), rel=1e-4, abs=1e-6)


@given(tree_cases)
def test_each_gain_is_the_drop_in_interior_area_of_its_move(case):
    """Applying one found move alone lowers the sum of interior areas by its gain."""
    tree, plo, phi = random_tree(*case)
    s, (gain, out, _) = _search_all(tree, 1024)
    base = ref.Tree(tree)

    def interior_area(t):
        return sum(float(t.area(n)) for n in t.post_order() if t.child[n, 0] >= 0)

    before = interior_area(base)
    for a in np.flatnonzero(out >= 0)[:8]:
        t = ref.Tree(tree)
        ref.apply_move(t, int(a), int(out[a]))
        jaxbvh.validate(t.to_bvh(), plo, phi)
        assert before - interior_area(t) == pytest.approx(float(gain[a]), rel=1e-3, abs=1e-5)
        assert gain[a] > 0


# ----------------------------------------------------------------------------------
# One iteration: selection and the batch
# ----------------------------------------------------------------------------------


def _one_iteration(tree, octaves=reinsert.ALL_OCTAVES):
    s = PREPARE(jaxbvh.to_jax(tree))
    m, taken, gains, count, _ = FIND(s, jnp.int32(octaves), jnp.int32(1024), jnp.float32(MIN_GAIN))
    new, moves, total, sah, *_ = ITERATION(
        s, jnp.asarray(tree.prim_count), jnp.float32(1), jnp.float32(1), jnp.int32(octaves),
        jnp.int32(1024), jnp.float32(MIN_GAIN))
    return s, m, np.asarray(taken), np.asarray(gains), new, int(moves), float(total), float(sah)


@given(tree_cases)
def test_iteration_equals_the_reference_applying_the_same_batch(case):
    """The parallel iteration's tree is the selected batch applied one move at a time, in
    rank order; the SAH drops by the batch's total gain (the moves are independent)."""
    tree, plo, phi = random_tree(*case)
    s, m, taken, gains, new, moves, total, sah = _one_iteration(tree)
    a, out = np.asarray(m.a), np.asarray(m.out)
    assert moves == taken.sum()
    batch = [(int(a[i]), int(out[i])) for i in np.flatnonzero(taken)]
    expected = ref.apply_batch(tree, batch)
    got = reinsert_search.to_tree(jaxbvh.to_jax(tree), new)
    assert_same_tree(got, expected)
    jaxbvh.validate(got, plo, phi)
    before = float(jaxbvh.sah(jaxbvh.to_jax(tree)))
    after = float(jaxbvh.sah(got))
    root_area = float(np.asarray(s.area)[int(s.root)])
    if root_area > 0:
        assert before - after == pytest.approx(total / root_area, rel=1e-3, abs=1e-5)
    assert after == pytest.approx(sah, rel=1e-5)


@given(tree_cases)
def test_selection_is_the_greedy_choice_over_disjoint_lock_sets(case):
    """The rounds of the JAX selection give the sequential greedy choice of the twin,
    fed the same moves, and the taken moves lock disjoint node sets."""
    tree, _, _ = random_tree(*case)
    s, m, taken, gains, *_ = _one_iteration(tree)
    t = ref.Tree(tree)
    a, out, lca = (np.asarray(x) for x in (m.a, m.out, m.lca))
    lanes = np.flatnonzero(a >= 0)
    moves = [(np.float32(gains[i]), int(a[i]), int(out[i]), int(lca[i])) for i in lanes]
    # the lanes come best first
    assert [mv[1] for mv in ref.rank_order(moves)] == [mv[1] for mv in moves]
    expected = {mv[1] for mv in ref.select(t, moves)}
    assert {int(a[i]) for i in np.flatnonzero(taken)} == expected
    held = set()
    for i in np.flatnonzero(taken):
        nodes = ref.lock_set(t, int(a[i]), int(out[i]), int(lca[i]))
        assert held.isdisjoint(nodes)
        held |= nodes
    if lanes.size:
        assert taken[lanes[0]]  # the best move is always taken


# ----------------------------------------------------------------------------------
# Whole runs
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(15))
@given(tree_cases, st.sampled_from([1.0, 0.2]), st.booleans())
def test_reinsert_equals_reference(case, first_fraction, settle):
    """Whole runs node for node as the twin, with and without skipping settled nodes
    (a traced setting: one program)."""
    tree, plo, phi = random_tree(*case)
    result = reinsert.reinsert(tree, first_fraction=first_fraction, settle=settle, split_axes=False)
    expected, info = ref.reinsert(tree, first_fraction=first_fraction, settle=settle)
    assert result.steps == info["iterations"] and result.moves == info["moves"]
    assert_same_tree(result.tree, expected)
    history = result.history[:result.steps]
    np.testing.assert_allclose(history, info["history"], rtol=1e-5)
    assert np.isnan(result.history[result.steps:]).all()
    np.testing.assert_array_equal(result.history_moves[:result.steps], [len(t) for t in info["taken"]])
    sah = check_result(tree, result, plo, phi)
    assert np.all(np.diff(np.concatenate([[float(result.sah_start)], history])) <= 1e-5 * sah)
    assert bool(result.converged) == (result.steps < reinsert.DEFAULT_MAX_ITERATIONS)
    # converged: one more iteration over all nodes finds nothing
    assert _one_iteration(result.tree)[5] == 0


def test_default_escalate_is_by_node_count():
    """Unless given, both sides widen the octaves after an iteration that lowers the SAH
    by at most ESCALATE_NODES / nodes (reinsert_rules.escalate_for): the default run
    equals the twin's and the run given that value, node for node; a fixed 1e-3 (the
    rule on neither side) takes another schedule on this tree."""
    assert reinsert_rules.escalate_for(118) == reinsert_rules.ESCALATE_NODES / 118
    assert reinsert_rules.escalate_for(118, 0.25) == 0.25 and reinsert_rules.escalate_for(0) > 0
    tree = random_tree(0, 60, 1)[0]
    nodes = int(np.sum(np.asarray(tree.parent) >= 0))
    default = reinsert.reinsert(tree, first_fraction=0.2, split_axes=False)
    given = reinsert.reinsert(tree, first_fraction=0.2, split_axes=False,
                              escalate=reinsert_rules.escalate_for(nodes))
    expected, info = ref.reinsert(tree, first_fraction=0.2)
    _, fixed = ref.reinsert(tree, first_fraction=0.2, escalate=1e-3)
    assert default.steps == given.steps == info["iterations"] != fixed["iterations"]
    assert_same_tree(default.tree, expected)
    assert_same_tree(given.tree, expected)


def test_widen_until_ends_the_run_where_it_would_widen():
    """With ``widen_until`` F both sides end after the first iteration that would widen
    candidates that are F of the nodes or more (reinsert_rules.widening_stop): the same
    iterations and tree as the twin, fewer the smaller F on this tree, not converged."""
    tree = random_tree(0, 60, 1)[0]
    nodes = int(np.sum(np.asarray(tree.parent) >= 0))
    assert reinsert_rules.widening_stop(None, nodes) == nodes + 1  # never: no widening of every node
    assert reinsert_rules.widening_stop(0.3, 10) == 3 and reinsert_rules.widening_stop(0.31, 10) == 4
    steps = []
    for widen_until in (0.3, 0.6):
        result = reinsert.reinsert(tree, first_fraction=0.2, split_axes=False, widen_until=widen_until)
        expected, info = ref.reinsert(tree, first_fraction=0.2, widen_until=widen_until)
        assert result.steps == info["iterations"] and not result.converged
        assert_same_tree(result.tree, expected)
        np.testing.assert_allclose(result.history[:result.steps], info["history"], rtol=1e-5)
        steps.append(int(result.steps))
    assert steps[0] < steps[1] < reinsert.reinsert(tree, first_fraction=0.2, split_axes=False).steps


def test_reinsert_with_split_axes_and_float64():
    tree, plo, phi = random_tree(3, 30, 2)
    result = reinsert.reinsert(tree)
    check_result(tree, result, plo, phi)
    assert (np.asarray(result.tree.axis)[np.asarray(result.tree.left) >= 0] >= 0).all()
    with jax.enable_x64(True):
        tree64, plo64, phi64 = random_tree(3, 30, 2, dtype=np.float64)
        result64 = reinsert.reinsert(tree64, split_axes=False)
        assert np.asarray(result64.tree.lo).dtype == np.float64
        check_result(tree64, result64, plo64, phi64)
        expected, _ = ref.reinsert(tree64)
        assert_same_tree(result64.tree, expected)


def test_time_budget_stops_early_with_a_valid_tree():
    tree, plo, phi = random_tree(12, 60, 1)
    full = reinsert.reinsert(tree, first_fraction=0.05)
    short = reinsert.reinsert(tree, first_fraction=0.05, time_budget=1e-9)
    check_result(tree, short, plo, phi)  # compiling comes before the budget: the first chunk runs
    assert short.steps == 1 < full.steps <= reinsert.DEFAULT_MAX_ITERATIONS
    np.testing.assert_array_equal(short.history[:1], full.history[:1])
    assert not short.converged and full.converged
    log = []
    logged = reinsert.reinsert(tree, on_step=log.append)
    assert [info.step for info in log] == list(range(len(log))) == list(range(logged.steps))
    assert {info.stage for info in log} == {"reinsert"} and log[-1].moves == 0
    np.testing.assert_allclose([info.sah for info in log], logged.history[:logged.steps])
    assert_same_tree(logged.tree, reinsert.reinsert(tree).tree)  # chunks never change the result


def test_tiny_trees_and_zero_traversal_cost():
    for n in (1, 2, 3):
        tree, plo, phi = random_tree(n, n)
        result = reinsert.reinsert(tree)
        check_result(tree, result, plo, phi)
        assert result.moves == 0 if n <= 2 else result.moves >= 0
    tree, plo, phi = random_tree(5, 20)
    result = reinsert.reinsert(tree, ct=0.0)  # no move changes the SAH
    assert result.steps == 0 and result.moves == 0
    check_result(tree, result, plo, phi, ct=0.0)


def test_no_retrace_for_trees_of_one_capacity():
    """Settings are traced values: new tree_cases of one capacity and new settings reuse the
    compiled loop of steps."""
    reinsert.reinsert(random_tree(1, 20)[0])
    before = driver.advance._cache_size()
    for seed in range(2, 5):
        reinsert.reinsert(random_tree(seed, 30, 2)[0], max_steps=7 * seed, first_fraction=0.1,
                          escalate=10.0 ** -seed, min_gain=1e-5 * seed, split_axes=seed % 2 == 0,
                          widen_until=0.2 * seed)
    assert driver.advance._cache_size() == before


def test_bad_arguments_raise_value_error():
    tree = random_tree(0, 5)[0]
    for kwargs in (dict(max_steps=0), dict(max_iterations=-1), dict(first_fraction=0),
                   dict(first_fraction=1.5), dict(ct=-1.0), dict(time_budget=0),
                   dict(on_step=3), dict(min_gain=-1.0), dict(escalate=-1.0),
                   dict(widen_until=0.0), dict(widen_until=1.5)):
        with pytest.raises(ValueError):
            reinsert.reinsert(tree, **kwargs)
    wide = jaxbvh.from_interchange({**jaxbvh.to_interchange(tree), "child": np.full((9, 3), -1, np.int32)})
    with pytest.raises(ValueError, match="binary"):
        reinsert.reinsert(wide)


@pytest.mark.skipif(not (SHARED_DATA / "trees").exists(), reason=f"shared data not found at {SHARED_DATA}")
def test_real_tree_iterations_equal_reference():
    """legocar (tinybvh, leaves of up to 32 triangles): three iterations from the largest
    parent areas, node for node as the twin; valid, leaves untouched, SAH lower."""
    tree, _ = jaxbvh.load(SHARED_DATA / "trees" / "legocar_binned_ref.npz")
    result = reinsert.reinsert(tree, max_iterations=3, first_fraction=0.02, split_axes=False)
    expected, info = ref.reinsert(tree, max_iterations=3, first_fraction=0.02)
    assert_same_tree(result.tree, expected)
    np.testing.assert_allclose(result.history[:result.steps], info["history"], rtol=1e-5)
    check_result(tree, result, None, None)
    assert float(result.sah) < float(result.sah_start) - 0.3
