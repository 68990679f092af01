"""Splitting leaves into one-primitive leaves (jaxbvh.optimize.split) against its twin."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_same_tree, boxes
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.optimize import split_reference
from jaxbvh.optimize.split import split_leaves
from jaxbvh.testing.strategies import trees
from jaxbvh.tree.layout import pad_to

ALL = ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "axis", "prim_index", "root")
NODES, PRIMS = 64, 32  # one capacity for every drawn tree: one compiled program


def split(tree, lo, hi):
    out, overflow = split_leaves(jaxbvh.to_jax(tree), jnp.asarray(lo), jnp.asarray(hi))
    return jaxbvh.to_numpy(out), bool(overflow)


def primitives_of_leaves(t):
    """Sorted multiset of the references each real leaf holds, and the leaves' sizes."""
    t = jaxbvh.to_numpy(t)
    leaf = (t.left < 0) & (t.prim_count > 0)
    runs = [t.prim_index[s:s + c] for s, c in zip(t.prim_start[leaf], t.prim_count[leaf])]
    return np.sort(np.concatenate(runs)), t.prim_count[leaf]


@settings(max_examples=40, deadline=None)
@given(built=st.integers(1, 8).flatmap(lambda leaf: trees(min_size=1, max_size=24, max_leaf=leaf)))
def test_split_equals_its_twin_and_leaves_one_primitive_per_leaf(built):
    tree = pad_to(built.tree, NODES, PRIMS)
    lo, hi = np.asarray(built.lo), np.asarray(built.hi)
    got, overflow = split(tree, lo, hi)
    want, want_overflow = split_reference.split_leaves(tree, lo, hi)
    assert_same_tree(got, want, fields=ALL)
    assert overflow == want_overflow is False  # 2P - 1 nodes always fit
    jaxbvh.validate(got, lo, hi)
    before, sizes_before = primitives_of_leaves(tree)
    after, sizes_after = primitives_of_leaves(got)
    np.testing.assert_array_equal(after, before)  # the same references, each in one leaf
    assert np.all(sizes_after == 1)
    # leaves that were single already are untouched
    t = jaxbvh.to_numpy(tree)
    single = (t.left < 0) & (t.prim_count == 1)
    np.testing.assert_array_equal(got.lo[single], t.lo[single])
    np.testing.assert_array_equal(got.prim_index[t.prim_start[single]], t.prim_index[t.prim_start[single]])


@settings(max_examples=15, deadline=None)
@given(built=trees(min_size=6, max_size=20, max_leaf=6, padding=False))
def test_a_tight_capacity_splits_what_fits_and_says_so(built):
    """No padding: the tree's own node count, far below 2P - 1 when leaves are large."""
    t = jaxbvh.to_numpy(built.tree)
    tree = pad_to(t, t.parent.shape[0] + 2, t.prim_index.shape[0])  # room for one cut, perhaps not all
    lo, hi = np.asarray(built.lo), np.asarray(built.hi)
    got, overflow = split(tree, lo, hi)
    want, want_overflow = split_reference.split_leaves(tree, lo, hi)
    assert_same_tree(got, want, fields=ALL)
    assert overflow == want_overflow
    jaxbvh.validate(got, lo, hi)
    leaf = (t.left < 0) & (t.prim_count > 0)
    needed = 2 * int(np.sum(t.prim_count[leaf] - 1))  # two new nodes per cut
    free = t.parent.shape[0] - int(np.sum((t.left >= 0) | leaf))
    assert overflow == (needed > free)


def test_split_then_merge_gives_back_a_tree_no_dearer_than_the_leaves():
    """Splitting raises the SAH of a leaf of coincident primitives; the exact merge takes it
    back: a leaf of four equal boxes splits into 7 nodes and merges into one leaf again."""
    from jaxbvh.optimize.leaves import merge_leaves

    lo = np.zeros((4, 3), np.float32)
    hi = np.ones((4, 3), np.float32)
    built = jaxbvh.testing.trees.make_tree(lo, hi, jaxbvh.testing.trees.Choices(np.random.default_rng(0)),
                                           max_leaf=4, nodes=8, prims=4)
    t = jaxbvh.to_numpy(built.tree)
    assert int(np.max(t.prim_count)) == 4  # the case under test: one leaf of all four
    got, overflow = split(t, lo, hi)
    assert not overflow and int(np.sum(got.left >= 0)) == 3
    assert float(jaxbvh.sah(got)) > float(jaxbvh.sah(t))
    dt = got.lo.dtype
    back = jaxbvh.to_numpy(merge_leaves(jaxbvh.to_jax(got), jnp.int32(4), jnp.asarray(1, dt), jnp.asarray(1, dt)))
    assert float(jaxbvh.sah(back)) == pytest.approx(float(jaxbvh.sah(t)))


def test_a_tree_with_references_stays_valid():
    """SBVH references: a leaf's boxes are clipped triangles; the halves stay inside the leaf."""
    from test_sbvh_trees import crossing_slivers

    from jaxbvh.builders import SBVHConfig, build_sbvh

    tri = crossing_slivers()
    from jaxbvh.optimize.leaves import merge_leaves

    built = build_sbvh(tri, SBVHConfig(bins=8, max_leaf=1, reference_capacity=4))
    assert int(built.references) > tri.shape[0]
    # a dear traversal step: leaves of several clipped references
    tree = jaxbvh.to_jax(built.tree)
    t = jaxbvh.to_numpy(merge_leaves(tree, jnp.int32(4), jnp.asarray(4.0, tree.lo.dtype), jnp.asarray(1.0, tree.lo.dtype)))
    assert int(np.max(t.prim_count)) > 1  # the case under test
    lo, hi = boxes(tri)
    got, overflow = split(t, lo.astype(np.float32), hi.astype(np.float32))
    want, _ = split_reference.split_leaves(t, lo.astype(np.float32), hi.astype(np.float32))
    assert_same_tree(got, want, fields=ALL)
    assert not overflow
    jaxbvh.validate(got, lo, hi, references=True, triangles=tri)


def test_the_pipeline_given_the_primitives_optimizes_the_split_tree():
    """``prims`` given: the pipeline runs on the split tree (the same result as on the twin's
    split tree by hand), and its final merge makes every leaf, at most ``max_leaf``, even
    where the input's leaves were larger."""
    from jaxbvh.optimize import optimize, pipeline
    from jaxbvh.testing import random_tree

    tree, lo, hi = random_tree(3, 40, 8)
    t = jaxbvh.to_numpy(tree)
    assert int(np.max(t.prim_count)) > 2  # the case under test: leaves above the limit
    got = pipeline.pipeline(tree, prims=(lo, hi), max_leaf=2)
    by_hand = optimize(split_reference.split_leaves(tree, lo, hi)[0], "pipeline", max_leaf=2)
    assert_same_tree(got.tree, by_hand.tree, fields=ALL)
    jaxbvh.validate(got.tree, lo, hi)
    out = jaxbvh.to_numpy(got.tree)
    assert np.all(out.prim_count[out.left < 0] <= 2)
    assert float(got.sah) <= float(jaxbvh.sah(t)) * (1 + 1e-6)  # this poor tree: far above


def test_the_pipeline_grows_a_compact_tree_to_hold_the_split():
    """A compact tree (a saved one: capacity of its own node count) cannot hold one leaf
    per primitive; given ``prims`` the pipeline grows it and splits every leaf: with
    ``max_leaf`` 1 (no merge) every leaf of the result holds one primitive."""
    from jaxbvh.optimize import pipeline
    from jaxbvh.testing import random_tree
    from jaxbvh.tree.interchange import compact

    tree, lo, hi = random_tree(5, 40, 6)
    small = compact(tree)
    t = jaxbvh.to_numpy(small)
    leaf = t.left < 0
    assert t.left.shape[0] < 2 * int(t.prim_count[leaf].sum()) - 1  # the case under test
    got = pipeline.pipeline(small, prims=(lo, hi), max_leaf=1)
    out = jaxbvh.to_numpy(got.tree)
    jaxbvh.validate(out, lo, hi)
    assert np.all(out.prim_count[(out.left < 0) & (out.prim_count > 0)] == 1)
