"""Batches of meshes: every per-tree result equals the single-tree call, node for node;
the plan keeps its bounds; bad meshes fail alone; two devices give what one gives."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from helpers import REPO, assert_same_costs, crossing_slivers, local_boxes
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import triangle_soups

import jaxbvh
from jaxbvh import batch
from jaxbvh.batch import plan
from jaxbvh.batch.layout import own_capacity
from jaxbvh.testing.plugin import examples
from jaxbvh.tree.layout import capacity_bucket

# the module (jaxbvh.batch.optimize is the function of the same name)
batch_optimize = importlib.import_module("jaxbvh.batch.optimize")
FIELDS = ("left", "right", "parent", "lo", "hi", "prim_start", "prim_count", "axis", "prim_index", "root")
# one group for every test batch (capacity of the largest): one compiled program per list shape
ONE_GROUP = batch.BatchConfig(max_padding=0.9)
# the same, rows vmapped (side by side, as on a GPU) rather than mapped (one after another)
ONE_GROUP_VMAP = batch.BatchConfig(max_padding=0.9, rows="vmap")
OPTIMIZERS = ("hc", "sa", "reinsert", "treelet", "pipeline")

# soups of 1-4, 9-12 and 9-12 triangles: every batch is one group of capacity 12 in 4 rows
# (one compiled program), the first tree cut back to its own capacity (4); the single
# builds compile twice (capacities 4 and 12)
soup_lists = st.tuples(*(triangle_soups(min_size=k - 3, max_size=k, extreme=False) for k in (4, 12, 12)))
# three soups of 9-12 triangles: the single runs compile once (capacity 12), the batch once
same_bucket_lists = st.lists(triangle_soups(min_size=9, max_size=12, extreme=False), min_size=3, max_size=3)


def assert_same_arrays(got, want, what=""):
    got, want = jaxbvh.to_numpy(got), jaxbvh.to_numpy(want)
    for field in FIELDS:
        a, b = np.asarray(getattr(got, field)), np.asarray(getattr(want, field))
        assert a.shape == b.shape, f"{what} {field}: shape {a.shape} != {b.shape}"
        np.testing.assert_array_equal(a, b, err_msg=f"{what} {field}")


# ----------------------------------------------------------------------------------
# Building and optimizing: the single-tree calls, node for node
# ----------------------------------------------------------------------------------


@pytest.mark.parametrize("method", list(jaxbvh.BOX_BUILDERS))
@settings(max_examples=examples(3))
@given(soups=soup_lists, max_leaf=st.sampled_from([1, 3]), config=st.sampled_from([ONE_GROUP, ONE_GROUP_VMAP]))
def test_batched_build_equals_single_builds(method, soups, max_leaf, config):
    meshes = [local_boxes(tri) for tri in soups]
    result = batch.build(meshes, method=method, max_leaf=max_leaf, bins=8, batch=config)
    assert result.errors == {} and len(result.trees.groups) == 1
    for i, ((lo, hi), tree) in enumerate(zip(meshes, result.trees.unstack())):
        assert_same_arrays(tree, jaxbvh.build(lo, hi, method=method, max_leaf=max_leaf, bins=8), f"mesh {i}")


@pytest.mark.parametrize("method", OPTIMIZERS)
@settings(max_examples=examples(2))
@given(soups=same_bucket_lists)
def test_batched_optimize_equals_single_runs(method, soups):
    meshes = [local_boxes(tri) for tri in soups]
    built = batch.build(meshes, method="lbvh", batch=ONE_GROUP).trees
    keys = [jax.random.key(i) for i in range(len(meshes))]
    options = dict(steps=6, period=2) if method == "sa" else {}
    out = batch.optimize(built, method, keys=keys if method == "sa" else None, **options)
    for i, ((lo, hi), tree) in enumerate(zip(meshes, out.trees.unstack())):
        single = jaxbvh.optimize.optimize(jaxbvh.build(lo, hi, method="lbvh"), method,
                                          key=keys[i] if method == "sa" else None, **options)
        assert_same_arrays(tree, single.tree, f"mesh {i}")
        assert_same_costs(out.sah[i], single.sah, f"mesh {i}")
        assert out.steps[i] == int(single.steps)
        assert out.moves[i] == int(single.moves) and out.converged[i] == bool(single.converged)


def test_a_converged_tree_stops_while_others_go_on():
    # vmapped rows share one loop: a 1-triangle mesh converges at once, a 12-triangle one
    # takes passes; each keeps its own count and its single run's tree
    rng = np.random.default_rng(3)
    small = (np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
    lo = rng.uniform(-1, 1, (12, 3)).astype(np.float32)
    big = (lo, lo + np.float32(0.2))
    built = batch.build([small, big], method="lbvh", batch=ONE_GROUP).trees
    out = batch.optimize(built, "hc", batch=ONE_GROUP_VMAP)
    single = jaxbvh.optimize.optimize(jaxbvh.build(*big, method="lbvh"), "hc")
    assert out.steps[0] < out.steps[1] == int(single.steps)
    assert_same_arrays(out.trees.unstack()[1], single.tree)


def test_a_tree_that_fails_to_optimize_fails_alone(monkeypatch):
    """errors="keep": a tree whose init raises, or whose compiled call raises, is left out
    with its own message; every other tree is delivered, each its single run's."""
    rng = np.random.default_rng(11)
    meshes = []
    for _ in range(4):  # 12 boxes each: the capacity of the batches above (programs shared)
        lo = rng.uniform(-1, 1, (12, 3)).astype(np.float32)
        meshes.append((lo, lo + rng.uniform(0, 0.3, (12, 3)).astype(np.float32)))
    built = batch.build(meshes, method="lbvh", batch=ONE_GROUP).trees
    singles = [jaxbvh.build(lo, hi, method="lbvh") for lo, hi in meshes]
    keys = [jax.random.key(i) for i in range(4)]
    keys[1] = "not a key"  # annealing's init of mesh 1 raises
    with pytest.raises(TypeError):
        batch.optimize(built, "sa", keys=keys, steps=6, period=2)
    out = batch.optimize(built, "sa", keys=keys, steps=6, period=2, errors="keep")
    assert list(out.errors) == [1] and out.errors[1].startswith("mesh 1: ") and "\n" not in out.errors[1]
    trees = out.trees.unstack()
    assert trees[1] is None and np.isnan(out.sah[1]) and out.steps[1] == -1 and not out.converged[1]
    for i in (0, 2, 3):
        single = jaxbvh.optimize.optimize(singles[i], "sa", key=keys[i], steps=6, period=2)
        assert_same_arrays(trees[i], single.tree, f"mesh {i}")
        assert out.steps[i] == int(single.steps)

    # a compiled call that raises for mesh 2's tree: the chunk runs again a tree per call
    run_chunk = batch_optimize._run_chunk
    bad = float(jaxbvh.sah(jaxbvh.to_jax(singles[2])))

    def failing(optimizer, states, *args):
        if any(float(s.progress.sah_start) == bad for s in states):
            raise RuntimeError("a call that fails\nover two lines")
        return run_chunk(optimizer, states, *args)

    monkeypatch.setattr(batch_optimize, "_run_chunk", failing)
    with pytest.raises(RuntimeError):
        batch.optimize(built, "hc")
    seen = []
    out = batch.optimize(built, "hc", errors="keep", on_chunk=lambda index: seen.append(sorted(index)))
    assert out.errors == {2: "mesh 2: a call that fails over two lines"} and seen == [[0, 1, 2, 3]]
    trees = out.trees.unstack()
    assert trees[2] is None and out.steps[2] == -1
    for i in (0, 1, 3):
        assert_same_arrays(trees[i], jaxbvh.optimize.optimize(singles[i], "hc").tree, f"mesh {i}")


# ----------------------------------------------------------------------------------
# Costs and traversal over a batch
# ----------------------------------------------------------------------------------


@settings(max_examples=examples(3))
@given(soups=soup_lists)
def test_batched_costs_and_trace_equal_single_calls(soups):
    meshes = [local_boxes(tri) for tri in soups]
    trees = batch.build(meshes, batch=ONE_GROUP).trees
    costs = batch.costs(trees)
    triangles = [np.stack([lo, (lo + hi) / 2, hi], axis=1) for lo, hi in meshes]  # in the boxes
    rays = [jaxbvh.rays.random_rays(jax.random.key(i), lo.min(0), hi.max(0), 20) for i, (lo, hi) in
            enumerate(meshes)]
    hits = batch.trace(trees, triangles, [np.asarray(o) for o, _ in rays], [np.asarray(d) for _, d in rays],
                       rays_per_call=16, engine="jax")
    for i, tree in enumerate(trees.unstack()):
        single = jaxbvh.all_costs(tree)
        for name, value in single.items():
            assert costs[name][i] == pytest.approx(value, rel=1e-6), name
        want = jaxbvh.rays.trace(tree, triangles[i], np.asarray(rays[i][0]), np.asarray(rays[i][1]), engine="jax")
        for field in ("t", "prim", "box_tests", "prim_tests", "nodes_visited"):
            np.testing.assert_array_equal(getattr(hits[i], field), getattr(want, field), err_msg=field)


def test_batched_collapse_equals_single_collapse():
    rng = np.random.default_rng(5)
    meshes = [(lo, lo + np.float32(0.1)) for lo in (rng.uniform(-1, 1, (n, 3)).astype(np.float32)
                                                    for n in (5, 9))]
    trees = batch.build(meshes, batch=ONE_GROUP).trees
    for got, tree in zip(batch.collapse(trees, "dp"), trees.unstack()):
        want = jaxbvh.collapse.collapse(tree, "dp")
        np.testing.assert_array_equal(np.asarray(got.tree.child), np.asarray(want.tree.child))
        assert float(got.rcost) == float(want.rcost)


# ----------------------------------------------------------------------------------
# The plan: groups, chunks, the memory bound
# ----------------------------------------------------------------------------------


# sizes spread over octaves, so that groups of many capacities and bounds that bind both occur
mesh_sizes = st.builds(lambda octave, frac: max(1, int(2 ** octave * frac)), st.integers(0, 17), st.floats(0.5, 1.0))


@settings(max_examples=examples(200))  # host arithmetic only: cheap
@given(sizes=st.lists(mesh_sizes, min_size=1, max_size=60),
       max_padding=st.sampled_from([0.0, 0.25, 0.5, 0.9]), memory_mb=st.sampled_from([0.01, 0.1, 1.0, 64.0]),
       devices=st.sampled_from([1, 2, 3]))
def test_plan_places_every_mesh_once_within_its_bounds(sizes, max_padding, memory_mb, devices):
    config = batch.BatchConfig(memory_mb=memory_mb, max_padding=max_padding)
    per_slot = plan.BYTES_PER_SLOT["build"]
    chunks = plan.chunks(sizes, config, per_slot, devices)
    placed = np.concatenate([c.index for c in chunks])
    assert sorted(placed.tolist()) == list(range(len(sizes)))
    for c in chunks:
        own = np.array([capacity_bucket(sizes[i]) for i in c.index])
        assert (own <= c.capacity).all() and (own >= c.capacity * (1 - max_padding)).all()
        assert c.rows >= c.index.size and c.rows % devices == 0
        # over the bound only when a single row per device is already too much
        assert plan.estimate_mb(c, per_slot) <= memory_mb or c.rows == devices
    # a group compiles at most two programs: full chunks and the last
    for cap in {c.capacity for c in chunks}:
        assert len({c.rows for c in chunks if c.capacity == cap}) <= 2


def test_max_padding_zero_gives_a_group_per_capacity_bucket():
    sizes = [3, 4, 5, 6, 7, 100, 1000]
    got = plan.groups(sizes, 0.0)
    assert [cap for cap, _ in got] == sorted({capacity_bucket(n) for n in sizes})


def test_batch_config_refuses_bad_knobs_by_name():
    with pytest.raises(ValueError, match="memory_mb"):
        batch.BatchConfig(memory_mb=0)
    with pytest.raises(ValueError, match="max_padding"):
        batch.BatchConfig(max_padding=1.0)
    with pytest.raises(ValueError, match="rows"):
        batch.BatchConfig(rows="pmap")


def test_own_capacity_never_cuts_a_real_node():
    lo = np.random.default_rng(0).uniform(-1, 1, (20, 3)).astype(np.float32)
    tree = jaxbvh.to_numpy(jaxbvh.build(lo, lo + np.float32(0.1)))
    with pytest.raises(ValueError, match="past the capacity"):
        own_capacity(tree, 3)


# ----------------------------------------------------------------------------------
# Bad input: the entry fails alone, with its own message
# ----------------------------------------------------------------------------------


def test_bad_meshes_fail_alone():
    rng = np.random.default_rng(1)
    good = (rng.uniform(-1, 1, (6, 3)).astype(np.float32),) * 2
    nan = (np.array([[np.nan, 0, 0], [0, 0, 0]], np.float32), np.ones((2, 3), np.float32))
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    meshes = [good, nan, empty, "not a mesh", good]
    result = batch.build(meshes, errors="keep", batch=ONE_GROUP)
    assert set(result.errors) == {1, 2, 3}
    assert "NaN" in result.errors[1] and "no primitives" in result.errors[2] and "pair" in result.errors[3]
    assert all("\n" not in m for m in result.errors.values())
    trees = result.trees.unstack()
    assert trees[1] is None and trees[2] is None and trees[3] is None
    assert_same_arrays(trees[4], jaxbvh.build(*good))
    with pytest.raises(ValueError, match="mesh 1"):
        batch.build(meshes)


def test_batched_sbvh_equals_single_sbvh_builds_and_optimizes():
    """SBVH needs the triangles: each mesh is built by the single builder, the trees
    grouped by reference slots (24 and 12 here), and every tree is the single build's;
    the batch optimizer takes trees with references."""
    tris = [crossing_slivers(rows, offset=0.01 * rows) for rows in (5, 6, 3, 5)]  # 10, 12, 6, 10 triangles
    tris[3] = tris[3][:9]
    meshes = [(t.min(1), t.max(1)) for t in tris]
    knobs = dict(alpha=0.0, bins=8, max_leaf=1)  # alpha 0: spatial splits tried everywhere
    result = batch.build(meshes, method="sbvh", triangles=tris, **knobs)
    assert result.errors == {} and sorted(result.trees.capacities) == [12, 24]
    out = batch.optimize(result.trees, "hc")
    references = 0
    for i, (t, (lo, hi), tree, optimized) in enumerate(zip(tris, meshes, result.trees.unstack(),
                                                          out.trees.unstack())):
        single = jaxbvh.build(lo, hi, method="sbvh", triangles=t, **knobs)
        assert_same_arrays(tree, single, f"mesh {i}")
        jaxbvh.validate(tree, lo, hi, references=True, triangles=t)
        references += int(np.asarray(tree.prim_count).sum()) - t.shape[0]
        assert_same_arrays(optimized, jaxbvh.optimize.optimize(single, "hc").tree, f"mesh {i} optimized")
    assert references > 0  # the trees do have triangles in several leaves


def test_batched_sbvh_needs_the_triangles_and_refuses_a_bad_mesh_alone():
    tris = [crossing_slivers(5), crossing_slivers(5, offset=0.02)[:9]]
    meshes = [(t.min(1), t.max(1)) for t in tris]
    with pytest.raises(ValueError, match="mesh 0: method 'sbvh' needs the triangles"):
        batch.build(meshes, method="sbvh")
    with pytest.raises(ValueError, match="2 meshes but 1 triangle arrays"):
        batch.build(meshes, method="sbvh", triangles=tris[:1])
    # mesh 0's triangles do not match its boxes: its own error, mesh 1 built
    kept = batch.build(meshes, method="sbvh", triangles=[tris[0][:3], tris[1]], errors="keep", bins=8)
    assert list(kept.errors) == [0] and "mesh 0" in kept.errors[0]
    trees = kept.trees.unstack()
    assert trees[0] is None
    assert_same_arrays(trees[1], jaxbvh.build(*meshes[1], method="sbvh", triangles=tris[1], bins=8))


# ----------------------------------------------------------------------------------
# Devices: two CPU devices give exactly what one gives (subprocess: a fresh JAX)
# ----------------------------------------------------------------------------------

_SUBPROCESS = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    sys.path.insert(0, {repo!r})
    from jaxbvh import batch
    assert batch.use_cpu_cores(2) == 2  # before JAX's first operation
    rng = np.random.default_rng(0)
    meshes = []
    for n in (5, 9, 14, 3, 11):
        lo = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        meshes.append((lo, lo + rng.uniform(0, 0.3, (n, 3)).astype(np.float32)))
    config = batch.BatchConfig(max_padding=0.9)
    out = {{"devices": jax.device_count()}}
    for devices in (1, 2):
        got = out[devices] = {{}}
        for method in ("sweep", "lbvh"):
            trees = batch.build(meshes, method=method, batch=config, devices=devices).trees
            got[method] = [t.left.tolist() + t.lo.ravel().tolist() for t in trees.unstack()]
        opt = batch.optimize(trees, "hc", devices=devices)
        got["hc"] = [t.left.tolist() + t.hi.ravel().tolist() for t in opt.trees.unstack()]
        got["sah"] = batch.costs(opt.trees, devices=devices)["sah"].tolist()
    print("RESULT" + json.dumps(out))
""")


def test_two_devices_give_what_one_gives():
    # one process whose CPU is split into two devices (use_cpu_cores, so a fresh process),
    # the batch over one and over both
    code = _SUBPROCESS.format(repo=str(REPO))
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads([line for line in proc.stdout.splitlines() if line.startswith("RESULT")][-1][len("RESULT"):])
    assert out["devices"] == 2
    for key in ("sweep", "lbvh", "hc", "sah"):
        assert out["2"][key] == out["1"][key], key


def test_cpu_devices_are_fixed_once_jax_has_started():
    # this process's JAX has started: the count it has is kept, another is refused by name
    have = len(jax.devices("cpu"))
    assert batch.use_cpu_cores() == have and batch.use_cpu_cores(have) == have
    with pytest.raises(ValueError, match=f"started with {have} CPU device"):
        batch.use_cpu_cores(have + 1)
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(ValueError, match="whole number"):
            batch.use_cpu_cores(bad)


def test_batched_trace_of_a_tree_deeper_than_the_stack_equals_the_single_trace():
    """A 99-deep chain (deeper than the walk's stack: its rays climb) beside a balanced
    tree in one group: the batch traces both with the single trace's fixed stack, so every
    hit and counter equals the single call's (a stack sized to the group's deepest tree
    would count fewer box tests on the chain and compile a program per depth)."""
    from jaxbvh.batch.layout import Group, TreeBatch
    from jaxbvh.rays.stack_walk import STACK
    from jaxbvh.tree.layout import capacity_bucket, depth, pad_to
    from jaxbvh.tree.interchange import from_interchange

    rng = np.random.default_rng(3)
    n = 100
    x = np.sort(rng.uniform(-1, 1, n)).astype(np.float32)
    tri = np.zeros((n, 3, 3), np.float32)  # triangles across the x axis, in order along it
    tri[:, :, 0] = x[:, None]
    tri[:, 1, 1] = tri[:, 2, 2] = 1
    box_lo, box_hi = tri.min(axis=1), tri.max(axis=1)
    n_int = n - 1
    child = np.full((2 * n - 1, 2), -1, np.int32)  # interior j: leaf of triangle j, interior j + 1
    child[:n_int, 0] = n_int + np.arange(n_int)
    child[:n_int, 1] = np.append(np.arange(1, n_int), 2 * n - 2)
    node_lo = np.concatenate([[box_lo[j:].min(0) for j in range(n_int)], box_lo])
    node_hi = np.concatenate([[box_hi[j:].max(0) for j in range(n_int)], box_hi])
    chain = from_interchange(dict(child=child, prim_start=np.concatenate([np.zeros(n_int), np.arange(n)]).astype(np.int32),
                                  prim_count=np.concatenate([np.zeros(n_int), np.ones(n)]).astype(np.int32),
                                  prim_index=np.arange(n, dtype=np.int32), lo=node_lo, hi=node_hi, root=np.int32(0)))
    jaxbvh.validate(chain, box_lo, box_hi)
    assert int(np.max(depth(chain))) == n - 1 > STACK
    balanced = jaxbvh.build(box_lo, box_hi)
    slots = capacity_bucket(n)
    padded = [jax.tree_util.tree_map(np.asarray, pad_to(t, 2 * slots, slots)) for t in (chain, balanced)]
    stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *padded)
    trees = TreeBatch((Group(stacked, np.arange(2), np.full(2, n, np.int64)),), 2)
    # rays down the chain from +x: each level leaves its leaf pending (more than the stack holds)
    origin = np.column_stack([np.full(40, 2.0), rng.uniform(0.05, 0.3, (40, 2))]).astype(np.float32)
    direction = np.column_stack([-np.ones(40), rng.uniform(-0.01, 0.01, (40, 2))]).astype(np.float32)
    deep = jaxbvh.rays.trace(chain, tri, origin, direction, capacity=n, engine="jax")
    spilled = jaxbvh.rays.trace(chain, tri, origin, direction, engine="jax")
    assert (spilled.box_tests > deep.box_tests).any()  # the rays do climb with the walk's stack
    hits = batch.trace(trees, [tri, tri], [origin] * 2, [direction] * 2, rays_per_call=40, engine="jax")
    for got, tree in zip(hits, (chain, balanced)):
        want = jaxbvh.rays.trace(tree, tri, origin, direction, engine="jax")
        for field in ("t", "prim", "box_tests", "prim_tests", "nodes_visited"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
