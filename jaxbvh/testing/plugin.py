"""The pytest plugin of :mod:`jaxbvh.testing`: mesh fixtures and two hypothesis profiles.

Registered as the entry point ``jaxbvh.testing.plugin`` (``[project.entry-points.pytest11]``),
so an installed jaxbvh offers it to every pytest run; without the install metadata load
it with ``pytest -p jaxbvh.testing.plugin`` or ``pytest_plugins = ["jaxbvh.testing.plugin"]``
in a top-level ``conftest.py``. Disable it with ``-p no:jaxbvh.testing.plugin``.

Hypothesis profiles (registered when hypothesis is installed; loaded by
``--hypothesis-profile NAME`` or ``HYPOTHESIS_PROFILE=NAME``, never behind your back):

* ``ci``: a fixed seed per test (``derandomize``), so a run is repeatable and its time
  known; 10 examples; no deadline (a first example compiles for seconds, the next reuse
  the program); the health checks for slow and large draws off (drawing hundreds of
  coordinates per example is slow by design).
* ``dev``: random draws and ten times the examples (100), to hunt for bugs locally.

A test that needs its own example count states it for ``ci`` with :func:`examples`
(``@settings(max_examples=examples(15))``), so ``dev`` scales it too.

Fixtures:

* ``bundled_mesh`` -- the mesh shipped inside the package (Keenan Crane's "Spot", 5,856
  triangles) as a :class:`jaxbvh.io.meshes.Mesh`;
* ``shared_data`` -- the folder of shared meshes, scenes and reference trees: the ini
  option ``jaxbvh_shared_data``, else ``$JAXBVH_SHARED_DATA``, else ``../shared/data``
  beside the rootdir; tests that ask for it are skipped when it is absent;
* ``shared_mesh`` -- a function ``name -> Mesh`` loading ``shared_data/meshes/<name>``
  (``.obj`` added when the name has no suffix), once per session.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from jaxbvh.io.meshes import Mesh, bundled_mesh_path, load_mesh

try:
    from hypothesis import HealthCheck, settings
except ImportError:  # hypothesis is optional: the fixtures work without it
    settings = None

PROFILES = ("ci", "dev")

if settings is not None:
    # ci: 10 examples a test, derandomized (repeatable, and the suite's time known: most of a
    # test's time here is compiling, spent once); dev: 100, random, to hunt locally
    settings.register_profile("ci", max_examples=10, deadline=None, derandomize=True, print_blob=True,
                              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    settings.register_profile("dev", settings.get_profile("ci"), max_examples=100, derandomize=False)


def examples(n: int) -> int:
    """A test's own example count, stated for the ``ci`` profile and scaled with the loaded one.

    ``@settings(max_examples=examples(15))`` runs 15 examples under ``ci`` and 150 under
    ``dev`` (ten times ``ci``), where a bare ``max_examples=15`` would pin 15 under both.
    Call it at decoration time, after the profile is loaded (pytest loads it before it
    collects test modules).
    """
    if settings is None:
        raise ImportError("examples() needs hypothesis: pip install jaxbvh[testing]")
    scale = settings.default.max_examples / settings.get_profile("ci").max_examples
    return max(1, round(n * scale))


def pytest_configure(config):
    """Load ``$HYPOTHESIS_PROFILE`` when it names one of our profiles."""
    name = os.environ.get("HYPOTHESIS_PROFILE", "")
    if settings is not None and name in PROFILES:
        settings.load_profile(name)


def pytest_addoption(parser):
    """The ini option ``jaxbvh_shared_data``: where the shared data folder is."""
    parser.addini("jaxbvh_shared_data", "folder of shared meshes, scenes and reference trees "
                  "(default: $JAXBVH_SHARED_DATA, else ../shared/data beside the rootdir)", default="")


def shared_data_path(config) -> Path:
    """The shared data folder for a pytest ``config`` (module docstring; may not exist)."""
    configured = config.getini("jaxbvh_shared_data") or os.environ.get("JAXBVH_SHARED_DATA", "")
    if configured:
        return Path(configured).expanduser().resolve()
    return Path(config.rootpath).resolve().parent / "shared" / "data"


@pytest.fixture(scope="session")
def bundled_mesh() -> Mesh:
    """The mesh shipped with jaxbvh (Spot, 5,856 triangles)."""
    return load_mesh(bundled_mesh_path())


@pytest.fixture(scope="session")
def shared_data(pytestconfig) -> Path:
    """The shared data folder; skips the test when it is absent."""
    path = shared_data_path(pytestconfig)
    if not path.is_dir():
        pytest.skip(f"shared data not found at {path} (set jaxbvh_shared_data or $JAXBVH_SHARED_DATA)")
    return path


@pytest.fixture(scope="session")
def shared_mesh(shared_data):
    """``name -> Mesh`` for ``shared_data/meshes/<name>``, each loaded once per session."""
    loaded: dict[str, Mesh] = {}

    def load(name: str) -> Mesh:
        path = shared_data / "meshes" / (name if Path(name).suffix else f"{name}.obj")
        if not path.is_file():
            pytest.skip(f"shared mesh {path} not found")
        if name not in loaded:
            loaded[name] = load_mesh(path)
        return loaded[name]

    return load
