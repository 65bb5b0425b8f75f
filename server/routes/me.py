"""``/v1/me``: who the token is (``kitti-eval login`` says it), as the policy admitted it."""

from __future__ import annotations

from fastapi import APIRouter

from ..access.deps import ReaderCaller
from ..access.policy import identity
from ..schemas import ErrorResponse

router = APIRouter(
    prefix="/v1/me",
    tags=["accounts"],
    responses={401: {"model": ErrorResponse, "description": "no token, or not a valid one"}},
)


@router.get("", summary="Who your token is: the user, whether an admin, whether read-only")
def me(caller: ReaderCaller) -> dict[str, bool | str]:
    """The caller as the service admitted it; the fields named here only (never the token nor its id)."""
    return identity(caller)
