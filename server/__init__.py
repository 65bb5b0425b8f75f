"""kitti-eval as an HTTP service: upload predictions, get KITTI AP back, keep the history.

``create_app(Settings(...))`` builds the FastAPI application; ``uvicorn kitti_eval_server.main:app`` runs it configured
from ``KITTI_EVAL_*`` environment variables; ``kitti_eval_server.main.serve(argv)`` is ``kitti-eval serve``.
"""

from __future__ import annotations

from .main import create_app, serve
from .settings import Settings

__all__ = ["create_app", "serve", "Settings"]
