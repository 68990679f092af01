"""The exact bottom-up leaf merge (jaxbvh.optimize.leaves) against its twin and a brute force."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_same_tree, random_tree, tree_cases
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.optimize import leaves_reference
from jaxbvh.numerics import half_area
from jaxbvh.optimize.leaves import merge_leaves
from jaxbvh.tree import cost_reference

ALL = ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "axis", "prim_index", "root")


def merged(tree, max_leaf, ct=1.0, ci=1.0):
    t = jaxbvh.to_jax(tree)
    dt = t.lo.dtype
    return jaxbvh.to_numpy(merge_leaves(t, jnp.int32(max_leaf), jnp.asarray(ct, dt), jnp.asarray(ci, dt)))


def all_costs(t, node, max_leaf, ct, ci):
    """Every SAH cost ``node``'s subtree can take by merging subtrees into leaves, and its
    primitive count (brute force, float64: every combination of the children's options)."""
    if t.left[node] < 0:
        return [ci * float(t.prim_count[node])], int(t.prim_count[node])
    a = {c: half_area(np.float64(t.lo[c]), np.float64(t.hi[c])) for c in (node, int(t.left[node]), int(t.right[node]))}
    left, nl = all_costs(t, int(t.left[node]), max_leaf, ct, ci)
    right, nr = all_costs(t, int(t.right[node]), max_leaf, ct, ci)
    s = a[node]
    keep = [ct + ((a[int(t.left[node])] * x + a[int(t.right[node])] * y) / s if s > 0 else x + y)
            for x, y in itertools.product(left, right)]
    keep = sorted(set(keep))[:64]  # the cheapest are what the minimum needs
    return keep + ([ci * (nl + nr)] if nl + nr <= max_leaf else []), nl + nr


@settings(max_examples=40, deadline=None)
@given(case=tree_cases, max_leaf=st.integers(1, 8), costs=st.sampled_from([(1.0, 1.0), (0.3, 1.0), (2.0, 0.5)]))
def test_merge_equals_its_twin_never_raises_the_sah_and_is_optimal(case, max_leaf, costs):
    tree, plo, phi = random_tree(*case)
    ct, ci = costs
    got = merged(tree, max_leaf, ct, ci)
    want = leaves_reference.merge_leaves(tree, max_leaf, ct, ci)
    assert_same_tree(got, want, fields=ALL)
    jaxbvh.validate(got, plo, phi)
    t = jaxbvh.to_numpy(tree)
    before, after = cost_reference.sah(t, ct, ci), cost_reference.sah(got, ct, ci)
    assert after <= before * (1 + 1e-6)
    best = min(all_costs(t, int(t.root), max_leaf, ct, ci)[0])
    assert after == pytest.approx(best, rel=1e-5)  # no other choice of merges is cheaper
    new = got.prim_count > np.where(t.left >= 0, 0, t.prim_count)  # leaves the merge made
    assert np.all(got.prim_count[new] <= max_leaf)
    if not new.any():  # nothing merged: the very same tree
        assert_same_tree(got, t, fields=ALL)


def test_max_leaf_one_merges_nothing_and_merging_twice_changes_nothing():
    tree, _, _ = random_tree(5, 40, 1)
    assert_same_tree(merged(tree, 1), tree, fields=ALL)
    once = merged(tree, 8, ct=4.0)  # a dear traversal step: leaves pay
    assert int(np.sum(once.prim_count > 1)) > 0  # the case under test: leaves were merged
    assert_same_tree(merged(once, 8, ct=4.0), once, fields=ALL)


def test_zero_area_subtrees_merge():
    """All boxes one point: every area is zero, children weigh 1, a leaf of N costs N
    against Ct + N split: everything up to max_leaf merges."""
    tree, plo, phi = random_tree(3, 12, 1, "point")
    got = merged(tree, 16)
    assert_same_tree(got, leaves_reference.merge_leaves(tree, 16), fields=ALL)
    assert int(np.sum(got.prim_count > 0)) == 1 and int(got.prim_count[int(got.root)]) == 12
    jaxbvh.validate(got, plo, phi)


def test_a_triangle_in_several_merged_leaves_is_kept_once():
    """SBVH leaves reference pieces of one triangle: the merged leaf holds it once, equal to
    the twin, and the tree stays valid in references mode."""
    from strategies import boxes
    from test_sbvh_trees import crossing_slivers

    from jaxbvh.builders import SBVHConfig, build_sbvh

    tri = crossing_slivers()
    built = build_sbvh(tri, SBVHConfig(bins=8, max_leaf=1, reference_capacity=4))
    assert int(built.references) > tri.shape[0]  # the case under test
    got = merged(built.tree, 16, ct=4.0)
    assert_same_tree(got, leaves_reference.merge_leaves(built.tree, 16, ct=4.0), fields=ALL)
    runs = [got.prim_index[s:s + c] for s, c in zip(got.prim_start, got.prim_count) if c > 0]
    assert all(len(set(r)) == len(r) for r in runs) and max(len(r) for r in runs) > 1
    assert int(np.sum(got.prim_count)) < int(built.references)  # duplicates went
    lo, hi = boxes(tri)
    jaxbvh.validate(got, lo, hi, references=True, triangles=tri)
    assert cost_reference.sah(got, 4.0) < cost_reference.sah(built.tree, 4.0)
