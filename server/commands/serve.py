"""``kitti-eval serve``: the HTTP service and its web page (the server extra). Everything after ``serve``
goes to the service's own parser, unparsed here."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from kitti_eval.errors import ConfigError

NAME = "serve"


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Listed for the help; :func:`kitti_eval.cli.main` hands everything after ``serve`` to :func:`run`."""
    return sub.add_parser(NAME, add_help=False, help="run the HTTP service and its web page (--help for its options)")


def run(argv: Sequence[str]) -> int:
    try:
        from kitti_eval_server.main import serve
    except ImportError as e:
        raise ConfigError(f"the service needs the server extra: pip install 'kitti-eval[server]' ({e})") from None
    return serve(list(argv))
