"""Cost targets (jaxbvh.tree.targets): the table's rule, the costs against the NumPy twins,
and optimizing for a target lowers that target's cost."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from helpers import random_tree, tree_cases
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.configs import DEFAULT_MAX_LEAF
from jaxbvh.optimize import leaves_reference, optimize
from jaxbvh.tree import cost_reference, targets
from jaxbvh.wide import collapse_reference

NAMES = tuple(targets.TARGETS)


@given(name=st.sampled_from(NAMES), ct=st.none() | st.floats(0, 8), ci=st.none() | st.floats(0, 8),
       max_leaf=st.none() | st.integers(1, 16))
def test_explicit_values_win_over_the_target(name, ct, ci, max_leaf):
    target = targets.TARGETS[name]
    got = targets.costs(name, ct=ct, ci=ci, max_leaf=max_leaf)
    assert got == {"ct": target.ct if ct is None else ct, "ci": target.ci if ci is None else ci,
                   "max_leaf": target.max_leaf if max_leaf is None else max_leaf}
    assert targets.costs(target) == targets.costs(name)  # a Target stands for its name


def test_the_default_target_is_the_classic_sah():
    default = targets.get(None)
    assert default.name == targets.DEFAULT_TARGET == "sah"
    assert (default.ct, default.ci, default.width) == (1.0, 1.0, 2)
    assert default.max_leaf == DEFAULT_MAX_LEAF


def test_unknown_target_names_every_target():
    with pytest.raises(ValueError) as error:
        targets.get("tinybvh-bvh16")
    assert "tinybvh-bvh16" in str(error.value)
    assert all(name in str(error.value) for name in NAMES)


def test_table_is_consistent():
    for name, t in targets.TARGETS.items():
        assert t.name == name
        assert t.ct > 0 and t.ci > 0 and t.node_ct > 0 and t.max_leaf >= 1 and t.width >= 2
        if t.width == 2:
            assert t.node_ct == t.ct  # a binary layout's node is the optimizers' node


@settings(max_examples=15, deadline=None)
@given(case=tree_cases, name=st.sampled_from(NAMES))
def test_target_cost_equals_the_twins(case, name):
    """A binary target's cost is the SAH at its constants; a wide one's is the NumPy
    twins' leaf merge (every subtree of <= max_leaf primitives) and optimal collapse."""
    tree, _, _ = random_tree(*case)
    t = jaxbvh.to_numpy(tree)
    target = targets.get(name)
    got = targets.target_cost(t, name)
    if target.width == 2 and not target.merge_leaves:
        want = cost_reference.sah(t, target.ct, target.ci)
    else:
        merged = leaves_reference.merge_leaves(t, target.max_leaf, target.max_leaf + 1.0, 1.0)
        test_cost = lambda k: target.node_ct * -(-np.asarray(k) // target.width)  # noqa: E731
        _, children, new_leaves = collapse_reference.optimal(merged, max_children=target.width,
                                                             test_cost=test_cost, ci=target.ci)
        r, leaves = collapse_reference.rcost(merged, children, new_leaves, test_cost=test_cost, ci=target.ci)
        want = r + leaves
    assert got == pytest.approx(float(want), rel=1e-4)


def test_explicit_values_change_the_cost():
    tree, _, _ = random_tree(3, 30, 1)
    base = targets.target_cost(tree, "tinybvh-bvh8")
    assert targets.target_cost(tree, "tinybvh-bvh8", ci=2 * targets.get("tinybvh-bvh8").ci) > base
    assert targets.target_cost(tree, "sah", ct=3.0) == pytest.approx(
        float(cost_reference.sah(jaxbvh.to_numpy(tree), 3.0, 1.0)), rel=1e-6)


@pytest.mark.parametrize("name", ["tinybvh-bvh8", "tinybvh-soa"])
def test_optimizing_for_a_target_lowers_its_cost(name):
    """The pipeline with ``target=`` ends below the start tree in that target's cost, and
    runs with the target's constants (its leaves stay within the target's limit)."""
    start, lo, hi = random_tree(11, 40, 1)  # a poor tree: much to gain
    result = optimize(start, "pipeline", target=name, max_rounds=2)
    before, after = targets.target_cost(start, name), targets.target_cost(result.tree, name)
    assert after < before
    sizes = np.asarray(result.tree.prim_count)
    assert sizes.max() <= targets.get(name).max_leaf
    jaxbvh.validate(result.tree, lo, hi)
    assert math.isfinite(after)


def test_optimize_target_gives_way_to_explicit_options():
    tree, _, _ = random_tree(5, 20, 1)
    with_target = optimize(tree, "treelet", target="tinybvh-bvh8", ct=0.5, max_passes=1)
    plain = optimize(tree, "treelet", ct=0.5, ci=targets.get("tinybvh-bvh8").ci, max_passes=1)
    np.testing.assert_array_equal(np.asarray(with_target.tree.left), np.asarray(plain.tree.left))
    with pytest.raises(ValueError, match="tinybvh-bvh8"):
        optimize(tree, "treelet", target="bvh8")


def test_the_documented_table_is_the_code():
    """docs/optimizers.md's table of targets states TARGETS' values (the code is the source)."""
    page = (Path(__file__).resolve().parents[2] / "docs" / "optimizers.md").read_text()
    rows = {}
    for line in page.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and cells[0].startswith("`") and cells[0].split("`")[1] in targets.TARGETS:
            rows[cells[0].split("`")[1]] = [float(c) for c in cells[1:]]
    assert set(rows) == set(targets.TARGETS)
    for name, (ct, node_ct, ci, max_leaf, width) in rows.items():
        t = targets.TARGETS[name]
        assert (ct, node_ct, ci, max_leaf, width) == (t.ct, t.node_ct, t.ci, t.max_leaf, t.width), name
