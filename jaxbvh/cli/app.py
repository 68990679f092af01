"""The ``jaxbvh`` command line tool.

Each subcommand is a module ``jaxbvh.cli.commands.<name>`` with ``add_parser(subparsers)``
and ``run(args) -> dict`` (found by name: adding a module adds the command); the dict is
printed as a table, or as one JSON object with ``--json``.

Exit status: 0 when done; 1 when the command ran but reports an invalid tree (the result
says ``"valid": false`` and lists the problems: ``jaxbvh stats``); 2 for bad input
(missing or malformed files, trees a command cannot work on, bad options, options out of
range, whether argparse or the command finds them), after one line ``jaxbvh: error:
...`` on stderr (no usage block: :class:`Parser`). Warnings are one line each too,
``jaxbvh: warning: ...`` (:func:`one_line_warnings`).

JAX's persistent compilation cache is on, as for every library user
(:mod:`jaxbvh.compile_cache`): compiled programs are reused across runs. It lives in
``~/.cache/jaxbvh/jax`` unless ``JAXBVH_CACHE_DIR`` names another folder
(``JAXBVH_CACHE=off``: no cache); parsed meshes are kept in its ``meshes/`` folder
(:func:`jaxbvh.io.meshes.use_mesh_cache`).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import sys
import warnings
from pathlib import Path

from jaxbvh import __version__, compile_cache
from jaxbvh.cli import command_kit, commands
from jaxbvh.cli.front import EXIT_USAGE, Parser
from jaxbvh.io import MeshError, use_mesh_cache
from jaxbvh.io import meshes as io
from jaxbvh.tree.validate import InvalidTreeError

# the order commands are listed in ``--help``; modules of ``jaxbvh.cli.commands`` not named
# here follow in alphabetical order
ORDER = ["build", "stats", "optimize", "trace"]


def command_names() -> list[str]:
    """Names of the subcommands: every public module of :mod:`jaxbvh.cli.commands`."""

    found = [m.name for m in pkgutil.iter_modules(commands.__path__) if not m.name.startswith("_")]
    return [n for n in ORDER if n in found] + sorted(n for n in found if n not in ORDER)

# exit statuses: 0 done (and any tree checked is valid); 1 the command ran and reports
# an invalid tree (``"valid": false`` in its result, e.g. ``jaxbvh stats``); 2 bad input or
# options, reported in one line on stderr
EXIT_INVALID = 1
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command ended by Ctrl-C


def exit_now(status: int) -> None:
    """End the process with ``status`` at once, without the interpreter's shutdown.

    After Ctrl-C inside a compile or a compiled call, XLA's threads may still be running,
    and finalizing the interpreter under them crashed (SIGSEGV, exit 139, after the
    ``interrupted`` line: one of four interrupted cold batches in our trials, issue 39).
    Every file the tool writes is complete or absent at any moment (atomic writes), so
    nothing is left to flush but stdout and stderr."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def cache_dir() -> Path:
    """Folder of the compilation cache (:func:`jaxbvh.compile_cache.cache_dir`)."""
    return compile_cache.cache_dir()


def enable_compilation_cache() -> Path | None:
    """Turn on the caches a command uses: JAX's compilation cache by the library's rules
    (:func:`jaxbvh.compile_cache.enable_default`: never over a cache configured in JAX,
    off with ``JAXBVH_CACHE=off``) and, with it, the parsed-mesh cache in its
    ``meshes/`` folder (the library's default, :func:`jaxbvh.io.mesh_cache_folder`).
    Returns the compilation cache's folder, None when it is off."""
    return compile_cache.enable_default()


@contextlib.contextmanager
def compilation_cache_on():
    """The tool's caches (:func:`enable_compilation_cache`) for the duration of one command.

    The mesh cache follows the compilation cache (the library's default) during the
    command and is put back as it was on exit; JAX's compilation cache stays as
    ``import jaxbvh`` leaves it (on by default), so calling :func:`main` from Python
    changes nothing a library user would not have had anyway.
    """
    meshes_before = use_mesh_cache(io.FOLLOW_COMPILE_CACHE)
    try:
        yield enable_compilation_cache()
    finally:
        io.use_mesh_cache(meshes_before)


def _load_commands() -> dict:
    return {name: importlib.import_module(f"jaxbvh.cli.commands.{name}") for name in command_names()}


def make_parser() -> tuple[argparse.ArgumentParser, dict]:
    """The ``jaxbvh`` parser with one subparser per command, and ``{command: module}`` (each
    module has ``add_parser`` and ``run``)."""
    parser = Parser(
        prog="jaxbvh",
        description="Build, inspect and optimize BVHs for ray tracing (JAX).",
        epilog="JAX compilation cache: ~/.cache/jaxbvh/jax (JAXBVH_CACHE_DIR moves it, "
               "JAXBVH_CACHE=off turns it off).")
    parser.add_argument("--version", action="version", version=f"jaxbvh {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    modules = _load_commands()
    for module in modules.values():
        sub = module.add_parser(subparsers)
        if not any("--json" in a.option_strings for a in sub._actions):
            sub.add_argument("--json", action="store_true",
                             help="print the result as one JSON object on stdout")
    return parser, modules


def _error_line(exc: BaseException) -> str:
    if isinstance(exc, InvalidTreeError):
        text = f"invalid BVH ({len(exc.problems)} problem(s)): " + "; ".join(exc.problems[:3])
        if len(exc.problems) > 3:
            text += f"; ... and {len(exc.problems) - 3} more"
    elif isinstance(exc, OSError) and exc.filename and exc.strerror:
        text = f"{exc.strerror}: {exc.filename}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())  # one line


@contextlib.contextmanager
def one_line_warnings():
    """Warnings as ``jaxbvh: warning: MESSAGE`` lines on stderr (no source line, no file
    of ours), for the duration of one command; Python's own display is put back after."""
    before = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"jaxbvh: warning: {' '.join(str(message).split())}", file=file or sys.stderr)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = before


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxbvh`` console script; returns the exit status."""

    parser, modules = make_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors (argparse prints them)
        return int(exc.code or 0)
    try:
        with compilation_cache_on(), one_line_warnings():
            result = modules[args.command].run(args)
    except (MeshError, InvalidTreeError, ValueError, FileNotFoundError, OSError) as exc:
        print(f"jaxbvh: error: {_error_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("jaxbvh: interrupted", file=sys.stderr)
        if argv is None:  # the process's own command line (the console script): end it now
            exit_now(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    command_kit.print_result(result, as_json=getattr(args, "json", False))
    status = EXIT_INVALID if result.get("valid") is False else 0
    return status


if __name__ == "__main__":
    sys.exit(main())
