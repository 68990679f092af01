"""The synopsis of every command, made from the parsers: ``python -m jaxbvh.cli.synopsis``.

The docs' command-line reference (``docs/cli.md``) is made from this text when the site
is built (``docs/hooks/generate.py``; a test checks it), so the flags it lists are the
parsers' own, with the metavars and choices argparse shows in ``--help``.
"""

from __future__ import annotations

import argparse

from jaxbvh.cli.app import make_parser

#: columns of the synopsis (argparse wraps each command's usage to fit)
WIDTH = 100


def synopsis(width: int = WIDTH) -> str:
    """One usage paragraph per command (argparse's, without ``-h``), in ``--help``'s order."""
    parser, _ = make_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    paragraphs = []
    for sub in commands.choices.values():
        # argparse's own usage formatting (what format_usage does), at a fixed width so
        # the text does not depend on the terminal
        formatter = argparse.HelpFormatter(sub.prog, width=width)
        actions = [a for a in sub._actions if "-h" not in a.option_strings]
        formatter.add_usage(sub.usage, actions, sub._mutually_exclusive_groups, prefix="")
        paragraphs.append(formatter.format_help().strip())
    paragraphs.append(f"{parser.prog} COMMAND --help")
    return "\n".join(paragraphs)


if __name__ == "__main__":
    print(synopsis())
