"""The join page (``/join/CODE``): a host's invitation link, where a person chooses a user name, gets an account
that takes part in the invitation's benchmark, is signed in, and is shown their token once (to use with
``kitti-eval login``). Public, as the JSON route ``/v1/join/CODE`` is: the same service method, the same limit per
client address; the form carries a CSRF token signed by the service (a cookie sent alike: there is no session
yet), as the sign-in form does."""

from __future__ import annotations

from urllib.parse import quote

import anyio.to_thread
from fastapi import APIRouter, Request
from fastapi.responses import Response
from starlette.exceptions import HTTPException

from ..access.auth import join_cookie, over_https
from ..access.deps import PublicCaller
from ..access.policy import SIGNIN_CSRF_S, Caller
from ..errors import ApiError, Gone, NotFound, clip
from ..params import ServiceDep
from ..service import Service
from .pages import render_page, signed_in
from .routes import error_page

__all__ = ["router"]

router = APIRouter(include_in_schema=False)


def _form(
    request: Request, service: Service, code: str, benchmark: str, status: int = 200, **context: object
) -> Response:
    """The form, with a fresh CSRF token in it and in its cookie."""
    csrf = service.policy.issue_signin_csrf()
    response = render_page(
        request,
        "join.html",
        status,
        code=code,
        benchmark=benchmark,
        csrf=csrf,
        caller=None,
        error=context.get("error"),
        name=context.get("name") or "",
    )
    name, path = join_cookie(request.scope)
    response.set_cookie(
        name, csrf, max_age=SIGNIN_CSRF_S, path=path, httponly=True, samesite="strict", secure=over_https(request.scope)
    )
    return response


@router.get("/join/{code}")
async def join_form(request: Request, code: str, service: ServiceDep, caller: PublicCaller) -> Response:
    try:
        invited = await anyio.to_thread.run_sync(lambda: service.invitations.invited(code, caller=caller))
    except (NotFound, Gone) as e:
        return error_page(request, e)
    return _form(request, service, code, invited.benchmark)


@router.post("/join/{code}")
async def join(request: Request, code: str, service: ServiceDep, caller: PublicCaller) -> Response:
    """Make the account (the service's join, as ``POST /v1/join/CODE``), open a web session with its token and show
    the token once, with the way on to the benchmark."""
    client = caller.client
    benchmark = ""
    name: object = None
    try:
        service.join_limiter.check(client)
        service.join_limiter.fail(client)  # every attempt counts, made or refused
        async with request.form(max_files=0, max_fields=4) as form:
            name, sent_csrf = form.get("name"), form.get("csrf")
        invited = await anyio.to_thread.run_sync(lambda: service.invitations.invited(code, caller=caller))
        benchmark = invited.benchmark
        service.policy.check_signin_csrf(sent_csrf, request.cookies.get(join_cookie(request.scope)[0]), form="join")
        user, token, benchmark = await anyio.to_thread.run_sync(
            lambda: service.invitations.join(code, name, caller=caller)
        )
        signed: Caller = await anyio.to_thread.run_sync(lambda: service.accounts.resolve(token))
        session = await anyio.to_thread.run_sync(
            lambda: service.accounts.open_session(signed.at(client), service.settings.session_hours)
        )
        shown = await anyio.to_thread.run_sync(lambda: service.accounts.resolve(session, session=True))
    except (NotFound, Gone) as e:
        gone = e
        await anyio.to_thread.run_sync(lambda: service.invitations.refused(code, gone, caller=caller, name=name))
        return error_page(request, e)
    except (ApiError, HTTPException) as e:
        if isinstance(e, ApiError):  # the refusals the audit log keeps, by the invitation's id
            refused = e
            await anyio.to_thread.run_sync(lambda: service.invitations.refused(code, refused, caller=caller, name=name))
        status = e.status_code
        message = e.detail if isinstance(e, HTTPException) else e.message
        response = _form(
            request,
            service,
            code,
            benchmark,
            status,
            error=clip(str(message)),
            name=name if isinstance(name, str) else "",
        )
        if isinstance(e, ApiError):
            response.headers.update(e.headers)
        return response
    response = render_page(
        request,
        "joined.html",
        201,
        user=user,
        token=token,
        benchmark=benchmark,
        benchmark_url=f"/benchmarks/{quote(benchmark, safe='')}",
        service_url=str(request.base_url).rstrip("/"),  # the address this page was asked at
        caller=shown,
    )
    response.headers["Cache-Control"] = "no-store"  # the token is shown this once
    return signed_in(response, request.scope, session, service.settings.session_hours, join_cookie(request.scope))
