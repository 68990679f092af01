"""Adaptive collapsing (jaxbvh.collapse, Susano Pinto 2010) and the level sweeps under it.

Checked against the literal NumPy twin (jaxbvh.reference.collapse) node by node, against
brute-force enumeration of every collapse of small trees, against the ordering the paper
reports (DP <= greedy, QBVH, binary), and through traversal: the binary tree with skip
flags makes the wide tree's box tests ray by ray.
"""

from __future__ import annotations

import itertools

import jax
import numpy as np
import pytest
from helpers import assert_one_line_error, random_tree, run_cli, run_json
from hypothesis import example, given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.rays import traversal as traverse
from jaxbvh.rays import traversal_reference as ref_rays
from jaxbvh.testing.plugin import examples
from jaxbvh.tree import pad_to
from jaxbvh.wide import collapse, collapse_dp, levels
from jaxbvh.wide import collapse_reference as ref

NODES, PRIMS = 128, 64  # one capacity for every random tree: one compile per configuration



trees = st.tuples(st.integers(0, 2**31), st.integers(1, 40), st.integers(1, 3),
                  st.sampled_from(["random", "random", "grid", "point"]))


def children_of(wide) -> dict:
    """``{node: [children in slot order]}`` of the interior nodes of a wide tree."""
    w = jaxbvh.to_numpy(wide)
    return {i: [int(c) for c in row if c >= 0] for i, row in enumerate(w.child) if (row >= 0).any()}


def as_sets(children: dict) -> dict:
    return {k: sorted(v) for k, v in children.items()}


def leaf_order(tree) -> list:
    """Leaves left to right (depth-first, children in slot order)."""
    t = jaxbvh.to_numpy(tree)
    out, stack = [], [int(t.root)]
    while stack:
        node = stack.pop()
        kids = [int(c) for c in t.child[node] if c >= 0]
        if not kids:
            out.append(node)
        stack += kids[::-1]
    return out


def check(result, tree, lo, hi, cost=None):
    """The output is valid, keeps the leaves in order, flags what it removed, prices itself."""
    jaxbvh.validate(result.tree, lo, hi)
    assert leaf_order(result.tree) == leaf_order(tree)
    interior = np.asarray(tree.left) >= 0
    np.testing.assert_array_equal(np.asarray(result.skip), interior & ~np.asarray(result.kept))
    assert float(result.rcost) == pytest.approx(float(collapse.rcost(result.tree, cost)), rel=1e-5, abs=1e-6)


# ----------------------------------------------------------------------------------
# Level schedule
# ----------------------------------------------------------------------------------


@jax.jit
def _schedule_and_sweeps(tree):
    """Schedule with tiny windows, and two sweeps over it: subtree sizes (bottom-up) and
    depths (top-down), as a user of :mod:`jaxbvh.wide.levels` would write them."""
    jnp = jax.numpy
    n = tree.left.shape[0]
    left = jnp.where(tree.left >= 0, tree.left, n)
    right = jnp.where(tree.right >= 0, tree.right, n)
    lv = levels.level_order(tree.left, tree.right, tree.root, tree.left >= 0, (8, 2))

    def up(size, start, valid):
        x = lv.window(start, valid)
        xs = jnp.minimum(x, n - 1)
        return size.at[x].set(1 + size[left[xs]] + size[right[xs]], mode="drop")

    def down(depth, start, valid):
        x = lv.window(start, valid)
        xs = jnp.minimum(x, n - 1)
        below = jnp.where(x < n, depth[xs] + 1, 0)
        return depth.at[jnp.where(x < n, left[xs], n)].set(below, mode="drop").at[
            jnp.where(x < n, right[xs], n)].set(below, mode="drop")

    size = levels.sweep_up(lv, up, jnp.ones(n + 1, jnp.int32).at[n].set(0))
    depth = levels.sweep_down(lv, down, jnp.zeros(n + 1, jnp.int32))
    return lv.order, lv.starts, lv.levels, lv.position, levels.depth_of(lv), size[:n], depth[:n], lv.pad


@settings(max_examples=examples(15))
@given(trees)
@example((1, 1, 1, "random"))  # no interior node: no level
def test_level_order_is_breadth_first(spec):
    tree, _, _ = random_tree(*spec)
    order, starts, n_levels, position, depth_of, size, down_depth, pad = map(
        np.asarray, _schedule_and_sweeps(jaxbvh.to_jax(tree)))
    pad = int(pad)
    interior = np.asarray(tree.left) >= 0
    depth = jaxbvh.tree.depth(tree)
    count = int(interior.sum())
    nodes = order[pad:pad + count]
    assert sorted(nodes.tolist()) == np.flatnonzero(interior).tolist()
    assert (order[:pad] == NODES).all() and (order[pad + count:] == NODES).all()
    assert (np.diff(depth[nodes]) >= 0).all()
    starts = starts[: int(n_levels) + 1]
    assert len(starts) == (depth[interior].max() + 2 if count else 1)
    for d in range(int(n_levels)):
        assert (depth[order[starts[d]:starts[d + 1]]] == d).all()
    for a, b in zip(nodes[:-1], nodes[1:]):  # breadth first: parents in order, left first
        pa, pb = tree.parent[a], tree.parent[b]
        if depth[a] == depth[b] and pa != pb:
            assert position[pa] < position[pb]
        if pa == pb:
            assert tree.left[pa] == a
    np.testing.assert_array_equal(position[nodes], np.arange(pad, pad + count))
    np.testing.assert_array_equal(depth_of[interior], depth[interior])
    real = jaxbvh.tree.real_nodes(tree)
    expect = np.zeros(NODES, int)
    for node in np.flatnonzero(real)[np.argsort(-depth[real], kind="stable")]:
        kids = [c for c in (tree.left[node], tree.right[node]) if c >= 0]
        expect[node] = 1 + sum(expect[c] for c in kids)
    np.testing.assert_array_equal(size[real], expect[real])
    np.testing.assert_array_equal(down_depth[real], depth[real])


# ----------------------------------------------------------------------------------
# The optimal DP
# ----------------------------------------------------------------------------------

def even_widths_cheap(k):
    """A user's T(k) on int arrays, not monotone: an even number of boxes costs k / 2."""
    return np.where(k % 2 == 0, k / 2, k)


COSTS = {"k": None, "ceil(k/4)": collapse.node_test_cost(4), "ceil(k/8)": collapse.node_test_cost(8),
         "user": even_widths_cheap}


@settings(max_examples=examples(15))
@given(trees, st.sampled_from([2, 3, 8]), st.sampled_from(list(COSTS)))
@example((1, 1, 1, "random"), 8, "k")        # one leaf: nothing to collapse
@example((2, 2, 1, "random"), 8, "k")        # root and two leaves
@example((3, 30, 1, "point"), 8, "k")        # every area zero: all ties
@example((4, 40, 1, "grid"), 3, "ceil(k/4)")
@example((5, 40, 3, "random"), 8, "user")    # multi-primitive leaves, a T that is not monotone
def test_dp_equals_reference(spec, k, cost_name):
    tree, lo, hi = random_tree(*spec)
    cost = COSTS[cost_name]
    result = collapse.optimal(tree, max_children=k, test_cost=cost)
    total, children, new_leaves = ref.optimal(tree, max_children=k, test_cost=cost)
    assert new_leaves == []
    assert as_sets(children_of(result.tree)) == as_sets(children)
    assert children_of(result.tree) == children  # left to right, as back-tracking lists them
    assert float(result.objective) == pytest.approx(float(total), rel=1e-5, abs=1e-6)
    # the DP's value is the cost of the tree it emits (both ways of computing it)
    assert float(result.rcost) == pytest.approx(float(result.objective), rel=1e-5, abs=1e-6)
    r, _ = ref.rcost(tree, children, test_cost=cost)
    assert float(result.rcost) == pytest.approx(float(r), rel=1e-5, abs=1e-6)
    assert float(collapse.rcost(result.tree, cost)) == pytest.approx(float(r), rel=1e-5, abs=1e-6)
    check(result, tree, lo, hi, cost)
    assert max((len(c) for c in children.values()), default=0) <= k


def brute_force(tree, k, cost):
    """Least R (float64) over every set of removed interior non-root nodes, widths <= k."""
    t = jaxbvh.to_numpy(tree)
    left, right, root = np.asarray(t.left), np.asarray(t.right), int(t.root)
    d = np.maximum(np.asarray(t.hi, np.float64) - np.asarray(t.lo, np.float64), 0)
    area = d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]
    a = area / area[root] if area[root] > 0 else np.ones_like(area)
    table = collapse.cost_table(cost, 2 * NODES)
    interior = [i for i in np.flatnonzero(left >= 0) if i != root]
    best = np.inf

    def entries(node, removed):
        if node in removed:
            return entries(int(left[node]), removed) + entries(int(right[node]), removed)
        return [node]

    for r in range(len(interior) + 1):
        for removed in itertools.combinations(interior, r):
            removed = set(removed)
            total, ok = 0.0, True
            for m in [root] + [i for i in interior if i not in removed]:
                width = len(entries(int(left[m]), removed)) + len(entries(int(right[m]), removed))
                if width > k:
                    ok = False
                    break
                total += a[m] * table[width]
            if ok:
                best = min(best, total)
    return best


@settings(max_examples=examples(15))
@given(st.integers(0, 2**31), st.integers(2, 9), st.sampled_from([2, 3, 8]), st.sampled_from(list(COSTS)),
       st.sampled_from(["random", "grid"]))
def test_dp_is_the_least_of_all_collapses(seed, n, k, cost_name, kind):
    tree, _, _ = random_tree(seed, n, 1, kind)
    cost = COSTS[cost_name]
    result = collapse.optimal(tree, max_children=k, test_cost=cost)
    best = brute_force(tree, k, cost)
    # least up to float32 rounding, and the tie rule: each choice within 64 eps of its best
    assert float(result.objective) == pytest.approx(best, rel=1e-4, abs=1e-6)
    assert float(result.objective) >= best * (1 - 1e-5) - 1e-6  # never below the least


@given(trees, st.sampled_from([2, 3, 8]))
def test_dp_not_worse_than_greedy_qbvh_binary(spec, k):
    tree, lo, hi = random_tree(*spec)
    dp = collapse.optimal(tree, max_children=k)
    tol = 1 + 1e-5
    assert float(dp.rcost) <= float(collapse.greedy(tree, max_children=k).rcost) * tol + 1e-6
    assert float(dp.rcost) <= float(dp.rcost_before) * tol + 1e-6
    if k >= 4:
        assert float(dp.rcost) <= float(collapse.qbvh(tree).rcost) * tol + 1e-6
    if k == 2:  # nothing can be removed without a third child
        assert np.asarray(dp.kept)[jaxbvh.tree.real_nodes(tree)].all()


# ----------------------------------------------------------------------------------
# Greedy pushup and QBVH
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(15))
@given(trees, st.sampled_from([None, 2, 3, 5]))
@example((3, 30, 1, "point"), None)
@example((3, 30, 1, "point"), 3)
@example((1, 1, 1, "random"), None)  # one leaf
@example((2, 2, 1, "random"), 3)     # root and two leaves
def test_greedy_equals_reference(spec, k):
    tree, lo, hi = random_tree(*spec)
    result = collapse.greedy(tree, max_children=k)
    children = ref.greedy(tree, max_children=k)
    assert as_sets(children_of(result.tree)) == as_sets(children)
    check(result, tree, lo, hi)
    r, _ = ref.rcost(tree, children)
    assert float(result.rcost) == pytest.approx(float(r), rel=1e-5, abs=1e-6)
    if k is not None:
        assert max((len(c) for c in children.values()), default=0) <= k


def test_greedy_rule_is_the_papers():
    """Children of half the parent's area or more are collapsed, smaller ones kept."""
    # root [0, 4]^3: child 1 as large as the root (P = 1: collapsed) over two small
    # leaves, and a small leaf 4 (kept)
    arrays = dict(child=np.array([[1, 4], [2, 3], [-1, -1], [-1, -1], [-1, -1]], np.int32),
                  prim_start=np.array([0, 0, 0, 1, 2], np.int32), prim_count=np.array([0, 0, 1, 1, 1], np.int32),
                  prim_index=np.arange(3, dtype=np.int32),
                  lo=np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [3, 3, 3], [0, 0, 0]], np.float32),
                  hi=np.array([[4, 4, 4], [4, 4, 4], [1, 1, 1], [4, 4, 4], [0.2, 0.2, 0.2]], np.float32),
                  root=np.int32(0))
    tree = pad_to(jaxbvh.from_interchange(arrays, pad=False), NODES, PRIMS)
    assert children_of(collapse.greedy(tree).tree) == {0: [2, 3, 4]}  # node 1 as large as the root
    assert as_sets(ref.greedy(tree)) == {0: [2, 3, 4]}
    assert children_of(collapse.greedy(tree, max_children=2).tree) == {0: [1, 4], 1: [2, 3]}


@given(trees)
@example((1, 1, 1, "random"))
@example((2, 2, 1, "random"))
@example((3, 30, 1, "point"))
def test_qbvh_equals_reference(spec):
    tree, lo, hi = random_tree(*spec)
    result = collapse.qbvh(tree)
    children = ref.qbvh(tree)
    assert as_sets(children_of(result.tree)) == as_sets(children)
    assert children_of(result.tree) == children
    depth = jaxbvh.tree.depth(tree)
    interior = np.asarray(tree.left) >= 0
    np.testing.assert_array_equal(np.asarray(result.kept)[interior], depth[interior] % 2 == 0)
    assert np.asarray(result.tree.child).shape[1] == 4
    check(result, tree, lo, hi)


# ----------------------------------------------------------------------------------
# Inputs: foreign node order, float64, trees from the builder, leaf merging
# ----------------------------------------------------------------------------------


def test_node_order_and_root_do_not_matter():
    """The same tree under two numberings collapses to the same tree (ids mapped)."""
    a, lo, hi = random_tree(5, 30, 2)
    t = jaxbvh.to_interchange(a)  # real nodes 0 .. m-1, as in ``a``
    m = t["child"].shape[0]
    new = np.random.default_rng(0).permutation(m)  # node i of a is node new[i] of b
    old = np.argsort(new)
    child = np.where(t["child"] >= 0, new[np.maximum(t["child"], 0)], -1)[old]
    arrays = dict(t, child=child, prim_start=t["prim_start"][old], prim_count=t["prim_count"][old],
                  lo=t["lo"][old], hi=t["hi"][old], root=np.int32(new[int(t["root"])]))
    b = pad_to(jaxbvh.from_interchange(arrays, pad=False), NODES, PRIMS)
    jaxbvh.validate(b, lo, hi)
    assert int(b.root) != int(a.root)
    for method in ("dp", "greedy", "qbvh"):
        ra, rb = collapse.collapse(a, method), collapse.collapse(b, collapse.CollapseConfig(method=method))
        assert float(ra.rcost) == pytest.approx(float(rb.rcost), rel=1e-6)
        assert sorted(new[np.flatnonzero(np.asarray(ra.kept))].tolist()) == \
            np.flatnonzero(np.asarray(rb.kept)).tolist()
        ca, cb = children_of(ra.tree), children_of(rb.tree)
        assert {int(new[k]): [int(new[c]) for c in v] for k, v in ca.items()} == cb


def test_float64():
    with jax.enable_x64(True):
        tree, lo, hi = random_tree(11, 40, 2)
        t64 = tree.replace(lo=np.asarray(tree.lo, np.float64), hi=np.asarray(tree.hi, np.float64))
        result = collapse.optimal(t64, max_children=4)
        assert np.asarray(result.tree.lo).dtype == np.float64
        assert np.asarray(result.rcost).dtype == np.float64
        total, children, _ = ref.optimal(t64, max_children=4)
        assert isinstance(total, np.float64)
        assert children_of(result.tree) == children
        assert float(result.objective) == pytest.approx(float(total), rel=1e-12)
        greedy = collapse.greedy(t64, max_children=4)
        assert as_sets(children_of(greedy.tree)) == as_sets(ref.greedy(t64, max_children=4))
        jaxbvh.validate(result.tree, lo.astype(np.float64), hi.astype(np.float64))


@pytest.mark.parametrize("method", ["dp", "greedy", "qbvh"])
def test_built_trees_of_degenerate_and_extreme_soups(method):
    """Builder output (level-order ids, split axes) over awkward inputs, saved and loaded."""
    rng = np.random.default_rng(3)
    for scale, kind in [(1.0, "random"), (1e-30, "random"), (1e30, "random"), (1.0, "point")]:
        c = rng.normal(size=(50, 3)) if kind == "random" else np.zeros((50, 3))
        lo = (c * scale).astype(np.float32)
        hi = ((c + rng.random((50, 3)) * 0.3) * scale).astype(np.float32) if kind == "random" else lo
        tree = jaxbvh.to_numpy(jaxbvh.build(lo, hi))
        result = collapse.collapse(tree, method)
        jaxbvh.validate(result.tree, lo, hi)
        assert np.isfinite(float(result.rcost))
        expected = {"dp": lambda: ref.optimal(tree)[1], "greedy": lambda: ref.greedy(tree),
                    "qbvh": lambda: ref.qbvh(tree)}[method]()
        assert as_sets(children_of(result.tree)) == as_sets(expected)


def test_save_and_load_the_wide_tree(tmp_path):
    tree, lo, hi = random_tree(8, 40, 2)
    result = collapse.optimal(tree)
    path = tmp_path / "wide.npz"
    jaxbvh.save(path, result.tree)
    loaded, _ = jaxbvh.load(path)
    assert isinstance(loaded, jaxbvh.WideBVH)
    jaxbvh.validate(loaded, lo, hi)
    assert jaxbvh.tree.node_count(loaded) == int(np.asarray(result.kept).sum())
    assert float(collapse.rcost(loaded)) == pytest.approx(float(result.rcost), rel=1e-6)


@settings(max_examples=examples(15))
@given(trees, st.sampled_from([2, 4]))
@example((3, 30, 1, "point"), 4)
def test_merging_leaves_equals_reference_and_lowers_the_total(spec, max_leaf):
    tree, lo, hi = random_tree(*spec)
    result = collapse.optimal(tree, max_children=4, max_leaf=max_leaf)
    total, children, new_leaves = ref.optimal(tree, max_children=4, max_leaf=max_leaf)
    assert as_sets(children_of(result.tree)) == as_sets(children)
    assert float(result.objective) == pytest.approx(float(total), rel=1e-5, abs=1e-6)
    assert float(result.rcost + result.leaf_cost) == pytest.approx(float(total), rel=1e-5, abs=1e-6)
    jaxbvh.validate(result.tree, lo, hi)
    assert result.skip is None
    before = float(result.rcost_before + result.leaf_cost_before)
    assert float(total) <= before * (1 + 1e-5) + 1e-6
    w = jaxbvh.to_numpy(result.tree)
    new = np.asarray(new_leaves, int)
    assert (w.prim_count[new] <= max_leaf).all() and (w.prim_count[new] >= 2).all()
    expect = ref.to_wide(tree, children, new_leaves, arity=4)
    for leaf in np.flatnonzero(w.prim_count > 0):
        s, c = w.prim_start[leaf], w.prim_count[leaf]
        e_s, e_c = expect.prim_start[leaf], expect.prim_count[leaf]
        assert sorted(w.prim_index[s:s + c]) == sorted(expect.prim_index[e_s:e_s + e_c])


# ----------------------------------------------------------------------------------
# Section 4.3: binary tree + skip flags traverses like the wide tree
# ----------------------------------------------------------------------------------


def test_skip_flags_make_the_wide_trees_box_tests_ray_by_ray():
    rng = np.random.default_rng(7)
    n = 60
    centre = rng.uniform(-1, 1, (n, 1, 3))
    tri = (centre + rng.normal(0, 0.2, (n, 3, 3))).astype(np.float32)
    tree = jaxbvh.to_numpy(jaxbvh.build(tri.min(axis=1), tri.max(axis=1), max_leaf=2))
    origin = rng.uniform(-1.5, 1.5, (96, 3)).astype(np.float32)
    target = tri[rng.integers(0, n, 96)].mean(axis=1)
    direction = (target - origin).astype(np.float32)
    counters = ("box_tests", "prim_tests", "nodes_visited", "leaves_visited", "hit_count")
    # one shape for every trace (4-wide trees, one stack size): few compiles
    opts = dict(batch=32, capacity=48)
    plain = traverse.all_hits(tree, tri, origin, direction, skip=np.zeros(tree.capacity, bool), **opts)
    for result in (collapse.optimal(tree, max_children=4), collapse.qbvh(tree)):
        assert np.asarray(result.skip).any()
        wide = traverse.all_hits(result.tree, tri, origin, direction, **opts)
        flagged = traverse.all_hits(tree, tri, origin, direction, skip=result.skip, **opts)
        for name in counters:
            np.testing.assert_array_equal(getattr(flagged, name), getattr(wide, name), err_msg=name)
        assert (flagged.box_tests != plain.box_tests).any()  # the flags do change the traversal
        # closest hits: another visiting order, the same hits
        c_wide = traverse.closest_hit(result.tree, tri, origin, direction, **opts)
        c_flag = traverse.closest_hit(tree, tri, origin, direction, skip=result.skip, **opts)
        np.testing.assert_array_equal(c_flag.prim, c_wide.prim)
        # the NumPy twin honours the flags the same way, ray by ray
        for mode, hits in (("all", flagged), ("closest", c_flag)):
            twin = ref_rays.trace(tree, tri, origin[:24], direction[:24], mode=mode, skip=result.skip)
            for name in ("box_tests", "prim_tests", "nodes_visited", "leaves_visited", "prim"):
                np.testing.assert_array_equal(getattr(hits, name)[:24], [r[name] for r in twin], err_msg=name)


def test_skip_flags_of_the_wrong_shape():
    tree, _, _ = random_tree(1, 10)
    with pytest.raises(ValueError, match="skip must be bool"):
        traverse.trace(tree, np.zeros((10, 3, 3), np.float32), np.zeros((2, 3), np.float32),
                       np.ones((2, 3), np.float32), skip=np.zeros(5, bool))


# ----------------------------------------------------------------------------------
# Bad input, retracing
# ----------------------------------------------------------------------------------


def test_the_config_says_how_wide():
    """CollapseConfig's ``widest`` is the width of the result: K, 8 for dp without one, 4
    for qbvh, no limit for greedy without one."""
    tree, _, _ = random_tree(3, 40)
    for config in (collapse.CollapseConfig(), collapse.CollapseConfig(max_children=3),
                   collapse.CollapseConfig(method="qbvh"), collapse.CollapseConfig(method="greedy", max_children=5)):
        result = collapse.collapse(tree, config)
        assert np.asarray(result.tree.child).shape[1] == config.widest
    assert collapse.CollapseConfig(method="greedy").widest is None
    assert collapse.CollapseConfig().widest == collapse.DEFAULT_MAX_CHILDREN
    with pytest.raises(TypeError, match="not both"):
        collapse.collapse(tree, collapse.CollapseConfig(), max_children=4)


def test_bad_input_is_named():
    tree, _, _ = random_tree(2, 12)
    wide = collapse.qbvh(tree).tree
    with pytest.raises(ValueError, match="binary tree"):
        collapse.optimal(wide)
    for k in (1, 0, collapse.MAX_CHILDREN_LIMIT + 1):
        with pytest.raises(ValueError, match="max_children"):
            collapse.optimal(tree, max_children=k)
        with pytest.raises(ValueError, match="max_children"):
            collapse.greedy(tree, max_children=k)
    with pytest.raises(ValueError, match="simd_width"):
        collapse.node_test_cost(-1)
    with pytest.raises(ValueError, match="finite and >= 0"):
        collapse.optimal(tree, test_cost=lambda k: 1 - k)
    with pytest.raises(ValueError, match="shape"):
        collapse.optimal(tree, test_cost=lambda k: 1.0)
    with pytest.raises(ValueError, match="max_leaf"):
        collapse.optimal(tree, max_leaf=0)
    with pytest.raises(ValueError, match="needs method 'dp'"):
        collapse.collapse(tree, "greedy", max_leaf=4)
    with pytest.raises(ValueError, match="4-wide"):
        collapse.collapse(tree, "qbvh", max_children=8)
    with pytest.raises(ValueError, match="unknown collapse method"):
        collapse.collapse(tree, "random")


def test_node_test_costs():
    k = np.arange(10)
    np.testing.assert_array_equal(collapse.node_test_cost(0)(k), k)
    np.testing.assert_array_equal(collapse.node_test_cost(4)(k), [0, 1, 1, 1, 1, 2, 2, 2, 2, 3])
    np.testing.assert_array_equal(collapse.node_test_cost(8)(k), [0, 1, 1, 1, 1, 1, 1, 1, 1, 2])


def test_no_retrace_for_same_capacity():
    a, _, _ = random_tree(3, 30)
    b, _, _ = random_tree(4, 17, 2, "grid")
    collapse.optimal(a)
    before = collapse_dp.decide._cache_size()
    collapse.optimal(b, test_cost=collapse.node_test_cost(4))  # other T: a value, not a shape
    assert collapse_dp.decide._cache_size() == before


# ----------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------


KEYS = {"method", "rcost_before", "rcost", "nodes_before", "nodes", "max_children", "simd_width", "seconds"}


def test_cli_collapse_a_tree(capsys, tmp_path):
    tree, lo, hi = random_tree(6, 60)  # loads at capacity NODES, PRIMS: compiles shared
    path = tmp_path / "binary.npz"
    jaxbvh.save(path, tree)
    out_path = tmp_path / "wide.npz"
    dp = run_json(capsys, "collapse", path, "--method", "dp", "-o", out_path)
    assert KEYS <= set(dp)
    assert dp["method"] == "dp" and dp["max_children"] == 8 and dp["simd_width"] == 0
    assert dp["rcost"] <= dp["rcost_before"] and dp["nodes"] < dp["nodes_before"]
    loaded, _ = jaxbvh.load(out_path)
    jaxbvh.validate(loaded, lo, hi)
    assert float(collapse.rcost(loaded)) == pytest.approx(dp["rcost"], rel=1e-6)
    greedy = run_json(capsys, "collapse", path, "--method", "greedy")
    qbvh = run_json(capsys, "collapse", path, "--method", "qbvh", "--simd-width", 4)
    assert greedy["max_children"] is None and qbvh["max_children"] == 4 and qbvh["simd_width"] == 4
    stats = run_json(capsys, "stats", out_path)
    assert stats["nodes"] == dp["nodes"] and stats["valid"]
    status, out, err = run_cli(capsys, "collapse", path, "--method", "dp")
    assert status == 0 and "rcost" in out


def test_cli_collapse_a_mesh(capsys, tmp_path):
    mesh = tmp_path / "grid.obj"
    rng = np.random.default_rng(0)
    v = rng.random((3 * 64, 3))
    mesh.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v) +
                    "".join(f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}\n" for i in range(64)))
    out_path = tmp_path / "wide.npz"
    got = run_json(capsys, "collapse", mesh, "--method", "dp", "--max-children", 4, "--max-leaf", 4,
                   "-o", out_path)
    assert got["kind"] == "mesh" and got["triangles"] == 64 and got["max_leaf"] == 4
    assert got["rcost"] + got["leaf_cost"] <= got["rcost_before"] + got["leaf_cost_before"] + 1e-6
    # the wide tree (saved with its frame) is read by the other commands
    stats = run_json(capsys, "stats", out_path, "--mesh", mesh)
    assert stats["valid"] and stats["nodes"] == got["nodes"]
    traced = run_json(capsys, "trace", out_path, mesh, "--rays", 64, "--batch", 64)
    assert traced["rays"] == 64 and traced["box_tests"] > 0


def test_cli_bad_input(capsys, tmp_path):
    tree, _, _ = random_tree(6, 60)
    path = tmp_path / "binary.npz"
    jaxbvh.save(path, tree)
    wide = tmp_path / "wide.npz"
    jaxbvh.save(wide, collapse.qbvh(tree).tree)
    assert_one_line_error(*run_cli(capsys, "collapse", wide), "binary tree is needed", "4-wide")
    assert_one_line_error(*run_cli(capsys, "collapse", path, "--max-children", 1), "--max-children")
    assert_one_line_error(*run_cli(capsys, "collapse", path, "--simd-width", -1), "--simd-width")
    assert_one_line_error(*run_cli(capsys, "collapse", path, "--method", "qbvh", "--max-children", 8),
                          "4-wide")
    assert_one_line_error(*run_cli(capsys, "collapse", path, "--method", "greedy", "--max-leaf", 4),
                          "--method dp")
    broken = jaxbvh.to_interchange(tree)
    broken["child"][int(broken["root"])] = [int(broken["root"]), -1]
    bad = tmp_path / "broken.npz"
    np.savez(bad, **broken)
    assert_one_line_error(*run_cli(capsys, "collapse", bad), "invalid BVH")
