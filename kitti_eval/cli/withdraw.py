"""``kitti-eval withdraw``: one of one's entries taken off the benchmark's board (the submission stays one's
own). Exit codes as ``submit``'s."""

from __future__ import annotations

import argparse
from typing import Any

from .common import EXIT_OK, say
from .remote import add_connection_arguments, client_of

__all__ = ["add_parser", "run"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "withdraw",
        help="take one of your entries off the board",
        description="Take one of your published submissions off the benchmark's board (it stays yours).",
        epilog=_EPILOG,
    )
    p.add_argument("submission", metavar="SUBMISSION_ID", help="the submission's id")
    p.add_argument("--benchmark", required=True, metavar="NAME", help="the benchmark's name")
    add_connection_arguments(p, saved=True)
    p.set_defaults(run=run, quiet=False)
    return p


def run(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        withdrawn = client.withdraw(args.benchmark, args.submission)
        say(f"withdrawn: submission {withdrawn.id} is off the board of {args.benchmark} (it stays yours)")
    return EXIT_OK
