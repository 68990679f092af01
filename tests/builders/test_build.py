"""Builders: every tree valid, equal to the NumPy reference, few compiles, clear errors."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CAPACITY, canonical, local_boxes
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import box_sets, triangle_soups

import jaxbvh
from jaxbvh.builders import configs, topdown
from jaxbvh.builders import topdown_reference as reference
from jaxbvh.numerics import scene_scale
from jaxbvh.testing.plugin import examples


# The properties build at the suite's one capacity (helpers.CAPACITY): one compiled
# program per builder for every drawn size, shared with the other modules that build at
# it; capacity buckets and a full capacity have tests of their own below.
@settings(max_examples=examples(15))
@given(tri=triangle_soups(), method=st.sampled_from(jaxbvh.BOX_BUILDERS), max_leaf=st.sampled_from([1, 2, 8]))
def test_every_build_is_valid(tri, method, max_leaf):
    lo, hi = local_boxes(tri)
    tree = jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=8, capacity=CAPACITY)
    jaxbvh.validate(tree, lo, hi)
    t = jaxbvh.to_numpy(tree)
    leaf_sizes = t.prim_count[t.prim_count > 0]
    assert leaf_sizes.max() <= max_leaf
    assert int(t.root) == 0


@settings(max_examples=examples(15))
@given(data=box_sets(max_size=48), method=st.sampled_from(jaxbvh.BOX_BUILDERS), max_leaf=st.sampled_from([1, 3]),
       bins=st.sampled_from([4, 16]))
def test_jax_builder_equals_reference(data, method, max_leaf, bins):
    lo, hi = data
    got = jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=bins, capacity=CAPACITY)
    want = reference.build(lo, hi, configs.make_config(method, max_leaf=max_leaf, bins=bins))
    jaxbvh.validate(want, lo, hi)
    assert canonical(got) == canonical(want)


@settings(max_examples=examples(15))
@given(tri=triangle_soups(max_size=30), method=st.sampled_from(jaxbvh.BOX_BUILDERS))
def test_jax_builder_equals_reference_on_extreme_soups(tri, method):
    lo, hi = local_boxes(tri)
    got = jaxbvh.build(lo, hi, method=method, max_leaf=2, bins=8, capacity=CAPACITY)
    want = reference.build(lo, hi, configs.make_config(method, max_leaf=2, bins=8))
    assert canonical(got) == canonical(want)


@settings(max_examples=examples(8))
@given(data=box_sets(min_size=9, max_size=16), method=st.sampled_from(jaxbvh.BOX_BUILDERS))
def test_float64_builder_equals_reference(data, method):
    with jax.enable_x64(True):
        lo, hi = (a.astype(np.float64) for a in data)
        got = jaxbvh.build(lo, hi, method=method, dtype=np.float64, capacity=16)  # one program per builder
        assert got.lo.dtype == np.float64
        want = reference.build(lo, hi, configs.make_config(method))
        jaxbvh.validate(got, lo, hi)
        assert canonical(got) == canonical(want)


@pytest.mark.parametrize("method", jaxbvh.BOX_BUILDERS)
def test_a_full_capacity_equals_reference(method):
    """Every slot real, none padding (the properties above always leave padding): the
    suite's programs at CAPACITY, so this compiles nothing new."""
    rng = np.random.default_rng(11)
    lo = rng.uniform(-1, 1, (CAPACITY, 3)).astype(np.float32)
    hi = lo + rng.uniform(0, 0.3, (CAPACITY, 3)).astype(np.float32)
    got = jaxbvh.build(lo, hi, method=method, max_leaf=3, bins=4, capacity=CAPACITY)
    assert got.prim_index.shape[0] == CAPACITY
    want = reference.build(lo, hi, configs.make_config(method, max_leaf=3, bins=4))
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
    for method in jaxbvh.BOX_BUILDERS:
        tree = jaxbvh.build(lo, lo, method=method, max_leaf=1)  # leaves of one: the split rule shows
        jaxbvh.validate(tree, lo, lo)
        assert jaxbvh.tree.depth(tree).max() == 6  # log2(64): ties split in the middle


def test_sah_builders_beat_median_split():
    rng = np.random.default_rng(0)
    c = rng.random((300, 3)) ** 3  # clustered towards a corner
    lo, hi = (c - 0.01).astype(np.float32), (c + 0.01).astype(np.float32)
    cost = {m: float(jaxbvh.sah(jaxbvh.build(lo, hi, method=m))) for m in jaxbvh.BOX_BUILDERS}
    assert cost["sweep"] <= cost["binned"] * 1.02
    assert cost["sweep"] < cost["median"]


def test_sizes_in_one_capacity_bucket_compile_once():
    rng = np.random.default_rng(1)
    sizes = [13, 14, 15, 16]
    assert {jaxbvh.capacity_bucket(n) for n in sizes} == {16}
    start = topdown.engine._cache_size()
    for n in sizes:
        lo = rng.random((n, 3)).astype(np.float32)
        jaxbvh.build(lo, lo + 0.1, max_leaf=n % 3 + 1)  # leaf size is not a static argument
    assert topdown.engine._cache_size() - start <= 1


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
    with pytest.raises(ValueError, match="bins"):
        jaxbvh.build(lo, lo, method="binned", bins=1)
    with pytest.raises(ValueError, match="ct"):
        jaxbvh.build(lo, lo, ct=-1.0)
    with pytest.raises(ValueError, match="lo > hi"):
        jaxbvh.build(lo, lo - 1)
    with pytest.raises(ValueError, match="x64"):
        jaxbvh.build(lo, lo, dtype=np.float64)


# ----------------------------------------------------------------------------------
# Configs: one per builder, the keyword form makes the same one
# ----------------------------------------------------------------------------------


def test_builders_map_methods_to_their_configs():
    assert list(jaxbvh.BOX_BUILDERS) == ["sweep", "binned", "median", "lbvh", "ploc"]
    assert list(jaxbvh.builders.TRIANGLE_BUILDERS) == ["sbvh"]
    assert list(jaxbvh.BUILDERS) == [*jaxbvh.BOX_BUILDERS, *jaxbvh.builders.TRIANGLE_BUILDERS]  # every builder
    for method, cls in jaxbvh.BUILDERS.items():
        assert cls.method == method and cls.__doc__ and dataclasses.is_dataclass(cls)
        with pytest.raises(dataclasses.FrozenInstanceError):
            cls().max_leaf = 2
    assert configs.DEFAULT_BUILDER in jaxbvh.BOX_BUILDERS


@settings(max_examples=examples(15))
@given(method=st.sampled_from(jaxbvh.BOX_BUILDERS),
       knob=st.sampled_from(["max_leaf", "ct", "ci", "bins", "radius", "morton_bits"]),
       value=st.one_of(st.integers(-2, 70), st.floats(-1, 40, allow_nan=False), st.just(True)))
def test_the_keyword_form_makes_the_methods_config(method, knob, value):
    """``build(lo, hi, method=m, **kw)`` is ``build(lo, hi, BOX_BUILDERS[m](**own kw))``: a
    knob of another builder is ignored, a knob of this one is checked by its Config
    (a ValueError naming it) and otherwise kept."""
    cls = jaxbvh.BOX_BUILDERS[method]
    own = knob in {f.name for f in dataclasses.fields(cls)}
    try:
        made = configs.make_config(method, **{knob: value})
    except ValueError as exc:
        assert own and knob in str(exc)
        with pytest.raises(ValueError, match=knob):
            cls(**{knob: value})
        return
    assert made == (cls(**{knob: value}) if own else cls())
    if own:
        assert getattr(made, knob) == value


def test_build_takes_a_config_or_the_keyword_form():
    rng = np.random.default_rng(3)
    lo = rng.random((40, 3)).astype(np.float32)
    hi = lo + rng.random((40, 3)).astype(np.float32) * np.float32(0.2)
    by_config = jaxbvh.build(lo, hi, configs.BinnedConfig(max_leaf=3, bins=4))
    assert canonical(by_config) == canonical(jaxbvh.build(lo, hi, method="binned", max_leaf=3, bins=4, radius=2))
    assert canonical(by_config) == canonical(reference.build(lo, hi, configs.BinnedConfig(max_leaf=3, bins=4)))
    assert canonical(jaxbvh.build(lo, hi, "median")) == canonical(jaxbvh.build(lo, hi, configs.MedianConfig()))
    assert canonical(jaxbvh.build(lo, hi)) == canonical(jaxbvh.build(lo, hi, configs.SweepConfig()))
    with pytest.raises(TypeError, match="not both"):
        jaxbvh.build(lo, hi, configs.SweepConfig(), max_leaf=2)
    with pytest.raises(TypeError, match="unknown builder option"):
        jaxbvh.build(lo, hi, max_leaves=2)
    with pytest.raises(TypeError, match="config must be"):
        jaxbvh.build(lo, hi, configs.BuilderConfig())


def test_builder_vmaps_over_trials():
    """The level-synchronous engine runs under vmap (random trials build in one call)."""
    rng = np.random.default_rng(7)
    lo = rng.random((3, 20, 3)).astype(np.float32)
    hi = lo + np.float32(0.05)

    def one(lo_i, hi_i):
        return topdown.engine(lo_i, hi_i, jnp.int32(20), jnp.int32(1), jnp.float32(1), jnp.float32(1),
                              jnp.float32(scene_scale(lo, hi)), method="sweep")

    trees = jax.vmap(one)(jnp.asarray(lo), jnp.asarray(hi))
    for b in range(3):
        tree = jax.tree_util.tree_map(lambda x: x[b], trees)
        jaxbvh.validate(tree, lo[b], hi[b])
        assert canonical(tree) == canonical(jaxbvh.build(lo[b], hi[b], pad=False))



# 26 boxes hypothesis found (binned, 4 bins, max_leaf 3): a node of two primitives, a point
# inside the other's box, ties its split exactly, and JAX rounded the split below the leaf
TIED_LEAF_BOXES = np.array([
    [0.07927519083023071, 0.7507896423339844, 0.49363234639167786, 0.4211066663265228, 0.8380655646324158, 0.609110414981842],
    [-0.8279573321342468, -0.5653653740882874, 0.6929411292076111, -0.27121391892433167, -0.23396947979927063, 0.8012726306915283],
    [-1.2546864748001099, 0.4499853253364563, 0.4232305884361267, -0.7242523431777954, 0.8349283337593079, 0.7650471329689026],
    [-0.1770164519548416, -0.5172217488288879, -0.5149955153465271, 0.04875626042485237, -0.2706485688686371, -0.3713020086288452],
    [-0.5016779899597168, -0.37271302938461304, -0.13122254610061646, -0.478843629360199, 0.15301825106143951, 0.14941558241844177],
    [0.10699470341205597, 0.9910005927085876, 0.5853238105773926, 0.10699470341205597, 0.9910005927085876, 0.5853238105773926],
    [0.23679940402507782, 0.8662647008895874, -0.5784876942634583, 0.2519175112247467, 1.0895758867263794, -0.56027752161026],
    [-0.7164435386657715, -0.06506525725126266, -1.109444260597229, -0.6427083015441895, 0.5152236819267273, -0.7147877812385559],
    [-1.057105541229248, -0.12734438478946686, -0.3294306993484497, -0.8001733422279358, 0.18689967691898346, 0.1942548155784607],
    [0.7310723662376404, 0.08136521279811859, -0.17687001824378967, 0.9375987648963928, 0.4355398118495941, 0.23334060609340668],
    [-0.112877257168293, -0.660699725151062, -1.2059861421585083, 0.10037100315093994, -0.34924060106277466, -0.7468377351760864],
    [-0.887949526309967, 0.3387455642223358, -0.8788123726844788, -0.3424419164657593, 0.42938292026519775, -0.3187607228755951],
    [-0.26248103380203247, -1.2184247970581055, 0.4169374108314514, -0.2593737244606018, -0.7666382789611816, 0.9032534956932068],
    [-0.6910778284072876, -0.4648014008998871, 0.7606642842292786, -0.6910778284072876, -0.4648014008998871, 0.7606642842292786],
    [0.015300259925425053, 0.5057619214057922, 0.041527241468429565, 0.02386298030614853, 0.8828390836715698, 0.5173414349555969],
    [0.32964080572128296, -1.0347635746002197, 0.014360600151121616, 0.637442946434021, -0.5992539525032043, 0.15021468698978424],
    [-0.04401186853647232, 0.6337406635284424, -0.3312937021255493, 0.07510081678628922, 0.8516168594360352, -0.22365006804466248],
    [0.09254969656467438, -1.1659339666366577, -0.396736204624176, 0.3001865744590759, -0.5970594882965088, -0.05273658037185669],
    [-0.45594772696495056, -0.7810579538345337, 0.347064346075058, -0.2519069015979767, -0.6181431412696838, 0.9182880520820618],
    [-0.3744511306285858, 0.6633773446083069, 0.02532658912241459, -0.10776419192552567, 1.2516142129898071, 0.33464017510414124],
    [0.05376267060637474, 0.007031000219285488, 0.1300702691078186, 0.3664623498916626, 0.544955313205719, 0.5757307410240173],
    [-0.8726198077201843, -0.24736791849136353, -0.7843284606933594, -0.5242280960083008, 0.008621790446341038, -0.2574157118797302],
    [-0.3184972405433655, -1.083419680595398, 0.9150415062904358, -0.07150956243276596, -0.52976393699646, 0.956270694732666],
    [-0.6989910006523132, 0.18767587840557098, -0.6844412684440613, -0.4409928619861603, 0.4993847608566284, -0.11387837678194046],
    [0.7481540441513062, 0.3244294822216034, -0.736768364906311, 0.7481540441513062, 0.3244294822216034, -0.736768364906311],
    [0.4750228822231293, 0.7010096907615662, 0.5163653492927551, 0.9052743911743164, 1.0787830352783203, 1.099301815032959]], np.float32)


def test_a_leaf_that_ties_its_split_stays_a_leaf():
    lo, hi = TIED_LEAF_BOXES[:, :3], TIED_LEAF_BOXES[:, 3:]
    got = jaxbvh.build(lo, hi, method="binned", max_leaf=3, bins=4)
    want = reference.build(lo, hi, configs.BinnedConfig(max_leaf=3, bins=4))
    assert canonical(got) == canonical(want)
    leaves = jaxbvh.to_numpy(got).prim_count
    assert (leaves == 2).any()  # the tied pair is one leaf
