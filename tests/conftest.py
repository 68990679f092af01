"""Settings for the whole test suite."""

from __future__ import annotations

import gc
import os

import pytest
from helpers import UNOPTIMIZED_XLA
from hypothesis import settings

# XLA compiles our programs cheaply in the tests: the suite is almost all compiling (small
# inputs, many shapes). Two flags (helpers.UNOPTIMIZED_XLA): LLVM's optimizations off
# (about a third cheaper), and the older loop emitters for fusions instead of the MLIR
# fusion emitters (compiles about 45% cheaper again; a fresh clone's .ci/run went from
# 15.0 to 8.4 min on an idle 2-core machine, with a round of new tests in between). XLA
# keeps IEEE semantics either way (no fast math), but it may order a float reduction
# differently: a sum can differ in its last bits between two programs, so costs from two
# different programs (a vmapped batch against single runs) are compared with
# helpers.assert_same_costs, while trees and every comparison with a NumPy twin hold
# exactly. JAXBVH_TEST_OPTIMIZED=1 runs the suite on optimized code (notebook kernels
# inherit the flags: with optimized code the optimize notebook ran faster but the builders
# and collapse notebooks compiled slower, and the whole suite took 15.6 min instead of
# 13.0).
if os.environ.get("JAXBVH_TEST_OPTIMIZED") != "1" and UNOPTIMIZED_XLA not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {UNOPTIMIZED_XLA}".strip()

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


# Tests that xdist hands out one by one, and first, not with the rest of their module: the
# notebooks (about four minutes in all). As one module they went to one worker late in the
# run, and the other worker waited for it at the end.
UNITS_OF_THEIR_OWN = ("tests/test_notebooks.py::test_notebook_runs[",)


def pytest_xdist_make_scheduler(config, log):
    """xdist's ``loadfile`` scheduling (pyproject.toml), but for :data:`UNITS_OF_THEIR_OWN`.

    A test module goes to one worker as a whole, so its tests share its compiled programs;
    xdist queues the modules with the most tests first. Each of :data:`UNITS_OF_THEIR_OWN`
    is a unit of its own, queued before the modules, so the long units are shared out while
    there is plenty of work left to balance them. (xdist's ``xdist_group`` marks are meant
    for this, but pytest 9 ignores the node ids xdist 3.8 rewrites for them.)
    """
    from xdist.scheduler import LoadFileScheduling

    class ModulesAndOwnUnits(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return nodeid if nodeid.startswith(UNITS_OF_THEIR_OWN) else super()._split_scope(nodeid)

        def _assign_work_unit(self, node) -> None:
            for scope in reversed([s for s in self.workqueue if s.startswith(UNITS_OF_THEIR_OWN)]):
                self.workqueue.move_to_end(scope, last=False)
            super()._assign_work_unit(node)

    return ModulesAndOwnUnits(config, log)


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache_out_of_home(tmp_path_factory):
    """One persistent compilation cache for this test process, in a temporary folder.

    The CLI's cache (``JAXBVH_CACHE_DIR``) points here, so tests never write to ~, and so
    does JAX's own cache for the library calls of the tests: a program compiled in one
    module is loaded, not compiled again, in the next (:func:`_release_compiled_programs`
    drops the in-memory programs between modules), and subprocesses (CLI runs, notebook
    kernels, fake-device runs) read the same folder through the environment. Each xdist
    worker has its own folder: JAX writes cache files without a lock.
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    path = tmp_path_factory.mktemp("jax-cache")
    settings = {"jax_compilation_cache_dir": str(path),
                "jax_persistent_cache_min_compile_time_secs": 0.0,
                "jax_persistent_cache_min_entry_size_bytes": 0}
    before = {name: getattr(jax.config, name) for name in settings}
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXBVH_CACHE_DIR", str(path))
        for name, value in settings.items():
            patch.setenv(name.upper(), str(value))
            jax.config.update(name, value)
        compilation_cache.reset_cache()
        yield path
    for name, value in before.items():
        jax.config.update(name, value)
    compilation_cache.reset_cache()


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
