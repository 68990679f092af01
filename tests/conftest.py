"""Settings for the whole test suite."""

from __future__ import annotations

import gc
import os

import pytest
from hypothesis import HealthCheck, settings

# One hypothesis profile for the whole suite, chosen by HYPOTHESIS_PROFILE (default "ci").
# "ci": what `python -m pytest` runs (.ci/run too): a fixed seed per test (derandomize), so a
# run is repeatable and its time known. "dev": random draws and five times the examples, to
# hunt locally (tests that set max_examples themselves are costly per example, and say why):
# HYPOTHESIS_PROFILE=dev python -m pytest tests/builders/test_build.py
# No deadline: a first example compiles (seconds), the next ones reuse the program.
# too_slow: generating hundreds of coordinates per example is slow by design;
# data_too_large: scenes of several triangle soups draw many values.
settings.register_profile("ci", max_examples=20, deadline=None, derandomize=True, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("dev", settings.get_profile("ci"), max_examples=100, derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


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



@pytest.fixture
def cache_dir(_compilation_cache_out_of_home):
    """The suite's compilation-cache folder (above)."""
    return _compilation_cache_out_of_home
