"""``/v1/admin``: users, projects, memberships, tokens, the audit log and the jobs. Admins only (the admin token, or
in accounts mode an admin's token that may write); every change is in the audit log."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from ..access.accounts import READ, WRITE
from ..access.deps import AdminCaller
from ..jobs.workers import admin_job_view
from ..params import ServiceDep
from ..schemas import ErrorResponse, iso
from ..store import TokenRecord, UserRecord

router = APIRouter(
    prefix="/v1/admin",
    tags=["admin"],
    responses={
        401: {"model": ErrorResponse, "description": "no token, or not a valid one"},
        403: {"model": ErrorResponse, "description": "not an admin, or a read-only token"},
        404: {"model": ErrorResponse, "description": "no such user, project, token or job"},
        409: {"model": ErrorResponse, "description": "the name is taken; the job cannot be cancelled or run again"},
    },
)


class UserIn(BaseModel):
    name: str = Field(description="1-64 letters, digits, '.', '_' or '-'", max_length=1000)
    admin: bool = False


class ProjectIn(BaseModel):
    name: str = Field(max_length=1000)


class MemberIn(BaseModel):
    user: str = Field(max_length=1000)
    project: str = Field(max_length=1000)


class TokenIn(BaseModel):
    user: str = Field(max_length=1000)
    read_only: bool = Field(False, description="may read (and gate) but not upload or change anything")
    expires_days: float | None = Field(None, description="valid this many days (default: until revoked)")


def _user(record: UserRecord) -> dict[str, Any]:
    return {"name": record.name, "admin": record.is_admin, "projects": list(record.projects)}


def _token(record: TokenRecord) -> dict[str, Any]:
    """A token's record; never its secret or digest."""
    return {
        "id": record.id,
        "user": record.user_name,
        "scopes": record.scopes.split(","),
        "created_at": iso(record.created_at),
        "expires_at": iso(record.expires_at) if record.expires_at else None,
        "revoked": record.revoked_at is not None,
    }


@router.get("/users", summary="Users and their projects")
def list_users(service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    return {"items": [_user(u) for u in service.accounts.users()]}


@router.post("/users", status_code=201, summary="Add a user")
def add_user(body: UserIn, service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    user = service.accounts.add_user(body.name, is_admin=body.admin, caller=caller)
    return _user(user)


@router.get("/projects", summary="Projects")
def list_projects(service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    return {"items": [{"name": p} for p in service.accounts.projects()]}


@router.post("/projects", status_code=201, summary="Add a project")
def add_project(body: ProjectIn, service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    return {"name": service.accounts.add_project(body.name, caller=caller)}


@router.post("/members", status_code=201, summary="Make a user a member of a project")
def add_member(body: MemberIn, service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    service.accounts.add_member(body.user, body.project, caller=caller)
    return _user(service.accounts.user(body.user))


@router.delete("/members/{user}/{project}", status_code=204, summary="End a membership")
def remove_member(user: str, project: str, service: ServiceDep, caller: AdminCaller) -> Response:
    service.accounts.remove_member(user, project, caller=caller)
    return Response(status_code=204)


@router.post("/tokens", status_code=201, summary="A new token for a user (shown once)")
def add_token(body: TokenIn, service: ServiceDep, caller: AdminCaller) -> JSONResponse:
    record, token = service.accounts.add_token(
        body.user,
        scopes=(READ,) if body.read_only else (READ, WRITE),
        expires_days=body.expires_days,
        caller=caller,
    )
    return JSONResponse({**_token(record), "token": token}, status_code=201, headers={"Cache-Control": "no-store"})


@router.get("/tokens", summary="Tokens (never their secrets)")
def list_tokens(
    service: ServiceDep, caller: AdminCaller, user: Annotated[str | None, Query(max_length=1000)] = None
) -> dict[str, Any]:
    return {"items": [_token(t) for t in service.accounts.tokens(user)]}


@router.delete("/tokens/{token_id}", status_code=204, summary="Revoke a token (and its web sessions)")
def revoke_token(token_id: str, service: ServiceDep, caller: AdminCaller) -> Response:
    service.accounts.revoke_token(token_id, caller=caller)
    return Response(status_code=204)


@router.get("/audit", summary="The audit log, newest first")
def list_audit(
    service: ServiceDep,
    caller: AdminCaller,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
) -> dict[str, Any]:
    rows = service.audit.entries(limit=limit, offset=offset)
    return {
        "items": [
            {
                "id": r.id,
                "at": iso(r.at),
                "actor": r.actor,
                "action": r.action,
                "target": r.target,
                "outcome": r.outcome,
                "client": r.client,
                "detail": r.detail,
            }
            for r in rows
        ],
        "limit": limit,
        "offset": offset,
    }


@router.get("/jobs", summary="Jobs of every owner, newest first, with the counts by state")
def list_jobs(
    service: ServiceDep,
    caller: AdminCaller,
    state: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query()] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
) -> dict[str, Any]:
    records = service.job_admin.listed(caller, state=state, limit=limit + 1, offset=offset)
    return {
        "items": [admin_job_view(r) for r in records[:limit]],
        "counts": service.job_admin.counts(caller),
        "limit": limit,
        "offset": offset,
        "next_offset": offset + limit if len(records) > limit else None,
    }


@router.post("/jobs/{job_id}/cancel", summary="Cancel a queued or running job (its result is not stored)")
def cancel_job(job_id: str, service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    return admin_job_view(service.job_admin.cancel(job_id, caller))


@router.post("/jobs/{job_id}/rerun", summary="Queue an ended job again (a failed or cancelled evaluation)")
def rerun_job(job_id: str, service: ServiceDep, caller: AdminCaller) -> dict[str, Any]:
    return admin_job_view(service.job_admin.rerun(job_id, caller))
