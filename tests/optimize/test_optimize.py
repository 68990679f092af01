"""The optimizer registry and entry point, and the treelet + reinsertion pipeline (jaxbvh.optimize)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import assert_same_tree, random_tree

import jaxbvh
from jaxbvh.configs import DEFAULT_MAX_LEAF
from jaxbvh.optimize import OPTIMIZERS, make_config, optimize, pipeline, reinsert, treelet
from jaxbvh.optimize.leaves_reference import merge_leaves
from jaxbvh.optimize.driver import TimeBudget


def check(tree, result, prim_lo, prim_hi):
    jaxbvh.validate(result.tree, prim_lo, prim_hi)
    t, out = jaxbvh.to_numpy(tree), jaxbvh.to_numpy(result.tree)
    # leaves are kept, but for the pipeline's final merge of subtrees into leaves
    kept = (t.prim_count > 0) & (out.prim_count == t.prim_count)
    np.testing.assert_array_equal(out.lo[kept], t.lo[kept])
    assert result.sah == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(result.tree))), rel=1e-6)
    assert result.sah <= result.sah_start * (1 + 1e-6)


def test_every_method_gives_a_valid_tree_and_reports_every_step():
    tree, plo, phi = random_tree(21, 50, 2)
    for method, optimizer in OPTIMIZERS.items():
        steps = []
        result = optimize(tree, method, on_step=steps.append, **(dict(steps=12) if method == "sa" else {}))
        check(tree, result, plo, phi)
        assert isinstance(result.tree.left, np.ndarray)  # NumPy from optimize()
        assert steps and len(steps) == len(result.trace) >= result.steps > 0
        assert [info.step for info in steps] == list(range(len(steps)))
        assert {info.method for info in steps} == {method}
        assert {info.stage for info in steps} <= set(optimizer.stages)
        # the one result type's run fields, as GRASP, the GA and re-braiding fill them
        assert result.stop == ("converged" if result.converged else "limit") and result.cost_name == "sah"
        assert 0 <= result.compile_seconds <= result.seconds and result.cost == result.sah


def chained_by_hand(tree, rounds=8, round_gain=1e-3, treelet_options=None, reinsert_options=None,
                    first_passes=pipeline.DEFAULT_FIRST_TREELET_PASSES, widen_until=pipeline.DEFAULT_WIDEN_UNTIL,
                    max_leaf=DEFAULT_MAX_LEAF):
    """The pipeline's rounds written out with the stages' own entry points, then the final
    leaf merge (its NumPy twin): ``(tree, stages)``."""
    t, sah, stages = tree, float(jaxbvh.sah(jaxbvh.to_jax(tree))), []
    for round_ in range(rounds):
        before = sah
        first = dict(first_fraction=reinsert.DEFAULT_FIRST_FRACTION if round_ == 0 else 1.0)
        passes = pipeline.DEFAULT_TREELET_PASSES
        if round_ == 0 and first_passes is not None:
            passes = min(passes, first_passes)
        r = treelet.restructure(t, max_passes=passes, split_axes=False, **(treelet_options or {}))
        t, stages = r.tree, stages + ["treelet"] * int(r.steps)
        sah = float(r.history[r.steps - 1]) if r.steps else sah
        # the pipeline's widen_until: the first round's hand-over (later rounds never widen)
        first["widen_until"] = widen_until
        r = reinsert.reinsert(t, split_axes=False, **{**first, **(reinsert_options or {})})
        t, stages = r.tree, stages + ["reinsert"] * int(r.steps)
        sah = float(r.history[r.steps - 1]) if r.steps else sah
        if before - sah < round_gain * before:
            break
    return merge_leaves(t, max_leaf), stages


def test_pipeline_is_its_stages_in_rounds():
    """The pipeline's tree is the one the stages give when chained by hand, step for step."""
    tree, plo, phi = random_tree(22, 60, 1)
    result = optimize(tree, "pipeline", split_axes=False)
    expected, stages = chained_by_hand(tree)
    assert_same_tree(result.tree, expected)
    assert [pipeline.STAGES[i] for i in result.history_stage[:result.steps]] == stages
    assert result.converged and "treelet" in stages[stages.index("reinsert"):]  # more than one round
    check(tree, result, plo, phi)
    axes = optimize(tree, "pipeline")  # with Kensler's split-axis pass: the same SAH
    assert axes.sah == pytest.approx(result.sah, rel=1e-6)
    assert_same_tree(axes.tree, jaxbvh.tree.assign_split_axes(result.tree), fields=("axis", "lo", "hi"))


def test_pipeline_passes_over_a_stage_with_nothing_to_do():
    """Two-leaf treelets never change a tree: the treelet stages take no step, and the
    pipeline is rounds of reinsertion; with Ct = 0 nothing changes the SAH at all."""
    tree, plo, phi = random_tree(24, 40, 1)
    result = optimize(tree, "pipeline", split_axes=False, max_rounds=3, treelet=dict(leaves=2))
    expected, stages = chained_by_hand(tree, rounds=3, treelet_options=dict(leaves=2))
    assert set(stages) == {"reinsert"}
    assert_same_tree(result.tree, expected)
    assert [pipeline.STAGES[i] for i in result.history_stage[:result.steps]] == stages
    check(tree, result, plo, phi)
    flat = optimize(tree, "pipeline", ct=0.0, treelet=dict(leaves=2))
    assert flat.steps == 0 and flat.moves == 0 and flat.converged


def test_pipeline_rounds_stop_at_max_rounds_and_chunks_change_nothing():
    tree, plo, phi = random_tree(22, 60, 1)
    one = optimize(tree, "pipeline", split_axes=False, max_rounds=1)
    expected, stages = chained_by_hand(tree, rounds=1)
    assert_same_tree(one.tree, expected)
    assert int(one.steps) == len(stages) and not one.converged  # the limit, not the gain rule
    log = []
    chunked = optimize(tree, "pipeline", split_axes=False, max_rounds=1, on_step=log.append)
    assert_same_tree(chunked.tree, one.tree)
    assert [info.stage for info in log] == stages
    for passes in (0, 1):  # the first round's own treelet passes (traced: the same program)
        short = optimize(tree, "pipeline", split_axes=False, max_rounds=2, first_treelet_passes=passes)
        expected, stages = chained_by_hand(tree, rounds=2, first_passes=passes)
        assert_same_tree(short.tree, expected)
        assert [pipeline.STAGES[i] for i in short.history_stage[:short.steps]] == stages
        assert stages[:passes + 1].count("treelet") == passes
    # the first round's hand-over (widen_until, traced: the same program) acts on this tree
    full = optimize(tree, "pipeline", split_axes=False, max_rounds=2, widen_until=None)
    expected, stages = chained_by_hand(tree, rounds=2, widen_until=None)
    assert_same_tree(full.tree, expected)
    assert [pipeline.STAGES[i] for i in full.history_stage[:full.steps]] == stages
    assert stages != chained_by_hand(tree, rounds=2)[1]


def test_pipeline_config():
    default = pipeline.Config()
    assert default.treelet.max_passes == pipeline.DEFAULT_TREELET_PASSES  # the pipeline's passes
    assert default.treelet.split_axes is False and default.reinsert.split_axes is False
    given = pipeline.Config(ct=2.0, treelet=dict(leaves=5), reinsert=reinsert.Config(max_steps=64, ct=3.0))
    assert (given.treelet.leaves, given.treelet.ct, given.reinsert.max_steps, given.reinsert.ct) == (5, 2.0, 64, 2.0)
    assert pipeline.Config(treelet=treelet.Config()) == default  # the stored stage configs are what runs
    for bad, knob in ((dict(round_gain=-1.0), "round_gain"), (dict(max_rounds=0), "max_rounds"),
                      (dict(treelet_passes=-1), "treelet_passes"), (dict(ci=-1.0), "ci"),
                      (dict(treelet=dict(leaves=11)), "leaves"), (dict(reinsert=3), "reinsert"),
                      (dict(reinsert=dict(first_fraction=0)), "first_fraction")):
        with pytest.raises(ValueError, match=knob):
            pipeline.Config(**bad)


def test_make_config_and_bad_arguments():
    tree, plo, phi = random_tree(23, 60, 1)
    assert make_config("reinsert") == reinsert.Config()
    assert make_config("reinsert", reinsert.Config(max_steps=9), first_fraction=1.0) == reinsert.Config(
        max_steps=9, first_fraction=1.0)
    assert make_config("pipeline", max_rounds=2).max_rounds == 2
    with pytest.raises(ValueError, match="method"):
        optimize(tree, "magic")
    with pytest.raises(ValueError, match="unknown option.*steps"):
        optimize(tree, "pipeline", steps=3)
    with pytest.raises(ValueError, match="treelet.Config"):
        optimize(tree, "treelet", config=reinsert.Config())
    with pytest.raises(ValueError, match="time_budget"):
        optimize(tree, "reinsert", time_budget=-1)
    with pytest.raises(ValueError, match="max_steps"):
        optimize(tree, "reinsert", max_steps=0)


def test_time_budget_stops_the_pipeline_after_its_first_step():
    """The budget counts the search, not compiling: the tiniest budget still runs the
    first chunk (one step) on a cold process, with no warning, and reports the seconds
    spent compiling apart; a budget spent during the first chunk stops after it."""
    import warnings

    from jaxbvh.optimize import driver

    tree, plo, phi = random_tree(23, 60, 1)
    jax.clear_caches()  # compiling must come before the budget, not out of it
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        first = optimize(tree, "pipeline", time_budget=1e-9)
    check(tree, first, plo, phi)
    assert int(first.steps) == 1 and [info.step for info in first.trace] == [0]
    assert float(first.sah) < float(first.sah_start) and first.compile_seconds > 0 and first.stop == "budget"
    whole = optimize(tree, "pipeline")  # compiled now: the same programs, a step for step equal start
    np.testing.assert_array_equal(first.history[:1], whole.history[:1])
    spent = TimeBudget(1e-9)
    spent.start()
    pipe = OPTIMIZERS["pipeline"]
    trace = []
    state = driver.drive(pipe, pipe.init(tree, None, None), budget=spent, trace=trace)
    short = driver.finish(pipe.result, state)
    check(tree, jax.device_get(short), plo, phi)
    assert [info.stage for info in trace] == ["treelet"] and int(short.steps) == 1
    assert not bool(short.converged)


# ----------------------------------------------------------------------------------
# jaxbvh optimize --method reinsert|treelet|pipeline (the command line)
# ----------------------------------------------------------------------------------


def test_cli_methods_give_valid_saved_trees(capsys, tmp_path):
    from helpers import grid_obj, run_json

    mesh = grid_obj(tmp_path / "grid.obj", n=5)
    results = {}
    for method in ("pipeline", "reinsert", "treelet"):
        out = tmp_path / f"{method}.npz"
        argv = ["optimize", mesh, "-o", out] + ([] if method == "pipeline" else ["--method", method])
        results[method] = result = run_json(capsys, *argv)  # the default is the pipeline
        assert result["method"] == method and result["valid"] is True
        assert result["after"]["sah"] <= result["before"]["sah"] * (1 + 1e-6)
        saved = run_json(capsys, "stats", out, "--mesh", mesh)  # the tree written is valid
        assert saved["valid"] is True
        assert saved["sah"] == pytest.approx(result["after"]["sah"], rel=1e-5)
    stages = results["pipeline"]["stages"]
    assert stages[0]["stage"] == "treelet"
    assert sum(s["steps"] for s in stages) == results["pipeline"]["passes"]
    assert all(a["stage"] != b["stage"] for a, b in zip(stages, stages[1:]))
    assert results["pipeline"]["treelet_leaves"] == 7 and "first_fraction" in results["reinsert"]
    assert "first_fraction" not in results["treelet"]


@pytest.mark.parametrize("argv, fragment", [
    (["--method", "reinsert", "--first-fraction", "0"], "--first-fraction"),
    (["--first-fraction", "1.5"], "--first-fraction"),
    (["--method", "treelet", "--treelet-leaves", "11"], "--treelet-leaves"),
    (["--method", "reinsert", "--time-budget", "0"], "--time-budget"),
    (["--method", "treelet", "--time-budget", "-1"], "--time-budget"),
])
def test_cli_bad_options_are_one_line_errors(capsys, tmp_path, argv, fragment):
    from helpers import assert_one_line_error, grid_obj, run_cli

    mesh = grid_obj(tmp_path / "grid.obj")
    assert_one_line_error(*run_cli(capsys, "optimize", mesh, *argv), fragment)


@pytest.mark.parametrize("method", ["reinsert", "treelet"])
@pytest.mark.parametrize("kind", ["cycle", "nan-box"])
def test_cli_methods_refuse_broken_trees(capsys, tmp_path, method, kind):
    from helpers import assert_one_line_error, broken_tree_file, run_cli

    mesh, path = broken_tree_file(tmp_path, kind)
    assert_one_line_error(*run_cli(capsys, "optimize", path, "--method", method), "invalid BVH", path.name)


def test_time_budget_clock_counts_from_start():
    import time

    none = TimeBudget(None)
    none.start()
    assert not any(none.spent() for _ in range(3)) and none.left() is None
    tiny = TimeBudget(1e-9)
    time.sleep(0.01)  # nothing is spent before start() (run() calls it first thing)
    assert not tiny.spent() and tiny.left() == 1e-9
    tiny.start()
    time.sleep(0.01)
    assert tiny.spent()
    long = TimeBudget(3600.0)
    long.start()
    assert not long.spent() and not long.spent()
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="time_budget"):
            TimeBudget(bad)


def test_pipeline_ends_with_the_leaf_merge():
    """With a dear traversal step, leaves of several primitives pay: the pipeline's tree
    is its max_leaf 1 tree merged exactly (the NumPy twin), at most max_leaf per leaf."""
    tree, plo, phi = random_tree(23, 50, 1)
    single = optimize(tree, "pipeline", ct=4.0, max_leaf=1)
    assert int(np.max(single.tree.prim_count)) == 1
    merged = optimize(tree, "pipeline", ct=4.0, max_leaf=3)
    jaxbvh.validate(merged.tree, plo, phi)
    assert merged.sah == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(merged.tree), 4.0)), rel=1e-6)
    want = merge_leaves(single.tree, 3, ct=4.0)  # (its runs laid out before the split-axis pass)
    assert_same_tree(merged.tree, want, fields=("left", "right", "parent", "lo", "hi", "prim_count", "root"))
    assert 1 < int(np.max(merged.tree.prim_count)) <= 3
    assert merged.sah < single.sah


def _states_equal(got, expected):
    for u, v in zip(jax.tree_util.tree_leaves((got.progress, got.inner)),
                    jax.tree_util.tree_leaves((expected.progress, expected.inner))):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


@pytest.mark.parametrize("options", [dict(), dict(first_treelet_passes=0, max_rounds=3),
                                     dict(treelet=dict(leaves=2), max_rounds=2)])
def test_pipeline_host_loop_is_the_loop_of_its_step(options):
    """The driver runs the pipeline stage by stage on the host (pipeline.advance); the
    state it reaches, whole or stopped after every step, is the loop of ``step``'s, bit
    for bit; and once the zero-step call has compiled, the run compiles nothing more."""
    from jaxbvh.optimize import driver
    from jaxbvh.optimize.protocol import CompileClock

    tree, plo, phi = random_tree(24, 60, 1)
    config = make_config("pipeline", None, split_axes=False, **options)
    start = pipeline.init(tree, config)
    expected = driver.advance(pipeline.step, start, np.int32(np.iinfo(np.int32).max))
    assert int(expected.progress.step) > 2 and bool(expected.progress.done)
    assert pipeline.advance(start, 0) is start  # no steps: compiles only
    with CompileClock() as clock:
        whole = pipeline.advance(start, int(np.iinfo(np.int32).max))
    # nothing traced anew (in a plain process nothing is compiled either; under the suite's
    # shared cache and XLA flags one or two programs were sent to XLA again: left open)
    assert clock.traces == 0
    _states_equal(whole, expected)
    state, stops = start, 0
    while not bool(state.progress.done):
        stops += 1
        state = pipeline.advance(state, stops)
        assert int(state.progress.step) == stops
    _states_equal(state, expected)
