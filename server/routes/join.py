"""``/v1/join/CODE``: make an account by an invitation (a host's link to a benchmark) and get its token, once.
Public: the invitation is the right; limited per client address (``KITTI_EVAL_JOIN_MAX_ATTEMPTS``)."""

from __future__ import annotations

from typing import Annotated

import anyio.to_thread
from fastapi import APIRouter, Path
from pydantic import BaseModel, Field

from ..access.deps import PublicCaller
from ..errors import ApiError
from ..params import ServiceDep
from ..schemas import ErrorResponse

router = APIRouter(prefix="/v1/join", tags=["accounts"])

#: what a join answers: the fields named here only
JOINED_FIELDS = ("user", "token", "benchmark")


class JoinIn(BaseModel):
    name: str = Field(description="your user name: 1-64 letters, digits, '.', '_' or '-'", max_length=1000)


@router.post(
    "/{code}",
    status_code=201,
    summary="Make your account by an invitation: its token is in the answer, once",
    responses={
        404: {"model": ErrorResponse, "description": "no such invitation (or the service has no accounts)"},
        409: {"model": ErrorResponse, "description": "the user name is taken"},
        410: {
            "model": ErrorResponse,
            "description": "the invitation is used up, expired or revoked, or its benchmark has closed",
        },
        429: {"model": ErrorResponse, "description": "too many attempts to join from this address"},
    },
)
async def join(
    body: JoinIn,
    service: ServiceDep,
    caller: PublicCaller,
    code: Annotated[str, Path(max_length=200, description="the code of the invitation's link, /join/CODE")],
) -> dict[str, str]:
    """An account that takes part in the invitation's benchmark, and a token that may read and write (use it with
    ``kitti-eval login``); it is shown this once and stored only as its sha256."""
    try:
        # on the event loop, as the door's limiter is: its counts are not shared with threads
        service.join_limiter.check(caller.client)
        service.join_limiter.fail(caller.client)  # every attempt counts, made or refused
        user, token, benchmark = await anyio.to_thread.run_sync(
            lambda: service.invitations.join(code, body.name, caller=caller)
        )
    except ApiError as e:  # the refusals the audit log keeps, by the invitation's id
        refused = e
        await anyio.to_thread.run_sync(
            lambda: service.invitations.refused(code, refused, caller=caller, name=body.name)
        )
        raise
    joined = {"user": user, "token": token, "benchmark": benchmark}
    return {k: joined[k] for k in JOINED_FIELDS}
