"""Lowered programs kept on disk (jaxbvh.program_store): the same results as plain jit,
keys that separate every program, damaged files replaced, and no tracing in a warm process."""

from __future__ import annotations

import contextlib
import functools
import os
import subprocess
import sys
import warnings
from pathlib import Path

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from jaxbvh import compile_cache, program_store
from jaxbvh.program_store import stored_jit


@contextlib.contextmanager
def cache_in(folder):
    """jaxbvh's compilation cache (and so the store) in ``folder`` for a while."""
    before = compile_cache.status()["folder"]
    compile_cache.enable(folder)
    try:
        yield Path(folder) / "programs"
    finally:
        compile_cache.enable(before) if before else compile_cache.disable()


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A fresh store folder for this test."""
    monkeypatch.delenv("JAXBVH_CACHE", raising=False)
    with cache_in(tmp_path) as folder:
        yield folder


def _stored_files(folder):
    return sorted(folder.glob("*/*.jaxprog")) if folder.exists() else []


def _executables(folder):
    return sorted(folder.glob("*/*.jaxexe")) if folder.exists() else []


def scaled_sum(x, y, *, power: int):
    return {"sum": (x ** power).sum() + y, "shape": jnp.zeros(x.shape[:1], jnp.int32)}


stored_scaled_sum = stored_jit(scaled_sum, static_argnames=("power",))


@settings(max_examples=15, deadline=None)
@given(rows=st.integers(1, 5), power=st.integers(1, 3), y=st.floats(-4, 4, width=32), wide=st.booleans())
def test_stored_program_equals_plain_jit(tmp_path_factory, rows, power, y, wide):
    with cache_in(tmp_path_factory.mktemp("store")) as folder:
        x = np.arange(rows * 2, dtype=np.float32).reshape(rows, 2) / 3
        if wide:
            x = x.astype(np.int32)
        want = jax.jit(scaled_sum, static_argnames=("power",))(x, y, power=power)
        got = stored_scaled_sum(x, y, power=power)          # exported, stored
        program_store.clear_memory()
        again = stored_scaled_sum(x, y, power=power)        # read back from the file
        for out in (got, again):
            assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(want)
            for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(want)):
                assert a.dtype == b.dtype and a.shape == b.shape
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert len(_stored_files(folder)) == 1


def test_each_static_value_shape_and_dtype_is_its_own_program(store):
    x = np.ones((3, 2), np.float32)
    stored_scaled_sum(x, 1.0, power=1)
    stored_scaled_sum(x, 2.0, power=1)                      # same shapes: same program
    assert len(_stored_files(store)) == 1
    stored_scaled_sum(x, 1.0, power=2)                      # another static value
    stored_scaled_sum(x[:2], 1.0, power=2)                  # another shape
    stored_scaled_sum(x.astype(np.int32), 1.0, power=2)     # another dtype
    assert len(_stored_files(store)) == 4
    assert float(stored_scaled_sum(x, 1.0, power=2)["sum"]) == 7.0


def test_a_damaged_file_is_replaced_not_trusted(store):
    x = np.ones((2, 2), np.float32)
    want = float(stored_scaled_sum(x, 0.5, power=3)["sum"])
    [path] = _stored_files(store)
    for damage in (b"", b"garbage", path.read_bytes()[:40]):
        path.write_bytes(damage)
        program_store.clear_memory()
        assert float(stored_scaled_sum(x, 0.5, power=3)["sum"]) == want
        assert path.read_bytes().startswith(b"jaxbvh-program-store")


def test_calls_while_tracing_and_unnameable_statics_use_plain_jit(store):
    x = jnp.ones((4, 2), jnp.float32)
    # inside a user's transformation: traced into their program, nothing stored
    grads = jax.grad(lambda v: stored_scaled_sum(v, 0.0, power=2)["sum"])(x)
    np.testing.assert_array_equal(np.asarray(grads), 2 * np.asarray(x))
    batched = jax.vmap(lambda v: stored_scaled_sum(v, 1.0, power=1)["sum"])(x[:, None, :])
    # a static argument by position, while tracing (plain jit must still see it as static)
    positional = stored_jit(lambda v, n: jnp.arange(n) * v.sum(), static_argnums=1)
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda v: positional(v, 3))(x)), [0.0, 8.0, 16.0])
    named = stored_jit(lambda v, n: jnp.arange(n) * v.sum(), static_argnames=("n",))
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda v: named(v, 2))(x)), [0.0, 8.0])
    np.testing.assert_array_equal(np.asarray(batched), np.asarray(x.sum(axis=1) + 1))
    assert _stored_files(store) == []

    # a closure as a static argument has no name that lasts past this process
    def apply(fun, v):
        return fun(v)

    stored_apply = stored_jit(apply, static_argnums=0)
    offset = 3.0
    assert float(stored_apply(lambda v: v.sum() + offset, x)) == 11.0
    assert _stored_files(store) == []
    # module-level functions (and partials of them) do
    assert float(stored_apply(jnp.sum, x)) == 8.0
    out = stored_apply(functools.partial(scaled_sum, y=1.0, power=2), x)
    assert float(out["sum"]) == 9.0
    assert len(_stored_files(store)) == 2


def test_the_switch_turns_the_store_off(store, monkeypatch):
    monkeypatch.setenv("JAXBVH_CACHE", "off")
    assert program_store.store_dir() is None
    stored_scaled_sum(np.ones((5, 2), np.float32), 1.0, power=1)
    assert _stored_files(store) == []
    monkeypatch.delenv("JAXBVH_CACHE")
    compile_cache.disable()   # the store goes with jaxbvh's compilation cache
    assert program_store.store_dir() is None
    stored_scaled_sum(np.ones((6, 2), np.float32), 1.0, power=1)
    assert _stored_files(store) == []


_WARM_PROBE = """
import sys, jax.monitoring
traced, events = [], []
def listen(event, duration, **kw):
    events.append(event)
    if event == "/jax/core/compile/jaxpr_trace_duration":
        traced.append(kw.get("fun_name"))
jax.monitoring.register_event_duration_secs_listener(listen)
import numpy as np, jaxbvh
from jaxbvh.program_store import EXECUTABLE_LOAD_EVENT
lo = np.random.default_rng(0).random((40, 3)).astype(np.float32)
tree = jaxbvh.build(lo, lo + 0.05, method="sweep")
print(float(jaxbvh.sah(tree)))
print(sorted(set(traced)), events.count(EXECUTABLE_LOAD_EVENT),
      events.count("/jax/core/compile/jaxpr_to_mlir_module_duration"))
print("scipy" in sys.modules)  # JAX's LAPACK set-up imports it; no program of ours calls LAPACK
import jax.numpy as jnp
from jaxbvh.program_store import stored_jit
solve = stored_jit(lambda a, b: jnp.linalg.solve(a, b))  # a stored program that calls LAPACK
a = np.array([[3.0, 1.0], [1.0, 2.0]], np.float32)
print(np.asarray(solve(a, np.array([9.0, 8.0], np.float32))).round(4).tolist())
"""


def test_a_warm_process_does_not_trace_the_builder(tmp_path):
    env = dict(os.environ, JAXBVH_CACHE_DIR=str(tmp_path))
    env.pop("JAXBVH_CACHE", None)
    runs = [subprocess.run([sys.executable, "-c", _WARM_PROBE], env=env, capture_output=True, text=True,
                           timeout=300) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    (cold_sah, cold_traced, _, cold_x), (warm_sah, warm_traced, warm_scipy, warm_x) = (
        r.stdout.split("\n")[:4] for r in runs)
    assert cold_sah == warm_sah
    cold_traced, cold_loads, _ = cold_traced.rsplit(" ", 2)
    warm_traced, warm_loads, warm_lowered = warm_traced.rsplit(" ", 2)
    assert "flat" in cold_traced   # exported in the cold process
    assert "flat" not in warm_traced  # loaded in the warm one
    # ... compiled code and all: nothing lowered, every program of the build from the store
    assert int(cold_loads) == 0 and int(warm_loads) >= 1 and int(warm_lowered) == 0
    # loading our stored programs left JAX's LAPACK set-up (and its scipy import) alone ...
    assert warm_scipy == "False"
    # ... and a stored program that does call LAPACK still gets it
    assert cold_x == warm_x == "[2.0, 3.0]"


def _with_host_callback(x):
    return jax.pure_callback(lambda v: np.asarray(v) * 2, jax.ShapeDtypeStruct(x.shape, x.dtype), x) + 1


def test_a_program_that_cannot_be_exported_runs_as_plain_jit_with_one_warning(store):
    stored = stored_jit(_with_host_callback)
    x = np.arange(3, dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="not stored"):
        first = stored(x)
    np.testing.assert_array_equal(np.asarray(first), [1.0, 3.0, 5.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once per function
        np.testing.assert_array_equal(np.asarray(stored(x[:2])), [1.0, 3.0])
    assert _stored_files(store) == []


def test_compiled_code_is_kept_only_when_compiled_here_and_damage_is_replaced(store, tmp_path):
    """A program's compiled code is kept beside it (a new process loads it, test above);
    code JAX's cache served is not kept (serialized again, it loses its kernels); a damaged
    kept file is removed, not trusted, and the program still gives its result."""
    x = np.arange(6, dtype=np.float32).reshape(3, 2)
    want = float(stored_scaled_sum(x, 0.25, power=2)["sum"])
    [kept] = _executables(store)
    assert kept.name.startswith(_stored_files(store)[0].stem)
    # the same program again, with its files gone: JAX's persistent cache serves it
    for path in (kept, *_stored_files(store)):
        path.unlink()
    program_store.clear_memory()
    assert float(stored_scaled_sum(x, 0.25, power=2)["sum"]) == want
    assert _stored_files(store) and _executables(store) == []
    # a new program, compiled here: kept; then damaged
    want = float(stored_scaled_sum(x, 0.5, power=3)["sum"])
    [kept] = _executables(store)
    for damage in (b"", b"garbage", kept.read_bytes()[:60]):
        kept.write_bytes(damage)
        program_store.clear_memory()
        assert float(stored_scaled_sum(x, 0.5, power=3)["sum"]) == want
        assert not kept.exists()  # removed, and not written again from JAX's cache
        kept.write_bytes(b"")


class _Refused:
    """A kept executable that XLA refuses to start (as one with lost kernels is)."""

    calls = 0

    def __call__(self, *leaves):
        _Refused.calls += 1
        raise jax.errors.JaxRuntimeError(
            "INTERNAL: Error dispatching computation: Function fusion not found (type id: 1)")


def test_a_kept_executable_that_cannot_start_is_removed_and_the_program_still_runs(store, monkeypatch):
    x = np.ones((4, 2), np.float32)
    want = float(stored_scaled_sum(x, 1.5, power=2)["sum"])
    [kept] = _executables(store)
    program_store.clear_memory()
    monkeypatch.setattr(program_store, "_read_executable", lambda path: _Refused())
    assert float(stored_scaled_sum(x, 1.5, power=2)["sum"]) == want
    assert float(stored_scaled_sum(x, 1.5, power=2)["sum"]) == want  # the refused one is not tried again
    assert _Refused.calls == 1
    assert not kept.exists()
