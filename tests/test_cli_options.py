"""Command-line options from the configs (jaxbvh.cli.options, ``jaxbvh optimize``): one
source of truth for every knob and default."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import pytest

from jaxbvh.cli.app import make_parser
from jaxbvh.cli.commands import optimize as command
from jaxbvh.cli.options import ConfigOptions, add_config_options, field_docs
from jaxbvh.optimize import OPTIMIZERS, pipeline, reinsert, treelet


def parse(*argv):
    parser, _ = make_parser()
    return parser.parse_args(["optimize", "tree.npz", *map(str, argv)])


def optimize_parser():
    parser, _ = make_parser()
    return next(a for a in parser._subparsers._group_actions[0].choices.values()
                if a.prog.endswith("optimize"))


@pytest.mark.parametrize("method", sorted(OPTIMIZERS))
def test_cli_defaults_are_the_config_defaults(method):
    """With no option given, every method's config is its library Config's default, and
    no config option has a default of its own on the command line."""
    args = parse("--method", method)
    assert command.make_config(args) == OPTIMIZERS[method].Config()
    for action in optimize_parser()._actions:
        if any(flag in command.OPTIONS.knobs for flag in action.option_strings):
            assert action.default is argparse.SUPPRESS, action.option_strings
    # the SAH constants come with the builder options: the same defaults as every Config
    assert (args.ct, args.ci) == (OPTIMIZERS[method].Config().ct, OPTIMIZERS[method].Config().ci)
    # the help states each Config default
    defaults = command.OPTIONS.defaults(method)
    assert defaults
    for flag, knobs in command.OPTIONS.knobs.items():
        for knob in knobs:
            if knob.method == method:
                assert f"(default: {_shown(defaults[knob.path])})" in command.OPTIONS.help(flag)


def _shown(value):
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "automatic"
    return f"{value:g}" if isinstance(value, float) else str(value)


def test_treelet_max_passes_default_is_the_library_s():
    """The command line used to offer --max-passes 1000 for treelets, where the library says 8."""
    assert command.make_config(parse("--method", "treelet")).max_passes == treelet.DEFAULT_MAX_PASSES == 8
    assert command.make_config(parse("--method", "treelet", "--max-passes", 3)).max_passes == 3


def test_options_set_the_fields_of_the_chosen_method_and_its_stages():
    args = parse("--max-passes", 5, "--treelet-leaves", 4, "--min-gain", 1e-3, "--no-split-axes",
                 "--first-fraction", 0.5, "--round-gain", 0.01, "--ct", 2)
    config = command.make_config(args)  # the default method: the pipeline
    assert isinstance(config, pipeline.Config)
    assert (config.reinsert.max_iterations, config.treelet.leaves, config.split_axes) == (5, 4, False)
    assert config.treelet.min_gain == config.reinsert.min_gain == 1e-3
    assert (config.reinsert.first_fraction, config.round_gain, config.ct, config.reinsert.ct) == (0.5, 0.01, 2, 2)
    assert config.treelet.max_passes == pipeline.DEFAULT_TREELET_PASSES  # not --max-passes
    args.method = "treelet"
    config = command.make_config(args)
    assert (config.max_passes, config.leaves, config.split_axes, config.ct) == (5, 4, False, 2)
    args.method = "reinsert"
    assert command.make_config(args) == reinsert.Config(max_iterations=5, min_gain=1e-3, split_axes=False,
                                                        first_fraction=0.5, ct=2.0)


@pytest.mark.parametrize("argv, flag", [
    (["--first-fraction", 1.5], "--first-fraction"),
    (["--method", "treelet", "--treelet-leaves", 11], "--treelet-leaves"),
    (["--method", "pipeline", "--max-rounds", 0], "--max-rounds"),
    (["--method", "reinsert", "--max-steps", 0, "--escalate", 0.5], "--max-steps"),
])
def test_a_refused_value_names_its_flag(argv, flag):
    with pytest.raises(ValueError, match=f"^{flag}: "):
        command.make_config(parse(*argv))


def test_annealing_schedule_by_name():
    """``--schedule`` offers the schedules by name."""
    action = next(a for a in optimize_parser()._actions if "--schedule" in a.option_strings)
    assert set(action.choices) == {"kensler", "cosine", "exponential"}
    config = command.make_config(parse("--method", "sa", "--schedule", "cosine", "--iterations", 40,
                                       "--max-passes", 7))
    assert (config.schedule, config.steps, config.max_quench) == ("cosine", 40, 7)
    with pytest.raises(SystemExit):
        parse("--method", "sa", "--schedule", "linear")


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
    assert options.config("m", parser.parse_args([])) == Outer()
    args = parser.parse_args(["--scale", "0.5", "--no-on", "--depth", "4", "--mode", "slow", "--name", "y",
                              "--seed", "3"])
    assert options.config("m", args) == Outer(0.5, 3, False, inner=Inner(4, "slow", "y"))
    assert "m (inner): how deep to go, in levels (default: 3)" in options.help("--depth")
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "medium"])
    with pytest.raises(SystemExit):
        parser.parse_args(["--scale", "big"])  # float from the annotation
    with pytest.raises(SystemExit):
        parser.parse_args(["--seed", "0.5"])  # int from the metadata's type
    with pytest.raises(ValueError, match="^--scale: scale must be >= 0"):
        options.config("m", parser.parse_args(["--scale", "-1"]))
