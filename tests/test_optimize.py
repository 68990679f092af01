"""The optimizer entry point and the treelet + reinsertion pipeline (jaxbvh.optimize)."""

from __future__ import annotations

import numpy as np
import pytest

import jaxbvh
from jaxbvh import reinsert, rotate, treelet
from jaxbvh.optimize import METHODS, PIPELINE_TREELET_PASSES, optimize
from test_reinsert import assert_same_tree, random_tree


def check(tree, result, prim_lo, prim_hi):
    jaxbvh.validate(result.tree, prim_lo, prim_hi)
    t = jaxbvh.to_numpy(tree)
    leaf = t.prim_count > 0
    np.testing.assert_array_equal(result.tree.lo[leaf], t.lo[leaf])
    assert result.sah == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(result.tree))), rel=1e-6)
    assert result.sah <= result.sah_start * (1 + 1e-6)


def test_every_method_gives_a_valid_tree_and_reports_every_step():
    tree, plo, phi = random_tree(21, 50, 2)
    for method in METHODS:
        steps = []
        result = optimize(tree, method, on_step=lambda *a: steps.append(a),
                          **(dict(steps=12) if method == "sa" else {}))
        check(tree, result, plo, phi)
        assert steps and len(steps) == len(result.trace) >= result.steps > 0
        assert {stage for stage, *_ in steps} <= {method, "treelet", "reinsert"}


def test_pipeline_is_its_stages_in_rounds():
    """The pipeline's tree is the one the stages give when chained by hand."""
    tree, plo, phi = random_tree(22, 60, 1)
    result = optimize(tree, "pipeline", split_axes=False)
    t, sah = tree, float(jaxbvh.sah(jaxbvh.to_jax(tree)))
    for round_ in range(8):
        before = sah
        t = treelet.restructure(t, max_passes=PIPELINE_TREELET_PASSES, split_axes=False).tree
        r = reinsert.reinsert(t, split_axes=False, first_fraction=1 / 32 if round_ == 0 else 1.0)
        t, sah = r.tree, float(r.sah)
        if before - sah < 1e-3 * before:
            break
    assert_same_tree(result.tree, t)
    check(tree, result, plo, phi)
    axes = optimize(tree, "pipeline")  # with Kensler's split-axis pass: the same SAH
    assert axes.sah == pytest.approx(result.sah, rel=1e-6)
    assert_same_tree(axes.tree, rotate.assign_split_axes(result.tree), fields=("axis", "lo", "hi"))


def test_time_budget_and_bad_arguments():
    tree, plo, phi = random_tree(23, 60, 1)
    short = optimize(tree, "pipeline", time_budget=1e-9)
    check(tree, short, plo, phi)
    assert [stage for stage, *_ in short.trace] == ["treelet", "treelet"][: len(short.trace)]
    with pytest.raises(ValueError, match="method"):
        optimize(tree, "magic")
    with pytest.raises(ValueError, match="pipeline options"):
        optimize(tree, "pipeline", steps=3)
    with pytest.raises(ValueError, match="time_budget"):
        optimize(tree, "reinsert", time_budget=-1)
