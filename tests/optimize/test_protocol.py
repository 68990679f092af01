"""Every optimizer of jaxbvh.optimize.OPTIMIZERS keeps the protocol (jaxbvh.optimize.protocol).

For each: ``init``/``step``/``result`` have the contract's shapes; ``step`` jitted once
serves every tree of one capacity; a done state is a fixed point; ``step`` vmapped over
two different trees padded to one capacity gives each tree its own single-tree result,
node for node; every result is a valid tree. The one batch driver
(``driver.run_states``) runs rows vmapped or mapped alike, filler rows run no step, and
a second batch of the same shapes compiles nothing. Small trees keep the compiles short.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_tree

import jaxbvh
from jaxbvh.optimize import OPTIMIZERS, driver
from jaxbvh.optimize.protocol import CompileClock, Optimizer, OptimizeResult, OptimizerState, Progress
from jaxbvh.tree import stack_trees, unstack_trees

#: small settings where the defaults would take long (annealing's schedule)
CONFIGS = {"sa": dict(steps=8, period=4)}
TREE_FIELDS = ("left", "right", "parent", "lo", "hi", "root", "axis")


def config_of(name):
    return OPTIMIZERS[name].Config(**CONFIGS.get(name, {}))


@pytest.fixture(scope="module")
def trees():
    """Two different trees of different capacities, padded to one by stack_trees."""
    a = random_tree(31, 20, 2, nodes=64, prims=32)
    b = random_tree(32, 45, 1, "grid", nodes=128, prims=64)
    batch = stack_trees([a[0], b[0]])
    return batch, unstack_trees(batch), [(a[1], a[2]), (b[1], b[2])]


def same_shapes(x, y):
    """Same pytree structure (static settings included), shapes and dtypes."""
    assert jax.tree_util.tree_structure(x) == jax.tree_util.tree_structure(y)
    for u, v in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)):
        assert (jnp.shape(u), jnp.result_type(u)) == (jnp.shape(v), jnp.result_type(v))


def plain(x):
    """``x`` as a NumPy array (random keys as their key data)."""
    if jnp.issubdtype(jnp.result_type(x), jax.dtypes.prng_key):
        x = jax.random.key_data(x)
    return np.asarray(x)


def assert_same_result(got, expected):
    for field in TREE_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(got.tree, field)),
                                      np.asarray(getattr(expected.tree, field)), err_msg=field)
    for field in ("steps", "moves", "converged", "history_moves", "history_stage"):
        np.testing.assert_array_equal(np.asarray(getattr(got, field)), np.asarray(getattr(expected, field)),
                                      err_msg=field)
    for field in ("sah", "sah_start", "history"):
        np.testing.assert_allclose(np.asarray(getattr(got, field)), np.asarray(getattr(expected, field)),
                                   rtol=1e-6, err_msg=field)


def test_the_registry():
    assert list(OPTIMIZERS) == ["hc", "sa", "reinsert", "treelet", "pipeline"]
    for name, optimizer in OPTIMIZERS.items():
        assert isinstance(optimizer, Optimizer) and optimizer.name == name
        assert optimizer.stages and optimizer.paper
        assert dataclasses.is_dataclass(optimizer.Config)
        config = optimizer.Config()
        with pytest.raises(dataclasses.FrozenInstanceError):
            config.ct = 2.0
    assert OPTIMIZERS["pipeline"].stages == ("treelet", "reinsert")
    # the package keeps its submodules under their own names
    import jaxbvh.optimize as package
    for module in ("reinsert", "treelet", "pipeline", "rotate"):
        assert getattr(package, module).__name__ == f"jaxbvh.optimize.{module}"


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_protocol(name, trees):
    optimizer = OPTIMIZERS[name]
    config = config_of(name)
    batch, singles, prims = trees
    keys = jax.random.split(jax.random.key(7), 2)

    # init: a state with the contract's parts; defaults when config and key are None
    state = optimizer.init(singles[0], config, keys[0])
    assert isinstance(state, OptimizerState) and isinstance(state.progress, Progress)
    assert int(state.progress.step) == 0 and not bool(state.progress.converged)
    assert float(state.progress.sah_start) == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(singles[0]))))
    same_shapes(optimizer.init(singles[0]), optimizer.init(singles[0], optimizer.Config(), None))
    if name != "sa":
        same_shapes(optimizer.init(singles[0], config), state)

    # step: one compiled program for every tree of one capacity; the state keeps its shapes
    traces = []

    def counted(s):
        traces.append(1)
        return optimizer.step(s)

    step = jax.jit(counted)
    finish = jax.jit(optimizer.result)
    same_shapes(jax.eval_shape(optimizer.step, state), state)
    expected = []
    for tree, key, (plo, phi) in zip(singles, keys, prims):
        s = optimizer.init(tree, config, key)
        for _ in range(int(s.progress.limit) + 1):
            if bool(s.progress.done):
                break
            s = step(s)
        assert bool(s.progress.done)
        # a done state is a fixed point
        again = step(s)
        for u, v in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(s)):
            np.testing.assert_array_equal(plain(u), plain(v))
        result = jax.device_get(finish(s))
        assert isinstance(result, OptimizeResult)
        jaxbvh.validate(result.tree, plo, phi)
        assert float(result.sah) <= float(result.sah_start) * (1 + 1e-6)
        assert float(result.sah) == pytest.approx(float(jaxbvh.sah(jaxbvh.to_jax(result.tree))), rel=1e-6)
        expected.append(result)
    assert len(traces) == 1  # no retrace for the second tree

    # the same through the driver: step vmapped over the batch until every tree is done
    results = driver.run_batch(optimizer, batch, config, keys=keys)
    for i, single in enumerate(expected):
        assert_same_result(jax.tree_util.tree_map(lambda x, i=i: x[i], results), single)


def test_the_batch_driver_maps_as_it_vmaps_runs_no_filler_and_does_not_retrace(trees):
    """``run_states``, the program every batch path runs (``run_batch``,
    ``rotate.optimize_batch``, ``jaxbvh.batch.optimize``): rows one after another
    (``"map"``) give what rows side by side give, node for node; a filler row (``real``
    False) runs no step; a batch of other trees of the same shapes traces nothing."""
    optimizer, config = OPTIMIZERS["hc"], config_of("hc")
    batch, singles, _ = trees
    states = driver.init_batch(optimizer, batch, config)
    vmapped = jax.device_get(driver.run_states(optimizer, states))
    mapped = jax.device_get(driver.run_states(optimizer, states, mode="map"))
    for i, tree in enumerate(singles):
        alone = driver.run(optimizer, tree, config)
        for got in (vmapped, mapped):
            assert_same_result(jax.tree_util.tree_map(lambda x, i=i: x[i], got), alone)
    assert min(vmapped.steps) > 0
    filled = jax.device_get(driver.run_states(optimizer, states, mode="map", real=[True, False]))
    assert int(filled.steps[0]) == int(vmapped.steps[0]) and int(filled.steps[1]) == 0
    others = stack_trees([random_tree(41, 20, 2, nodes=64, prims=32)[0],
                          random_tree(42, 45, 1, "grid", nodes=128, prims=64)[0]])
    other_states = driver.init_batch(optimizer, others, config)
    with CompileClock() as clock:
        again = jax.device_get(driver.run_states(optimizer, other_states))
    assert clock.traces == 0, clock.events
    assert not np.array_equal(again.tree.left, vmapped.tree.left)  # really other trees
