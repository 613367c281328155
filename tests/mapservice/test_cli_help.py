"""Every flag and positional of every `mapservice` subcommand has help text."""

from __future__ import annotations

import argparse

from mapservice.cli import build_parser


def walk(parser: argparse.ArgumentParser, path: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, f"{path} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield path, action


def test_every_cli_argument_has_help() -> None:
    """No argument of any subcommand lacks a help string (hidden ones are SUPPRESSed)."""
    missing = [
        f"{path} {'/'.join(a.option_strings) or a.dest}"
        for path, a in walk(build_parser(), "mapservice")
        if not a.help
    ]
    assert missing == []
