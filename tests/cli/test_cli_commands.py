"""The command line's layout: one module per command with its parser and its handler side by side, and an
entry module that only builds the parser from them and dispatches."""

from __future__ import annotations

import argparse
import ast
import importlib
from pathlib import Path
from typing import Any

import pytest

import kitti_eval.cli as cli

CLI = Path(cli.__file__).resolve().parent
COMMAND_NAMES = [
    "demo",
    "gate",
    "compare",
    "frames",
    "inspect",
    "errors",
    "describe",
    "validate",
    "submit",
    "login",
    "serve",
    "worker",
    "admin",
]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


def test_every_command_is_a_module_holding_its_parser_and_its_handler() -> None:
    commands = _subparsers(cli.build_parser())
    assert list(commands) == COMMAND_NAMES
    for name, parser in commands.items():
        module = importlib.import_module(f"kitti_eval.cli.{name}")
        assert Path(module.__file__ or "").parent == CLI
        assert module.add_parser in cli.COMMANDS
        if name != "serve":  # serve's arguments go to the service's own parser, unparsed
            assert parser.get_default("run") is module.run
    shared = {"__init__", "__main__", "common", "evaluate", "remote"}  # remote: what the client commands share
    assert {p.stem for p in CLI.glob("*.py")} == {*COMMAND_NAMES, *shared}


def test_the_entry_module_only_builds_and_dispatches() -> None:
    """No option is declared in the entry module and no command's work is done there."""
    source = (CLI / "__init__.py").read_text(encoding="utf-8")
    assert len(source.splitlines()) < 110
    tree = ast.parse(source)
    calls = {
        node.func.attr for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
    }
    assert "add_argument" not in calls and "add_argument_group" not in calls
    functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
    assert functions == {"build_parser", "main", "entry"}


def test_a_command_registers_with_one_entry_in_the_list(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """A module outside the package with an ``add_parser(sub)`` joins the help, the parser and the dispatch by
    being added to ``COMMANDS``."""
    seen: list[Any] = []

    def add_parser(sub: Any) -> argparse.ArgumentParser:
        p = sub.add_parser("tally", help="count things")
        p.add_argument("--token")
        p.set_defaults(run=lambda args: seen.append(args.token) or 7)
        return p

    monkeypatch.setattr(cli, "COMMANDS", (*cli.COMMANDS, add_parser))
    assert cli.main(["tally", "--token", "t0"]) == 7
    assert seen == ["t0"]
    assert cli.main(["--help"]) == 0
    assert "tally               count things" in capsys.readouterr().out
    assert list(_subparsers(cli.build_parser())) == [*COMMAND_NAMES, "tally"]


def test_the_old_names_still_build_the_parser_and_the_config() -> None:
    from kitti_eval.core.protocol import EvalConfig

    args = cli._parser().parse_args(["--gt", "g", "--pred", "p", "--classes", "Car", "--protocol", "openpcdet"])
    config = cli._config(args)
    assert isinstance(config, EvalConfig)
    assert config.classes == ("Car",) and config.protocol.name == "openpcdet"
