"""The commands that installed packages add to ``kitti-eval``: the entry points of the group
``kitti_eval.commands``, each naming a module with an ``add_parser(sub)`` (as the library's own commands have)
and, for a command that parses its own arguments, a ``run_argv(argv)`` that gets everything after its name.

The service's commands (``serve``, ``worker``, ``admin``) come this way from the service's package, so the
library imports nothing of the service. Where they cannot be found (the service's package is not installed),
``kitti-eval --help`` still lists them and running one says in one line how to install them.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points
from typing import Any

from .common import EXIT_INPUT, PROG

__all__ = ["GROUP", "SERVICE_COMMANDS", "INSTALL", "commands", "parsers", "own_parser"]

#: the entry point group a package registers its commands under
GROUP = "kitti_eval.commands"
#: the service's commands, as the help lists them where the service is not installed
SERVICE_COMMANDS = {
    "serve": "run the HTTP service and its web page",
    "worker": "run the service's evaluations in worker processes",
    "admin": "accounts, projects, tokens, ground truths and jobs of the service",
}
INSTALL = "pip install 'kitti-eval[server]'"


@functools.cache
def commands() -> dict[str, Any]:
    """The installed commands by name, loaded, the service's first in the order of the help; a command whose
    module cannot be found (its package was removed) is left out, and a service command stands in as missing."""
    found: dict[str, Any] = {}
    for point in entry_points(group=GROUP):
        try:
            found[point.name] = point.load()
        except ModuleNotFoundError as e:  # the package that registered it is gone (or has no such module now)
            if not e.name or not f"{point.module}.".startswith(f"{e.name}."):
                raise  # a module it imports is missing: its own fault, said as it is

    order = [*(n for n in SERVICE_COMMANDS if n in found), *sorted(n for n in found if n not in SERVICE_COMMANDS)]
    return {name: found[name] for name in order}


def _missing(name: str) -> Callable[[Sequence[str]], int]:
    def run(argv: Sequence[str]) -> int:
        missing = "no installed package provides it; an editable install older than its entry point: install again"
        print(f"{PROG} {name}: error: needs the server extra ({missing}): {INSTALL}", file=sys.stderr)
        return EXIT_INPUT

    return run


def _listed(name: str) -> Callable[[Any], argparse.ArgumentParser]:
    def add_parser(sub: Any) -> argparse.ArgumentParser:
        return sub.add_parser(name, add_help=False, help=f"{SERVICE_COMMANDS[name]} (needs the server extra)")

    return add_parser


def parsers() -> list[Callable[[Any], object]]:
    """Every installed command's ``add_parser``, and a stand-in for each of the service's that is not installed."""
    found = commands()
    missing = [_listed(name) for name in SERVICE_COMMANDS if name not in found]
    return [*(command.add_parser for command in found.values()), *missing]


def own_parser(name: str) -> Callable[[Sequence[str]], int] | None:
    """How the command ``name`` runs when it parses its own arguments (everything after its name), or says that
    it is not installed; None for every other name."""
    command = commands().get(name)
    if command is not None:
        return getattr(command, "run_argv", None)
    return _missing(name) if name in SERVICE_COMMANDS else None
