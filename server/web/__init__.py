"""Server-rendered HTML pages over the same records as the JSON API, with their stylesheet and script."""

from .routes import STATIC_DIR, router

__all__ = ["router", "STATIC_DIR"]
