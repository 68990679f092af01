"""The ``jaxbvh`` command line tool: :func:`main` (``jaxbvh.cli.app``) and one module per
subcommand in :mod:`jaxbvh.cli.commands`."""

from jaxbvh.cli.app import (
                            EXIT_INVALID,
                            EXIT_USAGE,
                            ORDER,
                            cache_dir,
                            command_names,
                            compilation_cache_on,
                            enable_compilation_cache,
                            main,
                            make_parser,
)

__all__ = ["EXIT_INVALID", "EXIT_USAGE", "ORDER", "cache_dir", "command_names", "compilation_cache_on",
           "enable_compilation_cache", "make_parser", "main"]
