"""Builders: every tree valid, equal to the NumPy reference, few compiles, clear errors."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.frame import Frame
from jaxbvh.reference import build as reference
from strategies import box_sets, boxes, triangle_soups
from helpers import canonical

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def local_boxes(tri, dtype=np.float32):
    lo, hi = boxes(tri)
    frame = Frame.fit(lo, hi)
    return frame.to_local(lo).astype(dtype), frame.to_local(hi).astype(dtype)


@SETTINGS
@given(tri=triangle_soups(), method=st.sampled_from(jaxbvh.BUILDERS), max_leaf=st.sampled_from([1, 2, 8]))
def test_every_build_is_valid(tri, method, max_leaf):
    lo, hi = local_boxes(tri)
    tree = jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=8)
    jaxbvh.validate(tree, lo, hi)
    t = jaxbvh.to_numpy(tree)
    leaf_sizes = t.prim_count[t.prim_count > 0]
    assert leaf_sizes.max() <= max_leaf
    assert int(t.root) == 0


@SETTINGS
@given(data=box_sets(max_size=48), method=st.sampled_from(jaxbvh.BUILDERS), max_leaf=st.sampled_from([1, 3]),
       bins=st.sampled_from([4, 16]))
def test_jax_builder_equals_reference(data, method, max_leaf, bins):
    lo, hi = data
    got = jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=bins)
    want = reference.build(lo, hi, method=method, max_leaf=max_leaf, bins=bins)
    jaxbvh.validate(want, lo, hi)
    assert canonical(got) == canonical(want)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tri=triangle_soups(max_size=30), method=st.sampled_from(jaxbvh.BUILDERS))
def test_jax_builder_equals_reference_on_extreme_soups(tri, method):
    lo, hi = local_boxes(tri)
    got = jaxbvh.build(lo, hi, method=method, max_leaf=2, bins=8)
    want = reference.build(lo, hi, method=method, max_leaf=2, bins=8)
    assert canonical(got) == canonical(want)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=box_sets(min_size=9, max_size=16), method=st.sampled_from(jaxbvh.BUILDERS))
def test_float64_builder_equals_reference(data, method):
    with jax.enable_x64(True):
        lo, hi = (a.astype(np.float64) for a in data)
        got = jaxbvh.build(lo, hi, method=method, dtype=np.float64)
        assert got.lo.dtype == np.float64
        want = reference.build(lo, hi, method=method)
        jaxbvh.validate(got, lo, hi)
        assert canonical(got) == canonical(want)


def test_one_and_two_primitives():
    lo = np.zeros((1, 3), np.float32)
    tree = jaxbvh.build(lo, lo + 1)
    jaxbvh.validate(tree, lo, lo + 1)
    assert float(jaxbvh.sah(tree)) == 1.0  # one leaf: Ci * 1
    lo2 = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    tree = jaxbvh.build(lo2, lo2 + 1)
    jaxbvh.validate(tree, lo2, lo2 + 1)
    assert jaxbvh.tree.node_count(tree) == 3


def test_all_primitives_in_one_point_give_a_balanced_tree():
    lo = np.zeros((64, 3), np.float32)
    for method in jaxbvh.BUILDERS:
        tree = jaxbvh.build(lo, lo, method=method)
        jaxbvh.validate(tree, lo, lo)
        assert jaxbvh.tree.depth(tree).max() == 6  # log2(64): ties split in the middle


def test_sah_builders_beat_median_split():
    rng = np.random.default_rng(0)
    c = rng.random((300, 3)) ** 3  # clustered towards a corner
    lo, hi = (c - 0.01).astype(np.float32), (c + 0.01).astype(np.float32)
    cost = {m: float(jaxbvh.sah(jaxbvh.build(lo, hi, method=m))) for m in jaxbvh.BUILDERS}
    assert cost["sweep"] <= cost["binned"] * 1.02
    assert cost["sweep"] < cost["median"]


def test_sizes_in_one_capacity_bucket_compile_once():
    from jaxbvh.build import _build

    rng = np.random.default_rng(1)
    sizes = [13, 14, 15, 16]
    assert {jaxbvh.capacity_bucket(n) for n in sizes} == {16}
    start = _build._cache_size()
    for n in sizes:
        lo = rng.random((n, 3)).astype(np.float32)
        jaxbvh.build(lo, lo + 0.1, max_leaf=n % 3 + 1)  # leaf size is not a static argument
    assert _build._cache_size() - start <= 1


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3)), "no primitives"),
    (np.zeros((4, 2)), "shape"),
    (np.array([[0, 0, 0], [np.nan, 0, 0]]), "NaN"),
    (np.array([[0, 0, 0], [np.inf, 0, 0]]), "infinite"),
])
def test_bad_boxes_get_clear_errors(bad, message):
    with pytest.raises(ValueError, match=message):
        jaxbvh.build(bad, bad)


def test_bad_options_get_clear_errors():
    lo = np.zeros((3, 3))
    with pytest.raises(ValueError, match="unknown builder"):
        jaxbvh.build(lo, lo, method="octree")
    with pytest.raises(ValueError, match="max_leaf"):
        jaxbvh.build(lo, lo, max_leaf=0)
    with pytest.raises(ValueError, match="lo > hi"):
        jaxbvh.build(lo, lo - 1)
    with pytest.raises(ValueError, match="x64"):
        jaxbvh.build(lo, lo, dtype=np.float64)


def test_builder_vmaps_over_trials():
    """The level-synchronous engine runs under vmap (random trials build in one call)."""
    import jax.numpy as jnp
    from jaxbvh.build import _build, scene_scale

    rng = np.random.default_rng(7)
    lo = rng.random((3, 20, 3)).astype(np.float32)
    hi = lo + np.float32(0.05)

    def one(lo_i, hi_i):
        return _build(lo_i, hi_i, jnp.int32(20), jnp.int32(1), jnp.float32(1), jnp.float32(1),
                      jnp.float32(scene_scale(lo, hi)), method="sweep", bins=0)

    trees = jax.vmap(one)(jnp.asarray(lo), jnp.asarray(hi))
    for b in range(3):
        tree = jax.tree_util.tree_map(lambda x: x[b], trees)
        jaxbvh.validate(tree, lo[b], hi[b])
        assert canonical(tree) == canonical(jaxbvh.build(lo[b], hi[b], pad=False))
