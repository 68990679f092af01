"""Treelet restructuring (jaxbvh.treelet) against brute force, its NumPy twin and the invariants."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import NODES, SHARED_DATA, assert_same_tree, check_result, random_tree, tree_cases
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.optimize import driver, treelet
from jaxbvh.optimize import treelet_reference as ref
from jaxbvh.testing.plugin import examples

MIN_GAIN = float(64 * np.finfo(np.float32).eps)


def test_split_tables():
    members, popcount, single, sizes = treelet.tables(7)
    assert sum(parts.size for _, parts in sizes) == 966  # (3^7 - 2^8 + 1) / 2 splits
    for sets, parts in sizes:
        for mask, row in zip(sets, parts):
            assert list(row) == treelet.splits(int(mask)) == ref.splits(int(mask))
            assert all(p & mask == p and p != mask and p & (mask & -mask) for p in row)
            # each unordered split once
            assert len({frozenset((int(p), int(mask ^ p))) for p in row}) == len(row)
    assert popcount[0b1011] == 3 and single[0b100] == 2 and single[0b110] == -1


@given(tree_cases, st.sampled_from([4, 6]), st.data())
def test_dynamic_programme_equals_brute_force(case, n, data):
    """The recursion over subsets finds the least cost over every binary tree of the
    treelet's leaves (all (2k - 3)!! of them), in NumPy and in JAX."""
    tree, _, _ = random_tree(*case)
    t = ref.Tree(tree, 1.0, 1.0)
    interior = [x for x in t.post_order() if t.child[x, 0] >= 0]
    if not interior:
        return
    root = data.draw(st.sampled_from(interior))
    leaves, inner = ref.form(t, root, n, MIN_GAIN)
    assert len(inner) == len(leaves) - 1 and inner[0] == root
    cost, split, *_ = ref.solve(t, leaves, MIN_GAIN)
    full = (1 << len(leaves)) - 1
    best_tree, best = ref.brute_force(t, leaves)
    assert float(cost[full]) == pytest.approx(float(best), rel=1e-5)
    # the JAX solver of the same treelet
    got = treelet.solve(treelet.init(tree, treelet.Config(leaves=n, min_gain=MIN_GAIN)), root)
    assert int(got.leaves) == len(leaves)
    assert list(np.asarray(got.inner)[: int(got.leaves) - 1]) == inner
    assert float(got.best) == pytest.approx(float(best), rel=1e-5)
    assert float(got.current) >= float(best) * (1 - 1e-5)  # the current topology is one of them
    best_j, current_j = float(got.best), float(got.current)
    if best_j < current_j * (1 - 2 * MIN_GAIN) or best_j >= current_j * (1 - MIN_GAIN / 2):  # clear of rounding
        assert bool(got.improves) == (best_j < current_j * (1 - MIN_GAIN))


@given(tree_cases, st.sampled_from([3, 5, 7]))
def test_treelets_grow_by_their_largest_leaf(case, n):
    """Karras & Aila's formation rule, checked on the result rather than replayed: a
    treelet is the subtree of ``root`` cut at its leaves, it has ``n`` leaves unless none
    of them can be expanded, and every expanded node is (up to the tie margin) at least
    as large as every treelet leaf left unexpanded that could have been."""
    tree, _, _ = random_tree(*case)
    t = ref.Tree(tree, 1.0, 1.0)
    for root in (x for x in t.post_order() if t.child[x, 0] >= 0):
        leaves, inner = ref.form(t, root, n, MIN_GAIN)
        assert inner[0] == root and len(inner) == len(leaves) - 1
        assert sorted(int(c) for x in inner for c in t.child[x]) == sorted(leaves + inner[1:])
        expandable = [x for x in leaves if t.child[x, 0] >= 0]
        assert len(leaves) == n or not expandable
        if expandable and len(inner) > 1:
            smallest = min(t.area[x] for x in inner[1:])
            assert smallest >= max(t.area[x] for x in expandable) * (1 - 2 * MIN_GAIN)


@settings(max_examples=examples(15))
@given(tree_cases)
def test_restructure_equals_reference(case):
    tree, plo, phi = random_tree(*case)
    result = treelet.restructure(tree, split_axes=False)
    expected, info = ref.restructure(tree, max_passes=treelet.DEFAULT_MAX_PASSES)
    assert result.steps == info["passes"] and result.moves == info["restructured"]
    assert_same_tree(result.tree, expected)
    history = result.history[: result.steps]
    np.testing.assert_allclose(history, info["history"], rtol=1e-5)
    assert np.isnan(result.history[result.steps:]).all()
    sah = check_result(tree, result, plo, phi)
    assert np.all(np.diff(np.concatenate([[float(result.sah_start)], history])) <= 1e-5 * sah)


def test_smaller_treelets_and_windows():
    tree, plo, phi = random_tree(9, 40, 2)
    a = treelet.restructure(tree, leaves=4, split_axes=False)
    expected, _ = ref.restructure(tree, leaves=4)
    assert_same_tree(a.tree, expected)
    check_result(tree, a, plo, phi)
    b = treelet.restructure(tree, split_axes=False)
    c = treelet.restructure(tree, split_axes=False, windows=(3,))  # speed only
    assert_same_tree(b.tree, c.tree)
    assert float(b.sah) <= float(a.sah) * (1 + 1e-6)  # 7 leaves see more than 4


def test_passes_solve_only_fresh_treelets():
    """A pass solves only the fresh nodes (a treelet rewrote them or a node below them):
    every other node, solved again, would change nothing; the pass that changes nothing
    leaves none fresh; ``resume`` after a move keeps the flags of the nodes it left alone."""
    tree = random_tree(9, 40, 2)[0]  # the capacity and program of test_smaller_treelets_and_windows
    interior = np.asarray(tree.left) >= 0
    state, skipped = treelet.init(tree, treelet.Config(split_axes=False)), 0  # result keeps the links
    while not bool(state.progress.done):
        state = driver.advance(treelet.step, state, state.progress.step + 1)
        fresh = np.asarray(state.inner.fresh)
        for node in np.nonzero(interior & ~fresh)[0]:
            assert not bool(treelet.solve(state, int(node)).improves), node
            skipped += 1
    assert bool(state.progress.converged) and state.progress.step > 1 and skipped > 0
    assert not fresh[interior].any()
    out = treelet.result(state).tree
    assert not np.asarray(treelet.resume(state, out).inner.fresh)[interior].any()
    parent, left, right = np.asarray(out.parent), np.array(out.left), np.array(out.right)
    moved = int(np.nonzero(interior & (parent >= 0))[0][0])  # a "move": its children swap sides
    left[moved], right[moved] = right[moved], left[moved]
    resumed = treelet.resume(state, out.replace(left=left, right=right))
    path, node = [], moved
    while node >= 0:
        path, node = path + [node], parent[node]
    assert sorted(np.nonzero(np.asarray(resumed.inner.fresh))[0]) == sorted(path)


def test_window_sizes_by_capacity():
    """Speed only: one window size below SMALL_WINDOWS_FROM nodes, a small one beside it
    from there on (legocar's real-tree test below runs that one against the twin); given
    windows are kept."""
    assert treelet.window_sizes(treelet.SMALL_WINDOWS_FROM - 1) == treelet.WINDOWS_SMALL_TREE == (256,)
    assert treelet.window_sizes(treelet.SMALL_WINDOWS_FROM) == treelet.WINDOWS_LARGE_TREE == (256, 16)
    assert treelet.window_sizes(1 << 20, (3,)) == (3,)
    tree = random_tree(9, 40, 2)[0]
    assert treelet.init(tree).static.windows == treelet.WINDOWS_SMALL_TREE
    assert treelet.init(tree, treelet.Config(windows=(5, 2))).static.windows == (5, 2)


def test_split_axes_is_a_traced_setting():
    """Runs with and without Kensler's split-axis pass share one compiled loop and one
    compiled result (``split_axes`` is a traced Param, as reinsertion's)."""
    tree, plo, phi = random_tree(14, 30, 2)
    treelet.restructure(tree, split_axes=False)
    before = driver.advance._cache_size(), driver.finish._cache_size()
    with_axes = treelet.restructure(tree, split_axes=True)
    assert (driver.advance._cache_size(), driver.finish._cache_size()) == before
    check_result(tree, with_axes, plo, phi)
    assert_same_tree(with_axes.tree, jaxbvh.tree.assign_split_axes(treelet.restructure(tree, split_axes=False).tree),
                     fields=("axis", "lo", "hi"))


def test_time_budget_progress_float64_and_tiny_trees():
    tree, plo, phi = random_tree(12, 60, 1)
    log = []
    full = treelet.restructure(tree, on_step=lambda info: log.append((info.step, info.sah, info.moves)))
    assert [i for i, *_ in log] == list(range(full.steps)) and log[-1][2] == 0
    assert bool(full.converged) and [info.stage for info in full.trace] == ["treelet"] * int(full.steps)
    short = treelet.restructure(tree, time_budget=1e-9)
    check_result(tree, short, plo, phi)  # compiling comes before the budget: the first chunk runs
    assert short.steps == 1 < full.steps and not short.converged
    for n in (1, 2, 3):
        small, slo, shi = random_tree(n, n)
        check_result(small, treelet.restructure(small), slo, shi)
    with jax.enable_x64(True):
        tree64, plo64, phi64 = random_tree(4, 30, 2, dtype=np.float64)
        result64 = treelet.restructure(tree64, split_axes=False)
        assert np.asarray(result64.tree.lo).dtype == np.float64
        check_result(tree64, result64, plo64, phi64)
        assert_same_tree(result64.tree, ref.restructure(tree64)[0])


def test_bad_arguments_raise_value_error():
    tree = random_tree(0, 5)[0]
    for kwargs in (dict(leaves=1), dict(leaves=treelet.MAX_LEAVES + 1), dict(max_passes=-1),
                   dict(ct=-1.0), dict(windows=()), dict(time_budget=0), dict(on_step=1),
                   dict(min_gain=-1.0)):
        with pytest.raises(ValueError):
            treelet.restructure(tree, **kwargs)


@pytest.mark.skipif(not (SHARED_DATA / "trees").exists(), reason=f"shared data not found at {SHARED_DATA}")
def test_real_tree_pass_equals_reference():
    tree, _ = jaxbvh.load(SHARED_DATA / "trees" / "legocar_binned_ref.npz")
    result = treelet.restructure(tree, max_passes=1, split_axes=False)
    expected, info = ref.restructure(tree, max_passes=1)
    assert_same_tree(result.tree, expected)
    assert result.moves == info["restructured"] > 0
    check_result(tree, result, None, None)
    assert float(result.sah) < float(result.sah_start) - 1.0
    assert NODES  # random trees share one capacity with test_reinsert
