"""The command line's face: ``--version``, a bare ``gpmpc``, and help (with its default) for every
argument of every command."""

from __future__ import annotations

import argparse

import pytest

from torch_gpmpc import __version__
from torch_gpmpc.cli import main
from torch_gpmpc.cli.parser import build_parser


def test_version(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"gpmpc {__version__}"


def test_a_bare_gpmpc_prints_help(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: gpmpc") and "run" in out and "reproduce" in out


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {"gpmpc": parser, **sub.choices}


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_argument_has_help_and_its_default(name):
    parser = _commands()[name]
    text = "".join(parser.format_help().split())  # help wraps lines anywhere
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction, argparse._VersionAction)):
            continue
        assert action.help, f"{name} {action.option_strings}: no help"
        default = action.default
        if isinstance(default, (int, float, str)) and not isinstance(default, bool):
            assert f"(default:{default})" in text, f"{name} {action.option_strings}: default {default!r} not shown"


def test_run_help_says_how_to_change_the_team_and_where_the_keys_are(capsys):
    text = " ".join(_commands()["run"].format_help().split())
    assert "num_agents" in text and "configuration reference" in text
