"""One error shape for every failure: ``{"error": {"code", "message"}}`` (plus ``frame``/``field`` when known).

Library errors (:mod:`kitti_eval.errors`) and the service's own (:class:`ApiError`) map to a status here and
nowhere else; an unexpected exception becomes a 500 whose body says nothing about the code that failed
(the traceback goes to the server log only).
"""

from __future__ import annotations

import errno
import logging
import sqlite3
from collections.abc import Mapping
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException

from kitti_eval.errors import (
    ArchiveError,
    ConfigError,
    InputError,
    KittiEvalError,
    UnknownFormatError,
    UnsafePickleError,
    WorkLimitError,
)

__all__ = [
    "ApiError",
    "NotFound",
    "Conflict",
    "Unauthorized",
    "Forbidden",
    "Sealed",
    "TooManyRequests",
    "Busy",
    "QueueFull",
    "TooManyQueued",
    "NotReady",
    "PayloadTooLarge",
    "DatabaseUnavailable",
    "InsufficientStorage",
    "StartupRefused",
    "fault_of",
    "ArchiveError",
    "BadRequest",
    "library_error_status",
    "MAX_MESSAGE_CHARS",
    "MAX_ECHO_CHARS",
    "clip",
    "echo",
    "error_body",
    "error_response",
    "install_error_handlers",
    "Gone",
    "is_api",
]

log = logging.getLogger("kitti_eval.server")


class ApiError(Exception):
    """A failure the service reports on purpose; subclasses fix the status and the code."""

    status_code = 400
    code = "bad_request"

    def __init__(self, message: str, *, headers: Mapping[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.headers = dict(headers or {})


class BadRequest(ApiError):
    """A request option is invalid (unknown format, malformed label, ...)."""

    status_code = 422
    code = "invalid_request"


class NotFound(ApiError):
    status_code = 404
    code = "not_found"


class Conflict(ApiError):
    status_code = 409
    code = "conflict"


class Gone(ApiError):
    """What was there is no more: an invitation used up, expired or revoked."""

    status_code = 410
    code = "gone"


class Unauthorized(ApiError):
    status_code = 401
    code = "unauthorized"

    def __init__(self, message: str) -> None:
        super().__init__(message, headers={"WWW-Authenticate": "Bearer"})


class Forbidden(ApiError):
    status_code = 403
    code = "forbidden"


class Sealed(Forbidden):
    """A per-frame view of a sealed ground truth: only aggregate results leave the service."""

    code = "sealed"


class TooManyRequests(ApiError):
    """Too many refused tokens from one client in a short time."""

    status_code = 429
    code = "too_many_requests"

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class Busy(ApiError):
    """Every evaluation slot and queue place is taken."""

    status_code = 503
    code = "busy"

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class QueueFull(Busy):
    """The job queue holds as many jobs, or as many bytes of their inputs, as the service keeps."""

    code = "queue_full"


class TooManyQueued(ApiError):
    """The caller has as many jobs queued or running as one caller may."""

    status_code = 429
    code = "too_many_queued"

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class NotReady(ApiError):
    status_code = 503
    code = "not_ready"

    def __init__(self, message: str, retry_after_s: int = 1) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class PayloadTooLarge(ApiError):
    status_code = 413
    code = "payload_too_large"


class DatabaseUnavailable(ApiError):
    """The database cannot be reached, or stays locked by another writer past the retry budget."""

    status_code = 503
    code = "database_unavailable"

    def __init__(self, message: str, retry_after_s: int = 2) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})


class InsufficientStorage(ApiError):
    """The data folder (scratch space, database) has no room left: nothing of the request is kept."""

    status_code = 507
    code = "insufficient_storage"


#: errno values of a full disk and of an exhausted quota
_NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT})
#: SQLite's primary result codes (the low byte of an extended one)
_SQLITE_BUSY, _SQLITE_LOCKED, _SQLITE_IOERR, _SQLITE_FULL, _SQLITE_CANTOPEN = 5, 6, 10, 13, 14


def fault_of(exc: BaseException, retry_after_s: int = 2) -> ApiError | None:
    """The service's error for a failure of the machine rather than of the request: a full disk (507
    ``insufficient_storage``) or a database that is down, restarting, or locked (503
    ``database_unavailable``); None for anything else (a bug: 500).

    The store retries a locked SQLite database (``KITTI_EVAL_DATABASE_BUSY_S``) before its error gets here."""
    if isinstance(exc, OSError):
        if exc.errno in _NO_SPACE:
            return InsufficientStorage("the server's data folder is out of space; nothing of this request was kept")
        return None
    if isinstance(exc, PoolTimeout):
        return DatabaseUnavailable("no database connection became free in time; retry later", retry_after_s)
    if not isinstance(exc, DBAPIError):
        return None
    cause = exc.orig
    if isinstance(cause, sqlite3.Error):
        primary = getattr(cause, "sqlite_errorcode", -1) & 0xFF
        if primary == _SQLITE_FULL:
            return InsufficientStorage("the server's database is out of disk space; nothing of this request was kept")
        if primary in (_SQLITE_BUSY, _SQLITE_LOCKED):
            return DatabaseUnavailable(
                "the database stayed locked by another writer past the retry budget (KITTI_EVAL_DATABASE_BUSY_S); "
                "retry later",
                retry_after_s,
            )
        if primary in (_SQLITE_IOERR, _SQLITE_CANTOPEN):
            return DatabaseUnavailable("the database file cannot be read or written; retry later", retry_after_s)
        return None
    if exc.connection_invalidated or isinstance(exc, OperationalError):
        return DatabaseUnavailable("the database is unavailable; retry later", retry_after_s)
    return None


class StartupRefused(ApiError):
    """The service will not start with these settings on this database; never an HTTP answer, it stops the
    startup with this message (and no traceback)."""

    status_code = 500
    code = "startup_refused"


#: library error -> (status, code); the first matching class wins
_LIBRARY_ERRORS: tuple[tuple[type[KittiEvalError], int, str], ...] = (
    (UnsafePickleError, 422, "unsafe_pickle"),
    (UnknownFormatError, 422, "unknown_format"),
    (ArchiveError, 422, "invalid_archive"),  # an uploaded zip/tar unsafe or unusable (traversal, links, bombs, ...)
    (WorkLimitError, 413, "over_work_limit"),  # more boxes or overlaps than the limits allow
    (InputError, 422, "invalid_input"),
    (ConfigError, 422, "invalid_config"),
    (KittiEvalError, 422, "invalid_input"),
)


def library_error_status(exc: KittiEvalError) -> tuple[int, str]:
    """The (status, code) a library error is answered with."""
    return next((s, c) for cls, s, c in _LIBRARY_ERRORS if isinstance(exc, cls))


#: longest message an error body carries: messages quote client input, which may be of any length
MAX_MESSAGE_CHARS = 1000
#: longest client value a message quotes in full (and the longest ``frame``/``field`` detail)
MAX_ECHO_CHARS = 100


def clip(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text``, or its first ``limit`` characters, an ellipsis and how long it was."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text)} characters in all)"


def echo(value: object, limit: int = MAX_ECHO_CHARS) -> str:
    """A client's value quoted in a message (as ``repr``), its first ``limit`` characters only when longer."""
    text = value if isinstance(value, str) else str(value)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}… ({len(text)} characters)"


def error_body(code: str, message: str, **details: Any) -> dict[str, Any]:
    """The error shape; the message and string details are cut to a bounded length whatever they quote."""
    err: dict[str, Any] = {"code": code, "message": clip(message)}
    err.update({k: clip(v, MAX_ECHO_CHARS) if isinstance(v, str) else v for k, v in details.items() if v is not None})
    return {"error": err}


def error_response(
    status: int, code: str, message: str, headers: Mapping[str, str] | None = None, **details: Any
) -> JSONResponse:
    return JSONResponse(error_body(code, message, **details), status_code=status, headers=dict(headers or {}))


#: statuses whose HTTP phrase is not the code the service's own error of that status uses
_SERVICE_CODES = {PayloadTooLarge.status_code: PayloadTooLarge.code}


def _status_code_name(status: int) -> str:
    """The code of an HTTPException's status: the service's own where it has one (so a 413 is
    ``payload_too_large`` whether the middleware or a route refuses the body), else the HTTP phrase."""
    if status in _SERVICE_CODES:
        return _SERVICE_CODES[status]
    try:
        return HTTPStatus(status).phrase.lower().replace(" ", "_").replace("-", "_")
    except ValueError:
        return "http_error"


def _location(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header"):
        where = {"body": "form field", "query": "query parameter", "path": "path parameter", "header": "header"}[
            parts[0]
        ]
        return f"{where} '{'.'.join(parts[1:])}'" if len(parts) > 1 else where
    return ".".join(parts)


def is_api(path: str) -> bool:
    """Paths a program calls (answered with JSON); the others are pages (answered with a page)."""
    return path.startswith("/v1/") or path in ("/v1", "/openapi.json", "/metrics")


async def _api_error(request: Request, exc: Exception) -> Response:
    """The one error shape; on a page (a route outside the API's schema: a refusal before the page's own code
    ran, such as its form's CSRF token) the app's error page, when it has one (``app.state.error_page``)."""
    assert isinstance(exc, ApiError)
    page = getattr(request.app.state, "error_page", None)
    route = request.scope.get("route")
    if page is not None and route is not None and getattr(route, "include_in_schema", True) is False:
        response: Response = page(request, exc)
        response.headers.update(exc.headers)
        return response
    return error_response(exc.status_code, exc.code, exc.message, exc.headers, **getattr(exc, "details", {}))


async def _library_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, KittiEvalError)
    status, code = library_error_status(exc)
    frame = getattr(exc, "frame", None)
    field = getattr(exc, "field", None)
    return error_response(status, code, str(exc), frame=frame, field=field)


async def _http_error(request: Request, exc: Exception) -> Response:
    """The one error shape; a browser asking for a page the service does not have (outside the API, HTML
    accepted) is shown the app's error page instead of JSON."""
    assert isinstance(exc, StarletteHTTPException)
    page = getattr(request.app.state, "error_page", None)
    if page is not None and not is_api(request.url.path) and "text/html" in request.headers.get("accept", ""):
        response: Response = page(request, exc)
        response.headers.update(exc.headers or {})
        return response
    message = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
    return error_response(exc.status_code, _status_code_name(exc.status_code), message, exc.headers)


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    problems = [f"{_location(tuple(e.get('loc', ())))}: {e.get('msg', 'invalid')}" for e in exc.errors()[:10]]
    return error_response(422, "invalid_request", "; ".join(problems) or "invalid request")


async def _fault(request: Request, exc: Exception) -> JSONResponse:
    """A database or disk failure: 503/507 when it is one the service knows (:func:`fault_of`), else a 500."""
    fault = fault_of(exc, _retry_after(request))
    if fault is None:
        return await _unexpected(request, exc)
    log.warning("%s on %s %s: %s", fault.code, request.method, request.url.path, exc)
    return error_response(fault.status_code, fault.code, fault.message, fault.headers)


def _retry_after(request: Request) -> int:
    service = getattr(request.app.state, "service", None)
    return int(getattr(getattr(service, "settings", None), "retry_after_s", 2))


#: what a 500 says: nothing of the failure itself (the log has it)
INTERNAL_ERROR_MESSAGE = "internal error; the server log has the details"


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(500, "internal_error", INTERNAL_ERROR_MESSAGE)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that turn every exception into the one error shape."""
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(KittiEvalError, _library_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    for fault in (OSError, DBAPIError, PoolTimeout):
        app.add_exception_handler(fault, _fault)
    app.add_exception_handler(Exception, _unexpected)
