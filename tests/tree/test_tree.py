"""Tree arrays: interchange form, save/load, foreign trees, and the invariant check."""

from __future__ import annotations

import re

import numpy as np
import pytest
from helpers import CAPACITY, SHARED_DATA, canonical
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import box_sets

import jaxbvh
from jaxbvh.builders import topdown_reference
from jaxbvh.builders.configs import SweepConfig
from jaxbvh.testing.plugin import examples
from jaxbvh.testing.trees import Choices, renumber
from jaxbvh.tree import cost_reference as reference
from jaxbvh.tree.frame import Frame


@given(st.integers(0, 10**6))
def test_capacity_bucket_is_tight_and_few(n):
    b = jaxbvh.capacity_bucket(n)
    assert b >= n and b >= 4
    assert b <= max(4, 1.5 * n + 1)
    # every bucket is 2^k or 3 * 2^(k-1)
    assert b & (b - 1) == 0 or (b % 3 == 0 and (b // 3) & (b // 3 - 1) == 0)


def test_capacity_bucket_refuses_a_minimum_that_cannot_grow():
    # a minimum of 1 never grows (its half is 0): the loop would never end
    with pytest.raises(ValueError, match="minimum"):
        jaxbvh.capacity_bucket(5, minimum=1)


@settings(max_examples=examples(15))
@given(data=box_sets(max_size=40), max_leaf=st.sampled_from([1, 3]), seed=st.integers(0, 2**31))
def test_any_node_order_and_root_loads_to_the_same_tree(data, max_leaf, seed, tmp_path_factory):
    lo, hi = data
    tree = jaxbvh.build(lo, hi, max_leaf=max_leaf, capacity=CAPACITY)  # one program for every size
    rng = np.random.default_rng(seed)
    # node ids permuted and leaf runs moved in prim_index (the kit's renumber), and each
    # node's two children swapped half the time
    arrays = jaxbvh.to_interchange(renumber(tree, Choices(rng)))
    if rng.random() < 0.5:
        arrays["child"] = arrays["child"][:, ::-1]
    path = tmp_path_factory.mktemp("trees") / "t.npz"
    np.savez(path, **arrays)
    loaded, frame = jaxbvh.load(path)
    assert frame.is_identity
    jaxbvh.validate(loaded, lo, hi)
    np.testing.assert_allclose(float(jaxbvh.sah(loaded)), float(jaxbvh.sah(tree)), rtol=1e-6)
    np.testing.assert_allclose(float(jaxbvh.sah(loaded)), reference.sah(loaded), rtol=2e-5)


def test_save_load_round_trip_keeps_tree_and_frame(tmp_path):
    rng = np.random.default_rng(0)
    lo = rng.random((30, 3)).astype(np.float32)
    hi = lo + 0.1
    tree = jaxbvh.build(lo, hi, max_leaf=2)
    frame = Frame(np.array([1e7, 2.0, -3.0]), 8.0)
    jaxbvh.save(tmp_path / "t.npz", tree, frame=frame)
    with np.load(tmp_path / "t.npz") as data:
        assert set(data.files) == {*jaxbvh.tree.INTERCHANGE_KEYS, "origin", "scale"}
        assert data["child"].dtype == np.int32 and data["child"].shape[1] == 2
        assert data["root"].shape == ()
    loaded, got_frame = jaxbvh.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(got_frame.origin, frame.origin)
    assert got_frame.scale == frame.scale
    jaxbvh.validate(loaded, lo, hi)
    assert canonical(loaded, with_axis=False) == canonical(tree, with_axis=False)  # axis is not stored


def test_unpadded_and_wide_trees_load():
    rng = np.random.default_rng(2)
    lo = rng.random((9, 3)).astype(np.float32)
    arrays = jaxbvh.to_interchange(jaxbvh.build(lo, lo + 0.1))
    exact = jaxbvh.from_interchange(arrays, pad=False)
    assert exact.capacity == 17
    # a 3-wide tree: root with three children, each a leaf of 3 primitives
    wide = dict(child=np.array([[1, 2, 3], [-1, -1, -1], [-1, -1, -1], [-1, -1, -1]], np.int32),
                prim_start=np.array([0, 0, 3, 6], np.int32), prim_count=np.array([0, 3, 3, 3], np.int32),
                prim_index=np.arange(9, dtype=np.int32), lo=None, hi=None, root=np.int32(0))
    groups = [lo[0:3], lo[3:6], lo[6:9]]
    wide["lo"] = np.stack([lo.min(0)] + [g.min(0) for g in groups]).astype(np.float32)
    wide["hi"] = np.stack([lo.max(0) + 0.1] + [g.max(0) + 0.1 for g in groups]).astype(np.float32)
    tree = jaxbvh.from_interchange(wide)
    assert isinstance(tree, jaxbvh.WideBVH) and tree.arity == 3
    jaxbvh.validate(tree, lo, lo + np.float32(0.1))
    np.testing.assert_allclose(float(jaxbvh.sah(jaxbvh.to_jax(tree))), reference.sah(tree), rtol=2e-5)


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop("lo"), "missing"),
    (lambda a: a.update(child=a["child"][:, :1]), "k>=2"),
    (lambda a: a.update(root=np.int32(10**6)), "outside"),
    (lambda a: a.update(child=np.where(a["child"] >= 0, 10**6, -1).astype(np.int32)), "ids must be"),
    (lambda a: a.update(prim_start=a["prim_start"] + 10**6), "outside its"),
    (lambda a: a.update(lo=a["lo"][:-1]), "lo"),
])
def test_malformed_interchange_arrays_are_named(change, message):
    lo = np.random.default_rng(5).random((6, 3)).astype(np.float32)
    arrays = jaxbvh.to_interchange(jaxbvh.build(lo, lo + 0.1))
    change(arrays)
    with pytest.raises(ValueError, match=message):
        jaxbvh.from_interchange(arrays)


def test_missing_and_garbage_tree_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        jaxbvh.load(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz"):
        jaxbvh.load(tmp_path / "junk.npz")


# --- the invariant check must catch every kind of damage --------------------------------

def _damage(kind, t, rng):
    t = jaxbvh.to_numpy(t)
    arrays = {f: np.array(getattr(t, f)) for f in
              ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "axis", "prim_index", "root")}
    interior = np.flatnonzero(arrays["left"] >= 0)
    leaves = np.flatnonzero(arrays["prim_count"] > 0)
    node = int(rng.choice(interior))
    if kind == "duplicate_prim":
        a, b = rng.choice(leaves, 2, replace=False)
        arrays["prim_index"][arrays["prim_start"][a]] = arrays["prim_index"][arrays["prim_start"][b]]
    elif kind == "wrong_parent":
        arrays["parent"][arrays["left"][node]] = arrays["right"][node]
    elif kind == "shrunk_box":
        arrays["hi"][node] = arrays["lo"][node]  # no longer holds its children
    elif kind == "leaf_misses_prim":
        leaf = int(rng.choice(leaves))
        arrays["lo"][leaf] = arrays["hi"][leaf]
    elif kind == "cycle":
        arrays["left"][node] = int(arrays["root"])
    elif kind == "shared_child":
        arrays["right"][node] = arrays["left"][node]
    elif kind == "lost_leaf":
        leaf = int(rng.choice(leaves))
        arrays["prim_count"][leaf] = 0
    elif kind == "one_child":
        arrays["right"][node] = -1
    elif kind == "parent_outside":
        arrays["parent"][arrays["left"][node]] = arrays["parent"].shape[0] + 3
    return jaxbvh.BVH(**arrays)


# the problem each damage must produce (a pattern of its line in the error)
DAMAGE_NAMED = {
    "duplicate_prim": r"primitive\(s\) \d+.* referenced more than once",
    "wrong_parent": r"parent of node\(s\) \d+.* does not name the node that lists them",
    "shrunk_box": r"box of node\(s\) \d+.* does not contain the box of child",
    "leaf_misses_prim": r"leaf box\(es\) \d+.* do not contain primitive",
    "cycle": r"node\(s\) \d+.* reached more than once from the root",
    "shared_child": r"node\(s\) \d+.* reached more than once from the root",  # names the shared child
    "lost_leaf": r"primitive\(s\) \d+.* referenced by no leaf",
    "one_child": r"interior node\(s\) \d+.* have only one child",
    "parent_outside": r"node\(s\) \d+.* name a parent outside the \d+ nodes",  # not an IndexError
}


@settings(max_examples=examples(15))
@given(data=box_sets(min_size=4, max_size=30), seed=st.integers(0, 2**31),
       kind=st.sampled_from(sorted(DAMAGE_NAMED)))
def test_validate_catches_damage(data, seed, kind):
    lo, hi = data
    hi = hi + np.float32(0.01)  # no zero-extent boxes: every damage is visible
    tree = jaxbvh.build(lo, hi, max_leaf=1)  # interior nodes and two leaves at least, whatever the boxes
    jaxbvh.validate(tree, lo, hi)
    broken = _damage(kind, tree, np.random.default_rng(seed))
    with pytest.raises(jaxbvh.InvalidTreeError, match=DAMAGE_NAMED[kind]):
        jaxbvh.validate(broken, lo, hi)


@pytest.mark.parametrize("kind", sorted(DAMAGE_NAMED))
def test_validate_names_each_damage(kind):
    """Every kind of damage, every time (the property test above samples them)."""
    rng = np.random.default_rng(7)
    lo = rng.uniform(-1, 1, (12, 3)).astype(np.float32)
    hi = lo + rng.uniform(0.01, 0.5, (12, 3)).astype(np.float32)
    broken = _damage(kind, jaxbvh.build(lo, hi), rng)
    assert any(re.search(DAMAGE_NAMED[kind], line) for line in jaxbvh.check(broken, lo, hi)), kind


# --- trees from another library -------------------------------------------------------

REFERENCE_TREES = {  # name: (mesh file, SAH tinybvh reported in shared/data/README.md)
    "bunny": ("meshes/stanford-bunny.obj", 31.880),
    "legocar": ("meshes/legocar.obj", 30.212),
    "drone": ("scenes/drone/scene.gltf", 15.397),
}


@pytest.mark.skipif(not SHARED_DATA.exists(), reason="needs ../shared/data (reference trees and meshes)")
@pytest.mark.parametrize("name", sorted(REFERENCE_TREES))
def test_tinybvh_trees_load_validate_and_cost_what_tinybvh_says(name):
    from jaxbvh.io import load_mesh

    mesh_file, tinybvh_sah = REFERENCE_TREES[name]
    tree, frame = jaxbvh.load(SHARED_DATA / "trees" / f"{name}_binned_ref.npz")
    assert frame.is_identity
    mesh = load_mesh(SHARED_DATA / mesh_file)
    lo, hi = mesh.prim_boxes()
    jaxbvh.validate(tree, lo.astype(np.float32), hi.astype(np.float32))
    assert float(jaxbvh.sah(jaxbvh.to_jax(tree))) == pytest.approx(tinybvh_sah, abs=1e-3)


@given(data=box_sets(max_size=30), extra=st.integers(0, 20))  # a compile per size: the profile's examples
def test_padding_is_inert(data, extra):
    """An unpadded tree of every drawn size, padded: the same costs, checks and tree. The
    tree is the sweep builder's NumPy twin's (tests/builders hold it equal to the builder):
    exactly sized, and no builder compile per size, only the costs' that this tests."""
    lo, hi = data
    tree = jaxbvh.to_jax(topdown_reference.build(lo, hi, SweepConfig()))
    padded = jaxbvh.tree.pad_to(tree, tree.capacity + extra, lo.shape[0] + extra)
    jaxbvh.validate(padded, lo, hi)
    assert float(jaxbvh.sah(jaxbvh.to_jax(padded))) == float(jaxbvh.sah(tree))
    assert canonical(padded) == canonical(tree)
    with pytest.raises(ValueError, match="below"):
        jaxbvh.tree.pad_to(tree, tree.capacity - 1, lo.shape[0])
