"""The service's commands of ``kitti-eval``: ``serve``, ``worker`` and ``admin``, one module each (its
``add_parser(sub)`` beside its ``run``), registered with the command line through the entry point group
``kitti_eval.commands`` (pyproject.toml). Building their parsers imports nothing of the service's dependencies;
running one without them says in one line how to install them."""

from __future__ import annotations

import sys

__all__ = ["INSTALL", "without_server_extra"]

INSTALL = "pip install 'kitti-eval[server]'"

#: the top-level modules of the server extra's packages (and of what they bring: pydantic, starlette)
_EXTRA_MODULES = frozenset(
    {
        "fastapi",
        "fastapi_offline",
        "jinja2",
        "multipart",
        "platformdirs",
        "prometheus_client",
        "psycopg",
        "pydantic",
        "pydantic_settings",
        "sqlalchemy",
        "starlette",
        "uvicorn",
    }
)


def without_server_extra(command: str, error: ImportError) -> int:
    """Say that ``kitti-eval COMMAND`` needs the server extra and how to install it (exit code 1), when
    ``error`` is a module of the extra missing; any other ImportError is a fault and raised as it is."""
    missing = (error.name or "").partition(".")[0]
    if missing not in _EXTRA_MODULES:
        raise error
    print(f"kitti-eval {command}: error: needs the server extra ({missing} is missing): {INSTALL}", file=sys.stderr)
    return 1
