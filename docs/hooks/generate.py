"""MkDocs hook: the parts of the site made from the code, so they cannot drift from it.

A page asks for a generated part with an HTML comment on a line of its own,
``<!-- gen: KIND ARGS -->``; :func:`expand` replaces it, indented as the comment is (inside
an admonition), and an unknown kind fails the build:

===================================  ===============================================
``knobs jaxbvh.x.SomeConfig [new]``  a table of the Config's knobs: default, meaning,
                                     command-line flag (from the dataclass fields and
                                     the commands' ``ConfigOptions``); ``new``: only
                                     those its nearest public base does not have
``synopsis``                         ``python -m jaxbvh.cli.synopsis``, the usage of
                                     every command
``help COMMAND``                     ``jaxbvh COMMAND --help``, at a fixed width
``include PATH``                     a file of the repository (``bench/results/*.md``),
                                     its headings demoted below the page's (bold lines
                                     inside an admonition: out of the page's outline)
``api PACKAGE``                      a ``:::`` block (mkdocstrings) per public module
                                     of the package (no ``_private``, no twins)
``twins``                            a ``:::`` block per NumPy twin (``*_reference``)
``toplevel``                         ``jaxbvh`` itself and a ``:::`` block per top-level
                                     module (``configs``, ``numerics``, ...)
``other-results``                    every ``bench/results`` table and plot that no page
                                     includes or shows (so a new result is never left out)
``docstring MODULE``                 the module's docstring, as the API pages show it
                                     (where a page explains what the code documents once)
===================================  ===============================================

A part may also be *committed*: the same comment, then the generated text, then
``<!-- end gen -->`` on a line of its own (same indent), so the page reads whole as a file
(``docs/cli.md``). The build regenerates the text between the markers (the site never
shows a stale copy), and :func:`refresh` rewrites it in the file:
``python docs/hooks/generate.py [PAGE ...]`` (default ``docs/cli.md``);
``tests/test_docs.py`` fails when a committed part differs from what the code gives now.
This module imports the docs tools only where the site needs them (``on_files``, the
docstring converter), so the tests and the script run without them.

It also publishes the benchmark plots (``bench/results/*.png``) at ``bench/NAME.png``,
so a page links to ``bench/optimize.png`` and the picture is the one the bench wrote;
and it gives every public package of ``jaxbvh`` an API page in the nav's "API reference"
(``api/NAME.md``, generated when the folder has none), so a new package is documented
without editing ``mkdocs.yml``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import os
import pkgutil
import re
import sys
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MARK = re.compile(r"^(?P<indent>[ \t]*)<!-- gen: (?P<kind>\S+)(?P<args>.*?) -->$", re.M)
END = "<!-- end gen -->"
# a committed part: the marker, the text the code made (any lines), the end marker
BLOCK = re.compile(r"^(?P<indent>[ \t]*)<!-- gen: (?P<kind>\S+)(?P<args>.*?) -->\n(?P<body>.*?)^(?P=indent)"
                   + re.escape(END) + r"$", re.M | re.S)
WIDTH = 100  # columns of generated --help text (as the synopsis)


# ----------------------------------------------------------------------------------
# knob tables
# ----------------------------------------------------------------------------------


def _command_options():
    """Every ConfigOptions the command line builds: the commands' module-level ones and
    the builder options every building command shares."""
    from jaxbvh.cli import command_kit, commands
    from jaxbvh.cli.options import ConfigOptions

    found = [command_kit.builder_options()]
    for info in pkgutil.iter_modules(commands.__path__):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        found += [v for v in vars(module).values() if isinstance(v, ConfigOptions)]
    return found


@functools.lru_cache(maxsize=None)  # one walk of the parsers per build
def flags_by_knob() -> dict[tuple[type, str], set[str]]:
    """``(Config class, field name) -> {flag}``: which flags set each knob, on any command."""
    out: dict[tuple[type, str], set[str]] = {}
    for options in _command_options():
        for flag, knobs in options.knobs.items():
            for knob in knobs:
                config = options.bases[knob.method]
                for name in knob.path[:-1]:
                    config = getattr(config, name)
                for cls in type(config).__mro__:  # a knob declared on a base class too
                    out.setdefault((cls, knob.path[-1]), set()).add(flag)
    return out


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _default(field: dataclasses.Field) -> str:
    from jaxbvh.cli.options import shown

    value = field.default
    if dataclasses.is_dataclass(value):
        return f"`{type(value).__module__}.{type(value).__qualname__}()`"
    if callable(value):
        return f"`{getattr(value, '__name__', value)}`"
    if isinstance(value, (bool, type(None))):
        return f"`{value!r}`"
    return f"`{shown(value)}`"


def knob_table(dotted: str, new: bool = False) -> str:
    """A Markdown table of the knobs of the Config class ``dotted`` (module.Class); with
    ``new``, only the knobs its nearest public dataclass base does not have."""
    from jaxbvh.cli.options import field_docs

    module, _, name = dotted.rpartition(".")
    Config = getattr(importlib.import_module(module), name)
    if not dataclasses.is_dataclass(Config):
        raise ValueError(f"gen knobs: {dotted} is not a Config dataclass")
    docs = field_docs(Config)
    flags = flags_by_knob()
    rows = ["| knob | default | what it sets | command line |", "|---|---|---|---|"]
    # the knobs of its nearest public dataclass base (a private one, _MortonConfig, is
    # part of what the subclass adds)
    bases = [b for b in Config.__mro__[1:] if dataclasses.is_dataclass(b) and not b.__name__.startswith("_")]
    inherited = {f.name for f in dataclasses.fields(bases[0])} if new and bases else set()
    for field in dataclasses.fields(Config):
        if field.name in inherited:
            continue
        text = field.metadata.get("help") or docs.get(field.name, "")
        flag = ", ".join(f"`{f}`" for f in sorted(flags.get((Config, field.name), ()))) or "(library only)"
        rows.append(f"| `{field.name}` | {_default(field)} | {_cell(text)} | {flag} |")
    return "\n".join(rows)


# ----------------------------------------------------------------------------------
# the command line
# ----------------------------------------------------------------------------------


@contextmanager
def _columns(width: int):
    """argparse sizes help to the terminal (``COLUMNS``): fix it while formatting."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(width + 2)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def synopsis_block() -> str:
    from jaxbvh.cli.synopsis import synopsis

    return f"```text\n{synopsis()}\n```"


def help_block(command: str) -> str:
    from jaxbvh.cli import make_parser

    parser, _ = make_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    if command not in action.choices:
        raise ValueError(f"gen help: no command {command!r}; commands: {', '.join(action.choices)}")
    with _columns(WIDTH):
        text = action.choices[command].format_help()
    return f"```text\n{text.rstrip()}\n```"


# ----------------------------------------------------------------------------------
# files and API blocks
# ----------------------------------------------------------------------------------


def include(path: str, level: int, nested: bool = False) -> str:
    """The file at ``path`` (repository-relative), headings moved below level ``level``,
    or made bold lines when ``nested`` (inside an admonition)."""
    text = (REPO / path).read_text()
    if nested:
        return re.sub(r"^#+ (.*)$", r"**\1**", text, flags=re.M)
    return re.sub(r"^(#+) ", lambda m: "#" * min(6, len(m.group(1)) + level) + " ", text, flags=re.M)


def public_modules(package: str, twins: bool = False) -> list[str]:
    """Modules under ``package``, public ones (no ``_`` in any part), twins or not twins."""
    root = importlib.import_module(package)
    names = [package] if not twins else []
    for info in pkgutil.walk_packages(root.__path__, package + "."):
        parts = info.name.split(".")
        if any(p.startswith("_") for p in parts):
            continue
        if info.name.endswith("_reference") == twins:
            names.append(info.name)
    return names


def api_blocks(modules: list[str]) -> str:
    """One section per module; a package shows its docstring only, under the page's own
    title (its modules follow)."""
    def block(m):
        if hasattr(importlib.import_module(m), "__path__"):
            return f"::: {m}\n    options:\n      members: false"
        return f"## `{m}`\n\n::: {m}"

    return "\n\n".join(block(m) for m in modules)


def docstring_of(module: str) -> str:
    import inspect

    here = str(Path(__file__).parent)  # the sibling griffe extension, for its converter
    if here not in sys.path:
        sys.path.insert(0, here)
    from rest_docstrings import markdown_of

    return markdown_of(inspect.getdoc(importlib.import_module(module)) or "")


def toplevel_blocks() -> str:
    """``jaxbvh`` (its docstring) and every public top-level module that is not a package."""
    root = importlib.import_module("jaxbvh")
    modules = [f"jaxbvh.{info.name}" for info in pkgutil.iter_modules(root.__path__)
               if not info.ispkg and not info.name.startswith("_")]
    return "## `jaxbvh`\n\n::: jaxbvh\n    options:\n      members: false\n\n" + api_blocks(modules)


def other_results(docs_dir: Path) -> str:
    """Every ``bench/results/*.md`` no page includes and every plot no page shows."""
    pages = "\n".join(p.read_text() for p in docs_dir.rglob("*.md"))
    results = REPO / "bench" / "results"
    parts = []
    for md in sorted(results.glob("*.md")):
        if f"<!-- gen: include bench/results/{md.name} -->" not in pages:
            parts.append(f"### `{md.name}`\n\n" + include(f"bench/results/{md.name}", 3))
    for png in sorted(results.glob("*.png")):
        if f"(bench/{png.name})" not in pages:
            parts.append(f"### `{png.name}`\n\n![{png.stem}](bench/{png.name})")
    return "\n\n".join(parts) or "None: every result is on a page above."


def _level(markdown: str, at: int) -> int:
    """The level of the last heading before position ``at`` (0 if none)."""
    heads = re.findall(r"^(#+) ", markdown[:at], re.M)
    return len(heads[-1]) if heads else 0


def _part(markdown: str, match: re.Match, docs_dir: Path) -> str:
    """The text of the generated part ``match`` asks for, indented as its marker."""
    indent = match.group("indent")
    text = _make(markdown, match.group("kind"), match.group("args").split(), match, docs_dir)
    return "\n".join(indent + line if line else line for line in text.split("\n"))


def expand(markdown: str, docs_dir: Path = REPO / "docs") -> str:
    """``markdown`` with every generated part made afresh, markers removed (module
    docstring): a committed part's text is replaced, a marker line is filled."""
    markdown = BLOCK.sub(lambda m: _part(markdown, m, docs_dir), markdown)
    return MARK.sub(lambda m: _part(markdown, m, docs_dir), markdown)


def refresh(markdown: str, docs_dir: Path = REPO / "docs") -> str:
    """``markdown`` with the text of every committed part (marker ... ``END``) made
    afresh, markers kept: what the file should hold. Marker lines without an end are
    left to the build."""
    def one(match: re.Match) -> str:
        indent = match.group("indent")
        head = f"{indent}<!-- gen: {match.group('kind')}{match.group('args')} -->"
        return f"{head}\n\n{_part(markdown, match, docs_dir)}\n\n{indent}{END}"

    return BLOCK.sub(one, markdown)


def _make(markdown: str, kind: str, args: list[str], match: re.Match, docs_dir: Path) -> str:
    """The generated part ``kind ARGS`` (module docstring's table)."""
    def part(kind: str, args: list[str], match: re.Match) -> str:
        if kind == "knobs" and (args[1:] in ([], ["new"])):
            return knob_table(args[0], new=args[1:] == ["new"])
        if kind == "synopsis" and not args:
            return synopsis_block()
        if kind == "help" and len(args) == 1:
            return help_block(args[0])
        if kind == "include" and len(args) == 1:
            return include(args[0], _level(markdown, match.start()), nested=bool(match.group("indent")))
        if kind == "api" and len(args) == 1:
            return api_blocks(public_modules(args[0]))
        if kind == "docstring" and len(args) == 1:
            return docstring_of(args[0])
        if kind == "toplevel" and not args:
            return toplevel_blocks()
        if kind == "other-results" and not args:
            return other_results(docs_dir)
        if kind == "twins" and not args:
            return api_blocks(public_modules("jaxbvh", twins=True))
        raise ValueError(f"unknown generated part: {match.group(0).splitlines()[0]}")

    return part(kind, args, match)


# ----------------------------------------------------------------------------------
# MkDocs events
# ----------------------------------------------------------------------------------


def on_page_markdown(markdown, page, config, files):
    return expand(markdown, Path(config["docs_dir"]))


API_SECTION = "API reference"
API_BEFORE = "api/shared.md"  # new package pages go before this entry


def public_packages() -> list[str]:
    root = importlib.import_module("jaxbvh")
    return [info.name for info in pkgutil.iter_modules(root.__path__) if info.ispkg and not info.name.startswith("_")]


def on_files(files, config):
    from mkdocs.structure.files import File

    for png in sorted((REPO / "bench" / "results").glob("*.png")):
        files.append(File.generated(config, f"bench/{png.name}", abs_src_path=str(png)))
    # runs before the nav is built from config["nav"]: a package without a page gets one
    section = next(entry[API_SECTION] for entry in config["nav"] if isinstance(entry, dict) and API_SECTION in entry)
    listed = [next(iter(e.values())) if isinstance(e, dict) else e for e in section]
    for name in public_packages():
        uri = f"api/{name}.md"
        if files.get_file_from_path(uri) is None:
            files.append(File.generated(config, uri, content=f"# `jaxbvh.{name}`\n\n<!-- gen: api jaxbvh.{name} -->\n"))
        if uri not in listed:
            at = listed.index(API_BEFORE) if API_BEFORE in listed else len(section)
            section.insert(at, {f"jaxbvh.{name}": uri})
            listed.insert(at, uri)
    return files


if __name__ == "__main__":
    # python docs/hooks/generate.py [PAGE ...]: rewrite the committed parts of the pages
    sys.path.insert(0, str(REPO))
    from jaxbvh.files import atomic_write

    for name in sys.argv[1:] or ["docs/cli.md"]:
        page = Path(name)
        old = page.read_text()
        new = refresh(old)
        if new != old:
            with atomic_write(page, "w") as f:
                f.write(new)
        print(f"{page}: {'rewritten' if new != old else 'current'}")
