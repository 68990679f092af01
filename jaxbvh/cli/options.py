"""Command-line options made from ``Config`` dataclasses: the library's knobs and defaults, once.

A command that runs one of several methods (``jaxbvh optimize --method ...``) offers
the fields of their configs as options, via :class:`ConfigOptions`:

* the flag is the field's name (``max_steps`` -> ``--max-steps``) unless a rename
  says otherwise (the command keeps its established spellings);
* the type comes from the default (``int``, ``float``, ``str``; a ``bool`` becomes a
  ``--x/--no-x`` pair) or, for a default of None, from the field's metadata ``type``
  (:func:`jaxbvh.configs.knob`) or its annotation (``float | None``);
* help, choices and metavar come from ``dataclasses.field(metadata=dict(help=...,
  choices=..., metavar=...))``, else the help from the Config's docstring, whose
  fields are written ``name``: text (the house style);
* a field whose default is itself a config (the pipeline's stage configs) offers its
  fields too, under their own names: one flag can set fields of several methods and
  of nested configs (``--min-gain`` sets both stages' margins of the pipeline).

No option has a default of its own (argparse's ``SUPPRESS``): a flag not given leaves
the Config's default in place, so the command line cannot drift from the library, and
the help text states the Config's defaults, per method. :meth:`ConfigOptions.config`
builds the chosen method's Config from the flags given; a value the Config refuses is
reported naming the flag.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import typing
from typing import Any, Mapping

#: argparse types of the supported field kinds, and their metavars unless a field names one
_TYPES = {int: int, float: float, str: str}
_METAVARS = {int: "N", float: "X", str: "TEXT"}


@dataclasses.dataclass(frozen=True)
class Knob:
    """One field of one method's Config that a flag sets."""

    method: str      # the method (key of the configs mapping)
    path: tuple      # field names from the method's Config down to the field
    kind: type       # bool, int, float or str
    default: Any     # the Config's default
    help: str        # from the field's metadata or the Config's docstring
    choices: tuple | None
    metavar: str | None


def field_docs(Config: type) -> dict[str, str]:
    """Help text of each field from a Config's docstring (``name``: text, or
    ``a``, ``b``: text), with reST roles and literals made plain."""
    doc = Config.__doc__ or ""
    marks = list(re.finditer(r"((?:``\w+``)(?:,\s*``\w+``)*)\s*:\s", doc))
    docs = {}
    for i, mark in enumerate(marks):
        end = marks[i + 1].start() if i + 1 < len(marks) else len(doc)
        text = doc[mark.end():end]
        text = re.sub(r":\w+:`~?([^`]+)`", lambda m: m.group(1).split(".")[-1], text)
        text = " ".join(text.replace("``", "").split()).rstrip(". ")
        for name in re.findall(r"``(\w+)``", mark.group(1)):
            docs.setdefault(name, text)
    return docs


def _kind(field: dataclasses.Field, default, hints: dict):
    """bool/int/float/str for a supported field, else None."""
    if isinstance(default, bool):
        return bool
    for kind in (int, float, str):
        if isinstance(default, kind):
            return kind
    if default is None:
        if field.metadata.get("type") in _TYPES:  # jaxbvh.configs.knob(None, type=...)
            return field.metadata["type"]
        hint = hints.get(field.name)
        args = set(typing.get_args(hint)) - {type(None)}
        if len(args) == 1 and next(iter(args)) in _TYPES:
            return next(iter(args))
    return None


def _default(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    raise TypeError(f"config field {field.name} has no default")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


class ConfigOptions:
    """argparse options for the fields of the Config dataclasses of several methods.

    ``configs``: method name -> Config class. ``exclude``: fields not offered, each a
    field name (anywhere), a dotted path (``"treelet.max_passes"``: that nested field)
    or ``"method:path"``; a field of an unsupported type (e.g. a tuple of work sizes)
    must be excluded. ``flags``: renames, keyed the same way, to a flag (``{"leaves":
    "--treelet-leaves"}``). ``choices``: field name -> allowed values (for a string
    field whose metadata names none).
    """

    def __init__(self, configs: Mapping[str, type], *, exclude=(), flags: Mapping[str, str] | None = None,
                 choices: Mapping[str, tuple] | None = None):
        self.configs = dict(configs)
        self.exclude = set(exclude)
        self.renames = dict(flags or {})
        self.extra_choices = dict(choices or {})
        self.knobs: dict[str, list[Knob]] = {}  # flag -> the fields it sets
        for method, Config in self.configs.items():
            self._walk(method, Config, ())
        for flag, knobs in self.knobs.items():
            kinds = {k.kind for k in knobs}
            if len(kinds) > 1:
                raise TypeError(f"{flag} would set fields of different types: "
                                + ", ".join(f"{k.method}:{'.'.join(k.path)}" for k in knobs))

    def _lookup(self, table, method: str, path: tuple):
        dotted = ".".join(path)
        for key in (f"{method}:{dotted}", dotted, path[-1]):
            if key in table:
                return key, table[key]
        return None, None

    def _walk(self, method: str, Config: type, prefix: tuple) -> None:
        docs = field_docs(Config)
        hints = typing.get_type_hints(Config)
        for field in dataclasses.fields(Config):
            path = prefix + (field.name,)
            if self._lookup({e: True for e in self.exclude}, method, path)[0] is not None:
                continue
            default = _default(field)
            if dataclasses.is_dataclass(default):
                self._walk(method, type(default), path)
                continue
            kind = _kind(field, default, hints)
            if kind is None:
                raise TypeError(f"{method}: config field {'.'.join(path)} ({field.type}) has no "
                                "command-line form; exclude it")
            meta = field.metadata
            choices = meta.get("choices", self._lookup(self.extra_choices, method, path)[1])
            knob = Knob(method, path, kind, default, meta.get("help", docs.get(field.name, "")),
                        tuple(choices) if choices is not None else None, meta.get("metavar"))
            flag = self._lookup(self.renames, method, path)[1] or _flag(field.name)
            self.knobs.setdefault(flag, []).append(knob)

    # -- the parser -------------------------------------------------------------------

    @staticmethod
    def dest(flag: str) -> str:
        """The argparse attribute of ``flag``."""
        return flag.lstrip("-").replace("-", "_")

    def help(self, flag: str) -> str:
        """What ``flag`` sets, per method, with the Config's default."""
        groups: dict[tuple, list[str]] = {}
        for knob in self.knobs[flag]:
            where = knob.method + (f" ({'.'.join(knob.path[:-1])})" if len(knob.path) > 1 else "")
            groups.setdefault((knob.help, _shown(knob.default)), []).append(where)
        parts = [f"{', '.join(dict.fromkeys(ws))}: {text or 'see the Config'} (default: {shown})"
                 for (text, shown), ws in groups.items()]
        return "; ".join(parts).replace("%", "%%")

    def add_to(self, parser: argparse.ArgumentParser, title: str | None = None) -> None:
        """Add every flag (none with a default of its own) to ``parser`` (in a group
        named ``title``, if given)."""
        target = parser.add_argument_group(title) if title else parser
        for flag, knobs in self.knobs.items():
            first = knobs[0]
            common = dict(dest=self.dest(flag), default=argparse.SUPPRESS, help=self.help(flag))
            if first.kind is bool:
                target.add_argument(flag, action=argparse.BooleanOptionalAction, **common)
                continue
            metavar = next((k.metavar for k in knobs if k.metavar), None)
            choices = next((k.choices for k in knobs if k.choices), None)
            target.add_argument(flag, type=_TYPES[first.kind], choices=choices,
                                metavar=None if choices else (metavar or _METAVARS[first.kind]), **common)

    # -- configs from the parsed arguments ------------------------------------------

    def given(self, method: str, args: argparse.Namespace) -> dict[tuple, tuple[str, Any]]:
        """The fields of ``method``'s Config set by flags in ``args``: path -> (flag, value)."""
        out = {}
        for flag, knobs in self.knobs.items():
            dest = self.dest(flag)
            if hasattr(args, dest):
                for knob in knobs:
                    if knob.method == method:
                        out[knob.path] = (flag, getattr(args, dest))
        return out

    def config(self, method: str, args: argparse.Namespace, **fixed):
        """``method``'s Config from the flags given in ``args`` (the Config's defaults
        for the rest) and ``fixed`` top-level fields (e.g. costs from other options).
        ``ValueError`` naming the flag when the Config refuses a value."""
        Config = self.configs[method]
        given = self.given(method, args)
        try:
            return _build(Config, {path: value for path, (_, value) in given.items()}, fixed)
        except ValueError as error:
            for path, (flag, value) in given.items():  # which flag alone is refused
                try:
                    _build(Config, {path: value}, fixed)
                except ValueError as alone:
                    raise ValueError(f"{flag}: {alone}") from None
            raise error

    def defaults(self, method: str) -> dict[tuple, Any]:
        """The Config default of every field a flag sets for ``method``: path -> value."""
        return {k.path: k.default for knobs in self.knobs.values() for k in knobs if k.method == method}


def _build(Config: type, values: dict[tuple, Any], fixed: dict):
    """``Config`` with the fields at ``values``' paths (nested configs rebuilt) and ``fixed``."""
    top: dict[str, Any] = dict(fixed)
    nested: dict[str, dict] = {}
    for path, value in values.items():
        if len(path) == 1:
            top[path[0]] = value
        else:
            nested.setdefault(path[0], {})[path[1:]] = value
    for name, inner in nested.items():
        field = Config.__dataclass_fields__[name]
        top[name] = _build(type(_default(field)), inner, {})
    return Config(**top)


def _shown(value) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "automatic"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def add_config_options(parser: argparse.ArgumentParser, Config: type, *, exclude=(),
                       flags: Mapping[str, str] | None = None, title: str | None = None,
                       name: str = "config") -> ConfigOptions:
    """Options for one Config's fields (``ConfigOptions({name: Config}, ...)``), added
    to ``parser``; returns the :class:`ConfigOptions` that builds the Config back."""
    options = ConfigOptions({name: Config}, exclude=exclude, flags=flags)
    options.add_to(parser, title)
    return options


__all__ = ["ConfigOptions", "Knob", "add_config_options", "field_docs"]
