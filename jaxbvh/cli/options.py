"""Command-line options made from ``Config`` dataclasses: the library's knobs, defaults and checks, once.

Every option of every command that sets a knob of a method's Config (the builders',
the optimizers' with the pipeline's stages, GRASP's, the genetic algorithm's, the
collapse's) is made here, by :class:`ConfigOptions`, from the fields that
:func:`jaxbvh.configs.knob` declares:

* the flag is the field's name (``max_steps`` -> ``--max-steps``) unless a rename
  says otherwise (``--treelet-leaves``); a spelling a command had before
  (``renamed``) still sets its knob, with a ``DeprecationWarning``;
* the type comes from the default (``int``, ``float``, ``str``; a ``bool`` becomes a
  ``--x/--no-x`` pair) or, for a default of None, from the knob's ``type`` or the
  field's annotation (``float | None``);
* help, choices and metavar come from the knob (else the help from the Config's
  docstring, whose fields are written ``name``: text, the house style);
* a knob whose default is itself a Config (the pipeline's stage configs) offers that
  Config's knobs too, under their own names: one flag can set knobs of several methods
  and of nested Configs (``--min-gain`` sets both stages' margins of the pipeline).

**No option has a default of its own** (argparse's ``SUPPRESS``): a flag not given
leaves the Config's default in place, so the command line cannot drift from the
library, and ``--help`` states each method's Config default. A Config may be given as
an instance instead of a class: its values are then the defaults (the two-level
builder's :data:`jaxbvh.twolevel.objects.DEFAULT_BUILDER`).

**One rule per value, the Config's.** :meth:`ConfigOptions.config` builds the chosen
method's Config from the flags given, and a value it refuses is a ``ValueError``
naming the flag (``--first-fraction must be ...``; the command line prints it as one
line, exit status 2). With ``check_while_parsing`` the knob's own check also runs while
parsing, so argparse reports the flag before the command starts; that needs a rule that
does not depend on the method, and is used for the builder options, whose knobs share
one check across every builder. The method is known only after parsing, so the other
commands check when they build the Config, first thing in ``run``.

**An option of another method is an error.** With ``method_flag`` (``--method``), a flag
given that sets no knob of the chosen method is a ``ValueError`` naming both (``--hottest
does not apply to --method pipeline; it is an option of --method sa``) rather than
silently ignored. Methods of one *family* (``families``) share their options instead: a
flag of another method of the family is accepted, and its value checked by that
method's Config, so it is never silently wrong. The builders are one family (one set of
builder options serves every builder, as :func:`jaxbvh.build`'s keyword form does), and
so are hill climbing and annealing (Kensler's rotations; hill climbing is annealing
without the heat).
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import typing
import warnings
from typing import Any, Callable, Mapping

#: argparse types of the supported knob kinds, and their metavars unless a knob names one
_TYPES = {int: int, float: float, str: str}
_METAVARS = {int: "N", float: "X", str: "TEXT"}


@dataclasses.dataclass(frozen=True)
class Knob:
    """One knob of one method's Config that a flag sets."""

    method: str              # the method (key of the configs mapping)
    path: tuple              # field names from the method's Config down to the knob
    kind: type               # bool, int, float or str
    default: Any             # the Config's default (or the given instance's value)
    help: str                # from the knob's metadata or the Config's docstring
    choices: tuple | None
    metavar: str | None
    check: Callable | None   # the knob's check ``(name, value) -> value`` (jaxbvh.configs)


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


def flag_of(name: str) -> str:
    """The flag of a knob unless renamed: ``max_leaf`` -> ``--max-leaf``."""
    return "--" + name.replace("_", "-")


def with_flags(message: str, flags: Mapping[str, str]) -> str:
    """``message`` with each knob name of ``flags`` (name -> flag) written as its flag
    (whole words only: ``max_steps`` is not touched by a rename of ``steps``)."""
    for name in sorted(flags, key=len, reverse=True):
        message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flags[name], message)
    return message


def _kind(field: dataclasses.Field, default, hints: dict):
    """bool/int/float/str for a supported knob, else None."""
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


def _instance(config):
    """A Config instance: ``config`` itself, or its class's defaults."""
    return config if dataclasses.is_dataclass(config) and not isinstance(config, type) else config()


def shown(value) -> str:
    """A default as ``--help`` states it."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "none"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


class ConfigOptions:
    """argparse options for the knobs of the Configs of one or several methods (module docstring).

    ``configs``: method name -> Config class (or instance: its values are the defaults).
    ``exclude``: knobs not offered, each a field name (anywhere), a dotted path
    (``"treelet.max_passes"``: that nested knob) or ``"method:path"``; a knob of a type
    with no command-line form (a tuple of work sizes, a dtype) must be excluded.
    ``flags``: renames, keyed the same way, to a flag (``{"leaves": "--treelet-leaves"}``).
    ``choices``: knob -> allowed values (for a string knob that names none). ``helps``:
    knob -> help text replacing the knob's. ``method_flag``: the option that picks the
    method (``"--method"``), named in errors. ``families``: method -> family name;
    methods of one family share their options (module docstring; by default each method
    is a family of its own). ``check_while_parsing``: run the knobs' checks in argparse
    (see the module docstring). ``renamed``: old flag -> ``{method: flag}`` (``"*"``: every
    method), spellings the command had; given, they set the new flag's knob (unless it
    is given too) with a ``DeprecationWarning``. An old flag that is still another
    knob's flag (``--max-passes``) is moved only for the methods named.
    """

    def __init__(self, configs: Mapping[str, Any], *, exclude=(), flags: Mapping[str, str] | None = None,
                 choices: Mapping[str, tuple] | None = None, helps: Mapping[str, str] | None = None,
                 method_flag: str | None = None, families: Mapping[str, str] | None = None,
                 check_while_parsing: bool = False, renamed: Mapping[str, Mapping[str, str]] | None = None):
        self.bases = {method: _instance(config) for method, config in configs.items()}
        self.exclude = set(exclude)
        self.renames = dict(flags or {})
        self.extra_choices = dict(choices or {})
        self.helps = dict(helps or {})
        self.method_flag = method_flag
        self.families = {method: (families or {}).get(method, method) for method in self.bases}
        self.check_while_parsing = check_while_parsing
        self.renamed = {old: dict(new) for old, new in (renamed or {}).items()}
        self.knobs: dict[str, list[Knob]] = {}  # flag -> the knobs it sets
        for method, base in self.bases.items():
            self._walk(method, base, ())
        for flag, knobs in self.knobs.items():
            kinds = {k.kind for k in knobs}
            if len(kinds) > 1:
                raise TypeError(f"{flag} would set knobs of different types: "
                                + ", ".join(f"{k.method}:{'.'.join(k.path)}" for k in knobs))

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(self.bases)

    def _lookup(self, table, method: str, path: tuple):
        dotted = ".".join(path)
        for key in (f"{method}:{dotted}", dotted, path[-1]):
            if key in table:
                return key, table[key]
        return None, None

    def _walk(self, method: str, base, prefix: tuple) -> None:
        Config = type(base)
        docs = field_docs(Config)
        hints = typing.get_type_hints(Config)
        for field in dataclasses.fields(Config):
            path = prefix + (field.name,)
            if self._lookup(dict.fromkeys(self.exclude), method, path)[0] is not None:
                continue
            default = getattr(base, field.name)
            if dataclasses.is_dataclass(default):
                self._walk(method, default, path)
                continue
            kind = _kind(field, default, hints)
            if kind is None:
                raise TypeError(f"{method}: config field {'.'.join(path)} ({field.type}) has no "
                                "command-line form; exclude it")
            meta = field.metadata
            choices = meta.get("choices", self._lookup(self.extra_choices, method, path)[1])
            text = self._lookup(self.helps, method, path)[1] or meta.get("help", docs.get(field.name, ""))
            knob = Knob(method, path, kind, default, text, tuple(choices) if choices is not None else None,
                        meta.get("metavar"), meta.get("check"))
            flag = self._lookup(self.renames, method, path)[1] or flag_of(field.name)
            self.knobs.setdefault(flag, []).append(knob)

    # -- the parser -------------------------------------------------------------------

    @staticmethod
    def dest(flag: str) -> str:
        """The argparse attribute of ``flag``."""
        return flag.lstrip("-").replace("-", "_")

    def help(self, flag: str) -> str:
        """What ``flag`` sets, with the Config's default (per method, where they differ
        or the flag serves only some methods)."""
        groups: dict[tuple, list[str]] = {}
        for knob in self.knobs[flag]:
            where = knob.method + (f" ({'.'.join(knob.path[:-1])})" if len(knob.path) > 1 else "")
            groups.setdefault((knob.help, shown(knob.default)), []).append(where)
        every = {k.method for k in self.knobs[flag]} == set(self.bases) and len(groups) == 1
        parts = [("" if every else f"{', '.join(dict.fromkeys(ws))}: ")
                 + f"{text or 'see the Config'} (default: {value})" for (text, value), ws in groups.items()]
        return "; ".join(parts).replace("%", "%%")

    def _parse(self, flag: str, kind: type) -> Callable[[str], Any]:
        """argparse ``type`` of ``flag``: the kind, and with ``check_while_parsing`` the knobs' checks."""
        checks = [(k.path[-1], k.check) for k in self.knobs[flag] if k.check] if self.check_while_parsing else []

        def parse(text: str):
            try:
                value = kind(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None
            for name, check in checks:
                try:
                    value = check(name, value)
                except ValueError as exc:
                    raise argparse.ArgumentTypeError(with_flags(str(exc), {name: flag})) from None
            return value

        parse.__name__ = kind.__name__  # argparse names the type in its messages
        return parse

    def add_to(self, parser: argparse.ArgumentParser, title: str | None = None) -> None:
        """Add every flag (none with a default of its own) to ``parser`` (in a group
        named ``title``, if given). Each action made has ``config_options`` (this object)."""
        target = parser.add_argument_group(title) if title else parser
        for flag, knobs in self.knobs.items():
            first = knobs[0]
            common = dict(dest=self.dest(flag), default=argparse.SUPPRESS, help=self.help(flag))
            if first.kind is bool:
                action = target.add_argument(flag, action=argparse.BooleanOptionalAction, **common)
            else:
                metavar = next((k.metavar for k in knobs if k.metavar), None)
                choices = next((k.choices for k in knobs if k.choices), None)
                action = target.add_argument(flag, type=self._parse(flag, first.kind), choices=choices,
                                             metavar=None if choices else (metavar or _METAVARS[first.kind]),
                                             **common)
            action.config_options = self
        for old, targets in self.renamed.items():  # hidden: --help shows the current spellings
            if old not in self.knobs:
                new = next(iter(targets.values()))
                target.add_argument(old, dest=self.dest(old), default=argparse.SUPPRESS,
                                    help=argparse.SUPPRESS, type=self._parse(new, self.knobs[new][0].kind))

    # -- configs from the parsed arguments ------------------------------------------

    def _method(self, method: str | None) -> str:
        if method is None:
            if len(self.bases) != 1:
                raise TypeError(f"name the method: one of {', '.join(self.bases)}")
            return next(iter(self.bases))
        return method

    def given(self, args: argparse.Namespace) -> dict[str, Any]:
        """The flags given in ``args`` (old spellings included): flag -> value."""
        flags = list(self.knobs) + [old for old in self.renamed if old not in self.knobs]
        return {flag: getattr(args, self.dest(flag)) for flag in flags if hasattr(args, self.dest(flag))}

    def _renamed_to_current(self, method: str, args: argparse.Namespace) -> None:
        """Move the values of old spellings given (``renamed``) to their current flags in
        ``args``, each with a ``DeprecationWarning`` (shown: a command line is no library
        caller whose warnings Python hides)."""
        for old, targets in self.renamed.items():
            new = targets.get(method, targets.get("*"))
            if new is None or not hasattr(args, self.dest(old)):
                continue
            value = getattr(args, self.dest(old))
            delattr(args, self.dest(old))
            if not hasattr(args, self.dest(new)):
                setattr(args, self.dest(new), value)
            where = "" if "*" in targets else f" with {self.method_flag or 'method'} {method}"
            with warnings.catch_warnings():
                warnings.simplefilter("always", DeprecationWarning)
                warnings.warn(f"{old}{where} is deprecated: use {new}", DeprecationWarning, stacklevel=3)

    def config(self, method: str | None, args: argparse.Namespace, **fixed):
        """``method``'s Config (None: the only one) from the flags given in ``args``, the
        defaults for the rest, and ``fixed`` top-level knobs (e.g. costs from other
        options). ``ValueError`` naming the flag when the Config refuses a value, or
        naming the flag and the method when a flag given does not apply to it."""
        method = self._method(method)
        self._renamed_to_current(method, args)
        given = {flag: value for flag, value in self.given(args).items() if flag in self.knobs}
        values: dict[tuple, Any] = {}
        mine: dict[str, list[tuple]] = {}
        for flag, value in given.items():
            paths = [k.path for k in self.knobs[flag] if k.method == method]
            if paths:
                mine[flag] = paths
                values.update({path: value for path in paths})
            else:
                self._check_other(method, flag, value)
        base = self.bases[method]
        try:
            return _build(base, values, fixed)
        except ValueError as error:
            raise ValueError(self._named(method, str(error), base, given, mine, fixed)) from None

    def _check_other(self, method: str, flag: str, value) -> None:
        """A flag given that sets no knob of ``method``: an error naming both, unless a
        method of its family owns it; then that method's Config checks the value."""
        chooser = self.method_flag or "method"
        owners = list(dict.fromkeys(k.method for k in self.knobs[flag]))
        kin = [owner for owner in owners if self.families[owner] == self.families[method]]
        if not kin:
            raise ValueError(f"{flag} does not apply to {chooser} {method}; it is an option of "
                             f"{chooser} {', '.join(owners)}")
        owner = kin[0]
        paths = [k.path for k in self.knobs[flag] if k.method == owner]
        try:
            _build(self.bases[owner], dict.fromkeys(paths, value), {})
        except ValueError as error:
            message = self._named(owner, str(error), self.bases[owner], {flag: value}, {flag: paths}, {})
            raise ValueError(f"{message} (an option of {chooser} {owner})") from None

    def _named(self, method, message, base, given, mine, fixed) -> str:
        """``message`` with the method's knob names written as flags, and led by the flag
        whose value alone is refused when the message does not name one."""
        names: dict[str, set] = {}
        for flag, knobs in self.knobs.items():
            for knob in knobs:
                if knob.method == method:
                    names.setdefault(knob.path[-1], set()).add(flag)
        message = with_flags(message, {name: next(iter(fl)) for name, fl in names.items() if len(fl) == 1})
        if any(flag in message for flag in given):
            return message
        try:
            _build(base, {}, fixed)
        except ValueError:
            return message  # the fixed values alone are refused: no flag to blame
        for flag, paths in mine.items():
            try:
                _build(base, {path: given[flag] for path in paths}, fixed)
            except ValueError:
                return f"{flag}: {message}"
        return message

    def defaults(self, method: str | None = None) -> dict[tuple, Any]:
        """The Config default of every knob a flag sets for ``method``: path -> value."""
        method = self._method(method)
        return {k.path: k.default for knobs in self.knobs.values() for k in knobs if k.method == method}


def _build(base, values: dict[tuple, Any], fixed: dict):
    """``base`` (a Config instance) with the knobs at ``values``' paths (nested Configs
    rebuilt) and ``fixed`` top-level knobs; the Config checks them all."""
    top: dict[str, Any] = dict(fixed)
    nested: dict[str, dict] = {}
    for path, value in values.items():
        if len(path) == 1:
            top[path[0]] = value
        else:
            nested.setdefault(path[0], {})[path[1:]] = value
    for name, inner in nested.items():
        top[name] = _build(getattr(base, name), inner, {})
    return dataclasses.replace(base, **top)


def add_config_options(parser: argparse.ArgumentParser, Config, *, title: str | None = None,
                       name: str = "config", **options) -> ConfigOptions:
    """Options for one Config's knobs (``ConfigOptions({name: Config}, **options)``), added
    to ``parser``; returns the :class:`ConfigOptions` that builds the Config back
    (``.config(None, args)``)."""
    made = ConfigOptions({name: Config}, **options)
    made.add_to(parser, title)
    return made


__all__ = ["ConfigOptions", "Knob", "add_config_options", "field_docs", "flag_of", "shown", "with_flags"]
