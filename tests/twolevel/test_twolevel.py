"""Two-level BVHs with re-braiding (jaxbvh.forest, jaxbvh.brefs, jaxbvh.twolevel, jaxbvh.scenes).

Random scenes: a few small objects (hypothesis triangle soups, extreme scales included)
placed by instances with identity, rigid, scaled, sheared and mirroring transforms.
Every array is padded to one shape (SHAPES) so the top-level build and the traversal
compile once for all examples.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh import scenes, twolevel
from jaxbvh.rays.traversal import moller_trumbore
from jaxbvh.testing.plugin import examples
from jaxbvh.tree.validate import InvalidTreeError
from jaxbvh.twolevel import brefs
from jaxbvh.twolevel import brefs_reference as ref
from jaxbvh.twolevel import objects as fm
from jaxbvh.twolevel.brefs_segments import widest_rank
from jaxbvh.twolevel.config import RebraidConfig
from tests.strategies import triangle_soups

SHAPES = {"nodes": 128, "prims": 64, "instances": 8, "brefs": 32, "boxes": 512}
FLAT = (512, 256)  # flattened trees padded to one shape for the traversal
STACK = 48


def _transform(rng, kind):
    if kind == "identity":
        return np.eye(4)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.diag(r))
    if np.linalg.det(rotation) < 0:
        rotation[:, 0] *= -1
    m = np.eye(4)
    if kind == "rigid":
        m[:3, :3] = rotation * rng.uniform(0.5, 2.0)
    elif kind == "affine":  # non-uniform scale and shear
        m[:3, :3] = rotation @ np.diag(rng.uniform(0.3, 3.0, 3)) @ (np.eye(3) + np.triu(rng.normal(0, 0.5, (3, 3)), 1))
    elif kind == "mirror":
        m[:3, :3] = rotation @ np.diag([-1.0, 1.0, 1.0])
    return m


@st.composite
def random_scenes(draw, max_objects=3, max_instances=8):
    """A :class:`Mesh` of 1-3 soups of <= 10 triangles and 2-8 instances of them.

    The whole scene sits at one scale (1e-30 ... 1e30), as a real scene would.
    """
    n_obj = draw(st.integers(1, max_objects))
    soups = [draw(triangle_soups(min_size=1, max_size=10, extreme=False)) for _ in range(n_obj)]
    scale = 10.0 ** draw(st.sampled_from([0, -30, 10, 30]))
    soups = [tri * scale for tri in soups]
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n_inst = draw(st.integers(2, max_instances))
    spread = draw(st.sampled_from([0.0, 0.3, 1.0, 3.0]))
    objects = [(tri.reshape(-1, 3), np.arange(3 * tri.shape[0]).reshape(-1, 3)) for tri in soups]
    instances = []
    for _ in range(n_inst):
        obj = int(rng.integers(n_obj))
        kind = rng.choice(["identity", "rigid", "affine", "mirror"], p=[0.25, 0.35, 0.25, 0.15])
        m = _transform(rng, kind)
        tri = soups[obj]
        size = float(np.ptp(tri.reshape(-1, 3), axis=0).max()) or 1.0
        if kind != "identity":
            m[:3, 3] = rng.normal(size=3) * spread * size
        instances.append((obj, m))
    return scenes.assemble(objects, instances, name="random")


def small_tree(seed):
    """A 22-triangle tree: fits SHAPES."""
    return scenes.tree_mesh(jax.random.key(seed), levels=1, branches=2, sides=3, leaves=1)


@st.composite
def forest_scenes(draw):
    """2-8 overlapping instances of one or two 22-triangle trees (deep enough to open)."""
    seeds = draw(st.lists(st.integers(0, 1000), min_size=1, max_size=2))
    return scenes.instanced_scene(jax.random.key(draw(st.integers(0, 2**31 - 1))),
                                  [small_tree(k) for k in seeds], draw(st.integers(2, 8)),
                                  spread=draw(st.sampled_from([0.2, 0.5, 1.0])), upright=draw(st.booleans()))


def top_level(mesh, trees, **options):
    forest, inst = fm.pack(mesh, trees, capacity=SHAPES)
    n = len(mesh.instances)
    result = brefs.build_top_level(forest, inst, n, array_size=SHAPES["brefs"], **options)
    return forest, inst, jaxbvh.to_numpy(result)


def canonical(top, slot_of):
    """Top-level tree as nested tuples; a leaf is its BRef's slot in the build array."""
    def rec(n):
        box = (tuple(top.lo[n].tolist()), tuple(top.hi[n].tolist()))
        if top.prim_count[n] > 0:
            return ("leaf", int(slot_of(top.prim_index[top.prim_start[n]])), box)
        return (int(top.axis[n]), rec(int(top.left[n])), rec(int(top.right[n])), box)
    return rec(int(top.root))


OPTIONS = st.fixed_dictionaries({
    "threshold": st.sampled_from([0.02, 0.1, 0.3, math.inf]),
    "budget": st.sampled_from([1.0, 1.5, 2.0, 4.0]),
    "overlap": st.sampled_from([0.0, 0.1, 0.5]),
    "estimate": st.booleans(),
    "rounds": st.sampled_from([1, 2, 64]),
})


# ----------------------------------------------------------------------------------
# The top-level build against its recursive twin
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(10))
@given(mesh=st.one_of(random_scenes(), forest_scenes()), options=OPTIONS, world_space=st.booleans())
def test_top_level_equals_reference_bref_by_bref(mesh, options, world_space):
    trees = fm.build_objects(mesh, world_space=world_space)
    forest, inst, res = top_level(mesh, trees, **options)
    n = len(mesh.instances)
    slots = brefs.brefs_capacity(n, options["threshold"], options["budget"])
    top_r, br = ref.build_top_level(forest, inst, n, threshold=options["threshold"], slots=slots,
                                    overlap=options["overlap"], estimate=options["estimate"], rounds=options["rounds"])
    count = int(res.count)
    position = res.position[:count]
    # every BRef in the same slot with the same node, instance, box and count
    np.testing.assert_array_equal(position, np.flatnonzero(br["node"] >= 0))
    for key in ("node", "instance", "prims", "lo", "hi"):
        np.testing.assert_array_equal(getattr(res, key)[:count], br[key][position], err_msg=key)
    assert count <= slots
    assert canonical(res.top, lambda b: res.position[b]) == canonical(top_r, lambda s: s)
    # the top level is a valid BVH over its BRefs, one BRef per leaf
    jaxbvh.validate(res.top, res.lo[:count], res.hi[:count])
    assert set(res.top.prim_count[res.top.prim_count > 0].tolist()) == {1}
    if math.isinf(options["threshold"]):  # plain two-level: the instances' roots
        assert count == n
        np.testing.assert_array_equal(np.sort(res.instance[:count]), np.arange(n))
        np.testing.assert_array_equal(res.node[:count], forest.root[inst.object[res.instance[:count]]])


@pytest.mark.parametrize("seed, spread, threshold, budget", [(0, 0.5, 0.05, 3.0), (1, 0.2, 0.3, 4.0),
                                                           (4, 0.5, 0.05, 3.0), (2, 0.2, 0.3, 4.0)])
def test_top_level_equals_reference_on_forests(seed, spread, threshold, budget):
    """Forests where how the spare room is split decides which BRefs open (checked: a spare
    split in the wrong proportion, or ties to the highest axis, fail here)."""
    mesh = scenes.instanced_scene(jax.random.key(seed), [small_tree(seed), small_tree(seed + 10)], 8,
                                  spread=spread)
    trees = fm.build_objects(mesh)
    forest, inst, res = top_level(mesh, trees, threshold=threshold, budget=budget)
    _, br = ref.build_top_level(forest, inst, 8, threshold=threshold,
                                slots=brefs.brefs_capacity(8, threshold, budget))
    count = int(res.count)
    assert count > 8  # opened something
    np.testing.assert_array_equal(res.position[:count], np.flatnonzero(br["node"] >= 0))
    for key in ("node", "instance", "prims", "lo", "hi"):
        np.testing.assert_array_equal(getattr(res, key)[:count], br[key][res.position[:count]], err_msg=key)


def _segmented_widths(rng, size):
    """Random contiguous segments over ``size`` slots (BRefs, then spare room) with few
    distinct widths (many ties) and candidates among the BRefs."""
    starts = np.sort(rng.choice(size, max(1, size // 5), replace=False))
    starts[0] = 0
    ends = starts + (rng.random(starts.size) * (np.append(starts[1:], size) - starts + 1)).astype(int)
    k = np.searchsorted(starts, np.arange(size), side="right") - 1
    block = np.arange(size) < ends[k]
    start = np.where(block, starts[k], size).astype(np.int32)
    length = np.where(block, ends[k] - starts[k], 0).astype(np.int32)
    width = (rng.integers(0, 5, size) / 4).astype(np.float32)
    return width, block & (rng.random(size) < 0.6), block, start, length


@pytest.mark.parametrize("size", [64, 46341])  # keys below 2^31, and the lexsort beyond
def test_widest_rank_orders_each_segments_candidates_by_width_then_slot(size):
    """The opening's widest-first rank (one sort of encoded int keys) equals a lexsort by
    (segment, width descending, slot) (checked: fails with the slot offset left out of the
    key or with the width order reversed)."""
    rng = np.random.default_rng(size)
    for _ in range(5 if size < 1000 else 1):
        width, candidate, block, start, length = _segmented_widths(rng, size)
        got = np.asarray(jax.jit(widest_rank)(width, candidate, block, start, length))
        seg = np.where(candidate, start, size)
        order = np.lexsort((np.arange(size), -width, seg))
        first = np.searchsorted(seg[order], seg[order])
        expected = np.empty(size, np.int64)
        expected[order] = np.arange(size) - first
        np.testing.assert_array_equal(got[candidate], expected[candidate])


@settings(max_examples=examples(10))
@given(mesh=st.one_of(random_scenes(), forest_scenes()), options=OPTIONS)
def test_flattened_tree_is_valid_and_traversal_finds_the_closest_hits(mesh, options):
    trees = fm.build_objects(mesh)
    tl = twolevel.build_from(mesh, trees, threshold=options["threshold"], budget=options["budget"],
                             overlap=options["overlap"], estimate=options["estimate"], rounds=options["rounds"],
                             shapes=SHAPES)
    flat = twolevel.flatten(tl, pad=False)
    lo, hi = mesh.local_boxes()
    jaxbvh.validate(flat, lo, hi)  # conservative world boxes contain the float32 triangle boxes
    # the BRefs are a cut: every world triangle under exactly one BRef (validate checked ids)
    assert int(np.asarray(tl.bref_prims)[: int(tl.bref_count)].sum()) == mesh.n_triangles or options["estimate"]
    flat = jaxbvh.tree.pad_to(flat, *FLAT)

    tri = np.zeros((FLAT[1], 3, 3), np.float32)  # degenerate padding: never hit; one shape
    tri[:mesh.n_triangles] = mesh.local_triangles()
    key = jax.random.key(0)
    origin, direction = jaxbvh.rays.make_rays(key, "random", flat, tri, 200)
    hits = twolevel.closest_hit(tl, origin, direction, capacity=STACK, engine="jax")
    t_brute, p_brute = twolevel.brute_force(tri, origin, direction)
    flat_hits = jaxbvh.rays.closest_hit(flat, tri, origin, direction, capacity=STACK)
    for name, t, prim in (("two-level", hits.t, hits.prim), ("flattened", flat_hits.t, flat_hits.prim)):
        np.testing.assert_array_equal(np.isfinite(t), np.isfinite(t_brute), err_msg=name)
        hit = np.isfinite(t)
        np.testing.assert_allclose(t[hit], t_brute[hit], rtol=1e-4, atol=1e-6, err_msg=name)
        # the same triangle, or one the brute force finds at the same distance (a shared edge)
        other = hit & (prim != p_brute)
        if other.any():
            t_other, _, _ = moller_trumbore(*np.moveaxis(tri[prim[other]], 1, 0), origin[other], direction[other])
            np.testing.assert_allclose(np.asarray(t_other), t_brute[other], rtol=1e-4, atol=1e-6, err_msg=name)
    assert (hits.box_tests >= 1).all() and (hits.prim_tests >= (hits.prim >= 0)).all()


@settings(max_examples=examples(6))
@given(mesh=st.one_of(random_scenes(), forest_scenes()), options=OPTIONS)
def test_a_short_stack_climbs_to_the_same_hits_and_primitive_tests(mesh, options):
    """A stack of 2 entries spills on almost every ray: the parent-link climb (through the
    forest, back to the top-level leaf a ray entered by, up the top level) finds the
    same closest hits with the same primitive tests as a stack that never spills."""
    trees = fm.build_objects(mesh)
    tl = twolevel.build_from(mesh, trees, threshold=options["threshold"], budget=options["budget"],
                             overlap=options["overlap"], estimate=options["estimate"], rounds=options["rounds"],
                             shapes=SHAPES)
    flat = jaxbvh.tree.pad_to(twolevel.flatten(tl, pad=False), *FLAT)
    origin, direction = jaxbvh.rays.make_rays(jax.random.key(1), "random", flat, None, 200)
    roomy = twolevel.closest_hit(tl, origin, direction, capacity=twolevel.stack_capacity(tl), engine="jax")
    short = twolevel.closest_hit(tl, origin, direction, capacity=2, engine="jax")
    # two compiled programs (stack sizes): the instance transform may round apart in the last bit
    np.testing.assert_allclose(short.t, roomy.t, rtol=1e-5)
    np.testing.assert_array_equal(short.prim, roomy.prim)
    np.testing.assert_array_equal(short.prim_tests, roomy.prim_tests)
    assert (short.box_tests >= roomy.box_tests).all()  # a climb tests its parent's children again
    assert not short.stack_overflow.any() and not short.step_limit.any()


# ----------------------------------------------------------------------------------
# Properties of the pieces
# ----------------------------------------------------------------------------------


def _subtree_triangles(forest, node):
    """Primitive ids below ``node`` of a forest (object-triangle ids) or a tree."""
    below, out = [node], []
    while below:
        m = below.pop()
        if forest.left[m] >= 0:
            below += [forest.left[m], forest.right[m]]
        else:
            s0 = forest.prim_start[m]
            out += list(forest.prim_index[s0:s0 + forest.prim_count[m]])
    return np.asarray(out)


@settings(max_examples=examples(10))
@given(mesh=st.one_of(random_scenes(), forest_scenes()))
def test_placed_boxes_are_the_tight_world_boxes_of_their_triangles(mesh):
    """Every (instance, node) box holds the node's triangles as the instance places them
    (exactly transformed, and as the world triangles of Mesh.local_triangles), lies
    within the margin of their exact box (much tighter than the node's transformed
    corners under a rotation), nests in its parent's, and is the node's own box under
    the identity; the look-up is the same in JAX and NumPy."""
    forest, inst = fm.pack(mesh, fm.build_objects(mesh), pad=False)
    world = mesh.local_triangles()
    eps = float(np.finfo(np.float32).eps)
    rows_n, rows_i = [], []
    for i, (obj, _) in enumerate(mesh.instances):
        nodes, todo = [], [int(forest.root[obj])]  # the object's nodes
        while todo:
            nodes.append(todo.pop())
            if forest.left[nodes[-1]] >= 0:
                todo += [forest.left[nodes[-1]], forest.right[nodes[-1]]]
        nodes = np.asarray(nodes)
        rows_n.append(nodes)
        rows_i.append(np.full(nodes.size, i))
    nodes, k = np.concatenate(rows_n), np.concatenate(rows_i)
    lo, hi = fm.bref_boxes(inst, nodes, k)
    j_lo, j_hi = jax.jit(fm.bref_boxes)(jaxbvh.to_jax(inst), nodes, k)
    np.testing.assert_array_equal(np.asarray(j_lo), lo)
    np.testing.assert_array_equal(np.asarray(j_hi), hi)
    m = inst.to_scene.astype(np.float64)
    for row, (n, i) in enumerate(zip(nodes, k)):
        g = _subtree_triangles(forest, n)
        v = forest.triangles[g].astype(np.float64).reshape(-1, 3) @ m[i, :, :3].T + m[i, :, 3]
        w = world[g + inst.prim_shift[i]].reshape(-1, 3)
        for pts in (v, w):
            assert np.all(lo[row] <= pts.min(0)) and np.all(pts.max(0) <= hi[row]), (n, i)
        # tight: off the exact box by no more than the margin (16 eps of the map's scale)
        scale = np.abs(m[i, :, 3]) + np.abs(m[i, :, :3]).sum(1) * np.abs(forest.triangles[g]).max()
        assert np.all(v.min(0) - lo[row] <= 16 * eps * scale + 1e-37), (n, i)
        assert np.all(hi[row] - v.max(0) <= 16 * eps * scale + 1e-37), (n, i)
        if inst.margin[i] == 0:
            np.testing.assert_array_equal(lo[row], forest.lo[n])
            np.testing.assert_array_equal(hi[row], forest.hi[n])
        p = forest.parent[n]
        if p >= 0:
            p_lo, p_hi = fm.bref_boxes(inst, np.array([p]), np.array([i]))
            assert np.all(p_lo[0] <= lo[row]) and np.all(hi[row] <= p_hi[0])
    # none: the empty box
    e_lo, e_hi = fm.bref_boxes(inst, np.array([-1]), np.array([0]))
    assert np.all(e_lo == np.inf) and np.all(e_hi == -np.inf)


@pytest.mark.parametrize("seed", [2, 5])
def test_a_pile_of_rotated_instances_keeps_its_opened_nodes(seed):
    """Piles of 4 rotated 22-triangle trees: with the boxes of the placed triangles the
    re-braided top level is lower than the plain one on both footings and kept (checked:
    with the union of corner boxes three levels down, the rule before, both kept the
    plain top level)."""
    mesh = scenes.pile(jax.random.key(seed), *small_tree(3), 4)
    trees = fm.build_objects(mesh)
    plain = twolevel.build_from(mesh, trees, threshold=math.inf, shapes=SHAPES)
    result = twolevel.run_from(mesh, trees, budget=4.0, shapes=SHAPES)
    tl = result.tree
    assert result.kept == "rebraided"
    for boxes in ("world", "object"):
        assert twolevel.sah(tl, boxes=boxes) < 0.95 * twolevel.sah(plain, boxes=boxes)


def test_a_node_box_that_misses_a_triangle_is_invalid():
    """The check behind every flattened tree: a re-braided pile whose opened BRef box, or
    a node below it, is shrunk off one of its world triangles fails jaxbvh.validate."""
    mesh = scenes.pile(jax.random.key(0), *small_tree(3), 4)
    tl = twolevel.build_from(mesh, fm.build_objects(mesh), budget=4.0, shapes=SHAPES)
    flat = twolevel.flatten(tl, pad=False)
    lo, hi = mesh.local_boxes()
    jaxbvh.validate(flat, lo, hi)
    top = np.asarray(tl.top.prim_count) > 0
    opened = np.asarray(tl.bref_node)[: int(tl.bref_count)] != np.asarray(tl.forest.root)[0]
    assert opened.any()  # BRefs below the roots reach the top level
    leaf = np.flatnonzero(top)[0]
    for node in (leaf, int(flat.left[leaf]) if flat.left[leaf] >= 0 else leaf):
        below = _subtree_triangles(flat, node)  # world triangle ids
        broken = flat.lo.copy()
        broken[node, 0] = np.nextafter(lo[below, 0].min(), np.inf)  # just off the lowest triangle
        with pytest.raises(jaxbvh.InvalidTreeError):
            jaxbvh.validate(dataclasses.replace(flat, lo=broken), lo, hi)


def test_plain_mesh_builds_no_top_level_and_equals_the_single_bvh():
    mesh = scenes.assemble([small_tree(3)], [(0, np.eye(4))])
    tl = twolevel.build(mesh, method="binned")
    assert int(tl.bref_count) == 1 and np.asarray(tl.top.left).shape == (1,)
    assert int(tl.bref_node[0]) == int(tl.forest.root[0]) and float(tl.instances.margin[0]) == 0
    lo, hi = mesh.local_boxes()
    single = jaxbvh.to_numpy(jaxbvh.build(lo, hi, method="binned", max_leaf=fm.OBJECT_MAX_LEAF))
    flat = twolevel.flatten(tl)
    jaxbvh.validate(flat, lo, hi)
    np.testing.assert_array_equal(jaxbvh.to_interchange(flat)["lo"], jaxbvh.to_interchange(single)["lo"])
    assert twolevel.sah(tl) == float(jaxbvh.sah(single))
    assert twolevel.stored_nodes(tl)["total"] == jaxbvh.tree.node_count(single) + 1


def test_object_frame_sah_bounds_and_limits():
    tree = small_tree(4)
    rng = np.random.default_rng(1)
    moved, turned = [], []
    for k in range(6):
        t = np.eye(4)
        t[:3, 3] = rng.normal(size=3)
        moved.append((0, t.copy()))
        t[:3, :3] = scenes.random_rotations(jax.random.key(k), 1)[0] * rng.uniform(0.5, 2)
        turned.append((0, t))
    for instances in (moved, turned):
        mesh = scenes.assemble([tree], instances)
        for threshold in (math.inf, 0.05):
            tl = twolevel.build_from(mesh, fm.build_objects(mesh), threshold=threshold, shapes=SHAPES)
            world, obj = twolevel.sah(tl), twolevel.sah(tl, boxes="object")
            if instances is moved:  # translated object boxes stay boxes: the same cost (but the margin)
                assert obj == pytest.approx(world, rel=1e-5)
            else:  # a rotated box has less area than the box around it
                assert obj < world
    # a plain mesh: the same tree, the same number
    plain = scenes.assemble([tree], [(0, np.eye(4))])
    tl = twolevel.build(plain)
    assert twolevel.sah(tl, boxes="object") == pytest.approx(twolevel.sah(tl), rel=1e-6)
    with pytest.raises(ValueError, match="boxes"):
        twolevel.sah(tl, boxes="local")


def test_object_frame_sah_of_a_skewed_instance_by_lagrange():
    """One instance under a rotation with unequal scales, its object built in its own
    frame: the object-frame SAH is the object tree's recursion with every node below the
    root costed by its parallelepiped's half area, computed here another way (Lagrange's
    identity, |a x b|^2 = |a|^2 |b|^2 - (a . b)^2), and the root by its world box."""
    transform = np.eye(4)
    transform[:3, :3] = np.asarray(scenes.random_rotations(jax.random.key(3), 1)[0]) @ np.diag([0.5, 1.0, 3.0])
    mesh = scenes.assemble([small_tree(2)], [(0, transform)])
    trees = fm.build_objects(mesh, world_space=False)
    tl = twolevel.build_from(mesh, trees, shapes=SHAPES)
    linear = np.asarray(fm.pack(mesh, trees, pad=False)[1].to_scene[0], np.float64)[:, :3]
    tree = jaxbvh.to_numpy(trees[0].tree)

    def area(node):
        ext = np.maximum(tree.hi[node].astype(np.float64) - tree.lo[node].astype(np.float64), 0)
        e = [linear[:, k] * ext[k] for k in range(3)]
        return sum(math.sqrt(max((a @ a) * (b @ b) - (a @ b) ** 2, 0.0)) for a, b in zip(e, e[1:] + e[:1]))

    def cost(node, own):
        if tree.left[node] < 0:
            return float(tree.prim_count[node])
        kids = (int(tree.left[node]), int(tree.right[node]))
        return 1.0 + sum(area(k) * cost(k, area(k)) for k in kids) / own

    d = np.maximum(np.asarray(tl.top.hi[0], np.float64) - np.asarray(tl.top.lo[0], np.float64), 0)
    world = d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    assert twolevel.sah(tl, boxes="object") == pytest.approx(cost(int(tree.root), world), rel=1e-6)


def test_estimated_counts_halve_from_the_object_count():
    mesh = scenes.instanced_scene(jax.random.key(3), [small_tree(0)], 6, spread=0.3)
    trees = fm.build_objects(mesh)
    forest, _, exact = top_level(mesh, trees, threshold=0.02, budget=4.0)
    _, _, guess = top_level(mesh, trees, threshold=0.02, budget=4.0, estimate=True)
    n = int(exact.count)
    assert n > 6  # something opened
    np.testing.assert_array_equal(exact.prims[:n], forest.subtree_prims[exact.node[:n]])
    # estimated counts: the object's count halved once per level below the root
    depth = jaxbvh.tree.depth(jaxbvh.BVH(left=forest.left, right=forest.right, parent=forest.parent,
                                         lo=forest.lo, hi=forest.hi, prim_start=forest.prim_start,
                                         prim_count=forest.prim_count, axis=forest.axis,
                                         prim_index=forest.prim_index, root=np.int32(0)))
    m = int(guess.count)
    total = forest.subtree_prims[forest.root[0]]
    for node, prims in zip(guess.node[:m], guess.prims[:m]):
        expect = total
        for _ in range(depth[node]):
            expect = max(expect // 2, 1)
        assert prims == expect


def test_top_level_compiles_once_for_every_threshold_and_scene():
    mesh = scenes.instanced_scene(jax.random.key(1), [small_tree(0)], 5)
    trees = fm.build_objects(mesh)
    top_level(mesh, trees, threshold=0.1)
    before = brefs.build_levels._cache_size()
    for threshold in (0.05, 0.5, math.inf):
        top_level(mesh, trees, threshold=threshold, budget=2.0)
    other = scenes.instanced_scene(jax.random.key(2), [small_tree(5)], 7)
    top_level(other, fm.build_objects(other), threshold=0.1)
    assert brefs.build_levels._cache_size() == before


def test_float64_build_matches_reference_and_validates():
    with jax.enable_x64(True):
        mesh = scenes.instanced_scene(jax.random.key(4), [small_tree(1)], 5, spread=0.3)
        trees = fm.build_objects(mesh, dtype=np.float64)
        forest, inst, res = top_level(mesh, trees, threshold=0.05)
        assert res.lo.dtype == np.float64 and forest.triangles.dtype == np.float64
        top_r, br = ref.build_top_level(forest, inst, 5, threshold=0.05, slots=20)
        count = int(res.count)
        np.testing.assert_array_equal(res.position[:count], np.flatnonzero(br["node"] >= 0))
        np.testing.assert_array_equal(res.lo[:count], br["lo"][res.position[:count]])
        tl = twolevel.build_from(mesh, trees, threshold=0.05, shapes=SHAPES)
        lo, hi = mesh.local_boxes(np.float64)
        jaxbvh.validate(twolevel.flatten(tl), lo, hi)


def _box_object(n_triangles):
    """``n_triangles`` copies of one triangle whose box is the unit cube."""
    v = np.array([[0.0, 0, 0], [1, 1, 1], [1, 0, 0]])
    return np.tile(v, (n_triangles, 1)), np.arange(3 * n_triangles).reshape(-1, 3)


def _shifted(obj, x):
    t = np.eye(4)
    t[0, 3] = x
    return (obj, t)


def test_bins_count_primitives_not_brefs():
    """Unit boxes at x = 0, 2, 4 with 1, 1 and 40 triangles: counting BRefs, both planes
    cost the same (and the lower one wins); counting primitives, the 40-triangle box goes
    alone (checked: binning that counts 1 per BRef fails here)."""
    mesh = scenes.assemble([_box_object(1), _box_object(40)],
                           [_shifted(0, 0.0), _shifted(0, 2.0), _shifted(1, 4.0)])
    for estimate in (False, True):
        _, _, res = top_level(mesh, fm.build_objects(mesh), threshold=math.inf, estimate=estimate)
        top = res.top
        root = int(top.root)
        left, right = int(top.left[root]), int(top.right[root])
        assert top.axis[root] == 0 and top.prim_count[left] == 0 and top.prim_count[right] == 1
        assert res.instance[top.prim_index[top.prim_start[right]]] == 2


def test_capacity_sets_the_bref_slots():
    """``capacity`` (e.g. the paper's #primitives / 1000) replaces ``budget`` x instances;
    as many slots as instances leave no room to open; fewer are refused."""
    mesh = _row_of_trees(0.0)  # three copies of one tree in one place: they open
    trees = fm.build_objects(mesh)
    _, _, roomy = top_level(mesh, trees, threshold=0.01, capacity=12)
    assert 3 < int(roomy.count) <= 12
    _, _, tight = top_level(mesh, trees, threshold=0.01, capacity=3)
    assert int(tight.count) == 3
    # room for one BRef more than instances: of the three equally wide roots the widest
    # opens, ties to the lowest slot (checked: opening all candidates or none leaves 3)
    forest, _, one = top_level(mesh, trees, threshold=0.01, capacity=4)
    assert int(one.count) == 4
    closed = one.instance[:4][one.node[:4] == forest.root[0]]
    assert sorted(closed.tolist()) == [1, 2]
    with pytest.raises(ValueError, match="capacity"):
        top_level(mesh, trees, threshold=0.01, capacity=2)


def _row_of_trees(step):
    """Three copies of one tree, shifted along x by ``step`` times its width."""
    v, f = small_tree(0)
    width = float(np.ptp(v[:, 0]))
    return scenes.assemble([(v, f)], [_shifted(0, k * step * width) for k in range(3)])


@pytest.mark.parametrize("step, opens", [(3.0, False), (0.95, False), (0.5, True), (0.0, True)])
def test_few_barely_overlapping_brefs_stop_opening(step, opens):
    """<= 4 BRefs that overlap by less than ``overlap`` (10%) of the shorter extent on some
    axis are not opened, however wide; more overlap opens them (checked: without the
    termination test every case opens)."""
    mesh = _row_of_trees(step)
    _, _, res = top_level(mesh, fm.build_objects(mesh), threshold=0.01, budget=4.0)
    assert (int(res.count) > 3) == opens
    if not opens:
        np.testing.assert_array_equal(np.sort(res.instance[:3]), [0, 1, 2])


def test_traversal_of_a_cyclic_top_level_stops_at_its_bound():
    """A top level whose root is its own left child: the loop ends at its step bound and the
    driver raises InvalidTreeError (the stack is made large enough that the bound, not the stack, stops it)."""
    import dataclasses

    mesh = _row_of_trees(0.5)
    tl = jaxbvh.to_numpy(twolevel.build_from(mesh, fm.build_objects(mesh), threshold=math.inf, shapes=SHAPES))
    top = tl.top
    left = np.array(top.left)
    left[int(top.root)] = int(top.root)
    broken = dataclasses.replace(tl, top=dataclasses.replace(top, left=left))
    size = np.asarray(top.hi[int(top.root)] - top.lo[int(top.root)], np.float32)
    centre = np.asarray(top.lo[int(top.root)] + 0.5 * size, np.float32)
    origin = np.repeat((centre - size)[None], 4, 0)  # rays through the root box's centre
    direction = np.repeat(size[None], 4, 0)
    with pytest.raises(InvalidTreeError, match="bound of"):
        twolevel.closest_hit(broken, origin, direction, capacity=4 * twolevel.step_bound(broken), engine="jax")


@pytest.mark.parametrize("options, message", [
    ({"threshold": 0.0}, "threshold"), ({"threshold": -1.0}, "threshold"),
    ({"threshold": float("nan")}, "threshold"), ({"budget": 0.5}, "budget"),
    ({"budget": float("inf")}, "budget"), ({"top_bins": 1}, "bins"), ({"overlap": -0.1}, "overlap"),
])
def test_bad_options_raise(options, message):
    mesh = scenes.instanced_scene(jax.random.key(0), [scenes.room(1.0, 1.0)], 2)
    with pytest.raises(ValueError, match=message):
        twolevel.build(mesh, **options)


# ----------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------


def test_instanced_scene_places_its_instances():
    tree = small_tree(0)
    a = scenes.instanced_scene(jax.random.key(7), [tree], 10, upright=True)
    b = scenes.instanced_scene(jax.random.key(7), [tree], 10, upright=True)
    np.testing.assert_array_equal(a.triangles, b.triangles)  # same key, same scene
    assert a.n_triangles == 10 * tree[1].shape[0] and len(a.instances) == 10
    for obj, transform in a.instances:  # rotations about y only, on the ground
        np.testing.assert_allclose(transform[1, :3], [0, transform[1, 1], 0], atol=1e-12)
        assert transform[1, 3] == 0
    v, f = a.objects[0]
    _, t = a.instances[3]
    np.testing.assert_allclose(a.triangles[3 * f.shape[0]:4 * f.shape[0]], (v @ t[:3, :3].T + t[:3, 3])[f])


def test_dynamic_scene_reuses_static_objects_each_frame():
    dyn = scenes.dynamic_scene(jax.random.key(0), *small_tree(2), n_static=4, frames=3)
    first = dyn.frame(0)
    static = fm.build_objects(first, only=range(dyn.moving_object))
    for k in range(3):
        mesh = dyn.frame(k)
        # the room bounds everything: the scene frame, and so the static trees, stay valid
        assert mesh.frame.scale == first.frame.scale
        np.testing.assert_array_equal(mesh.frame.origin, first.frame.origin)
        trees = dict(static)
        trees.update(fm.build_objects(mesh, only=[dyn.moving_object]))
        tl = twolevel.build_from(mesh, trees, shapes=SHAPES)
        lo, hi = mesh.local_boxes()
        jaxbvh.validate(twolevel.flatten(tl), lo, hi)
    # a tree built for another placement is refused
    moved = scenes.assemble(first.objects, [(o, t @ np.diag([2.0, 1, 1, 1])) for o, t in first.instances])
    with pytest.raises(ValueError, match="rebuild"):
        fm.pack(moved, static | fm.build_objects(first, only=[dyn.moving_object]))


# ----------------------------------------------------------------------------------
# Never worse than two-level; the budget rule; the overlapping scenes
# ----------------------------------------------------------------------------------


@st.composite
def material_scenes(draw):
    """A 22-triangle tree split into 2-8 objects by normal direction, each placed once."""
    return scenes.by_material(*small_tree(draw(st.integers(0, 1000))), groups=draw(st.sampled_from([2, 4, 8])))


@settings(max_examples=examples(12))
@given(mesh=st.one_of(random_scenes(), forest_scenes(), material_scenes()), options=OPTIONS)
def test_rebraided_sah_never_exceeds_two_level(mesh, options):
    trees = fm.build_objects(mesh)
    plain = twolevel.build_from(mesh, trees, threshold=math.inf, shapes=SHAPES)
    config = RebraidConfig(threshold=options["threshold"], budget=options["budget"], overlap=options["overlap"],
                           estimate=options["estimate"], rounds=options["rounds"])
    result = twolevel.run_from(mesh, trees, config, shapes=SHAPES)
    tl, info = result.tree, result.kept
    assert twolevel.sah(tl) <= twolevel.sah(plain) * (1 + 1e-6), info
    # ... and in object frames, what the two-level traversal tests below a BRef
    assert twolevel.sah(tl, boxes="object") <= twolevel.sah(plain, boxes="object") * (1 + 1e-6), info
    if result.kept == "two-level":  # the plain top level, BRef for BRef
        assert int(tl.bref_count) == len(mesh.instances)
    # the flattened tree stays valid with the root on the instances' box
    lo, hi = mesh.local_boxes()
    jaxbvh.validate(twolevel.flatten(tl, pad=False), lo, hi)


def test_an_opening_that_raises_the_sah_is_not_kept():
    """Found by search (seeds 0-10, spread 0.2 and 0.5: 2 of 20 scenes with BRefs opened,
    at BRef boxes 3 levels down): two instances of a 22-triangle tree and room for one
    more BRef. Opening one instance's root lets the binned split group one of its
    children with the other instance, a node larger than the object's own root it
    replaces; the SAH is above the plain two-level one, and the plain top level is kept
    (checked: without the comparison in build_from this fails)."""
    mesh = scenes.instanced_scene(jax.random.key(10), [small_tree(10)], 2, spread=0.2)
    trees = fm.build_objects(mesh)
    forest, inst, raw = top_level(mesh, trees, threshold=0.1, budget=1.5)
    n = len(mesh.instances)
    plain = twolevel.build_from(mesh, trees, threshold=math.inf, shapes=SHAPES)
    result = twolevel.run_from(mesh, trees, threshold=0.1, budget=1.5, shapes=SHAPES)
    tl = result.tree
    raw_tl = twolevel.TwoLevelBVH(top=raw.top, bref_node=raw.node, bref_instance=raw.instance, bref_lo=raw.lo,
                                  bref_hi=raw.hi, bref_prims=raw.prims, bref_count=raw.count, forest=forest,
                                  instances=inst, n_instances=np.int32(n))
    assert int(raw.count) > n and twolevel.sah(raw_tl) > twolevel.sah(plain)  # the raw opening is worse
    assert result.kept == "two-level" and twolevel.sah(tl) == twolevel.sah(plain)


def test_scene_slots_scale_with_the_scene():
    # the paper's rules where they give more: 4 x instances, #primitives / 1000
    assert brefs.scene_slots(256, 500_000, 0) == 1024
    assert brefs.scene_slots(10, 5_000_000, 10) == 5000
    # a small scene of objects placed once gets 16 each, but never below 64 triangles per slot
    assert brefs.scene_slots(8, 12_946, 8) == 128
    assert brefs.scene_slots(254, 32_396, 254) == 1016
    assert brefs.scene_slots(8, 640, 8) == 32
    # ... scaled by how many of their boxes a ray meets beyond the first (none: tiling)
    assert brefs.scene_slots(8, 12_946, 8, 1.5) == 64
    assert brefs.scene_slots(8, 12_946, 8, 1.0) == brefs.scene_slots(8, 12_946, 8, 0.5) == 13  # #prims / 1000
    assert brefs.scene_slots(254, 32_396, 254, 0.75) == 254
    assert brefs.scene_slots(40, 32_396, 8, 0.0) == 128  # shared objects keep the paper's 4 each
    mesh = scenes.by_material(*small_tree(1), groups=4)  # placed once by the identity
    lo = np.array([v.min(axis=0) for v, _ in mesh.objects])
    hi = np.array([v.max(axis=0) for v, _ in mesh.objects])
    half = lambda d: d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]  # noqa: E731
    overlap = half(hi - lo).sum() / half(hi.max(axis=0) - lo.min(axis=0))
    n = len(mesh.instances)
    assert twolevel.slots_of(mesh) == brefs.scene_slots(n, mesh.n_triangles, n, overlap) > n
    # a room of objects placed once that tile it (a ray meets < 2 of their boxes): no
    # spare slot, so build_from builds no re-braided top level
    room = scenes.furnished_room(jax.random.key(3), n_objects=6, triangles=8)
    assert twolevel.slots_of(room) == len(room.instances)
    assert twolevel.slots_of(mesh, budget=2.0) == 2 * len(mesh.instances)
    assert twolevel.slots_of(mesh, threshold=math.inf) == len(mesh.instances)


def test_overlapping_scenes_are_what_they_say():
    v, f = small_tree(2)
    # by material: every triangle once, each group placed once by the identity, groups by normal
    mesh = scenes.by_material(v, f, groups=8)
    assert mesh.n_triangles == f.shape[0] and all(np.array_equal(t, np.eye(4)) for _, t in mesh.instances)
    assert len({o for o, _ in mesh.instances}) == len(mesh.objects) >= 2
    for ov, of in mesh.objects:
        n = np.cross(ov[of[:, 1]] - ov[of[:, 0]], ov[of[:, 2]] - ov[of[:, 0]])
        assert len({tuple(row) for row in (n >= 0).tolist()}) == 1  # one octant per object
    # a pile: one object, rotated instances all around one centre (their boxes share it)
    pile = scenes.pile(jax.random.key(0), v, f, 5)
    assert len(pile.objects) == 1 and len(pile.instances) == 5
    centres = np.stack([t[:3, 3] for _, t in pile.instances])
    assert np.ptp(centres, axis=0).max() <= 0.1 * np.ptp(v, axis=0).max()
    # rails: each rod placed once, each spanning most of the scene
    rails = scenes.rails(jax.random.key(1), v, f, n_compact=4, n_rails=2)
    assert len(rails.objects) == 3 and len(rails.instances) == 6
    scene_size = np.ptp(rails.vertices, axis=0).max()
    for rv, _ in rails.objects[1:]:
        assert np.ptp(rv, axis=0).max() > 0.7 * scene_size
    mixed = scenes.mixed(jax.random.key(2), v, f, n_once=3, n_instanced=4)
    users = [o for o, _ in mixed.instances]
    assert len(set(users)) == 5 and users.count(4) == 4  # room + 3 placed once + 1 shared by 4
    room = scenes.furnished_room(jax.random.key(3), n_objects=6, triangles=8)
    assert len(room.objects) == len(room.instances) == 6 and room.n_triangles == 12 + 5 * 8


def testforest_depths_refuses_cyclic_links():
    """Node depths of a forest come from a bounded walk: a cycle in the links is refused,
    never an endless loop (the brief's rule: every loop over a tree has a bound)."""
    import types

    from jaxbvh.twolevel.objects import forest_depths

    good = types.SimpleNamespace(left=np.array([1, -1, -1]), right=np.array([2, -1, -1]), root=np.array([0]))
    np.testing.assert_array_equal(forest_depths(good), [0, 1, 1])
    cyclic = types.SimpleNamespace(left=np.array([1, 0, -1]), right=np.array([2, -1, -1]), root=np.array([0]))
    with pytest.raises(ValueError, match="cycle"):
        forest_depths(cyclic)


# ----------------------------------------------------------------------------------
# Compiled programs (issue 38): one top-level program and one builder program a scene
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(6))
@given(mesh=st.one_of(forest_scenes(), material_scenes()), size=st.sampled_from([16, 48]))
def test_a_larger_array_size_cut_back_is_the_plain_top_level(mesh, size):
    """The plain top level built at a larger array size (the re-braided one's program) and
    cut back to its own size equals the build at its own size, array by array."""
    trees = fm.build_objects(mesh)
    forest, inst = fm.pack(mesh, trees)
    n = len(mesh.instances)
    own = jaxbvh.to_numpy(brefs.build_top_level(forest, inst, n, threshold=math.inf))
    cap = own.node.shape[0]
    big = brefs.cut_to(jax.device_get(brefs.build_top_level(forest, inst, n, threshold=math.inf,
                                                            array_size=cap + size)), cap)
    for got, want in zip(jax.tree_util.tree_leaves(big), jax.tree_util.tree_leaves(own)):
        np.testing.assert_array_equal(got, want)


def test_plain_and_rebraided_top_levels_share_one_program():
    """A scene whose BRef slots fall in a larger capacity bucket than its instances builds
    both top levels with one compiled program (two before: one per array size,
    bench/results/bench_compile_sbvh_twolevel.md)."""
    mesh = scenes.instanced_scene(jax.random.key(3), [small_tree(3)], 5, spread=0.3)
    trees = fm.build_objects(mesh)
    slots = twolevel.slots_of(mesh, 0.1, budget=4.0)
    assert brefs.array_size_of(slots) > brefs.array_size_of(len(mesh.instances))
    brefs.build_levels.clear_cache()
    result = twolevel.run_from(mesh, trees, threshold=0.1, budget=4.0)
    assert brefs.build_levels._cache_size() == 1
    plain = twolevel.build_from(mesh, trees, threshold=math.inf)
    if result.kept == "two-level":  # the plain top level, cut back: as built alone
        for got, want in zip(jax.tree_util.tree_leaves(result.tree.top), jax.tree_util.tree_leaves(plain.top)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_objects_of_nearby_sizes_share_one_builder_program():
    """Objects of 22 and 30 triangles (capacity buckets 24 and 32) are built by one
    compiled builder program, each tree equal to the one built at its own size (two
    programs before: one per capacity bucket)."""
    from jaxbvh.builders import topdown
    small, large = small_tree(1), scenes.tree_mesh(jax.random.key(2), levels=1, branches=3, sides=3, leaves=1)
    mesh = scenes.instanced_scene(jax.random.key(5), [small, large], 3)
    sizes = [faces.shape[0] for _, faces in mesh.objects]
    assert len({fm.capacity_bucket(n) for n in sizes}) == 2, sizes
    topdown.engine.clear_cache()
    trees = fm.build_objects(mesh)
    assert topdown.engine._cache_size() == 1
    where = fm.placements(mesh)
    for obj, (vertices, faces) in enumerate(mesh.objects):
        alone = fm.build_object(vertices, faces, where[obj])
        for got, want in zip(jax.tree_util.tree_leaves(trees[obj].tree), jax.tree_util.tree_leaves(alone.tree)):
            np.testing.assert_array_equal(got, want)


def test_objects_of_very_different_sizes_keep_their_own_capacity():
    """Padding a small object to a large one's bucket past SHARED_PADDING is refused
    (one large object and many small ones would pay in run time)."""
    config = fm.DEFAULT_BUILDER
    assert fm.shared_capacity([615, 742, 949], config) == fm.capacity_bucket(949)
    assert fm.shared_capacity([10_000] + [12] * 50, config) is None
    assert fm.shared_capacity([615, 949], config.replace(pad=False)) is None
