"""The native engine: query kernels compiled by numba for the CPU, and when they run.

The queries (rays through a tree, closest points, boxes and radii) each exist twice: as a
JAX array program (the ``"jax"`` engine: runs inside a user's ``jit``, ``vmap`` and
``grad``, and on a GPU) and as a plain loop compiled by numba (the ``"native"`` engine:
one CPU thread walks one query at a time, 5-17x the array program's rays per CPU s,
``bench/results/bench_rays_native.md``; under XLA's CPU compiler every step of a walk is
dozens of kernels that each pass over all lanes, ``bench/results/ray_anatomy.md``). Both
follow the same rules and give the same answers; the tests hold them equal to each other
and to the NumPy twins.

One rule picks the engine (:func:`choose`), for every query:

* ``"jax"``: the array program, always.
* ``"native"``: the numba kernel; ``TypeError`` if the call is being traced (inside a
  ``jit``, ``vmap`` or ``grad``: the kernel needs concrete arrays) or the query is one the
  kernel does not cover (``supported=False``, e.g. a custom ray intersector);
  ``ImportError`` if numba is not installed.
* ``"auto"`` (the default): native when numba imports, JAX's default backend is the CPU,
  no argument is being traced and the query is supported; otherwise jax.

numba is imported on the first native call only (:func:`numba`; ``import jaxbvh`` does not
import it), and its compiled kernels are kept on disk in ``numba/`` of jaxbvh's
compilation-cache folder (:func:`cache_folder`, :mod:`jaxbvh.compile_cache`), so a second
process loads them instead of compiling them. A ``NUMBA_CACHE_DIR`` you set wins; with
jaxbvh's cache off (or a JAX cache of your own) nothing is written and each process
compiles its kernels again (:func:`caching` says which).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
from pathlib import Path

import jax

from jaxbvh import compile_cache

__all__ = ["DEFAULT_ENGINE", "ENGINES", "available", "cache_folder", "caching", "choose", "numba", "traced"]

#: the engines a query takes (module docstring)
ENGINES = ("auto", "jax", "native")

#: every query's default ``engine``
DEFAULT_ENGINE = "auto"

#: numba's own variable for its on-disk cache folder
_NUMBA_CACHE_VARIABLE = "NUMBA_CACHE_DIR"


@functools.cache
def available() -> bool:
    """Whether numba is installed (without importing it)."""
    return importlib.util.find_spec("numba") is not None


def cache_folder() -> Path | None:
    """Where numba keeps compiled kernels: ``numba/`` in jaxbvh's compilation-cache folder
    while jaxbvh's cache is on and its own, else None (nothing written)."""
    state = compile_cache.status()
    if state["owner"] != "jaxbvh" or compile_cache.switched_off():
        return None
    return Path(state["folder"]) / "numba"


#: whether the kernels keep their compiled code on disk (``cache=`` of ``numba.njit``);
#: set by :func:`numba`, read through :func:`caching`
_caching = {"on": False}


def numba():
    """The numba module, imported on first use with its on-disk cache pointed into
    jaxbvh's cache folder (module docstring); call it before defining kernels, and give
    them ``cache=caching()``. ``ImportError`` naming the fix when numba is missing."""
    if not available():
        raise ImportError("the native engine needs numba: pip install numba (or pass engine='jax')")
    if os.environ.get(_NUMBA_CACHE_VARIABLE):
        _caching["on"] = True  # the user's folder
    else:
        folder = cache_folder()
        if folder is not None:
            # numba reads its folder at import; if it is imported already, tell its config
            os.environ[_NUMBA_CACHE_VARIABLE] = str(folder)
            if "numba" in sys.modules:
                sys.modules["numba"].config.CACHE_DIR = str(folder)
            _caching["on"] = True
    import numba as module

    return module


def caching() -> bool:
    """Whether kernels defined after :func:`numba` keep their compiled code on disk."""
    return _caching["on"]


def traced(*args) -> bool:
    """Whether any array in ``args`` (pytrees allowed) is being traced by JAX."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(args))


def choose(engine: str, *args, supported: bool = True) -> str:
    """The engine (``"jax"`` or ``"native"``) that runs a query called with ``engine`` on
    arguments ``args`` (any pytrees); ``supported``: the native kernel covers this query
    (module docstring: the one rule)."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "jax":
        return "jax"
    is_traced = traced(*args)
    if engine == "native":
        if is_traced:
            raise TypeError("engine='native' runs on concrete arrays on the host and cannot run inside "
                            "jax.jit / vmap / grad: use engine='jax' there (or 'auto', which picks it)")
        if not supported:
            raise TypeError("engine='native' does not cover this query (e.g. a custom intersector): "
                            "use engine='jax'")
        if not available():
            raise ImportError("engine='native' needs numba: pip install numba (or pass engine='jax')")
        return "native"
    native = supported and not is_traced and jax.default_backend() == "cpu" and available()
    return "native" if native else "jax"
