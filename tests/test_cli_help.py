"""The CLI explains itself: every command has a description, every option help with its default, --version."""

from __future__ import annotations

import argparse

import pytest

from hil_server.cli import build_parser, main


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_command_and_option_explains_itself(name):
    cmd = _commands()[name]
    assert cmd.description and len(cmd.description) > 30, f"{name}: no description"
    missing = [
        a.option_strings or a.dest
        for a in cmd._actions
        if not isinstance(a, argparse._HelpAction) and a.help != argparse.SUPPRESS and not (a.help or "").strip()
    ]
    assert not missing, f"{name}: options without help: {missing}"
    text = cmd.format_help()
    for a in cmd._actions:  # a default that matters is shown (a flag's is that it is off: never "(default: True)")
        if isinstance(a, argparse._StoreConstAction):
            assert "%(default)" not in cmd.formatter_class(prog=name)._get_help_string(a), (name, a.dest)
            continue
        if a.option_strings and a.default not in (None, False, argparse.SUPPRESS) and a.help != argparse.SUPPRESS:
            assert "default" in (a.help or "") or f"default: {a.default}" in " ".join(text.split()), (name, a.dest)


def test_version_and_no_command(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("hazard-hil ")
    assert main([]) == 2  # no command: the overview, and a non-zero exit
