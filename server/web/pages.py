"""What every page shares: the templates (Jinja2, in web/templates) and their filters, the static files, a page
rendered for its caller, the status a failure's page answers with, a queued job's state in words."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jinja2
from fastapi import Request
from fastapi.responses import Response
from starlette.exceptions import HTTPException
from starlette.templating import Jinja2Templates
from starlette.types import Scope

from kitti_eval.errors import KittiEvalError

from ..access.auth import CALLER_KEY, over_https, session_cookie
from ..access.policy import Caller
from ..errors import ApiError, library_error_status
from ..schemas import iso
from .svg import points_text

__all__ = [
    "templates",
    "STATIC_DIR",
    "render_page",
    "status_of",
    "queued_text",
    "ap_digits",
    "fmt",
    "full",
    "signed",
    "delta_class",
]

STATIC_DIR = Path(__file__).resolve().parent / "static"
_TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"


def ap_digits(metric: str) -> int:
    """Decimals of an AP as the CLI's table prints it (``kitti_eval.report.render``): 2 for AOS, 4 for the
    others."""
    return 2 if metric == "aos" else 4


def fmt(value: float | None, metric: str) -> str:
    """An AP of ``metric`` as the CLI prints it, ``-`` where there is none."""
    return "-" if value is None else f"{value:.{ap_digits(metric)}f}"


def full(value: float | None) -> str:
    """The exact value for a ``data-value`` attribute (``repr`` round-trips a float); empty for none."""
    return "" if value is None else repr(float(value))


def signed(value: float | None, metric: str) -> str:
    """A difference of two APs of ``metric``, with its sign and the AP's decimals."""
    return "-" if value is None else f"{value:+.{ap_digits(metric)}f}"


def delta_class(value: float | None) -> str:
    if value is None:
        return "delta none"
    return "delta pos" if value > 0 else "delta neg" if value < 0 else "delta zero"


def _env() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(_TEMPLATES_DIR),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters.update(fmt=fmt, full=full, signed=signed, delta_class=delta_class, iso=iso, points=points_text)
    return env


templates = Jinja2Templates(env=_env())


def status_of(exc: ApiError | KittiEvalError | HTTPException) -> int:
    """The status the JSON API answers the same failure with (the mapping lives in ``kitti_eval_server.errors``)."""
    if isinstance(exc, (ApiError, HTTPException)):
        return exc.status_code
    return library_error_status(exc)[0]


def render_page(request: Request, template: str, status_code: int = 200, /, **context: Any) -> Response:
    caller: Caller | None = request.scope.get(CALLER_KEY)
    context.setdefault("caller", caller)  # None in open mode: no sign-in, no sign-out
    return templates.TemplateResponse(request, template, context, status_code=status_code)


def queued_text(position: int | None) -> str:
    """A queued job's state as the pages say it: ``queued (3rd in line)`` (``position``: 1 for the next)."""
    if position is None:
        return "queued"
    suffix = "th" if 10 <= position % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(position % 10, "th")
    return f"queued ({position}{suffix} in line)"


def signed_in(response: Response, scope: Scope, session: str, hours: float, form_cookie: tuple[str, str]) -> Response:
    """``response`` setting the new web session's cookie (``session``, for ``hours``) and clearing the cookie of
    the form that opened it (``form_cookie``: its name and path): a sign-in's or a join's."""
    response.set_cookie(
        session_cookie(scope),
        session,
        max_age=int(hours * 3600),
        path="/",
        httponly=True,
        samesite="strict",
        secure=over_https(scope),
    )
    name, path = form_cookie
    response.delete_cookie(name, path=path, httponly=True, samesite="strict", secure=over_https(scope))
    return response
