"""Annealing schedules (jaxbvh.optimize.schedules): Kensler's formula, the named makers,
and composition by optax. No rotation runs here (those are in test_rotate.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxbvh.optimize.schedules import EXPONENTIAL_FINAL, SCHEDULES, constant_schedule, kensler_schedule


def kensler_formula(i, steps, period, hottest):
    """Kensler 2008, section 4, literally (NumPy float64)."""
    i = np.asarray(i, np.float64)
    return np.maximum(0, -np.sin(2 * np.pi * i / period)) * np.maximum(0, steps - i) * hottest / steps


def test_kensler_schedule_values():
    s = kensler_schedule(1250, 50, 1.5)
    picks = [0, 10, 25, 37, 40, 600, 1249, 1260]
    got = np.array([float(s(k)) for k in picks])
    np.testing.assert_allclose(got, kensler_formula(picks, 1250, 50, 1.5), atol=1e-5)
    assert float(s(0)) == 0.0 and float(s(1260)) == 0.0  # starts cold, ends cold
    assert float(s(25)) == 0.0 and float(s(50 * 7 + 25)) == 0.0  # exactly cold at sin(pi)
    assert float(jax.jit(s)(jnp.int32(37))) == pytest.approx(kensler_formula(37, 1250, 50, 1.5), rel=1e-5)
    assert kensler_schedule(1250, 50, 1.5) is s  # same function object: jit caches hit
    with pytest.raises(ValueError):
        kensler_schedule(0)


@given(steps=st.integers(1, 3000), period=st.integers(1, 100), hottest=st.floats(0, 3),
       boundary=st.integers(0, 3000), data=st.data())
def test_kensler_schedule_composes_under_optax_join(steps, period, hottest, boundary, data):
    """``join_schedules([kensler, constant(0)], [steps])`` is Kensler's schedule (it ends
    cold); as the second piece it is shifted by its boundary; traced or not."""
    kensler = kensler_schedule(steps, period, hottest)
    then_cold = optax.join_schedules([kensler, optax.constant_schedule(0.0)], boundaries=[steps])
    late = optax.join_schedules([optax.constant_schedule(0.0), kensler], boundaries=[boundary])
    i = data.draw(st.integers(0, steps + boundary + 10))
    traced = jax.jit(then_cold)(jnp.int32(i))
    assert float(then_cold(i)) == float(kensler(i))
    assert float(traced) == pytest.approx(float(kensler(i)), rel=1e-6, abs=1e-7)
    assert float(late(i)) == (float(kensler(i - boundary)) if i >= boundary else 0.0)
    assert float(kensler(i)) == pytest.approx(kensler_formula(i, steps, period, hottest), abs=1e-6)


def test_named_schedule_makers():
    assert set(SCHEDULES) == {"kensler", "cosine", "exponential"}
    steps, hottest, period = 100, 0.3, 20
    made = {name: make(steps, hottest, period) for name, make in SCHEDULES.items()}
    assert made["kensler"] is kensler_schedule(steps, period, hottest)
    for name, make in SCHEDULES.items():  # equal arguments: the same function (jit caches hit)
        assert make(steps, hottest, period) is made[name], name
    i = np.arange(0, 2 * steps)
    cosine = np.array([float(made["cosine"](k)) for k in i])
    expected = hottest * 0.5 * (1 + np.cos(np.pi * np.minimum(i, steps) / steps))
    np.testing.assert_allclose(cosine, expected, atol=1e-6)
    exponential = np.array([float(made["exponential"](k)) for k in i])
    np.testing.assert_allclose(exponential, hottest * EXPONENTIAL_FINAL ** (i / steps), rtol=1e-5)
    np.testing.assert_allclose(float(made["exponential"](steps)), hottest * EXPONENTIAL_FINAL, rtol=1e-5)
    for name, make in SCHEDULES.items():
        with pytest.raises(ValueError, match="steps"):
            make(0, hottest, period)
        with pytest.raises(ValueError, match="hottest"):
            make(steps, -1.0, period)


def test_constant_schedule():
    assert float(constant_schedule(0.25)(7)) == 0.25
    assert float(jax.jit(constant_schedule(0.0))(jnp.int32(3))) == 0.0
    assert constant_schedule(0.25) is constant_schedule(0.25)
