"""Trees with references: the references-mode check finds each broken rule, accepts an SBVH,
and interchange files keep repeated primitive ids."""

from __future__ import annotations

import numpy as np
import pytest
from strategies import boxes

import jaxbvh
from jaxbvh.builders import SBVHConfig, build_sbvh


def slivers():
    tri = []
    for i in range(6):
        y = i / 6.0
        tri.append([[0, y, 0], [1, y + 0.01, 0.01], [1, y, 0.02]])
        tri.append([[y, 0, 0.01], [y + 0.01, 1, 0.0], [y, 1, 0.02]])
    tri.append([[0.5, 0.5, 0.01]] * 3)  # zero area: a point
    tri.append([[0.2, 0.3, 0.0], [0.9, 0.3, 0.0], [0.9, 0.3, 0.0]])  # zero area: a segment
    return np.asarray(tri, np.float32)


@pytest.fixture(scope="module")
def case():
    tri = slivers()
    tree = jaxbvh.to_numpy(build_sbvh(tri, SBVHConfig(bins=8, reference_capacity=4)).tree)
    assert jaxbvh.check(tree, *boxes(tri)) != []  # not valid as a plain tree: ids repeat
    return tree, tri


def problems(tree, tri):
    return jaxbvh.check(tree, *boxes(tri), references=True, triangles=tri)


def test_an_sbvh_passes_in_references_mode(case):
    tree, tri = case
    assert problems(tree, tri) == []


def test_a_shrunk_leaf_box_leaves_a_triangle_uncovered(case):
    tree, tri = case
    t = jaxbvh.to_numpy(tree)
    repeated = np.bincount(t.prim_index[t.prim_index >= 0]) > 1
    leaf = next(n for n in np.flatnonzero(t.prim_count > 0)
                if repeated[t.prim_index[t.prim_start[n]:t.prim_start[n] + t.prim_count[n]]].any())
    hi = t.hi.copy()
    hi[leaf] = t.lo[leaf] + (t.hi[leaf] - t.lo[leaf]) * 0.5
    found = problems(t.replace(hi=hi), tri)
    assert any("not covered" in p for p in found)


def test_a_dropped_or_doubled_reference_is_reported(case):
    tree, tri = case
    t = jaxbvh.to_numpy(tree)
    leaf = int(np.flatnonzero(t.prim_count > 0)[0])
    prim = int(t.prim_index[t.prim_start[leaf]])
    others = t.prim_index.copy()
    others[(others == prim)] = (prim + 1) % tri.shape[0]  # every reference of prim renamed
    assert any("referenced by no leaf" in p for p in problems(t.replace(prim_index=others), tri))
    if t.prim_count[leaf] > 1:
        twice = t.prim_index.copy()
        twice[t.prim_start[leaf] + 1] = prim
        assert any("more than once" in p for p in problems(t.replace(prim_index=twice), tri))


def test_interchange_files_keep_repeated_ids(case, tmp_path):
    tree, tri = case
    path = tmp_path / "sbvh.npz"
    jaxbvh.save(path, tree)
    loaded, _ = jaxbvh.load(path)
    assert problems(loaded, tri) == []
    assert float(jaxbvh.sah(loaded)) == pytest.approx(float(jaxbvh.sah(tree)), rel=1e-6)
