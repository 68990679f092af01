"""Every ```python block of the documentation runs: each page's blocks in order, in one
fresh Python process per page, as a reader would paste them (README.md and every page
under docs/, new pages included without editing this file).

The process starts in a scratch folder laid out as the repository root (its top-level
entries linked in, ``../shared`` beside it when the meshes folder is there), so relative
paths in the examples resolve as they do from a clone while the files an example writes
(``spot.npz``) stay out of the repository. It inherits the suite's environment: the
run-wide compilation cache (``JAXBVH_CACHE_DIR``, tests/conftest.py) and the cheap XLA
flags. The examples are written small (the bundled mesh, second-long budgets), so the
pages together cost the suite a few minutes, not a benchmark's worth.

A block that cannot run (a fragment, a multi-host launch) carries a marker on the line
before its fence, ``<!-- no-run: why -->``; :func:`test_unrunnable_blocks_are_rare` keeps
such blocks few and explained.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import REPO, SHARED_DATA

NO_RUN = re.compile(r"^\s*<!-- no-run: (?P<why>\S.*?) -->\s*$")
FENCE = re.compile(r"^(?P<indent>[ \t]*)```python\s*$")
PAGE_SECONDS = 300  # one page's limit: a page takes 8-30 CPU s with a cold cache (195 CPU s all pages)
MOST_UNRUNNABLE = 5  # blocks marked no-run, all pages together


@dataclass(frozen=True)
class Block:
    page: str  # repository-relative path
    line: int  # 1-based line of the first code line
    code: str
    no_run: str | None  # the marker's reason, None when the block runs


def pages() -> list[Path]:
    """README.md and every Markdown page of the site: not the hooks, not the history
    notes (docs/notes/: what was written at the time, kept as it was)."""
    docs = sorted(p for p in (REPO / "docs").rglob("*.md")
                  if not {"hooks", "notes"} & set(p.relative_to(REPO / "docs").parts))
    return [REPO / "README.md", *docs]


def blocks(page: Path) -> list[Block]:
    """The ```python blocks of ``page``, dedented (a block inside an admonition too)."""
    return blocks_in(page.read_text(), str(page.relative_to(REPO)))


def blocks_in(text: str, name: str) -> list[Block]:
    """The ```python blocks of the Markdown ``text`` of page ``name``."""
    lines = text.splitlines()
    found, i = [], 0
    while i < len(lines):
        fence = FENCE.match(lines[i])
        if not fence:
            i += 1
            continue
        start, indent = i + 1, fence.group("indent")
        end = start
        while end < len(lines) and lines[end].strip() != "```":
            end += 1
        before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marker = NO_RUN.match(before)
        code = "\n".join(line[len(indent):] if line.startswith(indent) else line for line in lines[start:end])
        found.append(Block(name, start + 1, textwrap.dedent(code) + "\n",
                           marker.group("why") if marker else None))
        i = end + 1
    return found


def runnable_pages() -> list[str]:
    """Pages with a block to run; not the README, whose one example
    tests/test_docs.py::test_readme_example_optimizes_and_exits runs (and checks more of)."""
    return [str(p.relative_to(REPO)) for p in pages()[1:] if any(b.no_run is None for b in blocks(p))]


# Runs the blocks in one namespace, each compiled under the page's name and line numbers,
# so a traceback points at the page's own line.
RUNNER = textwrap.dedent("""
    import json, sys
    namespace = {"__name__": "__main__"}
    for page, line, code in json.load(open(sys.argv[1])):
        exec(compile("\\n" * (line - 1) + code, page, "exec"), namespace)
""")


def scratch_root(tmp: Path) -> Path:
    """A folder that looks like the repository root (its entries linked in) with
    ``../shared`` beside it when the clone has one."""
    root = tmp / "repo"
    root.mkdir()
    for entry in REPO.iterdir():
        if entry.name not in (".git",):
            (root / entry.name).symlink_to(entry)
    shared = REPO.parent / "shared"
    if shared.is_dir():
        (tmp / "shared").symlink_to(shared)
    return root


@pytest.mark.parametrize("page", runnable_pages())
def test_page_examples_run(page, tmp_path):
    """The page's runnable blocks, in order, in one process, exit 0 within the limit."""
    todo = [(b.page, b.line, b.code) for b in blocks(REPO / page) if b.no_run is None]
    if any("../shared/" in code for _, _, code in todo) and not SHARED_DATA.is_dir():
        pytest.skip(f"{page} reads ../shared/data, which is not beside this clone")
    script = tmp_path / "blocks.json"
    script.write_text(json.dumps(todo))
    root = scratch_root(tmp_path)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
               MPLBACKEND="Agg")
    assert env.get("JAXBVH_CACHE_DIR"), "the suite's conftest sets the run-wide compilation cache"
    try:
        done = subprocess.run([sys.executable, "-c", RUNNER, str(script)], cwd=root, env=env,
                              capture_output=True, text=True, timeout=PAGE_SECONDS)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"{page}: its examples ran past {PAGE_SECONDS} s\n{(e.stderr or b'')[-3000:]!r}")
    assert done.returncode == 0, f"{page}: exit {done.returncode}\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"


def test_blocks_are_found():
    """The parser finds blocks where they are: the README's example, one per method page
    at least, a marker's reason."""
    readme = blocks(REPO / "README.md")
    assert readme and readme[0].code.startswith("import jaxbvh") and readme[0].no_run is None
    page = REPO / "docs" / "builders.md"
    assert blocks(page), "docs/builders.md has an example"
    text = "intro\n\n<!-- no-run: a fragment -->\n```python\nx = 1\n```\n\n!!! note\n    ```python\n    y = 2\n    ```\n"
    got = blocks_in(text, "probe.md")
    assert [(b.line, b.code, b.no_run) for b in got] == [(5, "x = 1\n", "a fragment"), (10, "y = 2\n", None)]


def test_unrunnable_blocks_are_rare():
    """Few blocks are marked no-run, each with its reason, and every page with Python has
    at least one block that runs."""
    marked = [b for p in pages() for b in blocks(p) if b.no_run is not None]
    assert len(marked) <= MOST_UNRUNNABLE, [f"{b.page}:{b.line} ({b.no_run})" for b in marked]
    only_marked = [str(p.relative_to(REPO)) for p in pages()
                   if blocks(p) and all(b.no_run is not None for b in blocks(p))]
    assert len(only_marked) <= 1, f"pages whose every example is marked no-run: {only_marked}"
    # a marker that is not on the line before a fence is a typo, not a skip
    for p in pages():
        lines = p.read_text().splitlines()
        for i, line in enumerate(lines):
            if "no-run" in line and NO_RUN.match(line):
                after = next((lines[j] for j in range(i + 1, len(lines)) if lines[j].strip()), "")
                assert FENCE.match(after), f"{p.relative_to(REPO)}:{i + 1}: no-run marker not before a python block"
