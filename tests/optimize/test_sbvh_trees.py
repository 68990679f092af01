"""Trees with references (SBVH) through every optimizer and collapsing: still valid in
references mode (each triangle covered by its leaf boxes), leaves untouched, SAH not worse."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from strategies import boxes

import jaxbvh
from jaxbvh.builders import SBVHConfig, build_sbvh
from jaxbvh.optimize import OPTIMIZERS
from jaxbvh.wide import collapse


def crossing_slivers(n_per_side=8):
    """Long thin triangles crossing on a grid, plus small ones: many references."""
    tri = []
    for i in range(n_per_side):
        y = i / n_per_side
        tri.append([[0, y, 0], [1, y + 0.01, 0.01], [1, y, 0.02]])
        tri.append([[y, 0, 0.01], [y + 0.01, 1, 0.0], [y, 1, 0.02]])
    rng = np.random.default_rng(0)
    small = rng.uniform(0, 1, (16, 1, 3)) + rng.uniform(-0.02, 0.02, (16, 3, 3))
    return np.concatenate([np.asarray(tri), small]).astype(np.float32)


@pytest.fixture(scope="module")
def ref_tree():
    tri = crossing_slivers()
    built = build_sbvh(tri, SBVHConfig(bins=8, max_leaf=2, reference_capacity=4))
    assert int(built.references) > tri.shape[0]  # the case under test: triangles in several leaves
    return built.tree, tri


def valid_with_references(tree, tri):
    lo, hi = boxes(tri)
    jaxbvh.validate(tree, lo, hi, references=True, triangles=tri)


@pytest.mark.parametrize("method", ["hc", "reinsert", "treelet", "pipeline"])
def test_optimizers_keep_a_tree_with_references_valid(ref_tree, method):
    tree, tri = ref_tree
    if method == "pipeline":  # its final leaf merge (default max_leaf) may merge leaves: valid, not worse
        merged = jaxbvh.optimize.run(OPTIMIZERS[method], tree)
        valid_with_references(merged.tree, tri)
        assert float(jaxbvh.sah(merged.tree)) <= float(jaxbvh.sah(tree)) * (1 + 1e-6)
    config = OPTIMIZERS[method].Config(max_leaf=1) if method == "pipeline" else None  # leaves kept
    result = jaxbvh.optimize.run(OPTIMIZERS[method], tree, config, key=jax.random.key(0))
    valid_with_references(result.tree, tri)
    before, after = jaxbvh.to_numpy(tree), jaxbvh.to_numpy(result.tree)
    np.testing.assert_array_equal(after.prim_index, before.prim_index)  # leaves untouched
    leaf = before.prim_count > 0
    np.testing.assert_array_equal(after.lo[leaf], before.lo[leaf])  # clipped boxes kept, not refit
    assert float(jaxbvh.sah(after)) <= float(jaxbvh.sah(before)) * (1 + 1e-6)


def test_collapse_keeps_a_tree_with_references_valid(ref_tree):
    tree, tri = ref_tree
    wide = collapse.collapse(tree).tree
    valid_with_references(wide, tri)
    assert jaxbvh.tree.layout.prim_total(wide) == jaxbvh.tree.layout.prim_total(tree)


def test_all_hits_lists_each_triangle_once(ref_tree):
    """A ray through a split triangle reaches it from two leaves: one hit, as in the binned tree."""
    tree, tri = ref_tree
    lo, hi = boxes(tri)
    plain = jaxbvh.build(lo, hi, method="binned", bins=8)
    rng = np.random.default_rng(1)
    # grazing rays along the slivers, in their slab: they pass through the boxes of several
    # pieces of a split triangle and pierce it once
    m = 512
    along = np.stack([np.ones(m), rng.uniform(-0.05, 0.05, m), rng.uniform(-0.02, 0.02, m)], 1)
    origin = np.stack([np.full(m, -0.5), rng.uniform(0, 1, m), rng.uniform(0, 0.02, m)], 1)
    swap = np.arange(m) % 2 == 1  # half of them along y
    along[swap] = along[swap][:, [1, 0, 2]]
    origin[swap] = origin[swap][:, [1, 0, 2]]
    direction = (along / np.linalg.norm(along, axis=1)[:, None]).astype(np.float32)
    origin = origin.astype(np.float32)
    got = jaxbvh.rays.traversal.all_hits(tree, tri, origin, direction, max_hits=64)
    want = jaxbvh.rays.traversal.all_hits(plain, tri, origin, direction, max_hits=64)
    np.testing.assert_array_equal(got.hit_count, want.hit_count)
    assert (np.asarray(got.hit_count) > 0).any()
    for name in ("closest_hit", "any_hit"):
        a = getattr(jaxbvh.rays.traversal, name)(tree, tri, origin, direction)
        b = getattr(jaxbvh.rays.traversal, name)(plain, tri, origin, direction)
        np.testing.assert_array_equal(np.asarray(a.prim) >= 0, np.asarray(b.prim) >= 0)
    closest = jaxbvh.rays.traversal.closest_hit(tree, tri, origin, direction)
    np.testing.assert_array_equal(closest.t, jaxbvh.rays.traversal.closest_hit(plain, tri, origin, direction).t)
