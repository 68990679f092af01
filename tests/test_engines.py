"""The native engine's one rule (jaxbvh.native): which engine runs, numba imported lazily
with its cache beside jaxbvh's."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest

from jaxbvh import native


def test_choose_follows_the_rule():
    x = jnp.zeros(3)
    assert native.choose("jax", x) == "jax"
    expected = "native" if native.available() and jax.default_backend() == "cpu" else "jax"
    assert native.choose("auto", x) == expected
    seen = []
    jax.jit(lambda y: (seen.append(native.choose("auto", {"a": y})), y)[1])(x)
    assert seen == ["jax"]  # traced: the array program, whatever is installed
    with pytest.raises(ValueError, match="engine must be one of"):
        native.choose("fast", x)


@pytest.mark.skipif(not native.available(), reason="numba not installed")
def test_native_refuses_traced_arguments():
    assert native.choose("native", jnp.zeros(3)) == "native"
    with pytest.raises(TypeError, match="cannot run inside"):
        jax.jit(lambda y: native.choose("native", y))(jnp.zeros(3))
    with pytest.raises(TypeError, match="cannot run inside"):
        jax.vmap(lambda y: native.choose("native", y))(jnp.zeros((2, 3)))


@pytest.mark.skipif(not native.available(), reason="numba not installed")
def test_numba_is_lazy_and_caches_beside_jaxbvh(tmp_path):
    # every module of both engines imported, numba still not: it loads on the first native call
    code = ("import sys, os, jaxbvh, jaxbvh.rays, jaxbvh.queries, jaxbvh.rays.native, jaxbvh.queries.native_search, jaxbvh.twolevel.native\n"
            "from jaxbvh import compile_cache, native\n"
            "assert 'numba' not in sys.modules, 'numba imported'\n"
            "native.numba()\n"
            "assert 'numba' in sys.modules\n"
            "print(os.environ['NUMBA_CACHE_DIR'])\n"
            "print(compile_cache.status()['folder'])\n")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR")}
    env.update(JAXBVH_CACHE_DIR=str(tmp_path / "cache"), JAXBVH_CACHE="on")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    numba_dir, jax_dir = out.stdout.split()
    assert numba_dir == os.path.join(jax_dir, "numba")
    # a folder the user chose wins
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == str(tmp_path / "mine")
