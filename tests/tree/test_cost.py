"""Costs: the JAX evaluation equals the literal float64 reference, at every extreme."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import CAPACITY
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import boxes, triangle_soups

import jaxbvh
from jaxbvh.testing.plugin import examples
from jaxbvh.tree import cost_reference as reference
from jaxbvh.tree.frame import Frame

# float32 evaluation of a float32 tree vs float64 evaluation of the same boxes
FLOAT32_RTOL = 2e-5


def built(tri, method="sweep", max_leaf=1, dtype=np.float32):
    """The tree of ``tri`` (at most CAPACITY triangles) at the suite's one capacity: one
    program per builder and one per cost for every drawn size."""
    lo, hi = boxes(tri)
    frame = Frame.fit(lo, hi)
    llo, lhi = frame.to_local(lo).astype(dtype), frame.to_local(hi).astype(dtype)
    return jaxbvh.build(llo, lhi, method=method, max_leaf=max_leaf, dtype=dtype, capacity=CAPACITY)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(), method=st.sampled_from(jaxbvh.BOX_BUILDERS), max_leaf=st.sampled_from([1, 4]),
       ct=st.sampled_from([1.0, 0.3]), ci=st.sampled_from([1.0, 2.5]))
def test_costs_equal_reference(tri, method, max_leaf, ct, ci):
    tree = built(tri, method, max_leaf)
    got = jaxbvh.all_costs(tree, ct, ci)
    assert np.isfinite(list(got.values())).all()
    np.testing.assert_allclose(got["sah"], reference.sah(tree, ct, ci), rtol=FLOAT32_RTOL)
    np.testing.assert_allclose(got["ng_trifonov"], reference.ng_trifonov_cost(tree), rtol=FLOAT32_RTOL)
    np.testing.assert_allclose(got["goldsmith_salmon"], reference.goldsmith_salmon_cost(tree), rtol=FLOAT32_RTOL)
    # every node, not just the root
    per_node = np.asarray(jaxbvh.node_costs(tree, ct, ci))
    for node, want in reference.node_costs(tree, ct, ci).items():
        np.testing.assert_allclose(per_node[node], want, rtol=FLOAT32_RTOL)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(extreme=False, min_size=2), exponent=st.sampled_from([-30, -12, 0, 12, 30]),
       offset=st.sampled_from([0.0, 1e7]))
def test_float32_costs_hold_at_extreme_scales_without_a_frame(tri, exponent, offset):
    """Raw float32 coordinates at 1e+-30: areas neither overflow nor underflow."""
    lo, hi = boxes((tri + offset) * 10.0 ** exponent)
    tree = jaxbvh.build(lo.astype(np.float32), hi.astype(np.float32), capacity=CAPACITY)
    assert np.isfinite(float(jaxbvh.sah(tree)))
    np.testing.assert_allclose(float(jaxbvh.sah(tree)), reference.sah(tree), rtol=FLOAT32_RTOL)


@settings(max_examples=examples(12))
@given(tri=triangle_soups(min_size=2, max_size=24))
def test_float32_agrees_with_float64(tri):
    """The scene frame keeps float32 within FLOAT32_RTOL of float64 at 1e7 offsets and 1e+-30."""
    with jax.enable_x64(True):
        tree64 = built(tri, dtype=np.float64)
        sah64 = float(jaxbvh.sah(tree64))
        # the same tree, boxes rounded to float32
        tree32 = jaxbvh.to_numpy(tree64)
        tree32 = tree32.replace(lo=tree32.lo.astype(np.float32), hi=tree32.hi.astype(np.float32))
    sah32 = float(jaxbvh.sah(jaxbvh.to_jax(tree32)))
    assert jaxbvh.to_jax(tree32).lo.dtype == np.float32
    np.testing.assert_allclose(sah32, sah64, rtol=FLOAT32_RTOL)
    np.testing.assert_allclose(sah64, reference.sah(tree64), rtol=1e-12)


def test_costs_do_not_depend_on_scale_or_offset():
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(50, 3, 3))
    base = jaxbvh.all_costs(built(tri))
    for scale in (1e-30, 1e30):
        for offset in (0.0, 1e7):
            moved = jaxbvh.all_costs(built((tri + offset) * scale))
            for key in base:
                np.testing.assert_allclose(moved[key], base[key], rtol=1e-4)


def test_zero_area_root_uses_unit_weights():
    """All primitives in one point: every child is hit whenever its parent is."""
    n = 8
    lo = np.full((n, 3), 5.0, np.float32)
    tree = jaxbvh.build(lo, lo, max_leaf=1)  # n leaves of one primitive, n - 1 interior nodes
    costs = jaxbvh.all_costs(tree)
    interior = n - 1
    assert costs["sah"] == pytest.approx(interior * 1.0 + n * 1.0)
    assert costs["ng_trifonov"] == pytest.approx(interior)
    assert costs["goldsmith_salmon"] == pytest.approx(2 * interior)
    assert costs["sah"] == pytest.approx(reference.sah(tree))


def test_flat_scene_has_finite_positive_costs():
    rng = np.random.default_rng(4)
    tri = rng.normal(size=(40, 3, 3))
    tri[..., 1] = 0.0
    costs = jaxbvh.all_costs(built(tri))
    assert all(np.isfinite(v) and v > 0 for v in costs.values())


def test_two_primitives_by_hand():
    lo = np.array([[0, 0, 0], [3, 0, 0]], np.float32)
    hi = lo + 1
    tree = jaxbvh.build(lo, hi)
    # root box 4x1x1: half-area 4+1+4 = 9; each leaf 1x1x1: 3
    assert float(jaxbvh.sah(tree, 1.0, 1.0)) == pytest.approx(1 + (3 * 1 + 3 * 1) / 9)
    assert float(jaxbvh.sah(tree, 2.0, 3.0)) == pytest.approx(2 + (3 * 3 + 3 * 3) / 9)
    assert float(jaxbvh.goldsmith_salmon_cost(tree)) == pytest.approx(2.0)
