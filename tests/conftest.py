"""Settings for the whole test suite."""

from __future__ import annotations

import gc

import pytest


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache_out_of_home(tmp_path_factory):
    """Point the CLI's compilation cache at a temporary folder: tests never write to ~."""
    path = tmp_path_factory.mktemp("jax-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXBVH_CACHE_DIR", str(path))
        yield path


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.

    Every XLA CPU executable keeps memory maps of its own for as long as a jit cache holds
    it. The whole suite in one process compiles thousands of programs (hypothesis draws
    many shapes) and passed Linux's limit of 65,530 maps per process (vm.max_map_count);
    XLA then segfaulted while compiling or serializing the next program.
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()

