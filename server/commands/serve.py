"""``kitti-eval serve``: the HTTP service and its web page (the server extra). Everything after ``serve``
goes to the service's own parser (:func:`kitti_eval_server.main.serve`), unparsed by the command line's.

Before it imports the web application (2 s of CPU), the command starts the service's worker processes
(:func:`~kitti_eval_server.jobs.spawn.start_early`), so that they import and warm their kernels meanwhile; the
service takes them over when they are those it would start itself, and stops them otherwise."""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from typing import Any

from . import without_server_extra

__all__ = ["NAME", "add_parser", "run_argv"]

NAME = "serve"


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Listed for the help; the command line hands everything after ``serve`` to :func:`run_argv`."""
    return sub.add_parser(NAME, add_help=False, help="run the HTTP service and its web page (--help for its options)")


def _start_workers_early(argv: Sequence[str]) -> None:
    """Start the worker processes the service's settings ask for, from the options that change them (the
    service's own parser reads them all again). Best effort: anything unclear leaves it to the service."""
    from ..jobs.spawn import start_early
    from ..settings import Settings, serve_overrides

    early = argparse.ArgumentParser(add_help=False)
    early.add_argument("-h", "--help", action="store_true")
    for option in ("--data-dir", "--database-url", "--auth"):
        early.add_argument(option)
    early.add_argument("--upgrade", action="store_true")
    try:
        args, _ = early.parse_known_args(list(argv))
        settings = Settings(**serve_overrides(args.data_dir, args.database_url, args.auth, args.upgrade, os.environ))
    except (SystemExit, ValueError):
        return
    if args.help or settings.db_upgrade or not settings.worker_processes:
        return  # an upgrade goes first: a worker process refuses an older schema
    start_early(
        settings.worker_processes,
        1,
        settings.shutdown_grace_s,
        settings.data_dir.resolve(),
        settings.resolved_database_url,
    )


def run_argv(argv: Sequence[str]) -> int:
    try:
        from ..data_folder import private_files
        from ..jobs.spawn import discard_early
    except ImportError as e:
        return without_server_extra(NAME, e)
    # the data folder, the database and what the workers unpack are not readable by other users, from the start
    with private_files():
        try:  # the worker process started early goes whichever way this ends but a service taking it over
            try:
                _start_workers_early(argv)
                from ..main import serve
            except ImportError as e:
                return without_server_extra(NAME, e)
            return serve(list(argv))
        finally:
            discard_early()
