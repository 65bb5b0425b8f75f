"""Server-rendered HTML pages over the same records as the JSON API, with their stylesheet and script."""

from .pages import STATIC_DIR
from .routes import router

__all__ = ["router", "STATIC_DIR"]
