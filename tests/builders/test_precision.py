"""Precision-true builds (issue 39): every builder's tree contains its primitives *as given*.

Boxes and triangles are given in world coordinates (never the scene frame the other
builder tests use): float64 far from the origin or at scales 1e-30 .. 1e30, float32 at
subnormal (1e-40) and near-subnormal (1e-37) scales, float64 at 1e-310 under x64. Each
tree is checked by the testing kit against the inputs as given, so a box narrowed to
nearest (or a coordinate XLA flushed to zero) fails. Small inputs at one capacity per
builder keep the compiles few.
"""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.builders.configs import SBVHConfig
from jaxbvh.builders.inputs import narrow_outward
from jaxbvh.numerics import round_down, round_up
from jaxbvh.testing import assert_valid_tree
from jaxbvh.testing.plugin import examples
from jaxbvh.testing.strategies import boxes, triangle_soups

METHODS = list(jaxbvh.BUILDERS)
CAPACITY = 16  # primitive slots of the box builders: every input here has at most 16
SLOTS = 96     # reference slots of the SBVH (tests/builders/test_sbvh.py's capacity)

pytestmark = pytest.mark.filterwarnings("ignore:.*is coarse:UserWarning")


def build_and_check(tri, method, dtype=None):
    """Build ``method``'s tree of ``tri`` [n, 3, 3] (world coordinates, as given) and
    check it against the boxes and triangles as given."""
    lo, hi = boxes(tri)
    if method == "sbvh":
        tree = jaxbvh.build(lo, hi, SBVHConfig(bins=8, spatial_bins=4, dtype=dtype), triangles=tri,
                            capacity=SLOTS)
        assert_valid_tree(tree, lo, hi, references=True, triangles=tri)
    else:
        tree = jaxbvh.build(lo, hi, method=method, max_leaf=2, bins=8, capacity=CAPACITY, dtype=dtype)
        assert_valid_tree(tree, lo, hi)
    return tree


def soup(n=12, seed=0):
    """``n`` triangles of extent about 1 around the origin, float64 [n, 3, 3]."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, (n, 1, 3)) + rng.uniform(-0.25, 0.25, (n, 3, 3))


#: the fuzz cases of issue 39: (triangles, dtype given), each broke every builder
CASES = {
    "extent 1 at offset 1e7 (float64)": lambda: soup() + 1e7,
    "extent 1e-3 at offset 1e7 (float64)": lambda: soup() * 1e-3 + 1e7,
    "scale 1e30 (float64)": lambda: soup() * 1e30,
    "scale 1e-30 (float64)": lambda: soup() * 1e-30,
    "scale 1e-40, subnormal (float32)": lambda: (soup() * 1e-40).astype(np.float32),
    "scale 1e-37 (float32)": lambda: (soup() * 1e-37).astype(np.float32),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("method", METHODS)
def test_the_issue_39_fuzz_cases_give_valid_trees(method, case):
    build_and_check(CASES[case](), method)


def test_float64_at_1e_310_under_x64_gives_valid_trees():
    """Subnormal float64 coordinates: XLA flushes them to zero in float64 too."""
    tri = soup() * 1e-310
    with jax.enable_x64(True):
        for method in METHODS:
            tree = build_and_check(tri, method, dtype=np.float64)
            assert tree.lo.dtype == np.float64


def test_the_testing_kit_docs_example_at_offset_1e7():
    """docs/testing.md's first property, on our builder, at the soup hypothesis shrank it to."""
    tri = np.asarray([[[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [0.0, 1.0, 0.25]]]) + 1e7
    lo, hi = boxes(tri)
    tree = jaxbvh.build(lo, hi)
    assert_valid_tree(tree, lo, hi)


@settings(max_examples=examples(20))
@given(tri=triangle_soups(1, 16), method=st.sampled_from(METHODS), dtype=st.sampled_from([np.float64, np.float32]))
def test_every_builder_is_valid_at_any_offset_and_scale(tri, method, dtype):
    """triangle_soups' extremes: offsets up to 1e7 scene sizes, scales 1e-30 .. 1e30."""
    build_and_check(tri.astype(dtype), method)


@settings(max_examples=examples(10))
@given(tri=triangle_soups(1, 16, extreme=False), method=st.sampled_from(METHODS),
       scale=st.sampled_from([1e-45, 1e-40, 1e-38, 1e-37]))
def test_every_builder_is_valid_at_float32_subnormal_scales(tri, method, scale):
    build_and_check((tri * scale).astype(np.float32), method)


@settings(max_examples=examples(6))
@given(tri=triangle_soups(1, 16), method=st.sampled_from(jaxbvh.BOX_BUILDERS))
def test_batch_build_is_valid_at_any_offset_and_scale(tri, method):
    """jaxbvh.batch.build: the soup, and the soup at offset 1e7 in float64."""
    meshes = [boxes(tri), boxes(soup() + 1e7)]
    result = jaxbvh.batch.build(meshes, method=method, max_leaf=2, bins=8)
    for tree, (lo, hi) in zip(result.trees.unstack(), meshes):
        assert_valid_tree(tree, lo, hi)


def test_batch_sbvh_is_valid_at_offset_1e7():
    tri = soup() + 1e7
    result = jaxbvh.batch.build([boxes(tri)], method="sbvh", triangles=[tri])
    (tree,) = result.trees.unstack()
    assert_valid_tree(tree, *boxes(tri), references=True, triangles=tri)


# ----------------------------------------------------------------------------------
# The rules: directed rounding, the refusal, the warning
# ----------------------------------------------------------------------------------

finite64 = st.floats(allow_nan=False, allow_infinity=False, min_value=-3e38, max_value=3e38)


@given(x=st.lists(finite64, min_size=1, max_size=8))
def test_round_down_and_up_are_the_nearest_float32_on_their_side_and_never_subnormal(x):
    x = np.asarray(x, np.float64)
    down, up = round_down(x, np.float32), round_up(x, np.float32)
    assert down.dtype == up.dtype == np.float32
    assert (down <= x).all() and (up >= x).all()
    tiny = np.finfo(np.float32).tiny
    for y in (down, up):
        assert ((y == 0) | (np.abs(y) >= tiny)).all()
    # nothing of float32 (normal or zero) lies strictly between the result and x
    above = np.nextafter(down, np.float32(np.inf))
    below = np.nextafter(up, np.float32(-np.inf))
    normal = lambda v: (v == 0) | (np.abs(v) >= tiny)  # noqa: E731
    assert ((above > x) | ~normal(above)).all()
    assert ((below < x) | ~normal(below)).all()
    exact = x.astype(np.float32).astype(np.float64) == x
    assert (down[exact & normal(x)] == x[exact & normal(x)]).all()


def test_float32_boxes_with_normal_coordinates_pass_unchanged():
    lo = np.asarray([[0.0, -1.5, 3e-38], [1e30, -2e-30, 7.0]], np.float32)
    hi = lo + np.float32(1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new_lo, new_hi = narrow_outward(lo, hi, np.float32)
    assert new_lo.tobytes() == lo.tobytes() and new_hi.tobytes() == hi.tobytes()


@pytest.mark.parametrize("method", METHODS)
def test_coordinates_beyond_float32_are_a_one_line_error(method):
    tri = soup() * 1e39
    with pytest.raises(ValueError, match="float32") as err:
        build_and_check(tri, method)
    assert "\n" not in str(err.value)


def test_rounding_that_coarsens_the_tree_warns_and_says_what_to_do():
    tri = soup() * 1e-3 + 1e7
    for method in ("binned", "sbvh"):
        with pytest.warns(UserWarning, match="local_"):
            build_and_check(tri, method)
    with warnings.catch_warnings():  # close to the origin: rounding is far below the scene's size
        warnings.simplefilter("error")
        build_and_check(soup(), "binned")
