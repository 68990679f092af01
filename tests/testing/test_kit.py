"""The testing kit itself: its strategies draw what they say, its assertions pass on what
is right and fail in one line on what is wrong, its oracles agree with each other and
bound what builders make, its plugin and its import needs."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import Phase, find, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.builders import configs, topdown_reference
from helpers import crossing_slivers

from jaxbvh.testing import (
    DEFECTS,
    assert_costs_close,
    assert_same_tree,
    assert_valid_tree,
    canonical,
    make_tree,
    oracles,
    plugin,
)
from jaxbvh.testing import strategies as kit
from jaxbvh.testing.trees import Choices
from jaxbvh.tree import cost_reference
from jaxbvh.wide import collapse_reference

REPO = Path(__file__).resolve().parents[2]


def one_line_failure(check, *args, **kwargs) -> str:
    """The message of the AssertionError ``check`` raises; it must be one line."""
    with pytest.raises(AssertionError) as caught:
        check(*args, **kwargs)
    message = str(caught.value)
    assert "\n" not in message, message
    return message


# Strategies

@given(kit.trees(arity=None, boxes=kit.box_sets(1, 24, extreme=True)))
def test_drawn_trees_are_valid_of_their_arity(built):
    assert_valid_tree(built.tree, built.lo, built.hi)
    width = np.asarray(built.tree.child).shape[1]
    assert isinstance(built.tree, jaxbvh.BVH) == (width == 2)
    children = (np.asarray(built.tree.child) >= 0).sum(1)
    assert children.max() <= width


VARIETIES = {
    "a root other than node 0": lambda t: int(t.root) != 0,
    "a node of three or more children": lambda t: ((np.asarray(t.child) >= 0).sum(1) > 2).any(),
    "a leaf of two or more primitives": lambda t: (np.asarray(t.prim_count) > 1).any(),
    "padding nodes": lambda t: (~jaxbvh.tree.real_nodes(t)).any(),
    "padding primitive slots": lambda t: (np.asarray(t.prim_index) < 0).any(),
    "runs out of node order": lambda t: (np.diff(np.asarray(t.prim_start)[np.asarray(t.prim_count) > 0]) < 0).any(),
}


@pytest.mark.parametrize("variety", sorted(VARIETIES))
def test_drawn_trees_reach_every_variety(variety):
    # the first tree found, not shrunk: shrinking a tree is slow and adds nothing here
    found = find(kit.trees(arity=4, max_leaf=3), lambda built: bool(VARIETIES[variety](built.tree)),
                 settings=settings(max_examples=200, database=None, derandomize=True, phases=[Phase.generate]))
    assert_valid_tree(found.tree, found.lo, found.hi)


@settings(max_examples=60)
@given(kit.broken_trees(arity=None))
def test_every_planted_defect_fails_the_check_naming_it(broken):
    message = one_line_failure(assert_valid_tree, broken.tree, broken.lo, broken.hi)
    assert message.startswith("invalid BVH: ")
    assert DEFECTS[broken.defect] in message, (broken.defect, message)


@pytest.mark.parametrize("defect", sorted(DEFECTS))
def test_plant_defect_plants_each_defect(defect):
    lo = np.array([[0, 0, 0], [1, 1, 1], [2, 0, 0], [3, 1, 1]], np.float32)
    built = make_tree(lo, lo + 1, Choices(np.random.default_rng(1)), max_leaf=2)
    assert_valid_tree(built.tree, built.lo, built.hi)
    tree, plo, phi = jaxbvh.testing.plant_defect(built.tree, built.lo, built.hi, defect,
                                                 Choices(np.random.default_rng(2)))
    assert DEFECTS[defect] in one_line_failure(assert_valid_tree, tree, plo, phi)
    assert_valid_tree(built.tree, built.lo, built.hi)  # the input tree is left as it was


@settings(max_examples=30)
@given(kit.scenes(extreme=True))
def test_scenes_place_every_object_and_keep_their_triangles(mesh):
    assert {o for o, _ in mesh.instances} == set(range(len(mesh.objects)))
    counts = [mesh.objects[o][1].shape[0] for o, _ in mesh.instances]
    assert mesh.n_triangles == sum(counts)
    assert np.isfinite(mesh.triangles).all()


@given(kit.triangle_soups(1, 12))
def test_soups_are_finite_triangles(tri):
    assert tri.ndim == 3 and tri.shape[1:] == (3, 3) and 1 <= tri.shape[0] <= 12
    assert np.isfinite(tri).all()


# Assertions

@given(kit.trees(arity=None), st.data())
def test_same_tree_up_to_numbering(built, data):
    other = data.draw(kit.renumbered(built.tree))
    assert_valid_tree(other, built.lo, built.hi)
    assert_same_tree(built.tree, other)
    assert_costs_close(built.tree, other, rtol=0)
    assert canonical(built.tree) == canonical(other)


@given(kit.trees(min_size=2, arity=2, max_leaf=1))
def test_same_tree_fails_on_two_swapped_leaves_naming_where(built):
    t = jaxbvh.to_interchange(built.tree)
    leaves = np.flatnonzero(t["prim_count"] > 0)
    a, b = leaves[:2]
    t["prim_index"][[t["prim_start"][a], t["prim_start"][b]]] = t["prim_index"][[t["prim_start"][b],
                                                                                 t["prim_start"][a]]]
    swapped = jaxbvh.from_interchange(t)
    message = one_line_failure(assert_same_tree, built.tree, swapped, boxes=False)
    assert message.startswith("trees differ at root") and "leaf of primitives" in message


def test_same_tree_reports_the_path_and_the_box():
    lo = np.array([[0, 0, 0], [2, 0, 0], [4, 0, 0]], np.float32)
    tree, _ = oracles.optimal_tree(lo, lo + 1)
    t = jaxbvh.to_interchange(tree)
    t["hi"][int(t["root"])] += 1
    message = one_line_failure(assert_same_tree, tree, jaxbvh.from_interchange(t))
    assert message.startswith("trees differ at root: box")
    assert_same_tree(tree, jaxbvh.from_interchange(t), boxes=False)


def test_same_tree_refuses_an_invalid_tree():
    lo = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    tree, _ = oracles.optimal_tree(lo, lo + 1)
    t = jaxbvh.to_interchange(tree)
    t["child"][int(t["root"])] = [int(t["root"]), t["child"][int(t["root"])][1]]
    assert "second tree is invalid" in one_line_failure(assert_same_tree, tree, jaxbvh.from_interchange(t))


def test_what_is_not_a_tree_is_refused_in_one_line(tmp_path):
    lo = np.array([[0, 0, 0], [2, 0, 0]], np.float32)
    tree, _ = oracles.optimal_tree(lo, lo + 1)
    jaxbvh.save(tmp_path / "t.npz", tree)
    with pytest.raises(TypeError, match=r"expected a BVH or WideBVH, got tuple \(jaxbvh.load returns"):
        assert_valid_tree(jaxbvh.load(tmp_path / "t.npz"), lo, lo + 1)
    with pytest.raises(TypeError, match="second tree: expected"):
        assert_same_tree(tree, {"child": None})


def test_costs_close_fails_past_rtol_in_one_line():
    assert_costs_close(1.0, 1.0 + 1e-7, rtol=1e-6)
    message = one_line_failure(assert_costs_close, 1.0, 1.1, rtol=1e-3)
    assert "SAH costs differ" in message and "rtol" in message
    assert "not finite" in one_line_failure(assert_costs_close, 1.0, float("nan"))


@settings(max_examples=10)
@given(kit.trees(arity=None))
def test_interchange_files_keep_drawn_trees(tmp_path_factory, built):
    # the kit's trees (wide, shuffled runs, padding) survive the file another library writes
    path = tmp_path_factory.mktemp("tree") / "t.npz"
    jaxbvh.save(path, built.tree)
    loaded, _ = jaxbvh.load(path)
    assert_same_tree(built.tree, loaded)
    assert_valid_tree(loaded, built.lo, built.hi)


def test_the_guides_worked_example_a_tree_tinybvh_wrote(shared_data, shared_mesh):
    # docs/testing.md: tinybvh's binned tree over legocar, checked through the interchange .npz
    mesh = shared_mesh("legocar")
    tree, _ = jaxbvh.load(shared_data / "trees" / "legocar_binned_ref.npz")
    lo, hi = (b.astype(np.float32) for b in mesh.prim_boxes())
    assert_valid_tree(tree, lo, hi)
    assert_costs_close(tree, 30.212, rtol=1e-4)  # the SAH the peer harness printed
    grown = hi.copy()
    grown[7] = np.nextafter(hi[7], np.float32(np.inf))  # triangle 7 pokes out of its leaf
    assert "do not contain primitive(s) 7" in one_line_failure(assert_valid_tree, tree, lo, grown)


# Oracles

@settings(max_examples=15)
@given(kit.trees(min_size=1, max_size=6, arity=2, max_leaf=1, padding=False))
def test_optimal_tree_is_valid_and_no_tree_beats_it(built):
    best, cost = oracles.optimal_tree(built.lo, built.hi)
    assert_valid_tree(best, built.lo, built.hi)
    assert cost == cost_reference.sah(best)
    assert cost <= cost_reference.sah(built.tree) * (1 + 1e-12)
    swept = topdown_reference.build(built.lo, built.hi, configs.SweepConfig(max_leaf=1))
    assert cost <= cost_reference.sah(swept) * (1 + 1e-12)


@settings(max_examples=15)
@given(kit.trees(min_size=2, max_size=6, arity=2, max_leaf=1, padding=False))
def test_optimal_treelet_over_every_leaf_is_the_optimal_tree(built):
    # two independent enumerations: the whole tree as one treelet is the best tree
    t = built.tree
    leaves = np.flatnonzero(np.asarray(t.prim_count) > 0)
    _, treelet_cost = oracles.optimal_treelet(t, leaves)
    _, best = oracles.optimal_tree(built.lo, built.hi)
    d = (built.hi.max(0) - built.lo.min(0)).astype(np.float64)
    if d[0] * d[1] + d[1] * d[2] + d[2] * d[0] > 0:  # a flat root: the costs follow different rules
        assert treelet_cost == pytest.approx(best, rel=1e-5)


@settings(max_examples=15)
@given(kit.trees(min_size=2, max_size=8, arity=2, max_leaf=1, padding=False), st.sampled_from([2, 3, 4]))
def test_optimal_collapse_equals_the_papers_dp(built, k):
    wide, cost = oracles.optimal_collapse(built.tree, max_children=k)
    assert_valid_tree(wide, built.lo, built.hi)
    dp_cost, _, _ = collapse_reference.optimal(built.tree, max_children=k)
    assert cost == pytest.approx(float(dp_cost), rel=1e-5, abs=1e-30)


@settings(max_examples=15)
@given(kit.triangle_soups(1, 8, extreme=False), st.integers(0, 7))
def test_closest_hits_find_a_triangle_aimed_at(tri, i):
    i = i % tri.shape[0]
    normal = np.cross(tri[i, 1] - tri[i, 0], tri[i, 2] - tri[i, 0])
    if not normal.any():
        return  # a degenerate triangle cannot be hit
    centre = tri[i].mean(0)
    origin = (centre + normal * 3)[None]
    direction = (centre - origin[0])[None]  # t = 1 at the centre
    t, prim = oracles.closest_hits(tri, origin, direction)
    assert prim[0] >= 0 and t[0] <= 1 + 1e-9
    assert oracles.any_hits(tri, origin, direction)[0]


def test_enumeration_refuses_big_inputs_in_one_line():
    lo = np.zeros((oracles.MAX_ENUMERATED + 1, 3))
    with pytest.raises(ValueError, match="enumeration needs"):
        oracles.optimal_tree(lo, lo)


# Plugin and import needs

def test_plugin_fixtures(bundled_mesh, shared_data, shared_mesh):
    assert bundled_mesh.n_triangles == 5856
    assert (shared_data / "meshes").is_dir()
    assert shared_mesh("spot") is shared_mesh("spot")  # loaded once


def test_plugin_profiles_are_registered():
    ci, dev = settings.get_profile("ci"), settings.get_profile("dev")
    assert ci.derandomize and not dev.derandomize and dev.max_examples == 10 * ci.max_examples
    assert plugin.PROFILES == ("ci", "dev")


def test_examples_are_stated_for_ci_and_scale_with_the_loaded_profile():
    current = settings.get_current_profile_name()
    try:
        for name, scale in (("ci", 1), ("dev", 10)):
            settings.load_profile(name)
            assert [plugin.examples(n) for n in (1, 15, 300)] == [scale, 15 * scale, 300 * scale], name
    finally:
        settings.load_profile(current)


def test_plugin_is_the_packages_pytest_entry_point():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["entry-points"]["pytest11"] == {"jaxbvh.testing.plugin": "jaxbvh.testing.plugin"}
    assert "hypothesis" in project["optional-dependencies"]["testing"]


def test_kit_imports_without_pytest_or_hypothesis():
    # the kit needs neither; strategies needs hypothesis; the plugin (under pytest) does not
    code = ("import sys; sys.modules['hypothesis'] = None\n"
            "import jaxbvh.testing, jaxbvh.testing.assertions, jaxbvh.testing.oracles, jaxbvh.testing.trees\n"
            "assert 'pytest' not in sys.modules\n"
            "import jaxbvh.testing.plugin\n"
            "try:\n    import jaxbvh.testing.strategies\nexcept ImportError:\n    print('needs hypothesis')\n")
    env = dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "needs hypothesis"


def test_assertions_take_trees_with_references():
    """An SBVH of a small mesh names triangles in several leaves: valid for
    ``jaxbvh.check(..., references=True, triangles=tri)`` and so for the kit when told
    (``references=``, ``triangles=``); refused as before when not told, and a leaf that
    loses a piece of a triangle is refused even with references."""
    from jaxbvh.builders import sbvh_reference

    tri = crossing_slivers()  # long, crossing triangles: spatial splits pay
    built = sbvh_reference.build(tri, configs.SBVHConfig(alpha=0.0, bins=8, max_leaf=1))
    tree, lo, hi = built.tree, tri.min(1), tri.max(1)
    assert built.references > tri.shape[0]  # a tree with references
    assert jaxbvh.check(tree, lo, hi, references=True, triangles=tri) == []
    assert_valid_tree(tree, lo, hi, references=True, triangles=tri)
    assert_same_tree(tree, tree, references=True)
    assert "more than once" in one_line_failure(assert_valid_tree, tree, lo, hi)
    # a leaf box shrunk to nothing: its piece of the triangle is no longer covered
    t = jaxbvh.to_numpy(tree)
    leaf = int(np.flatnonzero(np.asarray(t.prim_count) > 0)[0])
    t.lo[leaf] = t.hi[leaf]
    message = one_line_failure(assert_valid_tree, t, lo, hi, references=True, triangles=tri)
    assert message.startswith("invalid BVH: ")
