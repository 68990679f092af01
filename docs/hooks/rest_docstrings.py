"""Griffe extension: the house's reST-flavoured docstrings shown as Markdown.

The docstrings are written for ``help()`` and the terminal: ``:func:`build``` roles and
reST simple tables (rows between ``====  ====`` borders). Markdown has neither, so the
API pages would show the roles' colons and turn a table's border into a heading. This
rewrites, at load time, a role into inline code of its target's last name, a simple
table into a preformatted block (as it reads in the terminal) and a section title
into a bold line. ``literal`` double
backticks are already Markdown's inline code.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?\w+:`~?([^`<]+?)(?:\s*<[^>]*>)?`")
BORDER = re.compile(r"^\s*=+(\s+=+)+\s*$")
# a reST section title: a line of text underlined by = - ~ (Markdown would read a setext heading)
TITLE = re.compile(r"^(?P<title>[^\n=~-][^\n]*)\n(?P<rule>[=~-]{3,})[ \t]*$", re.M)


def role_to_code(match: re.Match) -> str:
    target = match.group(1).strip()
    return f"`{target.split('.')[-1] if '.' in target and ' ' not in target else target}`"


def fence_tables(text: str) -> str:
    """Each reST simple table (three border lines: top, under the header, bottom) fenced."""
    lines = text.split("\n")
    out, i = [], 0
    while i < len(lines):
        if BORDER.match(lines[i]):
            borders = [j for j in range(i, len(lines)) if BORDER.match(lines[j])][:3]
            if len(borders) == 3:
                out += ["```text", *lines[i:borders[2] + 1], "```"]
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
    return bold_titles(fence_tables(ROLE.sub(role_to_code, text)))


class RestDocstrings(griffe.Extension):
    def on_object(self, *, obj, loader, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown_of(obj.docstring.value)
