"""Goldsmith–Salmon insertion build (jaxbvh.insertion) against its NumPy twin and the invariants.

All random cases are padded to one capacity so the jitted build compiles once per
``max_children``.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import local_boxes
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import box_sets, triangle_soups

import jaxbvh
from jaxbvh import numerics
from jaxbvh.builders import insertion
from jaxbvh.builders import insertion_reference as ref
from jaxbvh.testing.plugin import examples
from jaxbvh.tree import cost_reference as ref_cost

CAP = 48  # one capacity for every random case


def assert_equals_unpadded_reference(got, want, n):
    """The JAX tree equals the unpadded reference node by node; the rest is padding."""
    g = jaxbvh.to_numpy(got)
    real = 2 * n - 1
    k = want.child.shape[1]
    assert int(g.root) == int(want.root)
    np.testing.assert_array_equal(g.child[:real, :k], want.child)
    assert (g.child[:real, k:] == -1).all() and (g.child[real:] == -1).all()
    np.testing.assert_array_equal(g.parent[:real], want.parent)
    np.testing.assert_array_equal(g.lo[:real], want.lo)
    np.testing.assert_array_equal(g.hi[:real], want.hi)
    np.testing.assert_array_equal(g.prim_count[:real], want.prim_count)
    np.testing.assert_array_equal(g.prim_start[:real], want.prim_start)
    assert (g.prim_count[real:] == 0).all() and (g.parent[real:] == -1).all()


def order_of(seed, n):
    return np.random.default_rng(seed).permutation(n)


@settings(max_examples=examples(15))
@given(data=box_sets(max_size=CAP), seed=st.integers(0, 2**31), max_children=st.sampled_from([2, 3, 8]))
def test_jax_build_equals_reference_node_by_node(data, seed, max_children):
    lo, hi = data
    order = order_of(seed, lo.shape[0])
    got = insertion.build(lo, hi, order, max_children=max_children, capacity=CAP)
    want = ref.build(lo, hi, order, max_children=max_children)
    jaxbvh.validate(got, lo, hi)
    jaxbvh.validate(want, lo, hi)
    assert_equals_unpadded_reference(got, want, lo.shape[0])
    arity = (np.asarray(got.child) >= 0).sum(axis=1)
    assert arity.max() <= max_children
    assert float(jaxbvh.goldsmith_salmon_cost(got)) == pytest.approx(ref_cost.goldsmith_salmon_cost(want), rel=1e-5)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(max_size=CAP), seed=st.integers(0, 2**31))
def test_extreme_and_degenerate_soups(tri, seed):
    """Scales 1e-30 .. 1e30, flat and one-point scenes, many exact ties."""
    lo, hi = local_boxes(tri)
    order = order_of(seed, lo.shape[0])
    got = insertion.build(lo, hi, order, capacity=CAP)
    jaxbvh.validate(got, lo, hi)
    assert_equals_unpadded_reference(got, ref.build(lo, hi, order, max_children=insertion.DEFAULT_MAX_CHILDREN), lo.shape[0])
    cost = float(jaxbvh.goldsmith_salmon_cost(got))
    assert np.isfinite(cost) and cost >= 0


@given(data=box_sets(min_size=2, max_size=30), seed=st.integers(0, 2**31), max_children=st.sampled_from([2, 8]))
def test_insertion_costs_add_up_to_the_tree_cost(data, seed, max_children):
    """The candidate costs are exact: the increases chosen sum to sum(area x children)."""
    lo, hi = (a.astype(np.float64) for a in data)
    trace: list = []
    tree = ref.build(lo, hi, order_of(seed, lo.shape[0]), max_children=max_children, trace=trace)
    assert len(trace) == lo.shape[0] - 1
    assert sum(kind == "pair" for _, _, kind, _ in trace) == lo.shape[0] - 1 - sum(
        kind == "child" for _, _, kind, _ in trace)
    scale = numerics.scene_scale(lo, hi)
    root_area = numerics.half_area(tree.lo[int(tree.root)], tree.hi[int(tree.root)], scale)
    total = sum(increase for _, _, _, increase in trace)
    if root_area > 0:
        assert total / root_area == pytest.approx(ref_cost.goldsmith_salmon_cost(tree), rel=1e-9, abs=1e-12)


def test_tie_goes_to_the_nearest_centre():
    """Two equal leaves both hold the new box: it pairs with the one whose centre is nearer."""
    a = ([0, 0, 0], [2, 2, 2])
    b = ([1, 1, 1], [3, 3, 3])
    for c, partner in ((([1.3] * 3), 0), (([1.7] * 3), 1)):
        lo = np.array([a[0], b[0], c], np.float32)
        hi = np.array([a[1], b[1], np.add(c, 0.2)], np.float32)
        for tree in (insertion.build(lo, hi, [0, 1, 2]), ref.build(lo, hi, [0, 1, 2], max_children=insertion.DEFAULT_MAX_CHILDREN)):
            t = jaxbvh.to_numpy(tree)
            # root (node 3) pairs a and b; c pairs with its partner under node 4, in the partner's slot
            assert int(t.root) == 3
            assert t.child[3, :2].tolist() == ([4, 1] if partner == 0 else [0, 4])
            assert t.child[4, :2].tolist() == [partner, 2]


def test_child_beats_pair_for_an_object_that_fills_the_node():
    """A box as large as the root joins the root (cost A(root)) rather than pairing (2 A)."""
    lo = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0]], np.float32)
    hi = np.array([[1, 1, 1], [2, 1, 1], [2, 1, 1]], np.float32)
    for tree in (insertion.build(lo, hi), ref.build(lo, hi, max_children=insertion.DEFAULT_MAX_CHILDREN)):
        t = jaxbvh.to_numpy(tree)
        assert int(t.root) == 3 and t.child[3, :3].tolist() == [0, 1, 2]


def test_arity_cap_two_makes_a_binary_tree():
    rng = np.random.default_rng(0)
    lo = np.zeros((20, 3), np.float32)  # every box the same: each would join the root
    tree = insertion.build(lo, lo + 1, rng.permutation(20), max_children=2, capacity=CAP)
    jaxbvh.validate(tree, lo, lo + 1)
    arity = (np.asarray(tree.child) >= 0).sum(axis=1)
    assert set(arity[arity > 0].tolist()) == {2}
    wide = insertion.build(lo, lo + 1, rng.permutation(20), max_children=3, capacity=CAP)
    arity = (np.asarray(wide.child) >= 0).sum(axis=1)
    assert arity.max() == 3 and (arity == 3).sum() > 3  # the cap binds, again and again


def test_one_and_two_primitives():
    lo = np.zeros((1, 3), np.float32)
    tree = insertion.build(lo, lo + 1)
    jaxbvh.validate(tree, lo, lo + 1)
    assert int(tree.root) == 0 and float(jaxbvh.goldsmith_salmon_cost(tree)) == 0.0
    lo2 = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    tree = insertion.build(lo2, lo2 + 1, [1, 0])
    jaxbvh.validate(tree, lo2, lo2 + 1)
    assert int(tree.root) == 2 and np.asarray(tree.child)[2, :2].tolist() == [1, 0]


def test_batch_equals_single_builds_and_costs():
    rng = np.random.default_rng(1)
    lo = rng.uniform(-1, 1, (40, 3)).astype(np.float32)
    hi = lo + rng.uniform(0, 0.3, (40, 3)).astype(np.float32)
    orders = np.stack([rng.permutation(40) for _ in range(5)])
    trees, costs = insertion.build_batch(lo, hi, orders, capacity=CAP)
    for i, order in enumerate(orders):
        tree = insertion.tree_at(trees, i)
        jaxbvh.validate(tree, lo, hi)
        assert_equals_unpadded_reference(tree, ref.build(lo, hi, order, max_children=insertion.DEFAULT_MAX_CHILDREN), 40)
        assert float(costs[i]) == float(jaxbvh.goldsmith_salmon_cost(tree))


@settings(max_examples=examples(6))
@given(data=box_sets(min_size=9, max_size=24), seed=st.integers(0, 2**31))
def test_float64_build_equals_reference(data, seed):
    with jax.enable_x64(True):
        lo, hi = (a.astype(np.float64) for a in data)
        order = order_of(seed, lo.shape[0])
        got = insertion.build(lo, hi, order, dtype=np.float64, capacity=CAP)
        assert got.lo.dtype == np.float64
        jaxbvh.validate(got, lo, hi)
        assert_equals_unpadded_reference(got, ref.build(lo, hi, order, max_children=insertion.DEFAULT_MAX_CHILDREN), lo.shape[0])


def test_one_compile_per_capacity_bucket():
    rng = np.random.default_rng(2)
    sizes = (17, 20, 23)  # all in the bucket of 24
    before = insertion.insert_batch._cache_size()
    for n in sizes:
        lo = rng.uniform(0, 1, (n, 3)).astype(np.float32)
        insertion.build(lo, lo + 0.1, rng.permutation(n))
    assert insertion.insert_batch._cache_size() - before <= 1


def test_bad_input_is_refused_with_a_clear_error():
    lo = np.zeros((4, 3), np.float32)
    with pytest.raises(ValueError, match="permutation"):
        insertion.build(lo, lo + 1, [0, 1, 1, 2])
    with pytest.raises(ValueError, match="shape"):
        insertion.build(lo, lo + 1, [0, 1, 2])
    with pytest.raises(ValueError, match="max_children"):
        insertion.build(lo, lo + 1, max_children=1)
    with pytest.raises(ValueError, match="NaN"):
        insertion.build(np.full((2, 3), np.nan, np.float32), np.ones((2, 3), np.float32))
    with pytest.raises(ValueError, match="no primitives"):
        insertion.build(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    with pytest.raises(ValueError, match="capacity"):
        insertion.build(lo, lo + 1, capacity=2)
    with pytest.raises(ValueError, match=r"\[B, n\]"):
        insertion.build_batch(lo, lo + 1, np.zeros((0, 4), np.int32))
