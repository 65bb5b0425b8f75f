"""Dependencies shared by the routes: the service, the admin check, the response format."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Query, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from kitti_eval.report.render import OutputFormat

from .errors import BadRequest, Forbidden, Unauthorized, echo
from .service import Service

__all__ = ["get_service", "ServiceDep", "require_admin", "AdminDep", "negotiate_format", "FormatDep"]


def get_service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


ServiceDep = Annotated[Service, Depends(get_service)]

_bearer = HTTPBearer(
    auto_error=False,
    description="the admin token (KITTI_EVAL_ADMIN_TOKEN, or the one generated in <data_dir>/admin-token)",
)


def require_admin(
    service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)]
) -> None:
    """401 without a bearer token, 403 with a wrong one."""
    if credentials is None:
        raise Unauthorized("this action needs the admin token: send 'Authorization: Bearer <token>'")
    if not hmac.compare_digest(credentials.credentials.encode(), service.admin_token.encode()):
        raise Forbidden("the admin token is not valid")


AdminDep = Depends(require_admin)

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
