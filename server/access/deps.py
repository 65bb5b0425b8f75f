"""Dependencies shared by the routes: the access each route declares (and the caller it is
admitted as, decided by :class:`~kitti_eval_server.access.policy.Policy`), the response format."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from functools import partial
from typing import Annotated

import anyio.to_thread
from fastapi import Depends, Query, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from kitti_eval.report.render import OutputFormat

from ..errors import BadRequest, Forbidden, echo
from .audit import Audit
from .auth import CALLER_KEY, client_of
from .policy import CSRF_HEADER, SAFE_METHODS, Access, Caller, Policy

__all__ = [
    "get_policy",
    "require_public",
    "require_anyone",
    "require_reader",
    "require_writer",
    "require_admin",
    "require_scraper",
    "PublicCaller",
    "AnyoneCaller",
    "ReaderCaller",
    "WriterCaller",
    "AdminCaller",
    "ScraperCaller",
    "negotiate_format",
    "FormatDep",
]


def get_policy(request: Request) -> Policy:
    policy: Policy = request.app.state.policy
    return policy


_bearer = HTTPBearer(
    auto_error=False,
    description="the admin token (KITTI_EVAL_ADMIN_TOKEN, or the one generated in <data_dir>/admin-token); "
    "with KITTI_EVAL_AUTH=accounts also a user's token (kitti-eval admin token add USER)",
)
_FORMS = ("application/x-www-form-urlencoded", "multipart/form-data")
#: the most fields and files a page form sends (the upload form: one file and a few fields)
FORM_MAX_FIELDS = 16


async def _csrf_sent(request: Request, policy: Policy, caller: Caller) -> tuple[str | None, bool]:
    """The CSRF token a web session's change carries: the X-CSRF-Token header, else a form's ``csrf`` field
    (read once here; the route's own ``request.form()`` gets the same parsed form)."""
    if not policy.checks_csrf(caller) or request.method.upper() in SAFE_METHODS:
        return None, False
    sent = request.headers.get(CSRF_HEADER)
    if sent is not None:
        return sent, True
    if request.headers.get("content-type", "").split(";")[0].strip().lower() in _FORMS:
        form = await request.form(max_files=1, max_fields=FORM_MAX_FIELDS)
        value = form.get("csrf")
        sent = value if isinstance(value, str) else None
    return sent, False


def _decider(access: Access) -> Callable[..., Awaitable[Caller]]:
    """The dependency a route declares its access with: the caller the door resolved (or open mode's
    everyone, or accounts mode's anonymous reader), admitted by the policy for ``access``, or 401/403. A
    refused use of a valid token goes to the audit log."""

    async def decide(
        request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)]
    ) -> Caller:
        policy = get_policy(request)
        client = client_of(request.scope)
        caller: Caller | None = request.scope.get(CALLER_KEY)
        if caller is None:
            caller = policy.without_token(client)
        csrf, in_header = await _csrf_sent(request, policy, caller)
        try:
            admitted = policy.admit(
                access,
                caller,
                method=request.method,
                bearer=credentials.credentials if credentials is not None else None,
                csrf=csrf,
                header=in_header,
            )
        except Forbidden as e:
            if policy.audits_refusal(caller):
                audit: Audit = request.app.state.service.audit
                await anyio.to_thread.run_sync(
                    partial(audit.refused_use, caller, f"{request.method} {request.url.path}", e.message)
                )
            raise
        return admitted

    decide.__name__ = f"require_{access.name.lower()}"
    decide.__qualname__ = decide.__name__
    decide.access = access  # type: ignore[attr-defined]  # read by the door (access_of)
    return decide


require_public = _decider(Access.PUBLIC)
require_anyone = _decider(Access.ANYONE)
require_reader = _decider(Access.READER)
require_writer = _decider(Access.WRITER)
require_admin = _decider(Access.ADMIN)
require_scraper = _decider(Access.SCRAPER)

#: route parameters that declare a route's access and hand it the admitted caller
PublicCaller = Annotated[Caller, Depends(require_public)]
AnyoneCaller = Annotated[Caller, Depends(require_anyone)]
ReaderCaller = Annotated[Caller, Depends(require_reader)]
WriterCaller = Annotated[Caller, Depends(require_writer)]
AdminCaller = Annotated[Caller, Depends(require_admin)]
ScraperCaller = Annotated[Caller, Depends(require_scraper)]


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
