"""``/v1/benchmarks``: hosted benchmarks on sealed test sets: submissions under a quota, publishing, the
leaderboard (readable without a token when the benchmark is public), and the admins' actions."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import anyio.to_thread
from fastapi import APIRouter, Depends, File, Header, Query, Request, UploadFile
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, Field

from ..access.deps import AdminCaller, AnyoneCaller, ReaderCaller, WriterCaller
from ..access.policy import Caller
from ..benchmarks import DEFAULT_KEY, Benchmarks
from ..benchmarks.phase_settings import PhaseSettings
from ..benchmarks.rules import PHASE_SEPARATOR
from ..idempotency import IDEMPOTENCY_DESCRIPTION, parse_key
from ..params import CurrentPhase, ServiceDep, SubmissionPhase
from ..schemas import ErrorResponse
from ..service import FileIn
from .jobs import still_pending

router = APIRouter(
    prefix="/v1/benchmarks",
    tags=["benchmarks"],
    responses={
        401: {"model": ErrorResponse, "description": "no token, or not a valid one"},
        403: {"model": ErrorResponse, "description": "not allowed (admins only, or a read-only token)"},
        404: {"model": ErrorResponse, "description": "no such benchmark or submission (or not yours)"},
    },
)


def get_benchmarks(request: Request) -> Benchmarks:
    benchmarks: Benchmarks = request.app.state.benchmarks
    return benchmarks


BenchmarksDep = Annotated[Benchmarks, Depends(get_benchmarks)]


class BenchmarkIn(BaseModel):
    name: str = Field(max_length=1000)
    ground_truth: str = Field(max_length=1000, description="a ground truth registered with sealed=true")
    title: str | None = Field(None, max_length=1000)
    description: str = Field("", max_length=100_000, description="Markdown (HTML is escaped)")
    protocol: Literal["official", "openpcdet"] = "official"
    classes: str = Field("Car,Pedestrian,Cyclist", max_length=1000)
    threshold_sets: str = Field("strict,loose", max_length=1000)
    key: list[str] = Field(
        default_factory=lambda: [DEFAULT_KEY],
        max_length=60,
        description="the ranking key: a column, or several whose mean is the key",
    )
    columns: list[str] = Field(
        default_factory=list, max_length=100, description="CLASS/METRIC/DIFFICULTY[/R40|R11[/SET]] (default: 3D AP)"
    )
    quota: str = Field("3/1", max_length=100, description="N/DAYS: accepted submissions per participant")
    public: bool = False
    open_to_all: bool = Field(
        False, description="every signed-in account may take part (else the members of the test set's project)"
    )
    share_test_set: bool = Field(
        False, description="the test set is already another benchmark's: take it for this one too (see the docs)"
    )
    opens_at: str | None = Field(None, max_length=100)
    closes_at: str | None = Field(None, max_length=100)
    split_percent: float | None = Field(None, description="the public part of the test frames, in percent")
    max_published: int | None = Field(  # its range is checked once, by the rules (check_max_published)
        None, description="published entries per participant, 1 to 1000 (default: no cap); withdraw to swap"
    )


class PublishIn(BaseModel):
    method: str = Field(max_length=1000)
    anonymous: bool = False
    affiliation: str | None = Field(None, max_length=1000)
    link: str | None = Field(None, max_length=1000)


@router.post("", status_code=201, summary="Create a benchmark on a sealed ground truth (admins)")
def create(body: BenchmarkIn, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    settings = PhaseSettings.parse(body.model_dump(exclude={"name", "share_test_set"}), benchmark=body.name)
    bench = benchmarks.catalog.create(body.name, settings, share_test_set=body.share_test_set, caller=caller)
    return benchmarks.catalog.describe(bench, caller)


@router.get("", summary="Benchmarks you can see")
def list_benchmarks(benchmarks: BenchmarksDep, caller: AnyoneCaller) -> dict[str, Any]:
    return {"items": [benchmarks.catalog.describe(b, caller) for b in benchmarks.catalog.visible(caller)]}


@router.get("/{name}", summary="One benchmark (admins: with the rescoring jobs by state)")
def get_benchmark(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AnyoneCaller) -> dict[str, Any]:
    return benchmarks.catalog.describe(benchmarks.catalog.get(row, caller), caller, rescoring=True)


@router.get("/{name}/frames", summary="The test frame ids (for kitti-eval validate --benchmark)")
async def frame_ids(
    row: CurrentPhase, benchmarks: BenchmarksDep, service: ServiceDep, caller: AnyoneCaller
) -> dict[str, Any]:
    frames = await service.run(benchmarks.catalog.frame_ids, row, caller)
    labels = "validation" if benchmarks.catalog.named(row).open_labels else "test"
    return {"benchmark": row.split(PHASE_SEPARATOR, 1)[0], "frames": frames, "labels": labels}  # its name


@router.get("/{name}/leaderboard", summary="The leaderboard (JSON, or CSV with format=csv)")
def leaderboard(
    row: CurrentPhase,
    benchmarks: BenchmarksDep,
    caller: AnyoneCaller,
    sort: Annotated[str | None, Query(max_length=200, description="rank, key, method, date or a column")] = None,
    order: Annotated[Literal["asc", "desc"] | None, Query()] = None,
    format: Annotated[Literal["json", "csv"], Query()] = "json",
) -> Response:
    board = benchmarks.board.leaderboard(row, caller, sort=sort, order=order)
    if format == "csv":
        return PlainTextResponse(
            benchmarks.board.leaderboard_csv(board),
            media_type="text/csv; charset=utf-8",
            headers={"Content-Disposition": f'attachment; filename="{board["benchmark"]}-leaderboard.csv"'},
        )
    return JSONResponse(board)


def _admin_state(row: str, benchmarks: Benchmarks, caller: Caller, **values: bool) -> dict[str, Any]:
    return benchmarks.catalog.describe(benchmarks.catalog.set_state(row, caller=caller, **values), caller)


@router.post("/{name}/close", summary="Close a benchmark to submissions (admins)")
def close(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    return _admin_state(row, benchmarks, caller, closed=True)


@router.post("/{name}/reopen", summary="Reopen a closed benchmark (admins)")
def reopen(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    return _admin_state(row, benchmarks, caller, closed=False)


@router.post("/{name}/reveal", summary="Show the private ranking of a closed benchmark (admins)")
def reveal(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    return _admin_state(row, benchmarks, caller, revealed=True)


@router.post(
    "/{name}/rescore",
    status_code=202,
    summary="Queue one job per submission that evaluates it again on the ground truth as registered (admins)",
)
async def rescore(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    """Returns at once with the jobs queued; `GET /v1/benchmarks/{name}` shows their progress (`rescoring`)."""
    return await anyio.to_thread.run_sync(lambda: benchmarks.submissions.rescore(row, caller=caller))


@router.get("/{name}/submissions/all", summary="Every submission, published or not (admins)")
def all_submissions(row: CurrentPhase, benchmarks: BenchmarksDep, caller: AdminCaller) -> dict[str, Any]:
    return {"items": benchmarks.submissions.all_submissions(row, caller)}


@router.post("/{name}/submissions/{submission_id}/disqualify", summary="Hide an entry, keeping it (admins)")
def disqualify(
    row: SubmissionPhase, submission_id: str, benchmarks: BenchmarksDep, caller: AdminCaller
) -> dict[str, Any]:
    return benchmarks.submissions.disqualify(row, submission_id, caller=caller)


#: the route of a submission (its refusals before its file: :mod:`kitti_eval_server.main`)
SUBMISSIONS = "/{name}/submissions"


@router.post(
    SUBMISSIONS,
    status_code=201,
    summary="Submit predictions on the test set",
    responses={
        202: {"description": "accepted (counted against the quota), not scored yet: the job to poll (Location)"},
        400: {"model": ErrorResponse, "description": "the Idempotency-Key is not 1-255 visible ASCII characters"},
        422: {
            "model": ErrorResponse,
            "description": "the submission breaks the rules (not counted); an Idempotency-Key sent before with "
            "another file (idempotency_key_reused)",
        },
        429: {"model": ErrorResponse, "description": "the quota is used; see Retry-After"},
    },
)
async def submit(
    row: CurrentPhase,
    benchmarks: BenchmarksDep,
    service: ServiceDep,
    caller: WriterCaller,
    predictions: Annotated[
        UploadFile, File(description="a zip or tar of KITTI result txt files (one a test frame), or a result.pkl")
    ],
    wait: Annotated[
        float | None,
        Query(
            ge=0,
            le=3600,
            description="seconds to wait for the scores (default KITTI_EVAL_WAIT_S): 201 with the submission when "
            "it is scored by then, else 202 with the job to poll (GET its Location); 0 answers at once",
        ),
    ] = None,
    idempotency_key: Annotated[
        str | None, Header(alias="Idempotency-Key", description=IDEMPOTENCY_DESCRIPTION, max_length=1000)
    ] = None,
) -> JSONResponse:
    """Checked, counted against the quota and accepted at once (the acceptance time is the submission's); its
    scoring is a job, run by the next free worker."""
    checked_key = parse_key(idempotency_key)  # the Idempotency-Key header, checked
    file = FileIn(predictions.file, predictions.filename)
    # refusals: 422 problems, 429 retry_at
    job = await service.accept(lambda: benchmarks.submissions.submit(row, file, caller, idempotency_key=checked_key))
    ended = await service.outcome(job.id, wait)
    if ended.state != "done":
        return await still_pending(service.jobs, ended)
    body = await anyio.to_thread.run_sync(benchmarks.submissions.submission, row, job.id, caller)
    where = f"/v1/benchmarks/{body['benchmark']}/submissions/{job.id}"  # the benchmark's name, whatever the phase
    return JSONResponse(body, status_code=201, headers={"Location": where})


@router.get("/{name}/submissions", summary="Your submissions and your quota")
def my_submissions(row: CurrentPhase, benchmarks: BenchmarksDep, caller: ReaderCaller) -> dict[str, Any]:
    return benchmarks.submissions.mine(row, caller)


@router.get("/{name}/submissions/{submission_id}", summary="One of your submissions, with its full result")
def my_submission(
    row: SubmissionPhase, submission_id: str, benchmarks: BenchmarksDep, caller: ReaderCaller
) -> dict[str, Any]:
    return benchmarks.submissions.submission(row, submission_id, caller)


@router.post("/{name}/submissions/{submission_id}/publish", summary="Show one of your submissions on the board")
def publish(
    row: SubmissionPhase, submission_id: str, body: PublishIn, benchmarks: BenchmarksDep, caller: WriterCaller
) -> dict[str, Any]:
    return benchmarks.submissions.publish(
        row,
        submission_id,
        caller,
        method=body.method,
        anonymous=body.anonymous,
        affiliation=body.affiliation,
        link=body.link,
    )


@router.post("/{name}/submissions/{submission_id}/withdraw", summary="Take one of your entries off the board")
def withdraw(
    row: SubmissionPhase, submission_id: str, benchmarks: BenchmarksDep, caller: WriterCaller
) -> dict[str, Any]:
    return benchmarks.submissions.withdraw(row, submission_id, caller)
