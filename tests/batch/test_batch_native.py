"""jaxbvh.batch.trace on the native engine: the same hits and counters as the JAX batch
and as the single native trace, mesh by mesh; a broken tree fails naming its mesh, or
alone (``errors="keep"``)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_batch import ONE_GROUP, soup_lists

import jaxbvh
from jaxbvh import batch
from jaxbvh.batch.layout import TreeBatch
from jaxbvh.testing.plugin import examples

pytest.importorskip("numba")

FIELDS = ("t", "prim", "u", "v", "box_tests", "prim_tests", "nodes_visited", "leaves_visited", "step_limit")


def meshes_and_rays(soups, n_rays=24):
    triangles = [np.asarray(tri, np.float32) for tri in soups]
    boxes = [(tri.min(axis=1), tri.max(axis=1)) for tri in triangles]
    rays = [jaxbvh.rays.random_rays(jax.random.key(i), lo.min(0), hi.max(0), n_rays) for i, (lo, hi) in
            enumerate(boxes)]
    return boxes, triangles, [np.asarray(o) for o, _ in rays], [np.asarray(d) for _, d in rays]


@settings(max_examples=examples(4), deadline=None)
@given(soups=soup_lists, mode=st.sampled_from(["closest", "any", "all"]))
def test_native_batch_trace_equals_the_jax_batch_and_the_single_trace(soups, mode):
    """Mesh by mesh: every field equal to the single native trace (bit for bit), and to
    the JAX batch on every ray whose ``t``, ``u``, ``v`` both compute to the same bit
    (XLA contracts multiply-adds, numba does not: jaxbvh.rays.native), distances close
    on the rest."""
    boxes, triangles, origin, direction = meshes_and_rays(soups)
    trees = batch.build(boxes, batch=ONE_GROUP).trees
    native = batch.trace(trees, triangles, origin, direction, mode=mode, engine="native")
    jax_hits = batch.trace(trees, triangles, origin, direction, mode=mode, engine="jax", rays_per_call=32)
    for i, tree in enumerate(trees.unstack()):
        single = jaxbvh.rays.trace(tree, triangles[i], origin[i], direction[i], mode=mode, engine="native")
        same = np.ones(len(origin[i]), bool)
        for name in ("t", "u", "v"):
            same &= getattr(native[i], name) == getattr(jax_hits[i], name)
        same |= np.isinf(native[i].t) & np.isinf(jax_hits[i].t)
        for name in FIELDS + (("hit_count", "hit_prims") if mode == "all" else ()):
            got = np.asarray(getattr(native[i], name))
            np.testing.assert_array_equal(got, getattr(single, name), err_msg=f"mesh {i} {name}: single")
            want = np.asarray(getattr(jax_hits[i], name))
            bad = (got != want).reshape(len(got), -1).any(axis=1) & same
            assert not bad.any(), f"mesh {i} {mode} {name} differs from the JAX batch on rays {np.flatnonzero(bad)}"
        hit = np.isfinite(native[i].t) & np.isfinite(jax_hits[i].t)
        np.testing.assert_allclose(native[i].t[hit], jax_hits[i].t[hit], rtol=1e-5)


def test_a_broken_tree_fails_naming_its_mesh():
    """A tree whose root is its own left child: the native batch stops at the step bound
    and names the mesh (as the JAX batch does)."""
    rng = np.random.default_rng(0)
    soups = [rng.uniform(-1, 1, (n, 3, 3)).astype(np.float32) for n in (6, 9)]
    boxes, triangles, origin, direction = meshes_and_rays(soups, 8)
    trees = batch.build(boxes, batch=ONE_GROUP).trees
    group = trees.groups[0]
    bad = int(np.flatnonzero(group.index == 1)[0])
    left = np.array(group.trees.left)
    left[bad, int(np.asarray(group.trees.root)[bad])] = int(np.asarray(group.trees.root)[bad])
    broken = TreeBatch((dataclasses.replace(group, trees=dataclasses.replace(group.trees, left=left)),)
                       + trees.groups[1:], trees.size)
    for engine in ("native", "jax"):
        with pytest.raises(ValueError, match="mesh 1"):
            batch.trace(broken, triangles, origin, direction, engine=engine)
        # errors="keep": the broken mesh alone is left out, named in one warning; the other delivered
        with pytest.warns(UserWarning, match=r"1 mesh\(es\) left out .*mesh 1:"):
            kept = batch.trace(broken, triangles, origin, direction, engine=engine, errors="keep")
        assert kept[1] is None
        single = jaxbvh.rays.trace(trees.unstack()[0], triangles[0], origin[0], direction[0], engine=engine)
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(kept[0], name), getattr(single, name), err_msg=f"{engine} {name}")
    with pytest.raises(ValueError, match="errors must be"):
        batch.trace(trees, triangles, origin, direction, errors="skip")
