"""Settings for the whole test suite."""

from __future__ import annotations

import gc
import os
import shutil
import tempfile
from pathlib import Path

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


# One persistent compilation cache for the whole run, in a temporary folder shared by the
# xdist workers (they inherit the controller's environment): a program compiled by one
# worker is loaded, not compiled again, by the other and by every later module
# (:func:`_release_compiled_programs` drops the in-memory programs between modules), and
# subprocesses (CLI runs, notebook kernels, fake-device runs) read the same folder through
# JAXBVH_CACHE_DIR. JAX reads and writes its entries under a file lock
# (jaxbvh.compile_cache), so the workers never see an entry half written. Tests never
# write to ~.
_RUN_CACHE_VARIABLE = "JAXBVH_TEST_RUN_CACHE"
if not os.environ.get(_RUN_CACHE_VARIABLE):
    os.environ[_RUN_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="jaxbvh-test-cache-")
    _MADE_RUN_CACHE = True
else:
    _MADE_RUN_CACHE = False
os.environ["JAXBVH_CACHE_DIR"] = os.environ[_RUN_CACHE_VARIABLE]
for _name in ("JAXBVH_CACHE", "JAX_COMPILATION_CACHE_DIR"):  # the library's rules, not the shell's
    os.environ.pop(_name, None)


def pytest_configure(config):
    """After the plugin registered the profiles, before any test module is collected:
    the hypothesis profile, and the run's compilation cache (above) in force before
    anything compiles."""
    from jaxbvh import compile_cache

    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
    compile_cache.enable(os.environ[_RUN_CACHE_VARIABLE])


# Tests that xdist hands out one by one, and first, not with the rest of their module: the
# notebooks (about four minutes in all) and the docs pages' examples (a process per page).
# As one module they went to one worker late in the run, and the other worker waited for
# it at the end.
UNITS_OF_THEIR_OWN = ("tests/test_notebooks.py::test_notebook_runs[", "tests/test_docs_examples.py::test_page_examples_run[")


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


def pytest_unconfigure(config):
    """The run's cache goes with the run (the process that made it removes it)."""
    if _MADE_RUN_CACHE and not os.environ.get("PYTEST_XDIST_WORKER"):
        shutil.rmtree(os.environ[_RUN_CACHE_VARIABLE], ignore_errors=True)


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache_out_of_home():
    """The run's shared compilation cache (above), in force in this process since
    :func:`pytest_configure`: the package's import had pointed JAX at the per-user folder
    before this conftest set the environment (pytest loads the kit's plugin, which
    imports jaxbvh, first), and a test may have changed it."""
    from jaxbvh import compile_cache

    path = Path(os.environ[_RUN_CACHE_VARIABLE])
    assert compile_cache.enable(path) == path
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

    from jaxbvh import program_store

    jax.clear_caches()
    program_store.clear_memory()
    gc.collect()



@pytest.fixture
def cache_dir(_compilation_cache_out_of_home):
    """The suite's compilation-cache folder (above)."""
    return _compilation_cache_out_of_home
