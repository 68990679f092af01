"""The native engine of the two-level walk (jaxbvh.twolevel.native) against its NumPy twin
(jaxbvh.twolevel.traversal_reference) and the JAX walk (jaxbvh.twolevel.traversal).

Scenes are test_twolevel's: instances with rotations, scales, shears and mirrors,
overlapping objects, re-braided top levels that open objects; float32 and float64; rays
that hit, miss, graze (aimed at triangle corners) and run along the axes (zero
direction components). Native and twin agree bit for bit on every field (neither
contracts multiply-adds); the JAX walk agrees on every field of every ray whose
distance it computes to the same bit, and to a few ulps of the coordinates on the rest
(XLA contracts multiply-adds in the instance transform).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_twolevel import OPTIONS, SHAPES, forest_scenes, random_scenes, small_tree

import jaxbvh
from jaxbvh import scenes, twolevel
from jaxbvh.testing.plugin import examples
from jaxbvh.tree.validate import InvalidTreeError
from jaxbvh.twolevel import objects as fm
from jaxbvh.twolevel import traversal_reference as ref

pytest.importorskip("numba")

FIELDS = ("t", "prim", "u", "v", "box_tests", "prim_tests", "nodes_visited", "leaves_visited", "step_limit")
COUNTERS = ("box_tests", "prim_tests", "nodes_visited", "leaves_visited")


@st.composite
def scenes_with_copies(draw):
    """test_twolevel's scenes, some with an instance placed twice (the same triangles
    twice: equal distances on two world ids, the tie the lower id wins)."""
    mesh = draw(st.one_of(random_scenes(), forest_scenes()))
    if draw(st.booleans()):
        mesh = scenes.assemble(mesh.objects, list(mesh.instances) + [mesh.instances[-1]], name="copies")
    return mesh


def built(mesh, options, dtype=np.float32):
    """The two-level tree of ``mesh`` (NumPy arrays, floats in ``dtype``)."""
    tl = jaxbvh.to_numpy(twolevel.build_from(mesh, fm.build_objects(mesh), threshold=options["threshold"],
                                             budget=options["budget"], overlap=options["overlap"],
                                             estimate=options["estimate"], rounds=options["rounds"], shapes=SHAPES))
    return as_dtype(tl, dtype)


def as_dtype(tree, dtype):
    """Every float array of a (nested) dataclass of arrays in ``dtype``."""
    def cast(x):
        if dataclasses.is_dataclass(x):
            return dataclasses.replace(x, **{f.name: cast(getattr(x, f.name)) for f in dataclasses.fields(x)})
        x = np.asarray(x)
        return x.astype(dtype) if x.dtype.kind == "f" else x
    return cast(tree)


def scene_rays(mesh, seed, n=48):
    """Rays from outside the scene's box: into it (most hit), away from it (miss), at
    triangle corners (grazing: through shared edges and corners), along the axes."""
    rng = np.random.default_rng(seed)
    tri = np.asarray(mesh.local_triangles(), np.float64)
    lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
    centre, size = (lo + hi) / 2, np.maximum(hi - lo, np.abs(hi).max() * 1e-3 + 1e-30)
    origin = centre + size * rng.normal(size=(n, 3)) * 1.5
    target = lo + size * rng.uniform(size=(n, 3))
    q = n // 4
    target[:q] = tri[rng.integers(0, len(tri), q), rng.integers(0, 3, q)]  # corners: grazing
    direction = target - origin
    direction[q:2 * q] *= -1  # away: misses
    axis = rng.integers(0, 3, q)
    direction[2 * q:3 * q] = 0
    direction[2 * q + np.arange(q), axis] = np.sign(centre - origin)[2 * q + np.arange(q), axis]
    origin[2 * q + np.arange(q)] = target[2 * q + np.arange(q)]
    origin[2 * q + np.arange(q), axis] = (centre - size)[axis]  # along an axis through the box
    return origin.astype(np.float32), direction.astype(np.float32)


def twin_field(twin, name, dtype):
    return np.array([r[name] for r in twin]).astype(dtype)


def assert_equal_to_twin(hits, twin, where=""):
    for name in FIELDS:
        got = np.asarray(getattr(hits, name))
        expected = twin_field(twin, name, got.dtype)
        bad = np.flatnonzero(got != expected)
        assert bad.size == 0, f"{where}{name} differs on rays {bad[:5]}: {got[bad[:5]]} vs {expected[bad[:5]]}"


@settings(max_examples=examples(12), deadline=None)
@given(mesh=scenes_with_copies(), options=OPTIONS, seed=st.integers(0, 2**32 - 1),
       dtype=st.sampled_from(["float32", "float64"]), mode=st.sampled_from(["closest", "any"]),
       capacity=st.sampled_from([2, 3, 64]))
def test_native_walk_equals_the_twin_bit_for_bit(mesh, options, seed, dtype, mode, capacity):
    """Hits, barycentrics and every counter, ray by ray (stacks of 2-3 spill and climb
    through objects and the top level; checked to fail with the tie rule reversed, the
    visiting order reversed and the climb's tag check dropped)."""
    tl = built(mesh, options, np.dtype(dtype))
    origin, direction = scene_rays(mesh, seed)
    with jax.enable_x64(dtype == "float64"):
        hits = twolevel.trace(tl, origin, direction, mode=mode, capacity=capacity, engine="native")
    twin = ref.trace(tl, origin, direction, dtype=np.dtype(dtype), mode=mode, capacity=capacity,
                     step_limit=twolevel.step_bound(tl))
    assert_equal_to_twin(hits, twin, f"{mode} {dtype} cap {capacity}: ")
    assert hits.t.dtype == np.dtype(dtype) and hits.prim.dtype == np.int32
    if mode == "closest":  # hit or miss as the brute force says (an independent check), grazing rays
        # apart (at a corner the object frame and the world frame may round to either side)
        rest = slice(len(origin) // 4, None)
        t_brute, _ = twolevel.brute_force(np.asarray(mesh.local_triangles(), np.float32), origin[rest], direction[rest])
        np.testing.assert_array_equal(np.isfinite(hits.t[rest]), np.isfinite(t_brute))


@settings(max_examples=examples(6), deadline=None)
@given(mesh=st.one_of(random_scenes(), forest_scenes()), options=OPTIONS, seed=st.integers(0, 2**32 - 1),
       mode=st.sampled_from(["closest", "any"]))
def test_native_walk_equals_the_jax_walk(mesh, options, seed, mode):
    """Every field equal on each ray whose ``t``, ``u``, ``v`` both engines compute to the
    same bit; XLA contracts multiply-adds in the instance transform and numba does not,
    so the others differ in the last bits of the object-frame ray: there the counters
    and the primitive still agree on almost every ray (a grazing ray may flip) and the
    distance is within a few ulps of the ray's reach (the twin test holds them exact)."""
    tl = built(mesh, options)
    origin, direction = scene_rays(mesh, seed)
    native = twolevel.trace(tl, origin, direction, mode=mode, capacity=2, engine="native")
    jax_hits = twolevel.trace(tl, origin, direction, mode=mode, capacity=2, engine="jax")
    same = np.ones(len(origin), bool)
    for name in ("t", "u", "v"):
        same &= (getattr(native, name) == getattr(jax_hits, name)) | (np.isinf(native.t) & np.isinf(jax_hits.t))
    for name in FIELDS:
        got, want = np.asarray(getattr(native, name)), np.asarray(getattr(jax_hits, name))
        assert got.dtype == want.dtype, name
        bad = np.flatnonzero((got != want) & same)
        assert bad.size == 0, f"{name} differs on rays {bad[:5]}: {got[bad[:5]]} vs {want[bad[:5]]}"
        if name in COUNTERS + ("prim",):
            assert np.mean(got != want) <= 0.1, f"{name} differs on {np.sum(got != want)} of {len(got)} rays"
    hit = np.isfinite(native.t) & np.isfinite(jax_hits.t)
    if mode == "closest":  # any-hit may stop at another hit where a grazing ray flips
        # in units of |direction| (a ray that hits has one)
        reach = (np.abs(origin[hit]).max(1) + np.abs(np.asarray(mesh.local_triangles())).max()) \
            / np.linalg.norm(direction[hit], axis=1)
        np.testing.assert_array_less(np.abs(native.t[hit] - jax_hits.t[hit]),
                                     64 * np.finfo(np.float32).eps * (np.abs(native.t[hit]) + reach) + 1e-45)


def _cyclic(tl, level):
    """``tl`` with a cycle: the top-level root its own left child, or an object's root
    its own left child."""
    if level == "top":
        top = tl.top
        left = np.array(top.left)
        left[int(top.root)] = int(top.root)
        return dataclasses.replace(tl, top=dataclasses.replace(top, left=left))
    f = tl.forest
    left = np.array(f.left)
    r = int(np.asarray(tl.bref_node)[0])
    left[r] = r
    return dataclasses.replace(tl, forest=dataclasses.replace(f, left=left))


@pytest.mark.parametrize("level", ["top", "forest"])
def test_a_cyclic_tree_raises_and_does_not_hang(level):
    """The step bound ends every ray of a tree with a cycle (in the top level, in an
    object) and the driver raises; checked to hang without the bound."""
    mesh = scenes.instanced_scene(jax.random.key(2), [small_tree(3)], 3, spread=0.2)
    tl = built(mesh, dict(threshold=np.inf, budget=1.0, overlap=0.1, estimate=False, rounds=1))
    broken = _cyclic(tl, level)
    origin, direction = scene_rays(mesh, 0, 16)
    with pytest.raises(InvalidTreeError, match="bound of"):
        twolevel.trace(broken, origin, direction, engine="native", capacity=64)


def test_native_inside_jit_raises_the_clear_error():
    mesh = scenes.instanced_scene(jax.random.key(2), [small_tree(3)], 2, spread=0.2)
    tl = built(mesh, dict(threshold=np.inf, budget=1.0, overlap=0.1, estimate=False, rounds=1))
    origin, direction = scene_rays(mesh, 0, 4)
    with pytest.raises(TypeError, match="cannot run inside"):
        jax.jit(lambda o, d: twolevel.closest_hit(tl, o, d, engine="native").t)(jnp.asarray(origin),
                                                                                  jnp.asarray(direction))
