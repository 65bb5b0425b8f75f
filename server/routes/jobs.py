"""``/v1/jobs``: what happened to an accepted evaluation (queued with its place, running, done with the
evaluation's id, failed with the error its input was refused with)."""

from __future__ import annotations

from typing import Any

import anyio.to_thread
from fastapi import APIRouter
from fastapi.responses import JSONResponse

from ..access.deps import ReaderCaller
from ..access.policy import Caller
from ..errors import NotFound, echo
from ..jobs.queue import JobQueue, JobRecord
from ..jobs.workers import job_view
from ..params import ServiceDep
from ..schemas import ErrorResponse
from ..service import Service

router = APIRouter(
    prefix="/v1/jobs",
    tags=["jobs"],
    responses={404: {"model": ErrorResponse, "description": "no such job (or not yours)"}},
)


async def still_pending(queue: JobQueue, record: JobRecord) -> JSONResponse:
    """The answer to a request whose job is still queued or running when it stops waiting: 202, the job and
    where to poll it."""
    position = await anyio.to_thread.run_sync(queue.position, record.id)
    headers = {"Location": f"/v1/jobs/{record.id}", "Retry-After": "1"}
    return JSONResponse(job_view(record, position), status_code=202, headers=headers)


def _sees(service: Service, caller: Caller, record: JobRecord) -> bool:
    """Whether the caller sees the job: an evaluation's while they see its project, a submission's while they
    still take part in its benchmark (:meth:`Policy.sees_job <kitti_eval_server.access.policy.Policy.sees_job>`)."""
    if record.kind in ("evaluation", "gate"):
        project = record.payload.get("project")
        return service.policy.sees_job(caller, record.owner, project=str(project) if project else None)
    project, open_to_all = service.benchmarks.catalog.taking_part(record.group) if record.group else (None, False)
    return service.policy.sees_job(caller, record.owner, project=project, open_to_all=open_to_all)


@router.get("/{job_id}", summary="An accepted evaluation's job: its state, and its evaluation once done")
async def get_job(job_id: str, service: ServiceDep, caller: ReaderCaller) -> dict[str, Any]:
    record = await anyio.to_thread.run_sync(service.jobs.get, job_id)
    if record is None or not await anyio.to_thread.run_sync(_sees, service, caller, record):
        raise NotFound(f"no job with id {echo(job_id)}")
    position = await anyio.to_thread.run_sync(service.jobs.position, job_id)
    return job_view(record, position)
