"""The command line's layout: one module per command with its parser and its handler side by side, and an
entry module that only builds the parser from them and dispatches."""

from __future__ import annotations

import argparse
import ast
import importlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import kitti_eval.cli as cli
import kitti_eval_server.commands as service_commands
from kitti_eval.cli import installed

CLI = Path(cli.__file__).resolve().parent
#: the service's commands, in its own package and found through the entry point group kitti_eval.commands
SERVICE_COMMANDS = Path(service_commands.__file__).resolve().parent
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
    "team",
    "submissions",
    "publish",
    "withdraw",
    "board",
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
    service = {"serve", "worker", "admin"}
    for name, parser in commands.items():
        package = "kitti_eval_server.commands" if name in service else "kitti_eval.cli"
        module = importlib.import_module(f"{package}.{name}")
        assert Path(module.__file__ or "").parent == (SERVICE_COMMANDS if name in service else CLI)
        assert module.add_parser in cli.COMMANDS
        if name != "serve":  # serve's arguments go to the service's own parser, unparsed
            assert parser.get_default("run") is module.run
    # remote: what the client commands share; installed: the commands other packages add
    shared = {"__init__", "__main__", "common", "evaluate", "remote", "installed"}
    assert {p.stem for p in CLI.glob("*.py")} == {*COMMAND_NAMES, *shared} - service
    # process: the entry of a worker's child process (python -m kitti_eval_server.commands.process), not a command
    assert {p.stem for p in SERVICE_COMMANDS.glob("*.py")} == {*service, "__init__", "process"}


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


def test_the_service_commands_come_through_their_entry_point() -> None:
    """``serve``, ``worker`` and ``admin`` are registered by the service's package under the group
    ``kitti_eval.commands``; the command line finds them there, and their options' help states the defaults."""
    from importlib.metadata import entry_points

    points = {p.name: p.value for p in entry_points(group=installed.GROUP)}
    assert points == {name: f"kitti_eval_server.commands.{name}" for name in ("serve", "worker", "admin")}
    assert list(installed.commands()) == ["serve", "worker", "admin"]
    assert installed.own_parser("serve") is importlib.import_module("kitti_eval_server.commands.serve").run_argv
    assert installed.own_parser("admin") is None and installed.own_parser("--gt") is None
    admin = _subparsers(cli.build_parser())["admin"]
    jobs = _subparsers(_subparsers(admin)["jobs"])["list"]
    (limit,) = [a for a in jobs._actions if "--limit" in a.option_strings]
    assert limit.help == "default: %(default)s" and limit.default == 50


#: run in a new interpreter: the command line with the modules ``hidden`` made unimportable
_WITHOUT = """
import sys
hidden = {hidden!r}

class Hide:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in hidden:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)

sys.meta_path.insert(0, Hide())
from kitti_eval.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _without(hidden: set[str], *argv: str) -> subprocess.CompletedProcess[str]:
    code = _WITHOUT.format(hidden=hidden)
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    "hidden",
    [
        {"fastapi", "uvicorn", "sqlalchemy", "pydantic", "pydantic_settings"},  # the extra's packages
        {"anyio", "starlette"},  # what they bring (an install where only these are missing)
        {"kitti_eval_server"},  # the service's package itself
    ],
)
def test_without_the_server_extra_the_service_commands_say_how_to_install_it(hidden: set[str]) -> None:
    """Without the server extra's packages (or without the service's package at all), ``kitti-eval --help`` still
    lists the service's commands, and each says in one line how to install what it needs: exit 1, no traceback."""
    listed = _without(hidden, "--help")
    assert listed.returncode == 0, listed.stderr
    names = [line.split()[0] for line in listed.stdout.splitlines() if line[:4] == "    " and line[4:5].isalpha()]
    assert names[-3:] == ["serve", "worker", "admin"]
    for argv in (["serve", "--port", "0"], ["worker", "--processes", "1"], ["admin", "user", "list"]):
        proc = _without(hidden, *argv)
        assert proc.returncode == 1 and proc.stdout == "", (argv, proc.stderr)
        (line,) = proc.stderr.splitlines()
        assert line.startswith(f"kitti-eval {argv[0]}: error: ") and "Traceback" not in proc.stderr
        assert line.endswith("pip install 'kitti-eval[server]'"), line
    evaluated = _without(hidden, "describe", str(Path(__file__).resolve().parents[1] / "golden"))
    assert "server extra" not in evaluated.stderr  # the library's own commands do not ask for it


def test_a_fault_is_not_taken_for_a_missing_extra(capsys) -> None:
    """Only a package the project does not hold being absent is a missing extra: a module of the project's own
    that cannot be found, or a name missing from a module, is raised as the fault it is."""
    from kitti_eval_server.commands import without_server_extra

    own = ModuleNotFoundError("No module named 'kitti_eval_server.gone'", name="kitti_eval_server.gone")
    renamed = ImportError("cannot import name 'serve' from 'kitti_eval_server.main'", name="kitti_eval_server.main")
    for fault in (own, renamed, ImportError("no name at all")):
        with pytest.raises(ImportError) as raised:
            without_server_extra("serve", fault)
        assert raised.value is fault
    assert without_server_extra("admin", ModuleNotFoundError("No module named 'anyio'", name="anyio")) == 1
    assert capsys.readouterr().err == (
        "kitti-eval admin: error: needs the server extra (anyio is missing): pip install 'kitti-eval[server]'\n"
    )


def test_an_entry_point_whose_package_is_gone_is_left_out_and_a_broken_one_is_said(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A command registered by a package since removed is left out (a service command then stands in as missing);
    one whose module is there but imports something that is not is a fault of that package, raised as it is."""
    from importlib.metadata import EntryPoint

    (tmp_path / "broken_plugin.py").write_text("import a_module_nobody_has\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    gone = [EntryPoint("serve", "a_package_removed.commands.serve", installed.GROUP)]
    broken = [EntryPoint("tally", "broken_plugin", installed.GROUP)]
    for points, outcome in ((gone, None), (broken, "a_module_nobody_has")):
        monkeypatch.setattr(installed, "entry_points", lambda group, points=points: points)
        installed.commands.cache_clear()
        try:
            if outcome is None:
                assert installed.commands() == {}
                assert installed.own_parser("serve") is not None  # the stand-in that says how to install it
            else:
                with pytest.raises(ModuleNotFoundError) as raised:
                    installed.commands()
                assert raised.value.name == outcome
        finally:
            installed.commands.cache_clear()
