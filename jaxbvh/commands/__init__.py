"""Subcommands of the ``jaxbvh`` tool, one module each (see :mod:`jaxbvh.cli`).

A command module exposes ``add_parser(subparsers) -> argparse.ArgumentParser`` and
``run(args) -> dict``; shared helpers live in :mod:`jaxbvh.commands._common`.
"""
