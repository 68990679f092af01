"""SBVH: equal to its NumPy twin, every tree valid with references, every triangle covered,
the binned builder when no spatial split pays, a bounded reference capacity, clear errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import canonical
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import boxes, triangle_soups

import jaxbvh
from jaxbvh.builders import SBVHConfig, build_sbvh, sbvh, sbvh_splits
from jaxbvh.builders import sbvh_reference as reference
from jaxbvh.numerics import TIE_TOLERANCE, half_area
from jaxbvh.testing.plugin import examples
from jaxbvh.tree.frame import Frame

SLOTS = 96  # one reference capacity for every soup (one compiled program per bins value)
BIG_SLOTS = 640  # past jaxbvh.builders.sbvh.SMALL_STAGE: two level programs, compacted references


def local_triangles(tri, dtype=np.float32):
    """Triangles in their scene frame, as the command line hands them to the builder."""
    lo, hi = boxes(tri)
    return Frame.fit(lo, hi).to_local(tri).astype(dtype)


def assert_children_hold_fewer_references(tree):
    """Every child holds fewer references than its parent (a node's references are the
    distinct triangles below it): a spatial split never hands a side all of its node's
    references (rules.separates), so splitting always progresses."""
    t = jaxbvh.to_numpy(tree)
    order, frontier = [], [int(t.root)]
    while frontier:  # breadth first from the root; reversed, children come before parents
        order += frontier
        frontier = [int(c) for i in frontier if t.left[i] >= 0 for c in (t.left[i], t.right[i])]
    below = {}
    for i in reversed(order):
        if t.left[i] >= 0:
            below[i] = below[int(t.left[i])] | below[int(t.right[i])]
            assert len(below[int(t.left[i])]) < len(below[i]) and len(below[int(t.right[i])]) < len(below[i])
        else:
            start = int(t.prim_start[i])
            below[i] = frozenset(t.prim_index[start: start + int(t.prim_count[i])].tolist())


def diagonal_quad():
    """A thin quad along the cube's diagonal, as two triangles: every spatial plane cuts
    both, and each side's clipped boxes are far smaller than the node's."""
    return np.asarray([[[0, 0, 0], [1, 1, 1], [0.1, 0, 0]], [[0.02, 0.02, 0.02], [1, 1, 1], [0.95, 1, 1]]],
                      np.float32)


def long_thin_scene():
    """Long slivers crossing each other on a grid: object splits overlap, spatial splits pay."""
    tri = []
    for i in range(6):
        y = i / 6.0
        tri.append([[0, y, 0], [1, y + 0.01, 0.01], [1, y, 0.02]])  # along x
        tri.append([[y, 0, 0.01], [y + 0.01, 1, 0.0], [y, 1, 0.02]])  # along y, in the same slab
    return np.asarray(tri, np.float32)


@settings(max_examples=examples(15))  # the twin costs ~1 s a soup
@given(tri=triangle_soups(max_size=24), alpha=st.sampled_from([0.0, 1e-5]), max_leaf=st.sampled_from([1, 3]),
       bins=st.sampled_from([(4, 8), (8, 4)]))
def test_jax_sbvh_equals_reference(tri, alpha, max_leaf, bins):
    """``bins``: (object split's bins, spatial split's most), each read where it belongs."""
    tri = local_triangles(tri)
    config = SBVHConfig(alpha=alpha, max_leaf=max_leaf, bins=bins[0], spatial_bins=bins[1])
    got = build_sbvh(tri, config, capacity=SLOTS)
    want = reference.build(tri, config, capacity=SLOTS)
    assert canonical(got.tree) == canonical(want.tree)
    assert (int(got.references), int(got.spatial_splits), bool(got.out_of_capacity)) == \
        (want.references, want.spatial_splits, want.out_of_capacity)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jax_sbvh_equals_reference_where_spatial_splits_and_unsplitting_happen(seed):
    """Long triangles at random angles among small ones: many spatial splits, clipped and
    unsplit references (the soups above rarely need spatial splits)."""
    rng = np.random.default_rng(seed)
    n = 80  # a fifth of them large: seeds 0, 1, 2 unsplit 7, 6, 3 straddlers (of 29, 12, 16)
    size = np.where(rng.random((n, 1, 1)) < 0.2, 1.0, 0.1)
    tri = (rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(size=(n, 3, 3)) * size).astype(np.float32)
    config = SBVHConfig(alpha=0.0, max_leaf=2, bins=8)
    # past SMALL_STAGE slots: the engine's narrow program compacts each level's references
    got = build_sbvh(tri, config, capacity=BIG_SLOTS)
    want = reference.build(tri, config, capacity=BIG_SLOTS)
    assert want.spatial_splits > 0
    assert canonical(got.tree) == canonical(want.tree)
    assert_children_hold_fewer_references(got.tree)
    assert (int(got.references), int(got.spatial_splits)) == (want.references, want.spatial_splits)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(max_size=40), alpha=st.sampled_from([0.0, 1e-5]), max_leaf=st.sampled_from([1, 4]))
def test_every_sbvh_tree_is_valid_with_references_and_covers_every_triangle(tri, alpha, max_leaf):
    """Degenerate (zero-area, one-point) and thin triangles, scales 1e-30 .. 1e30 included."""
    tri = local_triangles(tri)
    lo, hi = boxes(tri)
    got = build_sbvh(tri, SBVHConfig(alpha=alpha, max_leaf=max_leaf, bins=8), capacity=BIG_SLOTS)
    jaxbvh.validate(got.tree, lo, hi, references=True, triangles=tri)
    t = jaxbvh.to_numpy(got.tree)
    assert int(t.prim_count.sum()) == int(got.references) >= tri.shape[0]
    assert t.prim_count.max() <= max_leaf
    assert_children_hold_fewer_references(got.tree)


def test_a_spatial_split_leaves_each_side_fewer_references():
    """Two triangles that every plane cuts: without the rule each spatial split hands
    both sides both references, and at ``max_leaf`` 1 the node is split again and again
    (29 spatial splits, 60 references, depth 6); with it the object split is taken."""
    tri = diagonal_quad()
    config = SBVHConfig(alpha=0.0, max_leaf=1, bins=4)
    got = build_sbvh(tri, config, capacity=SLOTS)
    assert canonical(got.tree) == canonical(reference.build(tri, config, capacity=SLOTS).tree)
    assert int(got.references) == 2 and int(got.spatial_splits) == 0
    assert_children_hold_fewer_references(got.tree)


def test_spatial_splits_pay_on_long_thin_triangles():
    tri = long_thin_scene()
    lo, hi = boxes(tri)
    got = build_sbvh(tri, SBVHConfig(bins=8), capacity=SLOTS)
    binned = jaxbvh.build(lo, hi, method="binned", bins=8)
    jaxbvh.validate(got.tree, lo, hi, references=True, triangles=tri)
    assert int(got.spatial_splits) > 0 and int(got.references) > tri.shape[0]
    assert float(jaxbvh.sah(got.tree)) < float(jaxbvh.sah(binned))


@settings(max_examples=examples(15))
@given(tri=triangle_soups(max_size=30), max_leaf=st.sampled_from([1, 3]))
def test_without_spatial_splits_sbvh_is_the_binned_builder(tri, max_leaf):
    """``alpha`` past any overlap: only object splits, by the binned builder's rule."""
    tri = local_triangles(tri)
    lo, hi = boxes(tri)
    got = build_sbvh(tri, SBVHConfig(alpha=1e30, max_leaf=max_leaf, bins=8), capacity=SLOTS)
    assert int(got.spatial_splits) == 0 and int(got.references) == tri.shape[0]
    assert canonical(got.tree) == canonical(jaxbvh.build(lo, hi, method="binned", max_leaf=max_leaf, bins=8))


SWEEP_SLOTS, SWEEP_BINS = 4, 4


def swept(entries, exits, lo, hi):
    """The tie rule read plainly: per slot, every (axis, plane) priced ``A_L N_L + A_R
    N_R`` over the bins up to and after the plane (integer boxes: exact), the least
    cost, and the first (axis, plane) in axis-major order within the tie tolerance;
    axis 0, plane 0 and an infinite cost where no plane has references on both sides.
    ``entries``, ``exits`` [B, F, 3]; ``lo``, ``hi`` [3, B, F, 3] (coordinate, bin, slot, axis)."""
    out = []
    for f in range(SWEEP_SLOTS):
        costs = np.full((3, SWEEP_BINS - 1), np.inf)
        for a, k in np.ndindex(3, SWEEP_BINS - 1):
            n_l, n_r = entries[: k + 1, f, a].sum(), exits[k + 1:, f, a].sum()
            if n_l and n_r:
                a_l = half_area(lo[:, : k + 1, f, a].min(1), hi[:, : k + 1, f, a].max(1), 1.0)
                a_r = half_area(lo[:, k + 1:, f, a].min(1), hi[:, k + 1:, f, a].max(1), 1.0)
                costs[a, k] = a_l * n_l + a_r * n_r
        near = np.flatnonzero((costs.ravel() <= costs.min() * (1 + TIE_TOLERANCE)) & np.isfinite(costs.ravel()))
        first = near[0] if near.size else 0
        out.append((costs.min(), first // (SWEEP_BINS - 1), first % (SWEEP_BINS - 1)))
    return out


@jax.jit
def sweep(entries, exits, lo, hi):
    """:func:`jaxbvh.builders.sbvh_splits.sweep_bins` on the test's cells, every slot and axis usable."""
    return sbvh_splits.sweep_bins((entries, exits), list(lo), list(hi), jnp.ones((SWEEP_SLOTS, 3), bool),
                                  jnp.float32(1), SWEEP_BINS)


@settings(max_examples=examples(40), deadline=None)
@given(st.data())
def test_the_sweeps_take_the_least_cost_then_the_lowest_axis_then_the_lowest_plane(data):
    """``sbvh_splits.sweep_bins`` on small integer cells (exact costs, so ties are real
    and frequent): cost, axis and plane per slot as the rule reads plainly."""
    def ints(top, shape):
        size = int(np.prod(shape))
        return np.array(data.draw(st.lists(st.integers(0, top), min_size=size, max_size=size)), np.int32).reshape(shape)

    cells = (SWEEP_BINS, SWEEP_SLOTS, 3)
    entries, exits = ints(2, cells), ints(2, cells)
    lo = ints(3, (3,) + cells).astype(np.float32)
    hi = lo + ints(2, (3,) + cells)
    if data.draw(st.booleans()):  # the same cells on every axis: ties between axes
        entries, exits, lo, hi = (np.repeat(x[..., :1], 3, axis=-1) for x in (entries, exits, lo, hi))
    got = sweep(jnp.asarray(entries), jnp.asarray(exits), jnp.asarray(lo), jnp.asarray(hi))
    for f, (cost, axis, plane) in enumerate(swept(entries, exits, lo, hi)):
        assert (float(got.cost[f]), int(got.axis[f]), int(got.plane[f])) == (cost, axis, plane)


def test_levels_no_narrow_program_holds_run_in_the_wide_ones():
    """520 references at 640 slots: the top levels hold more than the narrow program's 512
    and run in the wide one (compiled only then, :func:`jaxbvh.builders.sbvh.engine`),
    the deeper ones back in the narrow one; the tree is the binned builder's all the same."""
    (_, narrow_live), *wide = sbvh.level_programs(BIG_SLOTS)
    rng = np.random.default_rng(7)
    tri = (rng.random((520, 1, 3)) + 0.02 * rng.random((520, 3, 3))).astype(np.float32)
    assert wide and narrow_live < tri.shape[0] <= BIG_SLOTS
    tri = local_triangles(tri)
    lo, hi = boxes(tri)
    got = build_sbvh(tri, SBVHConfig(alpha=1e30, max_leaf=1, bins=8), capacity=BIG_SLOTS)
    assert canonical(got.tree) == canonical(jaxbvh.build(lo, hi, method="binned", max_leaf=1, bins=8))


def test_reference_capacity_runs_out_gracefully():
    """No slot to spare: every spatial split is refused, the build says so and stays valid."""
    tri = long_thin_scene()
    lo, hi = boxes(tri)
    config = SBVHConfig(bins=8)
    got = build_sbvh(tri, config, capacity=tri.shape[0])
    want = reference.build(tri, config, capacity=tri.shape[0])
    assert bool(got.out_of_capacity) and want.out_of_capacity
    assert int(got.references) == tri.shape[0]
    assert canonical(got.tree) == canonical(want.tree)
    jaxbvh.validate(got.tree, lo, hi, references=True, triangles=tri)
    some = build_sbvh(tri, config, capacity=tri.shape[0] + 3)  # a few slots: granted in node order
    assert int(some.references) <= tri.shape[0] + 3
    assert canonical(some.tree) == canonical(reference.build(tri, config, capacity=tri.shape[0] + 3).tree)
    with pytest.warns(UserWarning, match="reference slots ran out"):
        jaxbvh.build(lo, hi, method="sbvh", triangles=tri, bins=8, capacity=tri.shape[0])


def test_build_takes_sbvh_by_name_and_config():
    tri = long_thin_scene()
    lo, hi = boxes(tri)
    by_name = jaxbvh.build(lo, hi, method="sbvh", triangles=tri, alpha=1e-5, bins=8, reference_capacity=4)
    by_config = jaxbvh.build(lo, hi, SBVHConfig(bins=8, reference_capacity=4), triangles=tri)
    assert canonical(by_name) == canonical(by_config)
    assert "sbvh" in jaxbvh.BUILDERS and "sbvh" not in jaxbvh.BOX_BUILDERS
    assert jaxbvh.builders.ALL_BUILDERS is jaxbvh.BUILDERS  # the older name


@pytest.mark.parametrize("call, message", [
    (lambda lo, hi, tri: jaxbvh.build(lo, hi, method="sbvh"), "needs the triangles"),
    (lambda lo, hi, tri: jaxbvh.build(lo[:2], hi[:2], method="sbvh", triangles=tri), "boxes of the"),
    (lambda lo, hi, tri: build_sbvh(tri[:, :2]), r"shape \[n, 3, 3\]"),
    (lambda lo, hi, tri: build_sbvh(np.where(np.arange(12)[:, None, None] == 3, np.nan, tri)),
     "NaN or infinite"),
    (lambda lo, hi, tri: build_sbvh(tri, capacity=5), "below the 12 triangles"),
    (lambda lo, hi, tri: SBVHConfig(alpha=-1.0), "alpha"),
    (lambda lo, hi, tri: SBVHConfig(reference_capacity=0.5), "reference_capacity"),
    (lambda lo, hi, tri: SBVHConfig(spatial_bins=1), "spatial_bins"),
])
def test_bad_input_is_a_one_line_error(call, message):
    tri = long_thin_scene()
    lo, hi = boxes(tri)
    with pytest.raises(ValueError, match=message) as info:
        call(lo, hi, tri)
    assert "\n" not in str(info.value)
