"""Settings for the whole test suite."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, scope="session")
def _compilation_cache_out_of_home(tmp_path_factory):
    """Point the CLI's compilation cache at a temporary folder: tests never write to ~."""
    path = tmp_path_factory.mktemp("jax-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXBVH_CACHE_DIR", str(path))
        yield path
