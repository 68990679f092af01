"""The compile policy (jaxbvh.compile_policy): each program family gets its options, the
user's XLA_FLAGS and choice win, the options reach XLA on the plain and the stored path,
and results do not depend on them."""

from __future__ import annotations

import contextlib
import os

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import UNOPTIMIZED_XLA, assert_same_costs, assert_same_tree, local_boxes
from hypothesis import given, settings

import jaxbvh
from jaxbvh import compile_cache, compile_policy, program_store
from jaxbvh.program_store import stored_jit
from strategies import triangle_soups

#: an option name XLA does not know: compiling with it fails, so a failure proves the
#: option reached XLA (and its absence that it did not)
BOGUS = "xla_jaxbvh_test_no_such_option"

#: XLA's options at full optimization and at the cheapest compile, spelled out so that
#: they hold whatever XLA_FLAGS the suite runs with (a program's options override them)
OPTIMIZED = {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True}
CHEAP = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


@contextlib.contextmanager
def using(policy, flags=None, monkeypatch=None):
    """``policy`` in force (and ``XLA_FLAGS`` as jaxbvh reads it set to ``flags``) for a while."""
    if flags is not None:
        monkeypatch.setenv("XLA_FLAGS", flags)
    before = compile_policy.set_policy(policy)
    try:
        yield
    finally:
        compile_policy.set_policy(before)


@pytest.fixture
def store(tmp_path, monkeypatch):
    """jaxbvh's compilation cache and program store in a fresh folder for this test."""
    monkeypatch.delenv("JAXBVH_CACHE", raising=False)
    before = compile_cache.status()["folder"]
    compile_cache.enable(tmp_path)
    try:
        yield tmp_path
    finally:
        compile_cache.enable(before) if before else compile_cache.disable()


def double_plus_one(x):
    return 2 * x + 1


def test_each_family_gets_its_policys_options_less_those_in_xla_flags(monkeypatch):
    monkeypatch.delenv(compile_policy.POLICY_VARIABLE, raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    for name, table in compile_policy.POLICIES.items():
        with using(name):
            for family in compile_policy.FAMILIES:
                assert compile_policy.options(family) == dict(table[family])
    # the suite's flags name both cheap options: no policy sets them per program then
    monkeypatch.setenv("XLA_FLAGS", UNOPTIMIZED_XLA)
    for name in compile_policy.POLICIES:
        with using(name):
            for family in compile_policy.FAMILIES:
                assert set(compile_policy.options(family)).isdisjoint(
                    {"xla_backend_optimization_level", "xla_cpu_use_fusion_emitters"})
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2 --xla_dump_to")
    with using({"once": CHEAP, "loop": {BOGUS: True}}):
        assert compile_policy.options("once") == {"xla_cpu_use_fusion_emitters": False}
        assert compile_policy.options("loop") == {BOGUS: True}


def test_the_environment_and_set_policy_choose_and_bad_names_fail(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv(compile_policy.POLICY_VARIABLE, "xla")
    assert compile_policy.options("once") == {} and compile_policy.options("loop") == {}
    monkeypatch.setenv(compile_policy.POLICY_VARIABLE, "fast-compile")
    assert compile_policy.options("loop") == dict(compile_policy.POLICIES["fast-compile"]["loop"])
    with using({"loop": {BOGUS: 1}}):  # set_policy wins over the environment; a family left out gets none
        assert compile_policy.options("loop") == {BOGUS: 1} and compile_policy.options("once") == {}
    assert compile_policy.options("loop") == dict(compile_policy.POLICIES["fast-compile"]["loop"])
    monkeypatch.setenv(compile_policy.POLICY_VARIABLE, "no-such-policy")
    with pytest.raises(ValueError, match="no-such-policy"):
        compile_policy.options("once")
    with pytest.raises(ValueError, match="weekly"):
        compile_policy.set_policy({"weekly": {}})
    with pytest.raises(ValueError, match="weekly"):
        stored_jit(double_plus_one, family="weekly")


def test_families_by_module_and_by_keyword():
    from jaxbvh.builders import topdown
    from jaxbvh.optimize import driver
    from jaxbvh.rays import traversal

    assert driver.advance.family == "loop"
    assert traversal.trace_batch.family == "loop"
    builders = [v for v in vars(topdown).values() if isinstance(v, program_store.StoredFunction)]
    assert builders and {b.family for b in builders} == {"once"}
    assert stored_jit(double_plus_one).family == compile_policy.family_of(__name__) == "once"
    assert stored_jit(double_plus_one, family="loop").family == "loop"


@pytest.mark.parametrize("stored", [False, True], ids=["plain", "stored"])
def test_the_options_reach_xla_on_both_paths(stored, tmp_path, monkeypatch, request):
    if stored:
        request.getfixturevalue("store")
    else:
        monkeypatch.setenv("JAXBVH_CACHE", "off")
    assert (program_store.store_dir() is not None) == stored
    fun = stored_jit(double_plus_one, family="loop")
    x = np.arange(3, dtype=np.float32)
    with using({"loop": {BOGUS: True}}):
        with pytest.raises(Exception, match=BOGUS):  # XLA refuses the option: it got it
            fun(x)
        # traced into a user's program (a nested jit takes no options): theirs are used
        np.testing.assert_array_equal(np.asarray(jax.jit(fun)(x)), [1.0, 3.0, 5.0])
        np.testing.assert_array_equal(np.asarray(jax.vmap(fun)(x[:, None])), [[1.0], [3.0], [5.0]])
        monkeypatch.setenv("XLA_FLAGS", f"--{BOGUS}=true")  # named in XLA_FLAGS: left to the flags
        np.testing.assert_array_equal(np.asarray(fun(x)), [1.0, 3.0, 5.0])
    monkeypatch.delenv("XLA_FLAGS")
    with using({"loop": {}}):
        np.testing.assert_array_equal(np.asarray(fun(x)), [1.0, 3.0, 5.0])
    with using({"once": {BOGUS: True}}):  # another family's options: not this program's
        np.testing.assert_array_equal(np.asarray(fun(x)), [1.0, 3.0, 5.0])


def test_each_option_set_is_its_own_program_and_jax_cache_entry_one_stored_file(store, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    fun = stored_jit(double_plus_one)
    x = np.arange(4, dtype=np.float32)

    def jax_entries():
        return {p.name for p in store.iterdir() if p.is_file() and not p.name.endswith((".lock", ".tmp"))}

    with using({"once": {}}):
        fun(x)
    first = jax_entries()
    with using({"once": {"xla_llvm_disable_expensive_passes": True}}):
        np.testing.assert_array_equal(np.asarray(fun(x)), 2 * x + 1)
        assert fun.compiler_options() == {"xla_llvm_disable_expensive_passes": True}
    assert len(fun._memo) == 2  # two programs in memory, one per option set
    assert len(jax_entries() - first) >= 1  # and JAX's persistent cache keys them apart
    # the lowered program is the same under every option set: stored once
    assert len(list((store / "programs").glob("*/*.jaxprog"))) == 1


@contextlib.contextmanager
def _flags_read_as(flags):
    """``XLA_FLAGS`` as jaxbvh reads it (XLA read its own at start-up) set to ``flags``."""
    before = os.environ.get("XLA_FLAGS")
    os.environ["XLA_FLAGS"] = flags
    try:
        yield
    finally:
        if before is None:
            del os.environ["XLA_FLAGS"]
        else:
            os.environ["XLA_FLAGS"] = before


def _optimized_and_cheap(run):
    """``run()`` under XLA's full optimization and under the cheapest compile (every
    option set per program, so whatever flags the suite runs with)."""
    outs = []
    with _flags_read_as(""):
        for table in (OPTIMIZED, CHEAP):
            with using({"once": table, "loop": table}):
                outs.append(run())
    return outs


@settings(max_examples=4, deadline=None)
@given(tri=triangle_soups(min_size=2, max_size=40))
def test_a_builder_and_an_optimizer_give_the_same_trees_under_every_policy(tri):
    lo, hi = local_boxes(tri)
    # one capacity for every example: one compiled program per option set
    optimized, cheap = _optimized_and_cheap(lambda: jaxbvh.build(lo, hi, method="sweep", max_leaf=1, capacity=64))
    assert_same_tree(optimized, cheap)
    optimized, cheap = _optimized_and_cheap(lambda: jaxbvh.optimize.optimize(optimized, "hc", max_passes=3))
    assert_same_tree(optimized.tree, cheap.tree)
    assert_same_costs(optimized.history, cheap.history)
    assert int(optimized.steps) == int(cheap.steps)
