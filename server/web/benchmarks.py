"""The benchmark pages: the list of benchmarks (``/benchmarks``), a benchmark with its board and, for a
participant, their rules, quota and submissions and the form to submit (``/benchmarks/{name}``), and one of
their submissions with its state, scores and the form to publish or withdraw it
(``/benchmarks/{name}/submissions/{id}``). Rendered on the server: every form works without scripts (the
upload's progress bar is the only thing a script adds), and the page of a submission still being scored
reloads itself (``<meta http-equiv="refresh">``). The public pages are readable without a token when the
benchmark is public; the forms go through the same service methods, and the same policy, as the JSON API.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from functools import partial
from typing import Annotated, Any, Literal
from urllib.parse import quote

import anyio.to_thread
from fastapi import APIRouter, Query, Request
from fastapi.responses import RedirectResponse, Response
from markupsafe import Markup
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from kitti_eval.errors import KittiEvalError

from ..access.deps import FORM_MAX_FIELDS, AnyoneCaller, ReaderCaller, WriterCaller
from ..access.policy import Caller
from ..benchmarks import Benchmarks, InvalidSubmission, render_markdown
from ..benchmarks.lifecycle import past_closing
from ..benchmarks.phases import current_row, row_of
from ..benchmarks.rules import PHASE_SEPARATOR
from ..errors import ApiError, BadRequest, NotFound, clip, fault_of
from ..idempotency import FORM_FIELD, new_form_key, parse_key
from ..jobs.workers import JobFailed
from ..params import ServiceDep, SubmissionPhase
from ..service import FileIn, Service
from .boards import board_entries, board_header, bootstrap_line, column_label, comparison_rows, full_time, number
from .pages import queued_text, render_page, status_of

__all__ = ["router", "REFRESH_S"]

router = APIRouter(include_in_schema=False)

#: how often the page of a submission still being scored reloads itself
REFRESH_S = 2
#: how long the submission form waits for the file's check and scoring before it shows the submission's page
#: (which follows the rest): a refused file is shown on the form when its job ran by then
FORM_WAIT_S = 10.0
_PUBLISH_FIELDS = 8


def _benchmarks(request: Request) -> Benchmarks:
    benchmarks: Benchmarks = request.app.state.benchmarks
    return benchmarks


def _failure(e: Exception, service: Service) -> ApiError | KittiEvalError | HTTPException | None:
    """What a form's request is answered with: the refusals the JSON API answers 4xx, a full disk (507); a
    scoring job that found the file breaks the rules, as the validator's sentences."""
    if isinstance(e, JobFailed):
        return _as_refusal(e)
    if isinstance(e, (ApiError, KittiEvalError, HTTPException)):
        return e
    return fault_of(e, service.settings.retry_after_s)


def _as_refusal(failed: JobFailed) -> ApiError:
    """A failed job as the form answers it: the validator's sentences when its check found the file breaks the
    rules, else the job's error."""
    problems = failed.details.get("problems")
    if failed.code == InvalidSubmission.code and isinstance(problems, list):
        return InvalidSubmission([str(p) for p in problems])
    return failed


def _message(failure: ApiError | KittiEvalError | HTTPException) -> str:
    return clip(str(failure.detail if isinstance(failure, HTTPException) else failure))


def _error(request: Request, failure: ApiError | KittiEvalError | HTTPException) -> Response:
    status = status_of(failure)
    return render_page(request, "error.html", status, status=status, message=_message(failure))


# ----------------------------------------------------------------------------------------------- the list


def _rules(bench: Mapping[str, Any]) -> dict[str, Any]:
    """A benchmark's rules as the pages say them."""
    n, days = bench["quota"]["submissions"], bench["quota"]["days"]
    split = bench.get("split_percent")
    return {
        "key": " + ".join(column_label(k) for k in bench["key"]) + (" (mean)" if len(bench["key"]) > 1 else ""),
        "quota": f"{n} submission{'s' if n != 1 else ''} per {days:g} day{'s' if days != 1 else ''}",
        "closes": full_time(bench["closes_at"]) if bench.get("closes_at") else None,
        "opens": full_time(bench["opens_at"]),
        "split": (
            None
            if split is None
            else f"the board shows the scores on a public part ({split:g} % of the test frames) until the reveal; "
            "the final ranking uses the rest"
        ),
        "max_published": bench.get("max_published"),
        "period": _period(bench),
    }


def _period(bench: Mapping[str, Any]) -> str:
    """A phase's period in words for its state (the ``state`` of :mod:`..benchmarks.lifecycle`): ``opens DATE``,
    ``open; closes DATE``, ``closed on DATE``, and the final ranking once revealed."""
    state = bench.get("state", "open" if bench.get("open") else "closed")
    closes_at = bench.get("closes_at")
    closes = full_time(closes_at) if closes_at else None
    if state == "scheduled":
        return f"opens {full_time(bench['opens_at'])}" + (f"; closes {closes}" if closes else "")
    if state == "open":
        return f"open; closes {closes}" if closes else "open; no closing date"
    # closed by its closes_at (a date past) or by hand (the date is not kept)
    ended = f"closed on {closes}" if closes_at and past_closing(datetime.fromisoformat(closes_at)) else "closed"
    return f"{ended}; final ranking" if state == "revealed" else ended


def _taking_now(phases: list[dict[str, Any]]) -> str | None:
    """The phase that takes submissions now, of a benchmark with phases (None: none does)."""
    return next((p["name"] for p in phases if p.get("state") == "open"), None)


def _participant(service: Service, caller: Caller) -> bool:
    """Whether the caller may submit (and so has submissions and a quota): a signed-in user's token."""
    return service.policy.is_participant(caller)


@router.get("/benchmarks")
def benchmarks_page(request: Request, service: ServiceDep, caller: AnyoneCaller) -> Response:
    """The benchmarks the caller sees, with their rules and, for a participant, the submissions left."""
    benchmarks = _benchmarks(request)
    rows = []
    for bench in benchmarks.catalog.visible(caller):
        described = benchmarks.catalog.describe(bench, caller)
        mine = benchmarks.submissions.mine(bench.name, caller) if _participant(service, caller) else None
        current: dict[str, Any] = next((p for p in described["phases"] if p["current"]), {})
        set_word = "validation set" if current.get("open_labels") else "test set"
        rows.append({"bench": described, "rules": _rules(described), "mine": mine, "set_word": set_word})
    return render_page(request, "benchmarks.html", rows=rows, participant=_participant(service, caller))


# ---------------------------------------------------------------------------------------------- one bench


def _states(service: Service, items: list[dict[str, Any]], key: list[str]) -> list[dict[str, Any]]:
    """The caller's submissions, each with the state its scoring is in and its key."""
    return [{**item, "state": _state(service, item), "key": _key(item.get("scores") or {}, key)} for item in items]


def _state(service: Service, submission: Mapping[str, Any]) -> dict[str, Any]:
    """A submission's state as the pages say it: queued (with its place in the queue), running, scored or
    failed (with the reason its evaluation was refused)."""
    if submission["status"] == "scored":
        return {"name": "scored", "text": "scored", "done": True}
    job = service.jobs.get(submission["id"])
    if submission["status"] == "failed" or (job is not None and job.state in ("failed", "cancelled")):
        reason = submission.get("reason") or (
            JobFailed(job.error).message if job is not None and job.error else "the evaluation failed"
        )
        return {"name": "failed", "text": "failed", "reason": clip(reason), "done": True}
    if job is not None and job.state == "running":
        return {"name": "running", "text": "being scored", "done": False}
    position = service.jobs.position(submission["id"])
    return {"name": "queued", "text": queued_text(position), "position": position, "done": False}


def _benchmark_context(
    request: Request, service: Service, caller: Caller, row: str, sort: str | None, order: str | None
) -> dict[str, Any]:
    benchmarks = _benchmarks(request)
    bench = benchmarks.catalog.get(row, caller)
    board = benchmarks.board.leaderboard(row, caller, sort=sort, order=order)
    described = benchmarks.catalog.describe(bench, caller)
    mine = None
    if _participant(service, caller):
        mine = benchmarks.submissions.mine(row, caller)
        mine["items"] = _states(service, mine["items"], described["key"])
    phases = sorted(described["phases"], key=lambda p: not p["current"])  # the current one first
    teams = None
    if described["team_size"] > 1 and _participant(service, caller) and not service.policy.administers(caller):
        teams = benchmarks.teams.list(bench.shown_name, caller)
    return {
        "phases": [{**p, "rules": _rules({**p, "key": described["key"]})} for p in phases] if len(phases) > 1 else [],
        "teams": teams,
        "team_error": None,
        "taking_now": _taking_now(phases),
        "set_word": "validation set" if bench.open_labels else "test set",
        "bench": described,
        "rules": _rules(described),
        "description": Markup(render_markdown(bench.description)),  # noqa: S704 - every character escaped first
        "board": board,
        "header": board_header(board["columns"]),
        "entries": board_entries(board),
        "bootstrap": bootstrap_line(board),
        "has_intervals": any("interval" in e for e in board["entries"]),
        "has_ranges": any("rank_range" in e for e in board["entries"]),
        "key_label": _rules(described)["key"],
        "key_short": _short_key(described["key"], board["columns"]),
        "number": number,
        "mine": mine,
        "next_slot": full_time(mine["quota"]["next_at"]) if mine and mine["quota"]["next_at"] else None,
        "accounts": service.policy.has_accounts(),
        "participants": service.invitations.participants(bench.shown_name, caller)
        if service.policy.has_accounts()
        else None,
        "max_upload_bytes": service.settings.max_upload_bytes,
        "idempotency_key": new_form_key(),
        "problems": None,
        "error": None,
    }


def _short_key(key: list[str], columns: list[str]) -> str:
    """The key as its column's header says it: without the recall mode and IoU set the columns share."""
    common = board_header(columns)["common"]
    label = " + ".join(column_label(k, common=common) for k in key)
    return f"mean of {label}" if len(key) > 1 else label


def _phase_row(request: Request, caller: Caller, name: str, phase: str | None) -> str:
    """The row of the phase a page shows: the one named (``?phase=``), else the current one."""
    benchmarks = _benchmarks(request)
    return row_of(benchmarks.catalog, name, phase, caller) if phase else current_row(benchmarks.catalog, name)


PhaseQuery = Annotated[str | None, Query(max_length=40, description="a phase of the benchmark (default: the current)")]


@router.get("/benchmarks/{name}")
def benchmark_page(
    request: Request,
    service: ServiceDep,
    caller: AnyoneCaller,
    name: str,
    sort: Annotated[str | None, Query(max_length=200)] = None,
    order: Annotated[Literal["asc", "desc"] | None, Query()] = None,
    phase: PhaseQuery = None,
) -> Response:
    try:
        context = _benchmark_context(request, service, caller, _phase_row(request, caller, name, phase), sort, order)
    except ApiError as e:
        return _error(request, e)
    return render_page(request, "benchmark.html", **context)


@router.post("/benchmarks/{name}/submissions")
async def submit_form(
    request: Request, service: ServiceDep, caller: WriterCaller, name: str, phase: PhaseQuery = None
) -> Response:
    """The submission form: counted against the quota and accepted, then checked and scored by its job (a
    refused file shows the validator's sentences here when the job ran within ``FORM_WAIT_S``, and counts
    nothing); then the submission's page, which follows its scoring."""
    benchmarks = _benchmarks(request)
    row = name  # a benchmark's name is its first phase's row (the page a refusal shows, when the phase is not found)
    try:
        row = _phase_row(request, caller, name, phase)
        async with request.form(max_files=1, max_fields=FORM_MAX_FIELDS) as form:
            predictions = form.get("predictions")
            if not isinstance(predictions, UploadFile) or not predictions.filename:
                raise BadRequest("choose a predictions file (a zip or tar of KITTI result txt files, or a result.pkl)")
            file = FileIn(predictions.file, predictions.filename)
            sent = form.get(FORM_FIELD)
            # the form's idempotency key: sent again, one submission
            idempotency_key = parse_key(sent) if isinstance(sent, str) and sent else None
            job = await service.accept(
                lambda: benchmarks.submissions.submit(row, file, caller, idempotency_key=idempotency_key)
            )
        try:
            await service.outcome(job.id, FORM_WAIT_S)  # the file's check runs in its job: a refusal shows here
        except JobFailed:
            if await anyio.to_thread.run_sync(_refused_job, service, caller, job.id) is not None:
                raise  # the file was refused (and removed): the form says why
            # its scoring failed: the submission's page says why

    except Exception as e:  # noqa: BLE001 - the refusals are answered as the page; anything else is raised
        failure = _failure(e, service)
        if failure is None:
            raise
        return await anyio.to_thread.run_sync(partial(_refused, request, service, caller, row, failure))
    return RedirectResponse(f"/benchmarks/{quote(_shown(row))}/submissions/{quote(job.id)}", status_code=303)


def _refused(
    request: Request,
    service: Service,
    caller: Caller,
    row: str,
    failure: ApiError | KittiEvalError | HTTPException,
) -> Response:
    """The benchmark's page again, with why the submission was refused (with the status the API answers)."""
    try:
        context = _benchmark_context(request, service, caller, row, None, None)
    except ApiError as e:
        return _error(request, e)
    if isinstance(failure, InvalidSubmission):
        context["problems"] = [clip(p) for p in failure.problems]
    else:
        context["error"] = _message(failure)
    response = render_page(request, "benchmark.html", status_of(failure), **context)
    if isinstance(failure, ApiError):
        response.headers.update(failure.headers)
    return response


# ----------------------------------------------------------------------------------------- one submission


def _submission_context(
    request: Request, service: Service, caller: Caller, row: str, submission_id: str
) -> dict[str, Any]:
    benchmarks = _benchmarks(request)
    submission = benchmarks.submissions.submission(row, submission_id, caller)
    bench = benchmarks.catalog.get(row, caller)
    described = benchmarks.catalog.describe(bench, caller)
    state = _state(service, submission)
    columns = described["columns"]
    scores = submission.get("scores") or {}
    return {
        "bench": described,
        "rules": _rules(described),
        "phased": len(described["phases"]) > 1,
        "frames_url": (
            f"/v1/benchmarks/{quote(bench.shown_name)}/submissions/{quote(submission['id'])}/frames"
            if bench.open_labels
            else None
        ),
        "sub": submission,
        "state": state,
        "refresh": None if state["done"] else REFRESH_S,
        "header": board_header(columns),
        "scores": scores,
        "key": scores and _key(scores, described["key"]),
        "key_label": _rules(described)["key"],
        "comparison": comparison_rows(submission["comparison"], submission["id"])
        if "comparison" in submission
        else None,
        "may_select": not bench.is_closed(),
        "number": number,
        "submitted": full_time(submission["created_at"]),
        "error": None,
        "form": {},
    }


def _key(scores: Mapping[str, float | None], key: list[str]) -> float | None:
    values = [scores.get(k) for k in key]
    if not values or any(v is None for v in values):
        return None
    return sum(v for v in values if v is not None) / len(values)


@router.get("/benchmarks/{name}/submissions/{submission_id}")
def submission_page(
    request: Request, service: ServiceDep, caller: ReaderCaller, row: SubmissionPhase, submission_id: str
) -> Response:
    try:
        context = _submission_context(request, service, caller, row, submission_id)
    except NotFound as e:
        refused = _refused_job(service, caller, submission_id)
        if refused is not None:  # its scoring found the file breaks the rules: it was removed, never counted
            return _refused(request, service, caller, row, refused)
        return _error(request, e)
    except ApiError as e:
        return _error(request, e)
    return render_page(request, "submission.html", **context)


def _refused_job(service: Service, caller: Caller, submission_id: str) -> ApiError | None:
    """Why the caller's submission was refused by its scoring job's check of the file, if it was: the
    validator's sentences as on the form, or the reader's refusal."""
    failed = service.benchmarks.scoring.refusal(submission_id, caller)
    return None if failed is None else _as_refusal(failed)


@router.post("/benchmarks/{name}/submissions/{submission_id}/publish")
async def publish_form(
    request: Request, service: ServiceDep, caller: WriterCaller, row: SubmissionPhase, submission_id: str
) -> Response:
    """Publish one of the caller's scored submissions on the board; then the board, at the entry."""
    benchmarks = _benchmarks(request)
    values: dict[str, str] = {}
    try:
        async with request.form(max_files=0, max_fields=_PUBLISH_FIELDS) as form:
            values = {k: v for k, v in form.items() if isinstance(v, str)}
        await anyio.to_thread.run_sync(
            lambda: benchmarks.submissions.publish(
                row,
                submission_id,
                caller,
                method=values.get("method", ""),
                anonymous=values.get("anonymous") == "true",
                affiliation=values.get("affiliation", "").strip() or None,
                link=values.get("link", "").strip() or None,
            )
        )
    except Exception as e:  # noqa: BLE001 - the refusals are answered as the page; anything else is raised
        failure = _failure(e, service)
        if failure is None:
            raise
        refill = {k: clip(v) for k, v in values.items() if k != "csrf"}
        return await anyio.to_thread.run_sync(
            partial(_submission_refused, request, service, caller, row, submission_id, failure, refill)
        )
    return RedirectResponse(f"{_page_of(benchmarks, row, caller)}#entry-{quote(submission_id)}", status_code=303)


@router.post("/benchmarks/{name}/submissions/{submission_id}/withdraw")
async def withdraw_form(
    request: Request, service: ServiceDep, caller: WriterCaller, row: SubmissionPhase, submission_id: str
) -> Response:
    """Take one of the caller's entries off the board; then the submission's page again."""
    benchmarks = _benchmarks(request)
    try:
        await anyio.to_thread.run_sync(lambda: benchmarks.submissions.withdraw(row, submission_id, caller))
    except ApiError as e:
        return await anyio.to_thread.run_sync(
            partial(_submission_refused, request, service, caller, row, submission_id, e, {})
        )
    return RedirectResponse(f"/benchmarks/{quote(_shown(row))}/submissions/{quote(submission_id)}", status_code=303)


def _submission_refused(
    request: Request,
    service: Service,
    caller: Caller,
    row: str,
    submission_id: str,
    failure: ApiError | KittiEvalError | HTTPException,
    form: dict[str, str],
) -> Response:
    try:
        context = _submission_context(request, service, caller, row, submission_id)
    except ApiError as e:
        return _error(request, e)
    context.update(error=_message(failure), form=form)
    return render_page(request, "submission.html", status_of(failure), **context)


# ------------------------------------------------------------------------------------------------ teams


def _shown(row: str) -> str:
    """The benchmark's name of a phase's row."""
    return row.split(PHASE_SEPARATOR, 1)[0]


def _page_of(benchmarks: Benchmarks, row: str, caller: Caller) -> str:
    """The page of the phase ``row`` is (of a benchmark with phases: ``?phase=``)."""
    bench = benchmarks.catalog.get(row, caller)
    phased = bench.is_later_phase or bool(bench.config.get("phases"))
    return f"/benchmarks/{quote(bench.shown_name)}" + (f"?phase={quote(bench.phase_name)}" if phased else "")


_TEAM_FIELDS = 3


@router.post("/benchmarks/{name}/teams")
async def team_form(request: Request, service: ServiceDep, caller: WriterCaller, name: str) -> Response:
    """Make a team (its name, the names of those it invites separated by commas); then the benchmark's page at the
    team."""
    benchmarks = _benchmarks(request)
    try:
        async with request.form(max_files=0, max_fields=_TEAM_FIELDS) as form:
            values = {k: v for k, v in form.items() if isinstance(v, str)}
        members = [m.strip() for m in values.get("members", "").split(",") if m.strip()]
        await anyio.to_thread.run_sync(lambda: benchmarks.teams.create(name, values.get("name", ""), members, caller))
    except ApiError as e:
        return await anyio.to_thread.run_sync(partial(_team_refused, request, service, caller, name, e))
    return RedirectResponse(f"/benchmarks/{quote(name)}#team", status_code=303)


@router.post("/benchmarks/{name}/teams/{team}/join")
async def join_form(request: Request, service: ServiceDep, caller: WriterCaller, name: str, team: str) -> Response:
    """Join a team that invited the caller; then the benchmark's page at the team."""
    benchmarks = _benchmarks(request)
    try:
        await anyio.to_thread.run_sync(lambda: benchmarks.teams.join(name, team, caller))
    except ApiError as e:
        return await anyio.to_thread.run_sync(partial(_team_refused, request, service, caller, name, e))
    return RedirectResponse(f"/benchmarks/{quote(name)}#team", status_code=303)


def _team_refused(request: Request, service: Service, caller: Caller, name: str, failure: ApiError) -> Response:
    try:
        context = _benchmark_context(
            request, service, caller, current_row(_benchmarks(request).catalog, name), None, None
        )
    except ApiError as e:
        return _error(request, e)
    context["team_error"] = _message(failure)
    return render_page(request, "benchmark.html", status_of(failure), **context)
