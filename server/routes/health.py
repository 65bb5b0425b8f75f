"""Liveness and readiness probes (unversioned: they describe the process, not the API)."""

from __future__ import annotations

from fastapi import APIRouter

from ..access.deps import PublicCaller
from ..errors import NotReady
from ..params import ServiceDep
from ..schemas import ErrorResponse, Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="The process is up")
async def healthz(caller: PublicCaller) -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Health,
    summary="Ready to evaluate (kernels warm, database reachable)",
    responses={503: {"model": ErrorResponse, "description": "warming up, or the database is unavailable"}},
)
def readyz(service: ServiceDep, caller: PublicCaller) -> dict[str, str]:
    problem = service.readiness()
    if problem is not None:
        raise NotReady(problem)
    return {"status": "ready"}
