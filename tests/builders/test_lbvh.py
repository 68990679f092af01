"""LBVH (jaxbvh.lbvh) and the Morton keys it sorts: equal to the NumPy twins, valid, one compile per bucket."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import canonical, local_boxes, padded
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import box_sets, triangle_soups

import jaxbvh
from jaxbvh.builders import lbvh, morton
from jaxbvh.builders import lbvh_reference as reference
from jaxbvh.builders import morton_reference as reference_morton
from jaxbvh.builders.configs import LBVHConfig, make_config
from jaxbvh.numerics import scene_scale
from jaxbvh.testing.plugin import examples


def build(lo, hi, max_leaf=1, morton_bits=30):
    """LBVH at the fixed test capacity (what jaxbvh.build does, padded further)."""
    return lbvh.build(*padded(lo, hi), lo.shape[0], scene_scale(lo, hi),
                      LBVHConfig(max_leaf=max_leaf, morton_bits=morton_bits))


@settings(max_examples=examples(15))
@given(data=box_sets(max_size=48), bits=st.sampled_from(morton.CODE_BITS), max_leaf=st.sampled_from([1, 3]))
def test_lbvh_equals_reference(data, bits, max_leaf):
    lo, hi = data
    got = build(lo, hi, max_leaf, bits)
    jaxbvh.validate(got, lo, hi)
    want = reference.build(lo, hi, LBVHConfig(max_leaf=max_leaf, morton_bits=bits))
    jaxbvh.validate(want, lo, hi)
    assert canonical(got) == canonical(want)
    assert np.asarray(got.prim_count).max() <= max_leaf


@settings(max_examples=examples(15))
@given(tri=triangle_soups(max_size=40), bits=st.sampled_from(morton.CODE_BITS), max_leaf=st.sampled_from([1, 4]))
def test_lbvh_equals_reference_on_extreme_soups(tri, bits, max_leaf):
    """Degenerate, flat, one-point and grid scenes, scales 1e-30 .. 1e30, duplicate centres."""
    lo, hi = local_boxes(tri)
    got = build(lo, hi, max_leaf, bits)
    jaxbvh.validate(got, lo, hi)
    assert canonical(got) == canonical(reference.build(lo, hi, LBVHConfig(max_leaf=max_leaf, morton_bits=bits)))


@settings(max_examples=examples(8))
@given(data=box_sets(min_size=2, max_size=40), bits=st.sampled_from(morton.CODE_BITS))
def test_float64_lbvh_equals_reference(data, bits):
    with jax.enable_x64(True):
        lo, hi = (a.astype(np.float64) for a in data)
        got = build(lo, hi, 2, bits)
        assert got.lo.dtype == np.float64
        jaxbvh.validate(got, lo, hi)
        assert canonical(got) == canonical(reference.build(lo, hi, LBVHConfig(max_leaf=2, morton_bits=bits)))


@given(tri=triangle_soups(max_size=40), bits=st.sampled_from(morton.CODE_BITS))
def test_keys_equal_reference_keys(tri, bits):
    lo, hi = local_boxes(tri)
    n = lo.shape[0]
    origin, scale = morton.quantization(*padded(lo, hi), n, bits)
    with morton.x64():
        keys = jax.jit(partial(morton.keys, bits=bits))(*map(jnp.asarray, padded(lo, hi)), jnp.int32(n),
                                                        jnp.asarray(origin), jnp.asarray(scale))
        keys = [int(k) for k in np.asarray(keys)]
    assert keys[:n] == reference_morton.keys(lo, hi, bits)
    assert all(k >> 63 == 1 for k in keys[n:])  # padding sorts last


def test_interleave_puts_x_highest():
    assert reference_morton.interleave(1, 0, 0, 10) == 0b100
    assert reference_morton.interleave(0, 1, 0, 10) == 0b010
    assert reference_morton.interleave(0, 0, 1, 10) == 0b001
    assert reference_morton.interleave(2, 0, 0, 10) == 0b100000
    with morton.x64():
        for per_axis in (10, 21):
            q = np.array([0, 1, 2, 5, 2 ** per_axis - 1], np.uint64)
            got = np.asarray(morton.spread_bits(jnp.asarray(q), per_axis))
            assert [int(g) for g in got] == [reference_morton.interleave(int(v), 0, 0, per_axis) >> 2 for v in q]


def test_split_axes_order_the_children():
    """An interior node's axis is that of its Morton bit: every left centre lies below every right one."""
    rng = np.random.default_rng(3)
    c = rng.random((200, 3)) * np.array([1.0, 0.3, 2.0])
    lo, hi = (c - 0.01).astype(np.float32), (c + 0.01).astype(np.float32)
    t = jaxbvh.to_numpy(jaxbvh.build(lo, hi, method="lbvh"))
    centre = 0.5 * lo + 0.5 * hi

    def prims(node):
        if t.prim_count[node] > 0:
            return t.prim_index[t.prim_start[node]:t.prim_start[node] + t.prim_count[node]].tolist()
        return prims(t.left[node]) + prims(t.right[node])

    interior = np.flatnonzero(t.left >= 0)
    assert (t.axis[interior] >= 0).all()  # distinct codes here: every split is a Morton bit
    for node in interior:
        a = t.axis[node]
        assert centre[prims(t.left[node]), a].max() < centre[prims(t.right[node]), a].min()


def test_one_and_two_primitives_and_duplicates():
    lo = np.zeros((1, 3), np.float32)
    tree = jaxbvh.build(lo, lo + 1, method="lbvh")
    jaxbvh.validate(tree, lo, lo + 1)
    assert jaxbvh.tree.node_count(tree) == 1 and int(tree.root) == 0
    lo2 = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    tree = jaxbvh.to_numpy(jaxbvh.build(lo2, lo2 + 1, method="lbvh"))
    jaxbvh.validate(tree, lo2, lo2 + 1)
    assert jaxbvh.tree.node_count(tree) == 3 and tree.axis[0] == 0
    # 48 primitives with one centre: split by id bits, so balanced; axes -1
    same = np.zeros((48, 3), np.float32)
    tree = jaxbvh.to_numpy(jaxbvh.build(same, same + 1, method="lbvh", max_leaf=1))
    jaxbvh.validate(tree, same, same + 1)
    assert jaxbvh.tree.depth(tree).max() == 6
    assert (tree.axis[tree.left >= 0] == -1).all()


@pytest.mark.parametrize("method", ["lbvh", "ploc"])
def test_small_subtrees_collapse_by_the_sah_test(method):
    """Eight far-apart groups of four identical boxes: with max_leaf 4 each group is one leaf."""
    rng = np.random.default_rng(5)
    corner = rng.permutation(np.stack(np.meshgrid([0, 10], [0, 10], [0, 10]), -1).reshape(-1, 3))
    lo = np.repeat(corner, 4, axis=0).astype(np.float32)
    hi = lo + 1
    for max_leaf, leaves in ((4, 8), (3, 16), (1, 32)):
        t = jaxbvh.to_numpy(jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf))
        jaxbvh.validate(t, lo, hi)
        sizes = t.prim_count[t.prim_count > 0]
        assert len(sizes) == leaves and sizes.max() <= max_leaf
        if max_leaf == 4:
            for leaf in np.flatnonzero(t.prim_count):
                ids = t.prim_index[t.prim_start[leaf]:t.prim_start[leaf] + 4]
                assert len(set(ids // 4)) == 1  # one group per leaf


@pytest.mark.parametrize("method", ["lbvh", "ploc"])
def test_a_leaf_that_costs_what_its_split_costs_stays_a_leaf(method):
    """Two flat unit squares side by side: Ci N = 2 = Ct + Ci (1 + 1) / 2 exactly; a tie keeps the leaf."""
    lo = np.array([[0, 0, 0], [1, 0, 0]], np.float32)
    hi = np.array([[1, 1, 0], [2, 1, 0]], np.float32)
    for max_leaf, nodes in ((2, 1), (1, 3)):
        tree = jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf)
        jaxbvh.validate(tree, lo, hi)
        assert jaxbvh.tree.node_count(tree) == nodes
        assert jaxbvh.tree.node_count(reference.build(lo, hi, LBVHConfig(max_leaf=max_leaf))) == nodes


def test_sizes_in_one_capacity_bucket_compile_once():
    rng = np.random.default_rng(1)
    sizes = [13, 14, 15, 16]
    assert {jaxbvh.capacity_bucket(n) for n in sizes} == {16}
    start = lbvh.topology._cache_size(), lbvh.assemble._cache_size()
    for n in sizes:
        lo = rng.random((n, 3)).astype(np.float32)
        jaxbvh.build(lo, lo + 0.1, method="lbvh", max_leaf=n % 3 + 2)  # max_leaf is traced
    assert lbvh.topology._cache_size() - start[0] <= 1
    assert lbvh.assemble._cache_size() - start[1] <= 1


def test_bad_options_get_clear_errors():
    lo = np.zeros((3, 3), np.float32)
    with pytest.raises(ValueError, match="morton_bits"):
        jaxbvh.build(lo, lo, method="lbvh", morton_bits=32)
    with pytest.raises(ValueError, match="no primitives"):
        jaxbvh.build(np.zeros((0, 3)), np.zeros((0, 3)), method="lbvh")
    with pytest.raises(ValueError, match="NaN"):
        jaxbvh.build(np.array([[np.nan, 0, 0]]), np.zeros((1, 3)), method="lbvh")


@pytest.mark.parametrize("method", ["lbvh", "ploc"])
def test_build_dispatch_keeps_dtype_padding_and_the_twin(method):
    """jaxbvh.build (checked, cast and padded by jaxbvh.builders.inputs.prepare) gives the twin's tree in every mode:
    float32 padded to the capacity bucket, unpadded (pad=False), float64 under x64."""
    from jaxbvh.builders import ploc_reference as reference_ploc
    from jaxbvh.builders.inputs import narrow_outward

    rng = np.random.default_rng(11)
    c = np.round(rng.uniform(-1, 1, (37, 3)) * 4) / 4  # shared centres: ties and duplicate codes
    lo, hi = c - 0.1, c + rng.uniform(0.1, 0.3, (37, 3))
    twin = reference.build if method == "lbvh" else reference_ploc.build
    options = dict(morton_bits=63, max_leaf=2) if method == "lbvh" else dict(radius=3, max_leaf=2)
    lo32, hi32 = narrow_outward(lo, hi, np.float32)  # float64 narrowed as every builder does: outward
    config = make_config(method, **options)
    want32 = canonical(twin(lo32, hi32, config))
    for pad, slots in ((True, 2 * jaxbvh.capacity_bucket(37)), (False, 2 * 37)):
        tree = jaxbvh.build(lo, hi, method=method, pad=pad, **options)  # float64 input, x64 off: float32
        assert tree.lo.dtype == np.float32 and tree.lo.shape == (slots, 3) and tree.left.shape == (slots,)
        jaxbvh.validate(tree, lo, hi)  # the boxes as given
        assert canonical(tree) == want32
    with jax.enable_x64(True):
        tree = jaxbvh.build(lo, hi, method=method, **options)
        assert tree.lo.dtype == np.float64
        jaxbvh.validate(tree, lo, hi)
        assert canonical(tree) == canonical(twin(lo, hi, config))
