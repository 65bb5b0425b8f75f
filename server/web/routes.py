"""The HTML pages: upload and history, one evaluation, a comparison, one frame. Not in the OpenAPI document.

The pages read the same records the JSON API serves and render them with Jinja2; a failure renders the page
(or a small error page) with the message and the status the JSON API gives the same failure.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from typing import Annotated, Any
from urllib.parse import quote, urlencode

import anyio.to_thread
from fastapi import APIRouter, Query, Request
from fastapi.responses import RedirectResponse, Response
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException
from starlette.types import Scope

from kitti_eval.analysis.decomposition import AOS_TYPES, ERROR_TYPES, TP_ERRORS
from kitti_eval.analysis.frame_question import FrameQuestion
from kitti_eval.core.protocol import ALL_METRICS, KNOWN_CLASSES, PROTOCOLS
from kitti_eval.errors import KittiEvalError

from ..access.auth import check_token, over_https, session_cookie, signin_cookie
from ..access.deps import FORM_MAX_FIELDS, PublicCaller, ReaderCaller, WriterCaller
from ..access.policy import SIGNIN_CSRF_S, Caller, Policy
from ..errors import (
    MAX_ECHO_CHARS,
    ApiError,
    BadRequest,
    NotFound,
    clip,
    echo,
    fault_of,
)
from ..evaluations.compare import compare
from ..idempotency import FORM_FIELD, new_form_key, parse_key
from ..jobs.queue import JobRecord
from ..jobs.workers import JobFailed
from ..params import MAX_SCORE, ServiceDep
from ..scoring.evaluator import ERRORS_SET, EvalOptions, parse_labels
from ..service import FileIn, Service
from ..store import EvaluationRecord
from .pages import queued_text, render_page, signed_in, status_of
from .svg import bar_chart, bev_view, pr_chart

__all__ = ["router", "sign_in_page", "error_page"]


_RECALLS = ("R40", "R11")
_DIFFICULTIES = ("easy", "moderate", "hard")
_SUMMARY_CLASSES = ("Car", "Pedestrian", "Cyclist")
_HISTORY = 50
_WORST = 20

router = APIRouter(include_in_schema=False)


# ----------------------------------------------------------------------------------------------- sign in


async def sign_in_page(scope: Scope, status: int = 200, error: str | None = None) -> Response:
    """The sign-in form (also the answer to a page requested without a valid session): a fresh CSRF token
    in the form and in a cookie, which the form's POST must send back alike."""
    request = Request(scope)
    policy: Policy = request.app.state.policy
    csrf = policy.issue_signin_csrf()
    response = render_page(request, "signin.html", status, status=status, error=error, csrf=csrf, caller=None)
    name, path = signin_cookie(scope)
    response.set_cookie(
        name, csrf, max_age=SIGNIN_CSRF_S, path=path, httponly=True, samesite="strict", secure=over_https(scope)
    )
    return response


@router.get("/signin")
async def sign_in_form(request: Request, service: ServiceDep, caller: PublicCaller) -> Response:
    if not service.policy.has_accounts():
        return RedirectResponse("/", status_code=303)
    return await sign_in_page(request.scope)


@router.post("/signin")
async def sign_in(request: Request, service: ServiceDep, caller: PublicCaller) -> Response:
    """Check the token once, as the door checks one (:func:`~kitti_eval_server.access.auth.check_token`: the same
    failure limit and audit), open a session (its own token, in an HttpOnly SameSite=Strict cookie) and go to
    the evaluations. The form carries its own CSRF token, signed by the service (a cookie sent alike: there is
    no session yet); the door has already refused a post from another origin."""
    if not service.policy.has_accounts():
        return RedirectResponse("/", status_code=303)
    client = caller.client
    try:
        service.limiter.check(client)
        async with request.form(max_files=0, max_fields=4) as form:
            token = form.get("token")
            sent_csrf = form.get("csrf")
        service.policy.check_signin_csrf(sent_csrf, request.cookies.get(signin_cookie(request.scope)[0]))
        if not isinstance(token, str) or not token.strip():
            raise BadRequest("paste your token (kitti-eval admin token add prints one)")
        signed = await check_token(service.accounts, service.limiter, token.strip(), client=client, target="/signin")
        if not service.policy.may_open_session(signed):
            raise BadRequest("the admin token cannot sign in to the pages; sign in with a user's token")
        session = await anyio.to_thread.run_sync(
            lambda: service.accounts.open_session(signed.at(client), service.settings.session_hours)
        )
    except (ApiError, HTTPException) as e:
        status = e.status_code
        message = e.detail if isinstance(e, HTTPException) else e.message
        response = await sign_in_page(request.scope, status, clip(str(message)))
        if isinstance(e, ApiError):
            response.headers.update(e.headers)
        return response
    response = RedirectResponse("/", status_code=303)
    return signed_in(response, request.scope, session, service.settings.session_hours, signin_cookie(request.scope))


@router.post("/signout")
async def sign_out(request: Request, service: ServiceDep, caller: ReaderCaller) -> Response:
    """End the session (its token is revoked) and clear the cookie (the session's CSRF token checked by the
    policy, as for every change)."""
    if not service.policy.has_accounts():
        return RedirectResponse("/", status_code=303)
    await anyio.to_thread.run_sync(lambda: service.accounts.close_session(caller))
    response = RedirectResponse("/signin", status_code=303)
    response.delete_cookie(
        session_cookie(request.scope), path="/", httponly=True, samesite="strict", secure=over_https(request.scope)
    )
    return response


def error_page(request: Request, exc: ApiError | KittiEvalError | HTTPException) -> Response:
    """A refusal or failure as a page (the status the JSON API would answer)."""
    return _error_page(request, exc)


def _error_page(request: Request, exc: ApiError | KittiEvalError | HTTPException) -> Response:
    message = exc.detail if isinstance(exc, HTTPException) else str(exc)
    return render_page(request, "error.html", status_of(exc), status=status_of(exc), message=clip(str(message)))


def _url(path: str, **params: Any) -> str:
    """``path?query``; list values repeat the key, None values are left out."""
    query = urlencode({k: v for k, v in params.items() if v is not None}, doseq=True)
    return f"{path}?{query}" if query else path


def model_name(record: EvaluationRecord) -> str:
    """How a page names an evaluation: its ``model`` label, else the predictions' file name."""
    return record.labels.get("model") or record.pred_filename


# -------------------------------------------------------------------------------------------------- home


def _history(service: Service, caller: Caller) -> list[dict[str, Any]]:
    rows = []
    for record in service.evaluations.listed(caller, limit=_HISTORY):
        summary = {cls: (record.summary.get(cls) or {}).get("3d") for cls in _SUMMARY_CLASSES}
        rows.append({"record": record, "name": model_name(record), "summary": summary})
    return rows


def _home(
    request: Request,
    service: Service,
    caller: Caller,
    *,
    status: int = 200,
    error: str | None = None,
    form: Mapping[str, str] | None = None,
) -> Response:
    return render_page(
        request,
        "home.html",
        status,
        error=error,
        form=dict(form or {}),
        ground_truths=[g.name for g in service.gt_catalog.to_evaluate(caller)],
        projects=_projects(service, caller),
        protocols=sorted(PROTOCOLS),
        history=_history(service, caller),
        summary_classes=_SUMMARY_CLASSES,
        max_upload_bytes=service.settings.max_upload_bytes,
        idempotency_key=new_form_key(),
    )


def _projects(service: Service, caller: Caller) -> list[str]:
    """The projects an upload from the form may go to (accounts mode): the caller's, every one for admins."""
    return service.policy.projects_of(caller, service.accounts.projects)


@router.get("/")
def home(request: Request, service: ServiceDep, caller: ReaderCaller) -> Response:
    return _home(request, service, caller)


@router.post("/ui/evaluations")
async def upload(request: Request, service: ServiceDep, caller: WriterCaller) -> Response:
    """The upload form: evaluate (with curves; with the error decomposition when its box is ticked) and
    redirect to the new evaluation's page."""
    values: dict[str, str] = {}
    try:
        async with request.form(max_files=1, max_fields=FORM_MAX_FIELDS) as form:
            values = {k: v for k, v in form.items() if isinstance(v, str)}
            predictions = form.get("predictions")
            if not isinstance(predictions, UploadFile) or not predictions.filename:
                raise BadRequest("choose a predictions file (a result.pkl, .pkl.gz, or a zip/tar of KITTI txt results)")
            labels = parse_labels({"model": values.get("model", "").strip()}, [])
            options = EvalOptions(
                protocol=values.get("protocol", "official"), curves=True, errors=values.get("errors") == "true"
            )
            upload = FileIn(predictions.file, predictions.filename)
            idempotency_key = parse_key(values.get(FORM_FIELD) or None)  # the form's own: sent again, one evaluation
            job = await service.accept(
                lambda: service.evaluations.accept(
                    upload,
                    values.get("gt") or None,
                    None,
                    options,
                    labels,
                    caller,
                    values.get("project") or None,
                    enqueue=service.enqueue_evaluation(caller),
                    idempotency_key=idempotency_key,
                )
            )
        await service.outcome(job.id, min(service.settings.wait_s, FORM_WAIT_S))  # else its page follows it
    except Exception as e:  # the refusals the JSON API answers 4xx, and a full disk (507)
        failure: ApiError | KittiEvalError | HTTPException | None = (
            e
            if isinstance(e, (ApiError, KittiEvalError, HTTPException))
            else fault_of(e, service.settings.retry_after_s)
        )
        if failure is None:
            raise
        message = failure.detail if isinstance(failure, HTTPException) else str(failure)
        refill = {k: clip(v) for k, v in values.items()}  # the form as sent, within bounds
        return await anyio.to_thread.run_sync(
            partial(_home, request, service, caller, status=status_of(failure), error=clip(str(message)), form=refill)
        )
    return RedirectResponse(f"/evaluations/{quote(job.id)}", status_code=303)


# -------------------------------------------------------------------------------------------- evaluation

#: how long the upload form waits for the evaluation before it shows the evaluation's page (which follows it)
FORM_WAIT_S = 10.0
#: how often the page of an evaluation still queued or running reloads itself
REFRESH_S = 2


def _job_page(request: Request, job: JobRecord, position: int | None) -> Response:
    """An accepted evaluation that is not stored: queued (with its place), running (both reload themselves
    every ``REFRESH_S`` without a script), failed with the reason its input was refused, or cancelled."""
    failure = JobFailed(job.error) if job.state == "failed" else None
    if job.state == "queued":
        text = queued_text(position)
    else:
        text = {"running": "being evaluated", "failed": "failed", "cancelled": "cancelled by an admin"}.get(
            job.state, job.state
        )
    status = failure.status_code if failure is not None else 409 if job.state == "cancelled" else 200
    return render_page(
        request,
        "job.html",
        status,
        job=job,
        state=job.state,
        text=text,
        refresh=REFRESH_S if job.state in ("queued", "running") else None,
        reason=clip(failure.message) if failure is not None else None,
        accepted=job.accepted_at.strftime("%Y-%m-%d %H:%M:%S UTC"),
    )


def score_tables(result: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One table per threshold set and recall mode: rows class × metric, cells per difficulty."""
    tables = []
    for oset in result["threshold_sets"]:
        for recall in _RECALLS:
            by_class = result["ap"][oset][recall]
            rows = [
                {
                    "cls": cls,
                    "metric": metric,
                    "cells": [
                        {"key": f"{oset}/{recall}/{cls}/{metric}/{d}", "value": values.get(d)} for d in _DIFFICULTIES
                    ],
                }
                for cls in result["classes"]
                for metric, values in by_class[cls].items()
            ]
            overlaps = {cls: result["overlaps"][cls][oset] for cls in result["classes"]}
            tables.append({"set": oset, "recall": recall, "rows": rows, "overlaps": overlaps})
    return tables


def curve_charts(result: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per threshold set: per class, one precision-recall chart per metric (empty without curves)."""
    curves = result.get("curves")
    if not curves:
        return []
    out = []
    for oset, by_class in curves.items():
        classes = []
        for cls, by_metric in by_class.items():
            charts = [
                {"metric": metric, "chart": pr_chart(by_difficulty, result["ap"][oset]["R40"][cls][metric])}
                for metric, by_difficulty in by_metric.items()
                if by_difficulty
            ]
            classes.append({"cls": cls, "charts": charts})
        out.append({"set": oset, "classes": classes})
    return out


def error_charts(result: Mapping[str, Any], difficulty: str, recall: str) -> dict[str, Any] | None:
    """The error decomposition of one difficulty and recall mode (the strict thresholds): per class a bar
    chart (groups per metric, a bar per error type, all classes on one scale) and the true-positive errors of
    every difficulty. None when the evaluation has no decomposition; ``error`` says why a choice is not shown."""
    if "errors" not in result:
        return None
    section: dict[str, Any] = {"set": ERRORS_SET, "recall": recall, "difficulty": difficulty, "classes": []}
    if recall not in _RECALLS or difficulty not in result["difficulties"]:
        section["error"] = (
            f"no error decomposition for {echo(recall)}, {echo(difficulty)}: "
            f"choose a difficulty of {', '.join(result['difficulties'])} and R40 or R11"
        )
        return section
    table = result["errors" if recall == "R40" else "errors_r11"]
    groups = {  # a difficulty not evaluated shows every type without a value
        cls: {
            metric: dict(by_diff.get(difficulty) or dict.fromkeys(AOS_TYPES if metric == "aos" else ERROR_TYPES))
            for metric, by_diff in by_metric.items()
        }
        for cls, by_metric in table.items()
    }
    values = [v for g in groups.values() for kinds in g.values() for v in kinds.values() if v is not None]
    lo, hi = min(values, default=0.0), max(values, default=0.0)
    for cls, by_metric in groups.items():
        tp = result["tp_errors"].get(cls) or {}
        rows = [{"difficulty": d, "values": {k: (tp.get(d) or {}).get(k) for k in TP_ERRORS}} for d in tp]
        section["classes"].append({"cls": cls, "chart": bar_chart(by_metric, lo=lo, hi=hi), "tp": rows})
    section["error"] = None
    return section


async def _worst_frames(
    service: Service, record: EvaluationRecord, choice: Mapping[str, str], caller: Caller
) -> dict[str, Any]:
    section: dict[str, Any] = {"rows": [], "error": None}
    try:
        found = await service.run(
            partial(
                service.evaluation_frames.frames,
                record.id,
                FrameQuestion(choice["cls"], choice["metric"], choice["difficulty"], choice["set"]),
                worst=_WORST,
                caller=caller,
            )
        )
    except (ApiError, KittiEvalError) as e:
        section["error"] = clip(str(e))
        return section
    for row in found["frames"]:
        row = dict(row)
        row["href"] = _url(f"/frames/{quote(str(row['frame']))}", e=record.id, **choice)
        section["rows"].append(row)
    return section


@router.get("/evaluations/{evaluation_id}")
async def evaluation_page(
    request: Request,
    service: ServiceDep,
    caller: ReaderCaller,
    evaluation_id: str,
    cls: str | None = None,
    metric: str = "3d",
    difficulty: str = "moderate",
    oset: Annotated[str | None, Query(alias="set")] = None,
    err_difficulty: str = "moderate",
    err_recall: str = "R40",
) -> Response:
    try:
        record = await anyio.to_thread.run_sync(service.evaluations.get, evaluation_id, caller)
    except NotFound as e:  # accepted and not done yet (or failed): its job's page, which follows it
        pending = await anyio.to_thread.run_sync(service.evaluations.job_of, evaluation_id, caller)
        if pending is None:
            return _error_page(request, e)
        return _job_page(request, *pending)
    except ApiError as e:
        return _error_page(request, e)
    result = record.result
    assert result is not None
    sets = list(result["threshold_sets"])
    choice = {
        "cls": cls or result["classes"][0],
        "metric": metric,
        "difficulty": difficulty,
        "set": oset or ("strict" if "strict" in sets else sets[0]),
    }
    return render_page(
        request,
        "evaluation.html",
        record=record,
        result=result,
        name=model_name(record),
        tables=score_tables(result),
        curves=curve_charts(result),
        errors=error_charts(result, err_difficulty, err_recall),
        choice=choice,
        error_choice={"err_difficulty": err_difficulty, "err_recall": err_recall},
        choices={
            "cls": result["classes"],
            "metric": result["metrics"],
            "difficulty": result["difficulties"],
            "set": sets,
        },
        worst=await _worst_frames(service, record, choice, caller),
    )


# ------------------------------------------------------------------------------------------------ compare


def compare_tables(comparison: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The comparison's AP values per threshold set and recall mode (R40 first): rows class × metric, cells
    (a, b, b - a) per difficulty (error-type values, Class/metric/difficulty/type/recall, are not AP)."""
    tables: dict[tuple[str, str], dict[tuple[str, str], dict[str, dict[str, Any]]]] = {}
    for v in _ap_values(comparison):
        cls, metric, d, recall, oset = v["key"].split("/")
        cell = {"key": f"{oset}/{recall}/{cls}/{metric}/{d}", "a": v["a"], "b": v["b"], "delta": v["delta"]}
        tables.setdefault((oset, recall), {}).setdefault((cls, metric), {})[d] = cell
    order = sorted(tables, key=lambda t: (comparison_sets(comparison).index(t[0]), _RECALLS.index(t[1])))
    return [
        {
            "set": oset,
            "recall": recall,
            "rows": [
                {"cls": cls, "metric": metric, "cells": [cells[d] for d in _DIFFICULTIES]}
                for (cls, metric), cells in tables[(oset, recall)].items()
            ],
        }
        for oset, recall in order
    ]


def comparison_sets(comparison: Mapping[str, Any]) -> list[str]:
    """The threshold sets of a comparison's AP values, in their order."""
    return list(dict.fromkeys(v["key"].rsplit("/", 1)[1] for v in _ap_values(comparison)))


def _ap_values(comparison: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [v for v in comparison["values"] if v["key"].rsplit("/", 1)[1] not in _RECALLS]


@router.get("/compare")
def compare_page(
    request: Request,
    service: ServiceDep,
    caller: ReaderCaller,
    a: str | None = None,
    b: str | None = None,
    e: Annotated[list[str] | None, Query()] = None,
) -> Response:
    """``?a=<base>&b=<other>``; or ``?e=<id>&e=<id>`` (the history form without JavaScript), older first."""
    try:
        if a is None and b is None and e is not None and len(e) == 2:
            a, b = sorted(e, key=lambda i: service.evaluations.get(i, caller).created_at)
        if not a or not b:
            raise BadRequest("compare needs two evaluations: /compare?a=<base id>&b=<other id>")
        base, other = service.evaluations.get(a, caller), service.evaluations.get(b, caller)
    except ApiError as exc:
        return _error_page(request, exc)
    assert base.result is not None and other.result is not None
    comparison = compare(base, other)
    return render_page(
        request,
        "compare.html",
        base=base,
        other=other,
        names=(model_name(base), model_name(other)),
        comparison=comparison,
        tables=compare_tables(comparison),
    )


# -------------------------------------------------------------------------------------------------- frame


def _parse_score(text: str | None) -> float | None:
    """The score threshold of the frame page: empty for none, else a finite number within the API's bound."""
    if text is None or not text.strip():
        return None
    try:
        score = float(text)
    except ValueError:
        score = math.nan
    if not -MAX_SCORE <= score <= MAX_SCORE:  # also not NaN
        raise BadRequest(f"score threshold must be a number between {-MAX_SCORE:g} and {MAX_SCORE:g}, got {echo(text)}")
    return score


def frame_models(
    data: Mapping[str, Any], ids: Sequence[str], url: Callable[[Sequence[str]], str]
) -> list[dict[str, Any]]:
    """Per evaluation of an inspected frame: its rows and counts as inspected, a bird's-eye view (all views of
    the frame at one scale) and the link that drops it from the view."""
    models = data["models"]
    everything = [d for m in models.values() for d in m["detections"]]
    out = []
    for name, model in models.items():
        others = [i for i in ids if i != model["evaluation"]]
        out.append(
            {
                "name": name,
                **model,
                "bev": bev_view(data["ground_truth"], model["detections"], missed=model["missed"], extent=everything),
                "remove": url(others) if others else None,
            }
        )
    return out


@router.get("/frames/{frame_id}")
async def frame_page(
    request: Request,
    service: ServiceDep,
    caller: ReaderCaller,
    frame_id: str,
    e: Annotated[list[str] | None, Query()] = None,
    cls: str = "Car",
    metric: str = "3d",
    difficulty: str = "moderate",
    oset: Annotated[str, Query(alias="set")] = "strict",
    score: str | None = None,
) -> Response:
    """One frame: the ground truth, then each evaluation's detections with their labels, side by side."""
    ids = list(dict.fromkeys(i for i in e or () if i))  # the "add" select may send an empty value
    # the choice as the form shows it again (a value of any length is shown in part)
    choice = {k: clip(v, MAX_ECHO_CHARS) for k, v in (("cls", cls), ("metric", metric), ("difficulty", difficulty))}
    choice.update(set=clip(oset, MAX_ECHO_CHARS), score=clip(score or "", MAX_ECHO_CHARS))

    def url(with_ids: Sequence[str]) -> str:
        return _url(
            f"/frames/{quote(frame_id)}",
            e=list(with_ids),
            cls=cls,
            metric=metric,
            difficulty=difficulty,
            set=oset,
            score=score or None,
        )

    listed = await anyio.to_thread.run_sync(partial(service.evaluations.listed, caller, limit=_HISTORY))
    history = [{"id": r.id, "name": model_name(r), "created_at": r.created_at} for r in listed if r.id not in ids]
    context: dict[str, Any] = {
        "frame": clip(frame_id, MAX_ECHO_CHARS),
        "ids": ids,
        "choice": choice,
        "history": history,
        "classes": list(dict.fromkeys((*KNOWN_CLASSES, choice["cls"]))),
        "metrics": [m.value for m in ALL_METRICS],
        "difficulties": _DIFFICULTIES,
        "data": None,
        "models": [],
        "error": None,
    }
    try:
        if not ids:
            raise BadRequest("name at least one evaluation: /frames/<frame>?e=<evaluation id>")
        data = await service.run(
            partial(
                service.evaluation_frames.inspect,
                ids,
                frame_id,
                cls=cls,
                metric=metric,
                difficulty=difficulty,
                oset=oset,
                score_threshold=_parse_score(score),
                caller=caller,
            )
        )
    except (ApiError, KittiEvalError) as exc:
        context["error"] = clip(str(exc))
        return render_page(request, "frame.html", status_of(exc), **context)
    context.update(data=data, models=frame_models(data, ids, url))
    return render_page(request, "frame.html", **context)
