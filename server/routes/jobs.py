"""``/v1/jobs``: what happened to an accepted evaluation (queued with its place, running, done with the
evaluation's id, failed with the error its input was refused with)."""

from __future__ import annotations

from typing import Any

import anyio.to_thread
from fastapi import APIRouter

from ..deps import ReaderCaller, ServiceDep
from ..errors import NotFound, echo
from ..schemas import ErrorResponse
from ..workers import job_view

router = APIRouter(
    prefix="/v1/jobs",
    tags=["jobs"],
    responses={404: {"model": ErrorResponse, "description": "no such job (or not yours)"}},
)


@router.get("/{job_id}", summary="An accepted evaluation's job: its state, and its evaluation once done")
async def get_job(job_id: str, service: ServiceDep, caller: ReaderCaller) -> dict[str, Any]:
    record = await anyio.to_thread.run_sync(service.jobs.get, job_id)
    if record is None or not service.policy.sees_job(caller, record.owner):
        raise NotFound(f"no job with id {echo(job_id)}")
    position = await anyio.to_thread.run_sync(service.jobs.position, job_id)
    return job_view(record, position)
