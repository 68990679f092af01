"""Settings for the whole test suite."""

from __future__ import annotations

import gc
import os

import pytest
from hypothesis import settings

# The kit's plugin: its hypothesis profiles "ci" and "dev" and its mesh fixtures (also
# its entry point, when the installed metadata is current; the same name, so loaded once).
pytest_plugins = ["jaxbvh.testing.plugin"]

# One hypothesis profile for the whole suite, chosen by HYPOTHESIS_PROFILE (default "ci"):
# "ci" is what `python -m pytest` runs (.ci/run too), a fixed seed per test; "dev" random
# draws and ten times the examples, to hunt locally (profiles: jaxbvh.testing.plugin):
# HYPOTHESIS_PROFILE=dev python -m pytest tests/builders/test_build.py


def pytest_configure(config):
    """After the plugin registered the profiles, before any test module is collected."""
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
