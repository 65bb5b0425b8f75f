"""``kitti-eval serve``: the HTTP service and its web page (the server extra). Everything after ``serve``
goes to the service's own parser (:func:`kitti_eval_server.main.serve`), unparsed by the command line's."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from . import without_server_extra

__all__ = ["NAME", "add_parser", "run_argv"]

NAME = "serve"


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Listed for the help; the command line hands everything after ``serve`` to :func:`run_argv`."""
    return sub.add_parser(NAME, add_help=False, help="run the HTTP service and its web page (--help for its options)")


def run_argv(argv: Sequence[str]) -> int:
    try:
        from ..main import serve
    except ImportError as e:
        return without_server_extra(NAME, e)
    return serve(list(argv))
