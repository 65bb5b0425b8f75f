"""``kitti-eval``: the command line. Parses, loads, evaluates, prints; holds no evaluation logic. Exit codes: 0
success, 1 bad input (unreadable, unsafe or inconsistent files), 2 usage error, 3 a gate rule failed (``gate``), 4
over a benchmark's quota (``submit``), 5 a service could not be reached (:mod:`.remote`). Data goes to stdout (or
``--output``); warnings and progress go to stderr.

This module only builds the parser and dispatches: the main job (``--gt``/``--pred``) is :mod:`.evaluate`; each
command is a module whose ``add_parser(sub)`` adds its subparser (``run`` its default), in :data:`COMMANDS`; what
they share is :mod:`.common`; another package's commands come through an entry point (:mod:`.installed`)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

from ..errors import ConfigError, KittiEvalError, ServiceError
from . import (
    board,
    compare,
    demo,
    describe,
    errors,
    evaluate,
    frames,
    gate,
    inspect,
    installed,
    login,
    publish,
    submissions,
    submit,
    team,
    validate,
    withdraw,
)
from .common import EXIT_INPUT, EXIT_USAGE, PROG, config, limits_from, say, say_defaults
from .remote import report

__all__ = ["main", "entry", "COMMANDS"]

#: every command's ``add_parser(sub)``, in the order ``kitti-eval --help`` lists them: the installed ones last
COMMANDS: tuple[Callable[[Any], object], ...] = (
    *(cmd.add_parser for cmd in (demo, gate, compare, frames, inspect, errors, describe, validate, submit, login)),
    *(cmd.add_parser for cmd in (team, submissions, publish, withdraw, board)),
    *installed.parsers(),
)


def build_parser() -> argparse.ArgumentParser:
    """The program's parser: the main job's options, then one subparser per command."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Exact KITTI 3D object detection evaluation (2D, BEV, 3D, AOS; R11 and R40) on a CPU.",
        epilog="Exit codes: 0 ok, 1 bad input, 2 usage error, 3 a gate rule failed, 4 over a quota, 5 no service.",
    )
    evaluate.add_arguments(p)
    sub = p.add_subparsers(dest="command", metavar="COMMAND", title="commands (each has its own --help)")
    for add_parser in COMMANDS:
        add_parser(sub)
    say_defaults(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and (run_argv := installed.own_parser(argv[0])) is not None:
            return run_argv(argv[1:])
        parser = build_parser()
        args = parser.parse_args(argv)
        with limits_from(args):
            if args.command is not None:
                return int(args.run(args))
            return evaluate.run(parser, args)
    except SystemExit as e:  # argparse: usage errors exit 2, --help exits 0
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    except ConfigError as e:
        say(f"error: {e}")
        return EXIT_USAGE
    except ServiceError as e:
        return report(e)
    except KittiEvalError as e:  # InputError and the rest of the tree: bad input
        say(f"error: {e}")
        return EXIT_INPUT
    except OSError as e:
        say(f"error: {e.strerror or e}: {e.filename or ''}".rstrip(": "))
        return EXIT_INPUT
    except KeyboardInterrupt:
        return 130


def entry() -> None:
    """The console script: :func:`main`, then leave without tearing the interpreter down.

    Everything the command writes is flushed or closed by then; skipping the teardown of numba, llvmlite
    and the loaded arrays saves about 0.15 s on every run.
    """
    code = main()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed pipe: nothing more can be said
        code = code or EXIT_INPUT
    os._exit(code)


_parser, _config = build_parser, config  # the names this module had when it was one file, for code that uses them
