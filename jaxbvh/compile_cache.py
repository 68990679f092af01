"""JAX's persistent compilation cache for jaxbvh: on by default, per user, never over yours.

Compiling is most of every first call on a CPU (a builder, an optimizer's loop of steps,
a trace): seconds to a minute per program, paid again by every new process. JAX can
keep compiled programs on disk and load them in a fraction of that time; this module
turns that on when jaxbvh is imported (:func:`enable_default`), so a notebook restart, a
second script or a second command pays only the loading.

Rules, in order (one place: :func:`enable_default`):

1. ``JAXBVH_CACHE=off`` (or ``0``, ``no``, ``false``) in the environment: jaxbvh touches
   nothing; JAX keeps whatever it was told.
2. A cache the user configured in JAX themselves (``jax.config.update(
   "jax_compilation_cache_dir", ...)`` before importing jaxbvh, or the
   ``JAX_COMPILATION_CACHE_DIR`` environment variable) is used as it is: jaxbvh changes
   none of its settings.
3. Otherwise the cache goes to :func:`cache_dir`: ``$JAXBVH_CACHE_DIR`` if set, else
   ``$XDG_CACHE_HOME/jaxbvh/jax`` (``~/.cache/jaxbvh/jax``). Every program is cached,
   however fast it compiled (JAX's defaults skip programs under 1 s, which is most of
   ours, yet each is a first-call cost), the folder is kept under
   :data:`MAX_CACHE_BYTES` (least recently used entries go first) and its entries are
   read and written under a file lock, so processes that share it (test workers,
   parallel scripts) never read an entry half written. Nothing is written until JAX
   compiles its first program (JAX makes the folder then); a folder that cannot be made
   (a read-only home) leaves the cache off, with no error.

The cache is process-wide JAX state: while it is on, the user's own JAX programs are
cached in the same folder. :func:`disable` turns jaxbvh's cache off again in a running
process; :func:`status` says what is in force. While it is on, parsed meshes are kept
beside the programs too (:func:`mesh_cache_dir`, :func:`jaxbvh.io.mesh_cache_folder`), so a
warm script does not parse its mesh files (nor import trimesh) again.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

__all__ = ["MAX_CACHE_BYTES", "cache_dir", "disable", "enable", "enable_default", "mesh_cache_dir", "status"]

#: the folder is kept under this size (bytes): least recently used programs are evicted
#: first. An SBVH build's programs on a mid-size mesh take tens of MB; a full test run of
#: the suite about a GB.
MAX_CACHE_BYTES = 4 * 1024 ** 3

#: environment variables: the folder, and the off switch
CACHE_DIR_VARIABLE = "JAXBVH_CACHE_DIR"
SWITCH_VARIABLE = "JAXBVH_CACHE"
_OFF = ("0", "off", "no", "false")

#: JAX options this module sets (and :func:`disable` puts back)
_OPTIONS = {"jax_compilation_cache_dir": None, "jax_persistent_cache_min_compile_time_secs": 0.0,
            "jax_persistent_cache_min_entry_size_bytes": 0, "jax_compilation_cache_max_size": MAX_CACHE_BYTES}

#: the folder jaxbvh pointed JAX at (None: jaxbvh's cache is not on), and JAX's settings before
_state: dict = {"path": None, "before": None}


def cache_dir() -> Path:
    """The folder of jaxbvh's compilation cache: ``$JAXBVH_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxbvh/jax``, else ``~/.cache/jaxbvh/jax``."""
    env = os.environ.get(CACHE_DIR_VARIABLE)
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "jaxbvh" / "jax"


def mesh_cache_dir() -> Path:
    """The folder of parsed meshes kept while jaxbvh's cache is on: ``meshes/`` in
    :func:`cache_dir` (:func:`jaxbvh.io.mesh_cache_folder`)."""
    return cache_dir() / "meshes"


def switched_off() -> bool:
    """True when ``JAXBVH_CACHE`` says off (``0``, ``off``, ``no``, ``false``)."""
    return os.environ.get(SWITCH_VARIABLE, "").strip().lower() in _OFF


def configured_by_user() -> bool:
    """True when JAX's cache was set up by someone other than jaxbvh: its folder option
    is set (or ``JAX_COMPILATION_CACHE_DIR``) and is not the one jaxbvh set."""
    import jax

    folder = jax.config.jax_compilation_cache_dir or os.environ.get("JAX_COMPILATION_CACHE_DIR")
    return bool(folder) and folder != _state["path"]


def enable(path: str | os.PathLike | None = None) -> Path | None:
    """Point JAX's persistent cache at ``path`` (default :func:`cache_dir`) with jaxbvh's
    settings (module docstring, rule 3); returns the folder, or None when it cannot be
    made. This overrides a cache configured in JAX; :func:`enable_default` does not."""
    import jax

    folder = Path(path).expanduser() if path is not None else cache_dir()
    if not _can_make(folder):
        return None  # a read-only home: run without the cache rather than fail
    if _state["path"] is None:
        _state["before"] = {name: getattr(jax.config, name) for name in _OPTIONS}
    settings = dict(_OPTIONS, jax_compilation_cache_dir=str(folder))
    if importlib.util.find_spec("filelock") is None:  # JAX locks and evicts with it
        settings["jax_compilation_cache_max_size"] = -1
    for name, value in settings.items():
        jax.config.update(name, value)
    _state["path"] = str(folder)
    _reset_jax_cache()
    return folder


def enable_default() -> Path | None:
    """The rules of the module docstring, applied once at ``import jaxbvh``: the folder
    jaxbvh's cache uses, or None when it stays off (switched off, a user's own JAX cache,
    or no folder can be made)."""
    if _state["path"] is not None:
        return Path(_state["path"])
    if switched_off() or configured_by_user():
        return None
    return enable()


def disable() -> None:
    """Turn jaxbvh's cache off in this process: JAX's options as they were before
    :func:`enable` (a cache the user configured is never touched)."""
    import jax

    if _state["path"] is None:
        return
    for name, value in _state["before"].items():
        jax.config.update(name, value)
    _state["path"], _state["before"] = None, None
    _reset_jax_cache()


def status() -> dict:
    """What is in force: ``{"folder": str | None, "owner": "jaxbvh" | "user" | None}``."""
    import jax

    folder = jax.config.jax_compilation_cache_dir or None
    if folder is None:
        return {"folder": None, "owner": None}
    return {"folder": folder, "owner": "jaxbvh" if folder == _state["path"] else "user"}


def _can_make(folder: Path) -> bool:
    """True when ``folder`` exists as a writable folder or could be made (its nearest
    existing ancestor is a writable folder); makes nothing."""
    for place in (folder, *folder.parents):
        if place.exists():
            return place.is_dir() and os.access(place, os.W_OK | os.X_OK)
    return False


def _reset_jax_cache() -> None:
    # JAX opens its cache once, at the first compile: make it open the folder set now
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()
