"""One source of truth: every command-line option that sets a knob is made from the
library's Config (jaxbvh.cli.options), so its default and its checks are the Config's.

For every command and every option that sets a Config knob: the option has no default
of its own, a run without it gets the Config's default, ``--help`` states that default,
and the option refuses exactly the values the Config refuses, naming the option. An
option of another method is an error naming both. No mesh is loaded: only the parsers
and the Configs run.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import inspect
import re
from typing import Any

import pytest
from helpers import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxbvh.builders.configs import BOX_BUILDERS, BUILDERS, DEFAULT_BUILDER
from jaxbvh.cli import make_parser
from jaxbvh.cli.commands import optimize as optimize_command
from jaxbvh.cli.options import ConfigOptions, add_config_options, field_docs, shown, with_flags
from jaxbvh.cli.synopsis import synopsis
from jaxbvh.optimize import DEFAULT_METHOD, OPTIMIZERS, optimize, pipeline, reinsert, treelet
from jaxbvh.testing.plugin import examples
from jaxbvh.twolevel import objects as two_level_objects

README = REPO / "README.md"

#: the established options that set knobs, per command (dropping one, or offering a knob
#: under another name, fails)
ESTABLISHED = {
    "build": {"--max-leaf", "--bins", "--radius", "--morton-bits", "--ct", "--ci"},
    "stats": {"--max-leaf", "--bins", "--radius", "--morton-bits", "--ct", "--ci"},
    "optimize": {"--max-leaf", "--bins", "--radius", "--morton-bits", "--ct", "--ci", "--steps",
                 "--period", "--hottest", "--chains", "--max-passes", "--max-quench", "--max-iterations",
                 "--first-fraction", "--max-steps",
                 "--treelet-leaves", "--schedule", "--min-gain", "--split-axes", "--round-gain",
                 "--max-rounds"},
    "trace": {"--ct", "--ci"},
    "collapse": {"--method", "--max-children", "--max-leaf", "--bins", "--radius", "--morton-bits",
                 "--ct", "--ci"},
    "evolve": {"--population", "--generations", "--crossover", "--mutation", "--max-children"},
    "grasp": {"--trials", "--noise", "--deviations", "--rcl", "--objective"},
    "rebraid": {"--max-leaf", "--bins"},
    "export": set(),
    "batch": {"--max-leaf", "--bins", "--radius", "--morton-bits", "--ct", "--ci", "--steps",
              "--max-passes", "--max-iterations", "--treelet-leaves", "--first-fraction", "--round-gain", "--memory-mb",
              "--max-padding"},
}


def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser, _ = make_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


SUBPARSERS = subparsers()


def knob_actions(command: str) -> list[argparse.Action]:
    """The actions of ``command`` that set Config knobs (made by ConfigOptions)."""
    return [a for a in SUBPARSERS[command]._actions if hasattr(a, "config_options")]


def positionals(command: str) -> list[str]:
    """Placeholder values of ``command``'s required positional arguments (the first
    choice of one that has choices, as ``batch build``)."""
    return [a.choices[0] if a.choices else f"input{i}.npz" for i, a in enumerate(SUBPARSERS[command]._actions)
            if not a.option_strings and a.nargs in (None, "+")]


def parse(command: str, *argv) -> argparse.Namespace:
    """``argv`` parsed by ``command``'s parser; a usage error is a ValueError with
    argparse's message (no exit, nothing on stderr)."""
    sub = SUBPARSERS[command]

    def error(message):
        raise ValueError(message)

    original, sub.error = sub.error, error
    try:
        return sub.parse_args(positionals(command) + [str(a) for a in argv])
    finally:
        sub.error = original


def method_argv(options: ConfigOptions, method: str) -> list[str]:
    return [options.method_flag, method] if options.method_flag else []


#: every (command, flag, method) whose flag sets a knob of that method's Config
CASES = [(command, flag, method)
         for command in SUBPARSERS
         for action in knob_actions(command)
         for flag in action.option_strings if flag in action.config_options.knobs
         for method in dict.fromkeys(k.method for k in action.config_options.knobs[flag])]


def options_of(command: str, flag: str) -> ConfigOptions:
    return next(a.config_options for a in knob_actions(command) if flag in a.option_strings)


# ----------------------------------------------------------------------------------
# Defaults: the Config's, and no other
# ----------------------------------------------------------------------------------


@pytest.mark.parametrize("command", sorted(SUBPARSERS))
def test_every_knob_option_has_the_config_default_and_states_it(command):
    offered = set()
    for action in knob_actions(command):
        options = action.config_options
        flag = next(f for f in action.option_strings if f in options.knobs)
        offered.add(flag)
        assert action.default is argparse.SUPPRESS, flag  # no default of its own
        for knob in options.knobs[flag]:
            assert f"(default: {shown(knob.default)})" in action.help % {}, (command, flag, knob)
    # a run with no option gets every method's library default
    for options in {id(a.config_options): a.config_options for a in knob_actions(command)}.values():
        for method in options.methods:
            args = parse(command, *method_argv(options, method))
            # rebraid builds object BVHs: their builder's defaults (leaves up to OBJECT_MAX_LEAF)
            library = two_level_objects.object_builder(method=method) \
                if command == "rebraid" and method in BOX_BUILDERS \
                else type(options.bases[method])()
            assert options.config(method, args) == library, (command, method)
    assert ESTABLISHED[command] <= offered, ESTABLISHED[command] - offered
    # no hand-made option stands for a knob of the command's Configs (a second default)
    names = set()
    for options in {id(a.config_options): a.config_options for a in knob_actions(command)}.values():
        for base in options.bases.values():
            names |= field_names(base)
    for action in SUBPARSERS[command]._actions:
        if action.dest in names:
            assert hasattr(action, "config_options"), (command, action.option_strings)


def field_names(config) -> set[str]:
    """Names of every knob of ``config`` and of its nested Configs."""
    out = set()
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        out |= field_names(value) if dataclasses.is_dataclass(value) else {field.name}
    return out


def test_method_choices_default_to_the_library():
    for command in ("build", "stats", "collapse", "optimize"):
        action = next(a for a in SUBPARSERS[command]._actions if a.dest == "builder")
        assert action.default == DEFAULT_BUILDER and list(action.choices) == list(BUILDERS)
    action = next(a for a in SUBPARSERS["rebraid"]._actions if a.dest == "builder")
    assert action.default == two_level_objects.DEFAULT_BUILDER.method == "binned"
    # two-level BVHs are built from boxes: only the builders that need no triangles are offered
    assert list(action.choices) == list(BOX_BUILDERS) and "sbvh" not in action.help
    action = next(a for a in SUBPARSERS["optimize"]._actions if a.dest == "method")
    assert action.default == DEFAULT_METHOD == "pipeline" and list(action.choices) == list(OPTIMIZERS)
    assert inspect.signature(optimize).parameters["method"].default == DEFAULT_METHOD


@pytest.mark.parametrize("method", sorted(OPTIMIZERS))
def test_optimize_defaults_are_the_config_defaults(method):
    """With no option given, every method's config is its library Config's default
    (with the builder options' SAH constants, whose defaults are the same)."""
    assert optimize_command.make_config(parse("optimize", "--method", method)) == OPTIMIZERS[method].Config()


def test_treelet_max_passes_default_is_the_library_s():
    """The command line used to offer --max-passes 1000 for treelets, where the library says 8."""
    make = optimize_command.make_config
    assert make(parse("optimize", "--method", "treelet")).max_passes == treelet.DEFAULT_MAX_PASSES == 8
    assert make(parse("optimize", "--method", "treelet", "--max-passes", 3)).max_passes == 3


# ----------------------------------------------------------------------------------
# Checks: the option refuses what the Config refuses, and says which option
# ----------------------------------------------------------------------------------


def library_config(base, path: tuple, value):
    """``base`` (a Config) with the knob at ``path`` set to ``value``, as the library
    makes it (a nested Config from a dict of its knobs: ``pipeline.Config(treelet=dict(leaves=5))``)."""
    if len(path) == 1:
        return dataclasses.replace(base, **{path[0]: value})
    assert len(path) == 2, path
    return dataclasses.replace(base, **{path[0]: {path[1]: value}})


def knob_value(config, path: tuple):
    for name in path:
        config = getattr(config, name)
    return config


def library(options: ConfigOptions, flag: str, method: str, value):
    """``method``'s Config with every knob ``flag`` sets at ``value`` (the library's check)."""
    config = options.bases[method]
    for knob in options.knobs[flag]:
        if knob.method == method:
            config = library_config(config, knob.path, value)
    return config


def refused(options: ConfigOptions, flag: str, method: str, value) -> bool:
    try:
        library(options, flag, method, value)
    except ValueError:
        return True
    return False


def values(kind: type, choices) -> st.SearchStrategy:
    if kind is int:
        return st.integers(-5, 100)
    if kind is float:
        return st.one_of(st.floats(-3, 3), st.floats(allow_nan=True, allow_infinity=True),
                         st.sampled_from([0.0, 1.0, 0.5, 1e-300]))
    known = list(choices or ()) + ["axes", "3", "0", "-1", "nt"]
    return st.one_of(st.sampled_from(known), st.text(min_size=1, max_size=4))


@settings(max_examples=examples(300))
@given(case=st.sampled_from(CASES), data=st.data())
def test_an_option_refuses_exactly_what_its_config_refuses(case, data):
    command, flag, method = case
    options = options_of(command, flag)
    knobs = [k for k in options.knobs[flag] if k.method == method]
    if knobs[0].kind is bool:  # nothing to refuse
        config = options.config(method, parse(command, *method_argv(options, method), f"--no-{flag[2:]}"))
        assert all(knob_value(config, k.path) is False for k in knobs)
        return
    value = data.draw(values(knobs[0].kind, knobs[0].choices), label="value")
    text = repr(value) if isinstance(value, float) else str(value)
    try:
        args = parse(command, *method_argv(options, method), f"{flag}={text}")
        config = options.config(method, args)
    except ValueError as exc:
        assert refused(options, flag, method, value), (flag, value, str(exc))
        assert flag in str(exc), str(exc)
        return
    assert config == library(options, flag, method, value), (flag, value)  # not refused, and set


def test_an_option_of_another_method_is_an_error_naming_both():
    """``jaxbvh optimize TREE --hottest -1`` used to ignore --hottest (the default method
    is the pipeline); every option of a method-choosing command is checked so, but
    between methods of one family (the builders; hill climbing and annealing)."""
    checked = 0
    for command in SUBPARSERS:
        for options in {id(a.config_options): a.config_options for a in knob_actions(command)}.values():
            if options.method_flag is None:
                continue
            for flag, knobs in options.knobs.items():
                owners = {k.method for k in knobs}
                families = {options.families[owner] for owner in owners}
                for method in set(options.methods) - owners:
                    default = knobs[0].default  # a value its own method takes
                    sample = {int: 1, float: 0.5, str: "x"}[knobs[0].kind] if default is None else default
                    value = "--no-" + flag[2:] if knobs[0].kind is bool else f"{flag}={sample}"
                    args = parse(command, options.method_flag, method, value)
                    if method in options.renamed.get(flag, {}):  # an old spelling of its own knob
                        continue
                    if options.families[method] in families:  # shared: accepted, not used
                        assert options.config(method, args) == options.config(
                            method, parse(command, options.method_flag, method))
                        continue
                    with pytest.raises(ValueError, match=f"^{flag} does not apply to "
                                                         f"{options.method_flag} {method};.*{sorted(owners)[0]}"):
                        options.config(method, args)
                    checked += 1
    assert checked > 20
    make = optimize_command.make_config
    with pytest.raises(ValueError, match="--hottest does not apply to --method pipeline"):
        make(parse("optimize", "--hottest", "-1"))
    # annealing's options with hill climbing: accepted, and checked by annealing's Config
    assert make(parse("optimize", "--method", "hc", "--steps", 8, "--chains", 2)) == OPTIMIZERS["hc"].Config()
    with pytest.raises(ValueError, match=r"^--hottest must be a number >= 0, got -1.0 \(an option of --method sa\)"):
        make(parse("optimize", "--method", "hc", "--hottest", "-1"))


def test_builder_options_serve_every_builder():
    """One set of builder options for every builder (a knob of another builder is
    checked, not used), checked while parsing: a usage error before anything runs."""
    args = parse("build", "--builder", "sweep", "--bins", 4, "--radius", 3)
    assert options_of("build", "--bins").config("sweep", args) == BUILDERS["sweep"]()
    with pytest.raises(ValueError, match="argument --bins: --bins must be an integer >= 2"):
        parse("build", "--builder", "sweep", "--bins", 1)


@pytest.mark.parametrize("argv, message", [
    (["--first-fraction", 1.5], "--first-fraction must be a finite number in (0, 1], got 1.5"),
    (["--method", "treelet", "--treelet-leaves", 11], "--treelet-leaves must be an integer in [2, 10]"),
    (["--method", "pipeline", "--max-rounds", 0], "--max-rounds must be an integer >= 1"),
    (["--method", "reinsert", "--max-steps", 0, "--escalate", 0.5], "--max-steps must be an integer >= 1"),
    (["--method", "sa", "--steps", -1], "--steps must be an integer >= 0"),
    (["--method", "reinsert", "--max-iterations", -1], "--max-iterations must be"),
])
def test_a_refused_value_names_its_flag(argv, message):
    with pytest.raises(ValueError) as caught:
        optimize_command.make_config(parse("optimize", *argv))
    assert str(caught.value).startswith(message), str(caught.value)


def test_two_options_together_are_named_as_options():
    grasp_options = options_of("grasp", "--noise")
    with pytest.raises(ValueError, match="--noise or --deviations, not both"):
        grasp_options.config(None, parse("grasp", "--noise", "0.1", "--deviations", "2"))
    collapse_options = options_of("collapse", "--max-children")
    with pytest.raises(ValueError, match="4-wide.*--max-children 8"):
        collapse_options.config(None, parse("collapse", "--method", "qbvh", "--max-children", "8"))


@pytest.mark.parametrize("method, old, field", [
    ("sa", ["--iterations", 40], "steps"), ("sa", ["--max-passes", 7], "max_quench"),
    ("reinsert", ["--max-passes", 7], "max_iterations"), ("pipeline", ["--max-passes", 7], "max_iterations"),
])
def test_old_spellings_set_their_knobs_with_a_deprecation_warning(method, old, field):
    """Before every flag was its field's name, --iterations set annealing's steps and
    --max-passes the step limits of annealing, reinsertion and the pipeline: both still
    do, warning (docs/optimizers.md, Words); the current flag wins when both are given."""
    make = optimize_command.make_config
    with pytest.warns(DeprecationWarning, match=f"{old[0]}.* is deprecated: use --{field.replace('_', '-')}"):
        config = make(parse("optimize", "--method", method, *old))
    stage = config.reinsert if method == "pipeline" else config
    assert getattr(stage, field) == old[1]
    with pytest.warns(DeprecationWarning):
        config = make(parse("optimize", "--method", method, *old, f"--{field.replace('_', '-')}", 3))
    assert getattr(config.reinsert if method == "pipeline" else config, field) == 3
    assert make(parse("optimize", "--method", "treelet", "--max-passes", 7)).max_passes == 7  # no warning: its own
    assert "--iterations" not in SUBPARSERS["optimize"].format_help()  # --help shows the current spellings


def test_with_flags_renames_whole_words_only():
    renames = {"steps": "--iterations", "max_steps": "--max-steps"}
    assert with_flags("max_steps must be >= 1; steps too; search steps_x", renames) == \
        "--max-steps must be >= 1; --iterations too; search steps_x"


# ----------------------------------------------------------------------------------
# Methods and their stages
# ----------------------------------------------------------------------------------


def test_options_set_the_fields_of_the_chosen_method_and_its_stages():
    make = optimize_command.make_config
    args = parse("optimize", "--max-iterations", 5, "--treelet-leaves", 4, "--min-gain", 1e-3, "--no-split-axes",
                 "--first-fraction", 0.5, "--round-gain", 0.01, "--ct", 2)
    config = make(args)  # the default method: the pipeline
    assert isinstance(config, pipeline.Config)
    assert (config.reinsert.max_iterations, config.treelet.leaves, config.split_axes) == (5, 4, False)
    assert config.treelet.min_gain == config.reinsert.min_gain == 1e-3
    assert (config.reinsert.first_fraction, config.round_gain, config.ct, config.reinsert.ct) == (0.5, 0.01, 2, 2)
    assert config.treelet.max_passes == pipeline.DEFAULT_TREELET_PASSES  # not --max-iterations
    args = parse("optimize", "--method", "treelet", "--max-passes", 5, "--treelet-leaves", 4, "--min-gain", 1e-3,
                 "--no-split-axes", "--ct", 2)
    config = make(args)
    assert (config.max_passes, config.leaves, config.split_axes, config.ct) == (5, 4, False, 2)
    args = parse("optimize", "--method", "reinsert", "--max-iterations", 5, "--min-gain", 1e-3, "--no-split-axes",
                 "--first-fraction", 0.5, "--ct", 2)
    assert make(args) == reinsert.Config(max_iterations=5, min_gain=1e-3, split_axes=False, first_fraction=0.5,
                                         ct=2.0)


def test_annealing_schedule_by_name():
    """``--schedule`` offers the schedules by name (the knob's choices)."""
    action = next(a for a in SUBPARSERS["optimize"]._actions if "--schedule" in a.option_strings)
    assert set(action.choices) == {"kensler", "cosine", "exponential"}
    config = optimize_command.make_config(parse("optimize", "--method", "sa", "--schedule", "cosine",
                                                "--steps", 40, "--max-quench", 7))
    assert (config.schedule, config.steps, config.max_quench) == ("cosine", 40, 7)
    with pytest.raises(ValueError, match="invalid choice"):
        parse("optimize", "--method", "sa", "--schedule", "linear")


# ----------------------------------------------------------------------------------
# The helper itself
# ----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Inner:
    """Knobs.

    ``depth``: how deep to go, in :data:`levels`. ``mode``, ``label``: what to call it
    (``mode`` of :func:`a.b.c`).
    """

    depth: int = 3
    mode: str = dataclasses.field(default="fast", metadata=dict(choices=("fast", "slow")))
    label: str = "x"


@dataclasses.dataclass(frozen=True)
class Outer:
    """Outer knobs. ``scale``: a factor. ``sizes``: work sizes."""

    scale: float | None = None
    seed: Any = dataclasses.field(default=None, metadata=dict(type=int, help="a seed"))
    on: bool = True
    sizes: tuple = (1, 2)
    inner: Inner = dataclasses.field(default_factory=Inner)

    def __post_init__(self):
        if self.scale is not None and self.scale < 0:
            raise ValueError(f"scale must be >= 0, got {self.scale}")


def test_field_docs_read_the_house_docstring_style():
    docs = field_docs(Inner)
    assert docs == {"depth": "how deep to go, in levels", "mode": "what to call it (mode of c)",
                    "label": "what to call it (mode of c)"}


def test_the_helper_on_a_nested_config():
    with pytest.raises(TypeError, match="sizes"):  # a tuple has no command-line form
        ConfigOptions({"m": Outer})
    parser = argparse.ArgumentParser()
    options = add_config_options(parser, Outer, exclude=("sizes",), flags={"inner.label": "--name"}, name="m")
    assert set(options.knobs) == {"--scale", "--seed", "--on", "--depth", "--mode", "--name"}
    assert options.config(None, parser.parse_args([])) == Outer()
    args = parser.parse_args(["--scale", "0.5", "--no-on", "--depth", "4", "--mode", "slow", "--name", "y",
                              "--seed", "3"])
    assert options.config("m", args) == Outer(0.5, 3, False, inner=Inner(4, "slow", "y"))
    assert "how deep to go, in levels (default: 3)" in options.help("--depth")
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "medium"])
    with pytest.raises(SystemExit):
        parser.parse_args(["--scale", "big"])  # float from the annotation
    with pytest.raises(SystemExit):
        parser.parse_args(["--seed", "0.5"])  # int from the metadata's type
    with pytest.raises(ValueError, match="^--scale must be >= 0"):
        options.config(None, parser.parse_args(["--scale", "-1"]))
    # an instance gives the defaults
    instance = add_config_options(argparse.ArgumentParser(), Outer(scale=2.0), exclude=("sizes",), name="m")
    assert instance.defaults()[("scale",)] == 2.0 and "(default: 2)" in instance.help("--scale")


# ----------------------------------------------------------------------------------
# The command-line reference's synopsis
# ----------------------------------------------------------------------------------

DOCS_CLI = REPO / "docs" / "cli.md"
DOCS_HOOK = REPO / "docs" / "hooks" / "generate.py"


def test_docs_synopsis_is_the_parsers():
    """The docs' command-line reference asks for the synopsis, and the site's hook writes
    ``python -m jaxbvh.cli.synopsis``'s output there (so no copy of it can go stale)."""
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS_HOOK)  # needs no docs tools
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.expand(DOCS_CLI.read_text())
    section = page[page.index("## Synopsis"):]
    block = re.search(r"```text\n(.*?)\n```", section, re.S).group(1)
    assert block == synopsis(), "docs/cli.md's synopsis is not the parsers'"
    assert "<!-- gen:" not in page, "a generated part of docs/cli.md was left unexpanded"


def test_readme_has_no_stale_synopsis():
    """README points to the reference instead of copying the synopsis (a copy would drift)."""
    text = README.read_text()
    assert "jaxbvh COMMAND --help" not in text and "docs/cli.md" in text
