"""Re-braiding reports as the optimizers do (jaxbvh.optimize.protocol.OptimizeResult; old name SearchResult).

``twolevel.run`` / ``run_from`` return a :class:`jaxbvh.twolevel.RebraidResult`: the
search fields (one step per stage, ``on_step`` once per stage) and the stage seconds,
BRef slots and kept top level that ``timings`` / ``info`` dicts used to receive; the
knobs are one RebraidConfig; a second scene of the same shapes traces and compiles
nothing. (Re-braiding builds one scene at a time: there is no batch to compare with a
loop.) Small 22-triangle trees keep the compiles short.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from jaxbvh import scenes, twolevel
from jaxbvh.optimize.protocol import STOP_REASONS, CompileClock, SearchResult, StepInfo
from jaxbvh.twolevel import objects as fm
from jaxbvh.twolevel.config import RebraidConfig

SHAPES = {"nodes": 128, "prims": 64, "instances": 8, "brefs": 32, "boxes": 512}


def pile(seed):
    """4 rotated instances of a 22-triangle tree (opening lowers the SAH: test_twolevel)."""
    tree = scenes.tree_mesh(jax.random.key(3), levels=1, branches=2, sides=3, leaves=1)
    return scenes.pile(jax.random.key(seed), *tree, 4)


def same_tree(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_run_from_reports_every_stage():
    mesh = pile(2)
    trees = fm.build_objects(mesh)
    infos = []
    result = twolevel.run_from(mesh, trees, RebraidConfig(budget=4.0), shapes=SHAPES, on_step=infos.append)
    assert isinstance(result, twolevel.RebraidResult) and isinstance(result, SearchResult)
    assert all(isinstance(i, StepInfo) for i in infos) and tuple(infos) == result.trace
    assert [i.stage for i in infos] == ["pack", "top"] and [i.step for i in infos] == [0, 1]
    assert result.steps == 2 and np.isnan(result.history).all() and result.history.shape == (2,)
    assert result.cost is None and result.stop in STOP_REASONS and not result.converged
    n = len(mesh.instances)
    assert result.kept == "rebraided" and infos[-1].moves == int(result.tree.bref_count) - n > 0
    assert result.slots == twolevel.slots_of(mesh, RebraidConfig().threshold, 4.0)
    assert list(result.stage_seconds) == ["pack", "top"] and min(result.stage_seconds.values()) >= 0
    assert sum(result.stage_seconds.values()) == pytest.approx(infos[-1].seconds)
    assert infos[-1].seconds <= result.seconds and 0 <= result.compile_seconds <= result.seconds
    # the knobs as keywords make the same Config; not both at once
    same_tree(twolevel.run_from(mesh, trees, budget=4.0, shapes=SHAPES).tree, result.tree)
    with pytest.raises(TypeError, match="not both"):
        twolevel.run_from(mesh, trees, RebraidConfig(), budget=4.0)
    # the plain two-level BVH: threshold inf opens nothing
    plain = twolevel.run_from(mesh, trees, RebraidConfig(threshold=math.inf), shapes=SHAPES)
    assert plain.kept == "two-level" and plain.trace[-1].moves == 0


def test_run_builds_the_objects_first_and_build_returns_its_tree():
    mesh = pile(5)
    result = twolevel.run(mesh, None, RebraidConfig(budget=4.0))
    assert [i.stage for i in result.trace] == ["objects", "pack", "top"] and result.steps == 3
    assert list(result.stage_seconds) == ["objects", "pack", "top"]
    same_tree(twolevel.build(mesh, budget=4.0), result.tree)
    # the old in-place dicts still work, with a warning, from the result's fields
    timings, info = {}, {}
    with pytest.warns(DeprecationWarning, match="stage_seconds"):
        tree = twolevel.build(mesh, budget=4.0, timings=timings, info=info)
    same_tree(tree, result.tree)
    assert set(timings) == {"objects", "pack", "top"} and info == {"slots": result.slots, "kept": result.kept}


def test_no_retrace_for_a_scene_of_the_same_shapes():
    config = RebraidConfig(budget=4.0)
    first_mesh, second_mesh = pile(2), pile(5)
    first = twolevel.run_from(first_mesh, fm.build_objects(first_mesh), config, shapes=SHAPES)
    trees = fm.build_objects(second_mesh)
    with CompileClock() as clock:
        second = twolevel.run_from(second_mesh, trees, config, shapes=SHAPES)  # other boxes, same shapes
    assert clock.traces == 0 and clock.seconds == 0.0, clock.events
    assert second.compile_seconds == 0.0
    assert not np.array_equal(np.asarray(first.tree.bref_lo), np.asarray(second.tree.bref_lo))
