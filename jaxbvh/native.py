"""The native engine: query kernels compiled by numba for the CPU, and when they run.

The queries (rays through a tree, closest points, boxes and radii) each exist twice: as a
JAX array program (the ``"jax"`` engine: runs inside a user's ``jit``, ``vmap`` and
``grad``, and on a GPU) and as a plain loop compiled by numba (the ``"native"`` engine:
one CPU thread walks one query at a time, many times faster than the array program on a
CPU, where XLA spreads every step of a walk over dozens of kernels that each pass over
all lanes; ``bench/results/ray_anatomy.md``). Both follow the same rules and give the
same answers; the tests hold them equal to each other and to the NumPy twins.

One rule picks the engine (:func:`choose`), for every query:

* ``"jax"``: the array program, always.
* ``"native"``: the numba kernel; an error if numba is not installed or the call is
  being traced (inside a ``jit``, ``vmap`` or ``grad``: the kernel needs concrete arrays).
* ``"auto"`` (the default): native when numba imports, JAX's default backend is the CPU
  and no argument is being traced; otherwise jax.

numba is imported on the first native call only (``import jaxbvh`` does not import it),
and its compiled kernels are kept on disk (``cache=True``) in ``numba/`` of jaxbvh's
compilation-cache folder (:mod:`jaxbvh.compile_cache`), so a second process loads them
instead of compiling them: unless ``NUMBA_CACHE_DIR`` is set already (yours wins), and
nowhere new when jaxbvh's cache is off (numba then uses its own default, beside the
module's sources).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys

import jax

from jaxbvh import compile_cache

__all__ = ["DEFAULT_ENGINE", "ENGINES", "available", "choose", "numba", "traced"]

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


def numba():
    """The numba module, imported on first use with its cache in jaxbvh's cache folder
    (module docstring). Raises ImportError naming the fix when numba is missing."""
    if "numba" not in sys.modules:
        if not available():
            raise ImportError("the native engine needs numba: pip install numba (or pass engine='jax')")
        if _NUMBA_CACHE_VARIABLE not in os.environ:
            folder = compile_cache.status()
            # numba reads its cache folder once, at import: set it before the first import
            if folder["owner"] == "jaxbvh" and not compile_cache.switched_off():
                os.environ[_NUMBA_CACHE_VARIABLE] = os.path.join(folder["folder"], "numba")
    import numba as module

    return module


def traced(*args) -> bool:
    """Whether any array in ``args`` (pytrees allowed) is being traced by JAX."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(args))


def choose(engine: str, *args) -> str:
    """The engine (``"jax"`` or ``"native"``) that runs a query called with ``engine`` on
    arguments ``args`` (module docstring: the one rule)."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "jax":
        return "jax"
    if engine == "native":
        if not available():
            raise ImportError("engine='native' needs numba: pip install numba (or pass engine='jax')")
        if traced(*args):
            raise ValueError("engine='native' needs concrete arrays, but this call is being traced (inside "
                             "jit, vmap or grad): pass engine='jax' (or 'auto', which picks it there)")
        return "native"
    return "native" if available() and jax.default_backend() == "cpu" and not traced(*args) else "jax"
