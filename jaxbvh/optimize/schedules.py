"""Annealing temperature schedules, optax style: a schedule is a function ``step -> T``.

Anything that takes a schedule (:func:`jaxbvh.optimize.rotate.anneal`) accepts every optax
schedule as well (``optax.linear_schedule``, ``optax.cosine_decay_schedule``,
``optax.join_schedules``, ...), and the schedules here are plain functions built from
``jnp``, so optax can compose them: ``optax.join_schedules([kensler_schedule(1250),
optax.constant_schedule(0.0)], [1250])`` is Kensler's schedule followed by a quench.
``step`` may be a Python int or a traced int32 scalar; the result is a float scalar
(float32 for the schedules here).

:data:`SCHEDULES` names the schedules the command line offers (``--schedule``): each
entry is a *maker* ``make(steps, hottest, period) -> schedule`` for an annealing run of
``steps`` passes with peak temperature ``hottest`` (the makers that have no period
ignore it). Makers are cached, so equal arguments give the same function object and
compiled programs are reused.
"""

from __future__ import annotations

from functools import lru_cache

import jax.numpy as jnp

KENSLER_STEPS = 1250
KENSLER_PERIOD = 50
KENSLER_HOTTEST = 1.5

# Peak temperature used by jaxbvh.rotate.anneal unless told otherwise. Temperatures
# here are in units of the node cost C(n) of jaxbvh.cost (SAH of the subtree relative
# to the node's own area, ct = ci = 1), and Kensler's h = 1.5 is far too hot on that
# scale: at h = 1.5 most uphill moves are taken, the tree random-walks, and after the
# quench annealing ends where hill climbing does (legocar 29.28 for both, N = 250).
# Measured (N = 250, one chain; table in bench/results/rotate.md): 0.1 - 0.15 works best on
# the tinybvh legocar and drone trees, 0.05 on larger or already good trees (bunny, spot),
# where 0.15 gains nothing over hill climbing. 0.15 is the default; try lower on big trees.
DEFAULT_HOTTEST = 0.15


@lru_cache(maxsize=64)  # the same parameters give the same function: jit caches hit
def kensler_schedule(steps: int = KENSLER_STEPS, period: int = KENSLER_PERIOD,
                     hottest: float = KENSLER_HOTTEST):
    """Kensler's clamped, linearly ramped sine (Kensler 2008, section 4).

    ``T(i) = max(0, -sin(2 pi i / period)) * (steps - i) * hottest / steps``, and 0 for
    ``i >= steps``. Defaults are the paper's: N = 1250 passes, f = 50, h = 1.5 (the
    paper's useful range for ``hottest`` is 0.8 - 2.2; on this library's node cost that is
    far too hot, see :data:`DEFAULT_HOTTEST`). The first half period is cold, so
    annealing starts as hill climbing.
    """
    if steps < 1:
        raise ValueError(f"kensler_schedule: steps must be >= 1, got {steps}")
    if period < 1:
        raise ValueError(f"kensler_schedule: period must be >= 1, got {period}")
    if not hottest >= 0:
        raise ValueError(f"kensler_schedule: hottest must be >= 0, got {hottest}")

    def schedule(step):
        return kensler_temperature(step, steps, period, hottest)

    return schedule


def kensler_temperature(step, steps, period, hottest):
    """Kensler's ``T(step)`` with every argument possibly traced (one compile for all)."""
    i = jnp.asarray(step, jnp.float32)
    period = jnp.asarray(period, jnp.float32)
    steps = jnp.asarray(steps, jnp.float32)
    phase = jnp.mod(i, period) / period
    # exactly 0 on the cold half: float32 sin(pi) is -8.7e-8, not 0, and a temperature
    # of 1e-7 would make acceptance hinge on the last bit of a cost difference
    wave = jnp.where(phase > 0.5, jnp.maximum(0.0, -jnp.sin(2.0 * jnp.pi * phase)), 0.0)
    ramp = jnp.maximum(0.0, (steps - i) * (hottest / steps))
    return (wave * ramp).astype(jnp.float32)


@lru_cache(maxsize=64)
def constant_schedule(value: float):
    """``T(i) = value`` for every step (``0`` turns annealing into greedy descent)."""

    def schedule(step):
        del step
        return jnp.asarray(value, jnp.float32)

    return schedule


# ----------------------------------------------------------------------------------
# Named schedule makers (the command line's --schedule)
# ----------------------------------------------------------------------------------

#: the exponential schedule falls to this fraction of ``hottest`` at the end of the
#: schedule (``T(i) = hottest * EXPONENTIAL_FINAL ** (i / steps)``: 1 % after ``steps``)
EXPONENTIAL_FINAL = 0.01


def _check_maker(name: str, steps: int, hottest: float) -> None:
    if steps < 1:
        raise ValueError(f"{name} schedule: steps must be >= 1, got {steps}")
    if not hottest >= 0:
        raise ValueError(f"{name} schedule: hottest must be >= 0, got {hottest}")


def make_kensler(steps: int, hottest: float, period: int):
    """Kensler's clamped, ramped sine (:func:`kensler_schedule`) in the makers' argument order."""
    return kensler_schedule(steps, period, hottest)


@lru_cache(maxsize=64)
def make_cosine(steps: int, hottest: float, period: int):
    """``optax.cosine_decay_schedule(hottest, steps)``: from ``hottest`` at pass 0 down to
    0 at pass ``steps`` along half a cosine (``period`` unused)."""
    del period
    _check_maker("cosine", steps, hottest)
    import optax  # here, not at import: optax's import costs ~0.25 s of every first run

    return optax.cosine_decay_schedule(hottest, steps)


@lru_cache(maxsize=64)
def make_exponential(steps: int, hottest: float, period: int):
    """``optax.exponential_decay(hottest, steps, EXPONENTIAL_FINAL)``: ``T(i) = hottest *
    0.01 ** (i / steps)`` (:data:`EXPONENTIAL_FINAL`), smooth (not staircase); ``period``
    unused."""
    del period
    _check_maker("exponential", steps, hottest)
    import optax

    return optax.exponential_decay(hottest, transition_steps=steps, decay_rate=EXPONENTIAL_FINAL)


#: named schedule makers ``make(steps, hottest, period) -> schedule`` (module docstring)
SCHEDULES = {"kensler": make_kensler, "cosine": make_cosine, "exponential": make_exponential}
