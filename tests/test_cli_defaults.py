"""One source of truth: the command line's defaults and checks are the library's Configs'.

For every option of build, stats, grasp, evolve, collapse and rebraid that sets a Config
knob, the option's default is the knob's default, and the option refuses exactly the
values the Config refuses, naming the option. No mesh is loaded: only the parser and
the Configs run.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxbvh import cli, twolevel
from jaxbvh.builders.configs import BUILDERS, DEFAULT_BUILDER, BinnedConfig, PLOCConfig, make_config
from jaxbvh.cli.commands import _common
from jaxbvh.stochastic.evolve import EvolveConfig
from jaxbvh.stochastic.grasp import GraspConfig
from jaxbvh.wide.collapse import CollapseConfig

BUILDER_KNOBS = {"max_leaf", "bins", "radius", "morton_bits", "ct", "ci"}
# command -> (the Configs its options set, the knobs it must offer as options)
COMMANDS = {
    "build": (list(BUILDERS.values()), BUILDER_KNOBS),
    "stats": (list(BUILDERS.values()), BUILDER_KNOBS),
    "collapse": (list(BUILDERS.values()) + [CollapseConfig], BUILDER_KNOBS | {"method", "max_children"}),
    "rebraid": ([BinnedConfig], {"max_leaf", "bins"}),
    "grasp": ([GraspConfig], {"trials", "noise", "deviations", "rcl", "objective"}),
    "evolve": ([EvolveConfig], {"population", "generations", "crossover", "mutation", "max_children"}),
}


def subparser(command: str) -> argparse.ArgumentParser:
    parser, _ = cli.make_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[command]


def knob_defaults(classes) -> dict:
    """``{knob: default}`` over ``classes``; a knob several of them have has one default."""
    out = {}
    for cls in classes:
        for f in dataclasses.fields(cls):
            assert out.get(f.name, f.default) == f.default, f"{f.name}: {out[f.name]!r} vs {cls.__name__}"
            out[f.name] = f.default
    return out


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_defaults_to_its_knob(command):
    classes, offered = COMMANDS[command]
    defaults = knob_defaults(classes)
    seen = set()
    for action in subparser(command)._actions:
        if action.dest in defaults:
            assert action.default == defaults[action.dest], (command, action.option_strings)
            assert type(action.default) is type(defaults[action.dest])
            seen.add(action.dest)
    assert seen == offered  # an option dropped, or a knob offered under another name, fails too


@pytest.mark.parametrize("command", ["build", "stats", "collapse"])
def test_the_builder_option_defaults_to_the_library_builder(command):
    action = next(a for a in subparser(command)._actions if a.dest == "builder")
    assert action.default == DEFAULT_BUILDER == type(make_config()).method
    assert list(action.choices) == list(BUILDERS)


def test_rebraid_defaults_are_the_two_level_builder():
    """rebraid's options default to :func:`jaxbvh.twolevel.build`'s (whose builder is binned)."""
    library = {name: p.default for name, p in inspect.signature(twolevel.build).parameters.items()}
    dests = {"builder": "method", "max_leaf": "max_leaf", "bins": "bins", "threshold": "threshold",
             "budget": "budget", "top_bins": "top_bins", "overlap": "overlap", "estimate": "estimate"}
    options = {a.dest: a.default for a in subparser("rebraid")._actions}
    for dest, name in dests.items():
        assert options[dest] == library[name], dest


# ----------------------------------------------------------------------------------
# The option refuses what the Config refuses, and says which option
# ----------------------------------------------------------------------------------


def refused(config_class, **values) -> bool:
    try:
        config_class(**values)
    except ValueError:
        return True
    return False


@settings(max_examples=60, deadline=None)
@given(knob=st.sampled_from(["max_leaf", "bins", "radius", "morton_bits"]), value=st.integers(-3, 70))
def test_builder_options_are_checked_while_parsing_by_the_config(knob, value):
    cls = PLOCConfig if knob in ("radius", "morton_bits") else BinnedConfig
    parser = subparser("build")
    parser.error = lambda message: (_ for _ in ()).throw(ValueError(message))  # no exit, no stderr
    try:
        args = parser.parse_args([_common.flag(knob), str(value)])
    except ValueError as exc:
        assert refused(cls, **{knob: value})
        assert _common.flag(knob) in str(exc)
    else:
        assert not refused(cls, **{knob: value})
        assert getattr(args, knob) == value


def numbers():
    return st.one_of(st.integers(-3, 120), st.floats(-2, 2, allow_nan=False), st.just(math.inf))


@settings(max_examples=80, deadline=None)
@given(command=st.sampled_from(["grasp", "evolve"]), data=st.data())
def test_run_time_options_are_checked_by_the_config(command, data):
    """grasp and evolve check in run() through their Config: a bad value is a one-line
    ValueError naming the option (``--population``, not ``population``)."""
    config_class = COMMANDS[command][0][0]
    knob = data.draw(st.sampled_from(sorted(COMMANDS[command][1] - {"rcl", "objective"})))
    value = data.draw(numbers())
    args = subparser(command).parse_args(["mesh.obj"])
    setattr(args, knob, value)
    try:
        config = _common.config_from_args(config_class, args)
    except ValueError as exc:
        assert refused(config_class, **{knob: value})
        assert _common.flag(knob) in str(exc)
    else:
        assert getattr(config, knob) == value


def test_two_options_together_are_named_as_options():
    args = subparser("grasp").parse_args(["mesh.obj", "--noise", "0.1", "--deviations", "2"])
    with pytest.raises(ValueError, match="--noise or --deviations, not both"):
        _common.config_from_args(GraspConfig, args)
    args = subparser("collapse").parse_args(["tree.npz", "--method", "qbvh", "--max-children", "8"])
    with pytest.raises(ValueError, match="4-wide.*--max-children 8"):
        _common.config_from_args(CollapseConfig, args)
