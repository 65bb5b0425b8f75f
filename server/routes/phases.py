"""A benchmark's phases and teams: ``/v1/benchmarks/{name}/phases/{phase}/...`` (each phase's submissions and
board) and ``/v1/benchmarks/{name}/teams``. The benchmark's routes without a phase address its current phase
and a submission's routes the phase the submission is in (:mod:`kitti_eval_server.params`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, File, Header, Query, UploadFile
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from ..access.deps import AnyoneCaller, ReaderCaller, WriterCaller
from ..benchmarks.open_labels import submission_frames as frames_of
from ..benchmarks.phases import phase_views, row_of
from ..errors import NotFound, echo
from ..idempotency import IDEMPOTENCY_DESCRIPTION
from ..params import ServiceDep, SubmissionPhase
from ..schemas import ErrorResponse
from . import benchmarks as single
from .benchmarks import BenchmarksDep
from .frames import FrameCountsQ

__all__ = ["router"]

router = APIRouter(
    prefix="/v1/benchmarks",
    tags=["benchmarks"],
    responses={
        401: {"model": ErrorResponse, "description": "no token, or not a valid one"},
        403: {"model": ErrorResponse, "description": "not allowed"},
        404: {"model": ErrorResponse, "description": "no such benchmark or phase"},
    },
)


class TeamIn(BaseModel):
    name: str = Field(max_length=1000)
    members: list[str] = Field(default_factory=list, max_length=100, description="the others invited to join it")


@router.get("/{name}/phases", summary="The benchmark's phases, the current one marked")
def phases(name: str, benchmarks: BenchmarksDep, caller: AnyoneCaller) -> dict[str, Any]:
    bench = benchmarks.catalog.get(name, caller)
    if bench.is_later_phase:
        raise NotFound(f"no benchmark named {echo(name)}")
    return {"benchmark": bench.shown_name, "items": phase_views(benchmarks.catalog, bench, caller)}


@router.get("/{name}/phases/{phase}", summary="One phase of the benchmark")
def phase(name: str, phase: str, benchmarks: BenchmarksDep, caller: AnyoneCaller) -> dict[str, Any]:
    row = row_of(benchmarks.catalog, name, phase, caller)
    return benchmarks.catalog.describe(benchmarks.catalog.get(row, caller), caller, rescoring=True)


@router.get("/{name}/phases/{phase}/frames", summary="A phase's test frame ids (for kitti-eval submit --phase)")
async def phase_frame_ids(
    name: str, phase: str, benchmarks: BenchmarksDep, service: ServiceDep, caller: AnyoneCaller
) -> dict[str, Any]:
    row = row_of(benchmarks.catalog, name, phase, caller)
    frames = await service.run(benchmarks.catalog.frame_ids, row, caller)
    labels = "validation" if benchmarks.catalog.named(row).open_labels else "test"
    return {"benchmark": name, "phase": phase, "frames": frames, "labels": labels}


@router.get("/{name}/phases/{phase}/leaderboard", summary="A phase's leaderboard (JSON, or CSV with format=csv)")
def phase_leaderboard(
    name: str,
    phase: str,
    benchmarks: BenchmarksDep,
    caller: AnyoneCaller,
    sort: Annotated[str | None, Query(max_length=200, description="rank, key, method, date or a column")] = None,
    order: Annotated[Literal["asc", "desc"] | None, Query()] = None,
    format: Annotated[Literal["json", "csv"], Query()] = "json",
) -> Response:
    row = row_of(benchmarks.catalog, name, phase, caller)
    return single.leaderboard(row, benchmarks, caller, sort=sort, order=order, format=format)


#: the route of a phase's submission (its refusals before its file: :mod:`kitti_eval_server.main`)
PHASE_SUBMISSIONS = "/{name}/phases/{phase}/submissions"


@router.post(
    PHASE_SUBMISSIONS,
    status_code=201,
    summary="Submit predictions to a phase",
    responses={
        202: {"description": "accepted (counted against the quota), not scored yet: the job to poll (Location)"},
        422: {"model": ErrorResponse, "description": "the submission breaks the rules (not counted)"},
        429: {"model": ErrorResponse, "description": "the quota (the team's, in a team) is used; see Retry-After"},
    },
)
async def phase_submit(
    name: str,
    phase: str,
    benchmarks: BenchmarksDep,
    service: ServiceDep,
    caller: WriterCaller,
    predictions: Annotated[
        UploadFile, File(description="a zip or tar of KITTI result txt files (one a test frame), or a result.pkl")
    ],
    wait: Annotated[float | None, Query(ge=0, le=3600, description="seconds to wait for the scores")] = None,
    idempotency_key: Annotated[
        str | None, Header(alias="Idempotency-Key", description=IDEMPOTENCY_DESCRIPTION, max_length=1000)
    ] = None,
) -> JSONResponse:
    row = row_of(benchmarks.catalog, name, phase, caller)
    return await single.submit(row, benchmarks, service, caller, predictions, wait, idempotency_key)


@router.get("/{name}/phases/{phase}/submissions", summary="Your submissions to a phase and its quota")
def phase_submissions(name: str, phase: str, benchmarks: BenchmarksDep, caller: ReaderCaller) -> dict[str, Any]:
    return benchmarks.submissions.mine(row_of(benchmarks.catalog, name, phase, caller), caller)


@router.get(
    "/{name}/submissions/{submission_id}/frames",
    summary="TP, FP and FN per frame of one of your submissions, in a phase on open labels",
)
async def submission_frames(
    row: SubmissionPhase,
    submission_id: str,
    benchmarks: BenchmarksDep,
    service: ServiceDep,
    caller: ReaderCaller,
    question: FrameCountsQ,
) -> dict[str, Any]:
    """As `GET /v1/evaluations/{id}/frames` for an evaluation; a sealed phase's frames are refused (403 `sealed`)."""
    return await service.run(lambda: frames_of(benchmarks, row, submission_id, caller, **question))


@router.get("/{name}/teams", summary="The benchmark's teams (for those who take part in it) and yours")
def teams(name: str, benchmarks: BenchmarksDep, caller: ReaderCaller) -> dict[str, Any]:
    return benchmarks.teams.list(name, caller)


@router.post("/{name}/teams", status_code=201, summary="Make a team and invite others who take part")
def make_team(name: str, body: TeamIn, benchmarks: BenchmarksDep, caller: WriterCaller) -> dict[str, Any]:
    """The caller is the team's first member; those named in ``members`` are invited and join when they accept
    (``POST .../teams/TEAM/join``); one team per participant per benchmark; the quota of each phase is the team's
    (what a member submitted alone before joining counts against it)."""
    return benchmarks.teams.create(name, body.name, body.members, caller)


@router.post("/{name}/teams/{team}/join", summary="Join a team that invited you")
def join_team(name: str, team: str, benchmarks: BenchmarksDep, caller: WriterCaller) -> dict[str, Any]:
    return benchmarks.teams.join(name, team, caller)


@router.post("/{name}/teams/leave", summary="Leave your team (until the benchmark's last phase has closed)")
def leave_team(name: str, benchmarks: BenchmarksDep, caller: WriterCaller) -> dict[str, Any]:
    """What you submit from then on counts against your own quota; what you submitted for the team still counts
    against the team's quota and your own while it is in the quota's window, and the board keeps naming the team
    on the entries made for it."""
    return benchmarks.teams.leave(name, caller)
