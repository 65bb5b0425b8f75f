"""``kitti-eval login``: the token the client (``submit``, ``--service``) sends to a service, checked against it
and saved for it in the user's config folder, readable by the user only; says which user the token is."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from ..errors import ConfigError
from .common import EXIT_OK, say
from .remote import add_connection_arguments

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "login",
        help="save the token that 'submit' and '--service' send to a service",
        description="Check a token against the service and save it for it, readable by you only, in the "
        "user's config folder ($KITTI_EVAL_CONFIG_DIR instead when set). The token is read from the terminal "
        "without echo, or from stdin's first line. $KITTI_EVAL_TOKEN, when set, is sent instead of a saved one.",
    )
    add_connection_arguments(p, required=True)
    p.set_defaults(run=run, quiet=False)
    return p


def run(args: argparse.Namespace) -> int:
    from ..client_config import config_dir, save_token

    config_dir()  # a folder to save it in (or the sentence naming the settings), before the token is asked for
    if sys.stdin.isatty():
        import getpass

        token = getpass.getpass(f"token for {args.service}: ")
    else:
        token = sys.stdin.readline()
    token = token.strip()
    if not token:
        raise ConfigError("no token given")
    from ..client import Client, Retries

    allow_http = True if args.allow_http else None
    with Client(args.service, token, retries=Retries(within_s=args.retry_for), allow_http=allow_http) as client:
        me = client.whoami()  # 401 for a token the service does not know
    path = save_token(args.service, token)
    read_only = ", read-only (it may read and gate, not submit nor store an evaluation)" if me["read_only"] else ""
    say(f"the token is {me['user']}'s{read_only}: saved in {path} for {args.service}")
    return EXIT_OK
