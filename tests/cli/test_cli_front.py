"""The console script's front answers help, the version and usage errors without JAX,
exactly as the real parsers would (jaxbvh.cli.front)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import pytest

from jaxbvh.cli import front, make_parser


def test_the_spec_file_is_the_live_parsers():
    """parser_spec.json is generated from the parsers (python -m jaxbvh.cli.front): a change
    to any option without regenerating it fails here."""
    assert front.SPEC_PATH.read_text() == front.spec_text()


def _subparsers(parser):
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_the_rebuilt_parsers_print_the_same_help(monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    real, _ = make_parser()
    quick = front.rebuild(front.read_spec())
    assert quick.format_help() == real.format_help()
    real_subs, quick_subs = _subparsers(real), _subparsers(quick)
    assert list(quick_subs) == list(real_subs)
    for name, parser in real_subs.items():
        assert quick_subs[name].format_help() == parser.format_help(), name


@pytest.mark.parametrize("argv", [["build", "--bins", "many"], ["trace", "--rays", "0"], ["frobnicate"],
                                  ["optimize"], ["build", "--builder", "octree"], ["stats", "--nope"]])
def test_usage_errors_read_the_same_from_the_front(argv, capsys):
    """Same exit status, same one line, as the real tool gives."""
    real, _ = make_parser()
    with pytest.raises(SystemExit) as exc:
        real.parse_args(argv)
    real_err = capsys.readouterr().err
    assert front.answer(argv) == exc.value.code == 2
    assert capsys.readouterr().err == real_err


def test_valid_command_lines_go_on_to_the_tool():
    assert front.answer(["build", "--bins", "8"]) is None
    assert front.answer(["build", "--max-leaf", "0"]) in (None, 2)  # a knob's own check: either side


_NO_JAX = """
import sys
from jaxbvh.cli import front
codes = [front.main(a) for a in (["--help"], ["--version"], ["build", "--help"], ["build", "--bins", "x"])]
print("CODES", codes, "jax" in sys.modules, "trimesh" in sys.modules)
"""


def test_help_version_and_usage_errors_import_no_jax():
    env = {k: v for k, v in os.environ.items() if k != "JAXBVH_CACHE"}
    done = subprocess.run([sys.executable, "-c", _NO_JAX], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "CODES [0, 0, 0, 2] False False" in done.stdout


def test_a_stale_or_missing_spec_takes_the_slow_path(monkeypatch, tmp_path):
    spec = front.read_spec()
    stale = tmp_path / "spec.json"
    stale.write_text(json.dumps(dict(spec, version="0.0.0")))
    monkeypatch.setattr(front, "SPEC_PATH", stale)
    assert front.read_spec() is None and front.answer(["--version"]) is None
    monkeypatch.setattr(front, "SPEC_PATH", tmp_path / "missing.json")
    assert front.answer(["--help"]) is None
    stale.write_text("{not json")
    monkeypatch.setattr(front, "SPEC_PATH", stale)
    assert front.answer(["--help"]) is None
