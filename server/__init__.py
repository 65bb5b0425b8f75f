"""kitti-eval as an HTTP service: upload predictions, get KITTI AP back, keep the history.

``create_app(Settings(...))`` builds the FastAPI application; ``uvicorn kitti_eval_server.main:app`` runs it configured
from ``KITTI_EVAL_*`` environment variables; ``kitti_eval_server.main.serve(argv)`` is ``kitti-eval serve``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .main import create_app, serve
    from .settings import Settings

__all__ = ["create_app", "serve", "Settings"]


def __getattr__(name: str) -> Any:
    """The public names, imported on first use: ``kitti-eval --help`` loads the service's commands
    (:mod:`kitti_eval_server.commands`) without the web framework."""
    if name in ("create_app", "serve"):
        from . import main

        return getattr(main, name)
    if name == "Settings":
        from .settings import Settings

        return Settings
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
