"""``kitti-eval publish``: one of one's scored submissions shown on the benchmark's board under a method's name.
Exit codes as ``submit``'s."""

from __future__ import annotations

import argparse
from typing import Any

from .common import EXIT_OK, say
from .remote import add_connection_arguments, client_of

__all__ = ["add_parser", "run"]

_EPILOG = "Exit codes: 0 done, 2 usage error or a request the service refuses, 5 the service could not be reached."


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "publish",
        help="show one of your scored submissions on the board under a method's name",
        description="Show one of your scored submissions on the benchmark's board (the phase it is in).",
        epilog=_EPILOG,
    )
    p.add_argument("submission", metavar="SUBMISSION_ID", help="the submission's id (kitti-eval submissions lists)")
    p.add_argument("--benchmark", required=True, metavar="NAME", help="the benchmark's name")
    p.add_argument("--method", metavar="TEXT", help="the method's name on the board (default: the file's name)")
    p.add_argument("--affiliation", metavar="TEXT", help="shown beside it (default: none)")
    p.add_argument("--link", metavar="URL", help="the method's paper or code (default: none)")
    p.add_argument(
        "--anonymous", action="store_true", help="show neither your name, affiliation nor link (default: off)"
    )
    add_connection_arguments(p, saved=True)
    p.set_defaults(run=run, quiet=False)
    return p


def run(args: argparse.Namespace) -> int:
    with client_of(args) as client:
        method = args.method or client.submission(args.benchmark, args.submission).view.get("filename") or "method"
        published = client.publish(
            args.benchmark,
            args.submission,
            method=method,
            anonymous=args.anonymous,
            affiliation=args.affiliation,
            link=args.link,
        )
        say(f"published: submission {published.id} is on the board of {args.benchmark} as {method!r}")
        say(f"the board: {client.service}/benchmarks/{args.benchmark}")
    return EXIT_OK
