"""The command line's front: ``--help``, ``--version`` and usage errors without importing JAX.

Importing JAX costs about 2 s of CPU, and the real parsers are built from the methods'
Configs, which live beside their JAX code. So the console script starts here: the
parsers are described once, as data (:func:`describe`, written to ``parser_spec.json``
beside this module by ``python -m jaxbvh.cli.front``; a test holds the file equal to
the live parsers, which stay the one source of truth), and :func:`main` rebuilds them
from that file with argparse alone (:func:`rebuild`). Whatever that parser answers by
itself (help, the version, a usage error: exit 0 or 2) is answered without JAX; any
command line it accepts goes on to the real tool (:func:`jaxbvh.cli.app.main`), which
parses it again. A missing, unreadable or stale file (another version) only means the
slow path.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

from jaxbvh.configs import INT_MAX  # JAX-free, like everything this module imports

SPEC_PATH = Path(__file__).with_name("parser_spec.json")

#: exit status of bad input or options (one source: :mod:`jaxbvh.cli.app` re-exports it)
EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """argparse's parser with usage errors in the tool's one-line form:
    ``jaxbvh: error: COMMAND: MESSAGE (see jaxbvh COMMAND --help)``, exit status 2,
    like every other bad input (argparse would print the usage block first)."""

    def error(self, message):
        """Print ``message`` as one ``jaxbvh: error:`` line and exit with status 2."""
        command = self.prog.split(" ", 1)[1] + ": " if " " in self.prog else ""
        text = " ".join(f"{command}{message} (see {self.prog} --help)".split())
        self.exit(EXIT_USAGE, f"jaxbvh: error: {text}\n")


class int_option:  # noqa: N801 (used as argparse's ``type=``, like ``int``)
    """argparse ``type`` accepting integers in ``[minimum, maximum]`` (default: int32's
    largest, the arrays' id and counter type)."""

    def __init__(self, minimum: int, maximum: int = INT_MAX):
        self.minimum, self.maximum = int(minimum), int(maximum)
        self.__name__ = "integer"  # argparse names the type in its error messages

    def __call__(self, text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not self.minimum <= value <= self.maximum:
            raise argparse.ArgumentTypeError(f"expected an integer in [{self.minimum}, {self.maximum}], got {value}")
        return value


_ACTIONS = {"store": argparse._StoreAction, "store_true": argparse._StoreTrueAction,
            "help": argparse._HelpAction, "version": argparse._VersionAction,
            "boolean_optional": argparse.BooleanOptionalAction}
_TYPES = {"int": int, "float": float, "str": str}


def _type_name(kind) -> str | list | None:
    if kind is None:
        return None
    if isinstance(kind, int_option):
        return ["int_option", kind.minimum, kind.maximum]
    for name, known in _TYPES.items():
        if kind is known:
            return name
    if callable(kind) and getattr(kind, "__name__", None) in _TYPES:
        # a Config knob's parse (jaxbvh.cli.options): the front converts as it does and
        # leaves the knob's own checks to the real parser, which runs next
        return ["kind", kind.__name__]
    raise TypeError(f"the front cannot describe an option of type {kind!r}")


def _type_of(name):
    if name is None:
        return None
    if isinstance(name, list) and name[0] == "kind":
        return _kind_parse(_TYPES[name[1]])
    if isinstance(name, list):
        return int_option(name[1], name[2])
    return _TYPES[name]


def _kind_parse(kind):
    """The conversion of a Config knob's parse, with its message (the knob's checks are the
    real parser's)."""

    def parse(text: str):
        try:
            return kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind.__name__}, got {text!r}") from None

    parse.__name__ = kind.__name__
    return parse


def _describe_action(action: argparse.Action) -> dict:
    kind = next((name for name, cls in _ACTIONS.items() if type(action) is cls), None)
    if kind is None:
        raise TypeError(f"the front cannot describe an argparse action {type(action).__name__}")
    out = {"kind": kind, "option_strings": list(action.option_strings), "dest": action.dest,
           "help": action.help}
    if kind == "version":
        out["version"] = action.version
    if kind == "store":
        out.update(nargs=action.nargs, const=action.const, type=_type_name(action.type),
                   choices=None if action.choices is None else list(action.choices),
                   required=action.required,
                   metavar=list(action.metavar) if isinstance(action.metavar, tuple) else action.metavar)
    if kind in ("store", "store_true", "boolean_optional"):
        out["default"] = action.default
        if kind == "boolean_optional":
            out["required"] = action.required
    return out


def _describe_parser(parser: argparse.ArgumentParser) -> dict:
    if parser.formatter_class is not argparse.HelpFormatter or parser._mutually_exclusive_groups:
        raise TypeError("the front describes parsers with argparse's default formatter and no "
                        "mutually exclusive groups")
    # actions in the order they were added (argparse's usage line follows it), each
    # naming its group (the help's sections)
    group_of = {id(a): i for i, g in enumerate(parser._action_groups) for a in g._group_actions}
    groups = [{"title": g.title, "description": g.description} for g in parser._action_groups]
    actions = [dict(_describe_action(a), group=group_of[id(a)]) for a in parser._actions
               if not isinstance(a, argparse._SubParsersAction)]
    out = {"prog": parser.prog, "usage": parser.usage, "description": parser.description,
           "epilog": parser.epilog, "groups": groups, "actions": actions}
    sub = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if sub:
        helps = {a.dest: a.help for a in sub[0]._choices_actions}
        out["commands"] = {"dest": sub[0].dest, "metavar": sub[0].metavar, "required": sub[0].required,
                           "choices": {name: {"help": helps.get(name), "parser": _describe_parser(p)}
                                       for name, p in sub[0].choices.items()}}
    return out


def describe(parser: argparse.ArgumentParser | None = None) -> dict:
    """The tool's parsers as data (JSON-ready); ``parser`` default: the real ones
    (:func:`jaxbvh.cli.app.make_parser`, which imports JAX)."""
    from jaxbvh import __version__

    if parser is None:
        from jaxbvh.cli.app import make_parser

        parser, _ = make_parser()
    return {"version": __version__, "parser": _describe_parser(parser)}


def _suppress(value):
    """argparse tells SUPPRESS by identity: the string read back from JSON is made it again."""
    return argparse.SUPPRESS if value == argparse.SUPPRESS else value


def _add_action(container, spec: dict) -> None:
    spec = {key: _suppress(value) if isinstance(value, str) else value for key, value in spec.items()}
    kwargs = {"dest": spec["dest"], "help": spec["help"], "action": _ACTIONS[spec["kind"]]}
    if spec["kind"] == "version":
        kwargs["version"] = spec["version"]
    if spec["kind"] == "store":
        metavar = spec["metavar"]
        kwargs.update(nargs=spec["nargs"], const=spec["const"], type=_type_of(spec["type"]),
                      choices=spec["choices"], metavar=tuple(metavar) if isinstance(metavar, list) else metavar)
        if spec["option_strings"]:
            kwargs["required"] = spec["required"]
    if spec["kind"] in ("store", "store_true", "boolean_optional"):
        kwargs["default"] = spec["default"]
        if spec["kind"] == "boolean_optional":
            kwargs["required"] = spec["required"]
    if not spec["option_strings"]:  # a positional: its dest is its name
        name = kwargs.pop("dest")
        container.add_argument(name, **kwargs)
    else:
        flags = spec["option_strings"]
        if spec["kind"] == "boolean_optional":  # argparse adds each --no-FLAG itself
            flags = [f for f in flags if not (f.startswith("--no-") and "--" + f[5:] in flags)]
        container.add_argument(*flags, **kwargs)


def _fill(parser: argparse.ArgumentParser, spec: dict) -> None:
    containers = []
    for group in spec["groups"]:
        if group["title"] == parser._positionals.title:
            containers.append(parser._positionals)
        elif group["title"] == parser._optionals.title:
            containers.append(parser._optionals)
        else:
            containers.append(parser.add_argument_group(group["title"], group["description"]))
    for action in spec["actions"]:
        if action["kind"] != "help":  # add_help made it
            _add_action(containers[action["group"]], {k: v for k, v in action.items() if k != "group"})
    commands = spec.get("commands")
    if commands:
        sub = parser.add_subparsers(dest=commands["dest"], metavar=commands["metavar"])
        sub.required = commands["required"]
        for name, choice in commands["choices"].items():
            child = choice["parser"]
            kwargs = {"description": child["description"], "epilog": child["epilog"], "usage": child["usage"]}
            if choice["help"] is not None:
                kwargs["help"] = choice["help"]
            _fill(sub.add_parser(name, **kwargs), child)


def rebuild(spec: dict) -> argparse.ArgumentParser:
    """The parser :func:`describe` described, made with argparse alone."""
    top = spec["parser"]
    parser = Parser(prog=top["prog"], usage=top["usage"], description=top["description"], epilog=top["epilog"])
    _fill(parser, top)
    return parser


def read_spec() -> dict | None:
    """``parser_spec.json`` when it is there, readable and of this version; else None."""
    from jaxbvh import __version__

    try:
        spec = json.loads(SPEC_PATH.read_text())
    except (OSError, ValueError):
        return None
    return spec if isinstance(spec, dict) and spec.get("version") == __version__ else None


def answer(argv: list[str]) -> int | None:
    """The exit status when the front answers ``argv`` itself (help, version, a usage
    error, printed as argparse prints them), None when the command has to run."""
    spec = read_spec()
    if spec is None:
        return None
    try:
        rebuild(spec).parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxbvh`` console script: :func:`answer`, else the real tool."""
    status = answer(sys.argv[1:] if argv is None else list(argv))
    if status is not None:
        return status
    from jaxbvh.cli.app import main as run_command

    return run_command(argv)


def spec_text() -> str:
    """The text of ``parser_spec.json`` for the live parsers (key order kept: it is the
    order of the commands and options in ``--help``)."""
    return json.dumps(describe(), indent=1) + "\n"


def write_spec(path: Path = SPEC_PATH) -> Path:
    """Write :func:`describe` of the real parsers to ``path`` (a temporary file renamed
    into place)."""
    text = spec_text()
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


if __name__ == "__main__":  # the module as imported, not as __main__: one int_option class
    print(importlib.import_module("jaxbvh.cli.front").write_spec())
