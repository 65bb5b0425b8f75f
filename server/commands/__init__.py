"""The service's commands of ``kitti-eval``: ``serve``, ``worker`` and ``admin``, one module each (its
``add_parser(sub)`` beside its ``run``), registered with the command line through the entry point group
``kitti_eval.commands`` (pyproject.toml). Building their parsers imports nothing of the service's dependencies;
running one without them says in one line how to install them."""

from __future__ import annotations

import sys

__all__ = ["INSTALL", "without_server_extra"]

INSTALL = "pip install 'kitti-eval[server]'"

#: this project's own packages: a module of theirs that cannot be found is a fault, not a missing extra
_OWN = frozenset({"kitti_eval", "kitti_eval_server"})


def without_server_extra(command: str, error: ImportError) -> int:
    """Say that ``kitti-eval COMMAND`` needs the server extra and how to install it (exit code 1), when
    ``error`` says that a package the service imports (fastapi, uvicorn, sqlalchemy, or one they need: anyio,
    pydantic, ...) is not installed; any other ImportError (a name missing from a module, a module of this
    project's missing) is a fault and raised as it is."""
    missing = (error.name or "").partition(".")[0]
    if not isinstance(error, ModuleNotFoundError) or not missing or missing in _OWN:
        raise error
    print(f"kitti-eval {command}: error: needs the server extra ({missing} is missing): {INSTALL}", file=sys.stderr)
    return 1
