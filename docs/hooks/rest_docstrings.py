"""Griffe extension: the house's reST-flavoured docstrings shown as Markdown.

The docstrings are written for ``help()`` and the terminal: ``:func:`build``` roles and
reST simple tables (rows between ``====  ====`` borders). Markdown has neither, so the
API pages would show the roles' colons and turn a table's border into a heading. This
rewrites, at load time, a role into inline code of its target (as Sphinx shows it), a simple
table into a Markdown table and a section title into a bold line. ``literal`` double
backticks are already Markdown's inline code.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?\w+:`(~?)([^`<]+?)(?:\s*<[^>]*>)?`")
BORDER = re.compile(r"^\s*=+(\s+=+)+\s*$")
# a reST section title: a line of text underlined by = - ~ (Markdown would read a setext heading)
TITLE = re.compile(r"^(?P<title>[^\n=~-][^\n]*)\n(?P<rule>[=~-]{3,})[ \t]*$", re.M)


def role_to_code(match: re.Match) -> str:
    """As Sphinx shows a role: its target, or with ``~`` the target's last name."""
    short, target = match.group(1), match.group(2).strip()
    return f"`{target.split('.')[-1] if short else target}`"


def _columns(border: str) -> list[int]:
    """Start of each column: where each run of ``=`` of a border begins."""
    return [m.start() for m in re.finditer(r"=+", border)]


def _cells(line: str, starts: list[int]) -> list[str]:
    ends = starts[1:] + [None]
    return [line[a:b].strip() if b is not None else line[a:].strip() for a, b in zip(starts, ends)]


def simple_table(lines: list[str]) -> list[str]:
    """A reST simple table (its lines, borders included) as a Markdown table. A line whose
    first cell is empty continues the row above (the house's wrapped text)."""
    starts = _columns(lines[0])
    borders = [i for i, line in enumerate(lines) if BORDER.match(line)]
    header = [_cells(line, starts) for line in lines[borders[0] + 1:borders[1]]]
    rows: list[list[str]] = []
    for line in lines[borders[1] + 1:borders[2]]:
        if not line.strip():
            continue
        cells = _cells(line, starts)
        if rows and not cells[0]:
            rows[-1] = [f"{a} {b}".strip() for a, b in zip(rows[-1], cells)]
        else:
            rows.append(cells)
    head = [" ".join(parts).strip() for parts in zip(*header)] if header else [""] * len(starts)
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(starts)]
    out += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
    return out


def convert_tables(text: str) -> str:
    """Each reST simple table (three border lines: top, under the header, bottom) as a
    Markdown table, with a blank line before and after it."""
    lines = text.split("\n")
    out, i = [], 0
    while i < len(lines):
        if BORDER.match(lines[i]):
            borders = [j for j in range(i, len(lines)) if BORDER.match(lines[j])][:3]
            if len(borders) == 3:
                indent = lines[i][:len(lines[i]) - len(lines[i].lstrip())]
                table = [line[len(indent):] for line in lines[i:borders[2] + 1]]
                out += ["", *(indent + row for row in simple_table(table)), ""]
                i = borders[2] + 1
                continue
        out.append(lines[i])
        i += 1
    return "\n".join(out)


def bold_titles(text: str) -> str:
    """reST section titles as bold paragraphs: a heading inside a docstring would break the
    page's outline (the API page gives each module and member its heading)."""
    return TITLE.sub(lambda m: f"**{m.group('title').strip()}**\n", text)


def markdown_of(text: str) -> str:
    return bold_titles(convert_tables(ROLE.sub(role_to_code, text)))


class RestDocstrings(griffe.Extension):
    def on_object(self, *, obj, loader, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown_of(obj.docstring.value)
