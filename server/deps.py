"""Dependencies shared by the routes: the service, the admin check, the response format."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Query, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from kitti_eval.report.render import OutputFormat

from .accounts import OPEN, Caller
from .auth import CALLER_KEY, client_of
from .errors import BadRequest, Forbidden, Unauthorized, echo
from .service import Service

__all__ = [
    "get_service",
    "ServiceDep",
    "get_caller",
    "CallerDep",
    "require_admin",
    "AdminDep",
    "AdminCallerDep",
    "BearerDep",
    "require_write",
    "WriteDep",
    "forbid",
    "negotiate_format",
    "FormatDep",
]


def get_service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


ServiceDep = Annotated[Service, Depends(get_service)]

_bearer = HTTPBearer(
    auto_error=False,
    description="the admin token (KITTI_EVAL_ADMIN_TOKEN, or the one generated in <data_dir>/admin-token); "
    "with KITTI_EVAL_AUTH=accounts also a user's token (kitti-eval admin token add USER)",
)


def get_caller(request: Request) -> Caller:
    """Who sends the request: in accounts mode the caller the token stands for (resolved by
    :class:`~server.auth.AuthMiddleware`), in open mode anyone."""
    caller: Caller = request.scope.get(CALLER_KEY, OPEN)
    return caller


CallerDep = Annotated[Caller, Depends(get_caller)]


def forbid(service: Service, request: Request, caller: Caller, what: str) -> Forbidden:
    """A refused use of a valid token, in the audit log."""
    service.accounts.audit(
        actor=caller.actor,
        action="token.forbidden",
        target=f"{request.method} {request.url.path}",
        outcome="refused",
        client=client_of(request.scope),
        detail=what,
    )
    return Forbidden(what)


def require_admin(
    service: ServiceDep,
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)],
) -> Caller:
    """Open mode: 401 without a bearer token, 403 with a wrong one. Accounts mode (the token checked
    already): 403 unless it is the admin token or an admin's token that may write."""
    caller = get_caller(request)
    if service.settings.auth == "accounts":
        if not caller.is_admin:
            raise forbid(service, request, caller, "this action is for admins")
        if not caller.can_write:
            raise forbid(service, request, caller, "this token is read-only")
        return caller
    if credentials is None:
        raise Unauthorized("this action needs the admin token: send 'Authorization: Bearer <token>'")
    if not hmac.compare_digest(credentials.credentials.encode(), service.admin_token.encode()):
        raise Forbidden("the admin token is not valid")
    return Caller("admin-token", is_admin=True)


AdminDep = Depends(require_admin)
#: the admin acting (for the audit log), as a route parameter
AdminCallerDep = Annotated[Caller, Depends(require_admin)]
#: the bearer credentials alone, for a route that checks them itself (after its parameters are validated)
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)]


def require_write(service: ServiceDep, request: Request) -> Caller:
    """403 for a read-only token."""
    caller = get_caller(request)
    if not caller.can_write:
        raise forbid(service, request, caller, "this token is read-only")
    return caller


WriteDep = Annotated[Caller, Depends(require_write)]

_MEDIA_TYPES = {
    "application/json": OutputFormat.JSON,
    "text/markdown": OutputFormat.MARKDOWN,
    "text/plain": OutputFormat.TABLE,
}


def _from_accept(accept: str) -> OutputFormat:
    best: tuple[float, OutputFormat] | None = None
    for part in accept.split(","):
        media, *params = (p.strip() for p in part.split(";"))
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        fmt = _MEDIA_TYPES.get(media.lower())
        if fmt is not None and q > 0 and (best is None or q > best[0]):
            best = (q, fmt)
    return best[1] if best else OutputFormat.JSON


def negotiate_format(
    request: Request,
    format: Annotated[
        str | None,
        Query(
            description="json (default), table (OpenPCDet's text) or markdown; overrides Accept "
            "(application/json, text/plain, text/markdown)"
        ),
    ] = None,
) -> OutputFormat:
    if format is not None:
        try:
            return OutputFormat(format)
        except ValueError:
            raise BadRequest(f"format must be one of json, table, markdown; got {echo(format)}") from None
    return _from_accept(request.headers.get("accept", ""))


FormatDep = Annotated[OutputFormat, Depends(negotiate_format)]
