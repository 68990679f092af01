"""The ``jaxbvh`` command line tool: :func:`main` (``jaxbvh.cli.app``) and one module per
subcommand in :mod:`jaxbvh.cli.commands`. The console script starts at
:func:`jaxbvh.cli.front.main`, which answers ``--help``, ``--version`` and usage errors
without importing JAX; the names below load the tool (and JAX) on first use."""

from __future__ import annotations

import importlib

__all__ = ["EXIT_INVALID", "EXIT_USAGE", "ORDER", "cache_dir", "command_names", "compilation_cache_on",
           "enable_compilation_cache", "make_parser", "main"]


def __getattr__(name: str):
    if name not in __all__:
        raise AttributeError(f"module 'jaxbvh.cli' has no attribute {name!r}")
    value = getattr(importlib.import_module("jaxbvh.cli.app"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
