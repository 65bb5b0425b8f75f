"""``/v1/gates``: the CLI's gate rules against stored evaluations, so CI can gate with one request; and
``/v1/gates/evaluations``: an evaluation a gate asks for without keeping it (a read-only token's), whose result
its owner reads once (:mod:`kitti_eval_server.evaluations.gate_evaluations`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import anyio.to_thread
from fastapi import APIRouter, File, Form, Header, Query, UploadFile
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from kitti_eval.analysis.gate import (
    GateRules,
    Verdict,
    render_junit,
    render_verdict_markdown,
    rules_from_options,
    run_gate,
)
from kitti_eval.errors import ConfigError
from kitti_eval.report.render import OutputFormat

from ..access.deps import FormatDep, ReaderCaller
from ..errors import BadRequest, NotFound
from ..idempotency import IDEMPOTENCY_DESCRIPTION, parse_key
from ..params import ServiceDep
from ..schemas import ErrorResponse, EvaluationResponse
from ..scoring.evaluator import parse_labels
from ..service import FileIn
from .evaluations import EvalOptionsForm, text_answer
from .jobs import still_pending

router = APIRouter(
    prefix="/v1/gates",
    tags=["gates"],
    responses={
        404: {"model": ErrorResponse, "description": "unknown evaluation or no baseline"},
        422: {"model": ErrorResponse, "description": "invalid rules"},
    },
)


class GateRequest(BaseModel):
    """Rules as the CLI's: values named Class/metric/difficulty[/R40|R11[/strict|loose]]."""

    evaluation: str = Field(description="id of the evaluation to gate")
    baseline: str | None = Field(None, description="id of the baseline evaluation")
    baseline_label: str | None = Field(
        None,
        description="instead of baseline: the newest evaluation with this label (key=value, e.g. "
        "branch=main) against the same ground truth",
    )
    min: list[str] = Field(default_factory=list, description="floors, e.g. 'Car/3d/moderate >= 78.5'")
    max_drop: list[str] = Field(default_factory=list, description="'0.5' (every value) or 'Car/3d/moderate=1.0'")
    require_classes: list[str] = Field(default_factory=list)


class GateCheck(BaseModel):
    rule: str
    key: str
    passed: bool
    current: float | None = None
    baseline: float | None = None
    delta: float | None = None
    message: str = ""


class GateResponse(BaseModel):
    passed: bool
    evaluation: str
    baseline: str | None
    checks: list[GateCheck]


def _rules(req: GateRequest) -> GateRules:
    """The library's reading of the rules (the CLI's): min are floors, max_drop maximum drops."""
    try:
        return rules_from_options(
            req.min, req.max_drop, req.require_classes, baseline=bool(req.baseline or req.baseline_label)
        )
    except ConfigError as e:
        raise BadRequest(str(e)) from None


@router.post(
    "",
    response_model=GateResponse,
    summary="Check AP rules on a stored evaluation",
    responses={412: {"model": GateResponse, "description": "a rule failed (same body as 200)"}},
)
def run_gate_request(
    req: GateRequest,
    service: ServiceDep,
    caller: ReaderCaller,
    format: Literal["json", "markdown", "junit"] = Query("json"),  # noqa: A002
) -> Response:
    """200 when every rule passes, 412 when one fails (so `curl --fail-with-body` gates a CI job), with the
    verdict as JSON, Markdown or JUnit XML."""
    rules = _rules(req)
    current = service.evaluations.get(req.evaluation, caller)
    baseline = None
    if req.baseline:
        baseline = service.evaluations.get(req.baseline, caller)
    elif req.baseline_label:
        wanted = parse_labels({}, [req.baseline_label])
        found = [
            r
            for r in service.evaluations.listed(caller, gt_name=current.gt_name, labels=wanted, limit=2)
            if r.id != current.id
        ]
        if not found:
            raise NotFound(f"no evaluation labelled {req.baseline_label} against the same ground truth")
        baseline = service.evaluations.get(found[0].id, caller)
    assert current.result is not None
    try:
        verdict: Verdict = run_gate(current.result, rules, baseline.result if baseline else None)
    except ConfigError as e:
        raise BadRequest(str(e)) from None
    status = 200 if verdict.passed else 412
    if format == "markdown":
        return Response(render_verdict_markdown(verdict), status_code=status, media_type="text/markdown")
    if format == "junit":
        return Response(render_junit(verdict), status_code=status, media_type="application/xml")
    body: dict[str, Any] = {
        "passed": verdict.passed,
        "evaluation": current.id,
        "baseline": baseline.id if baseline else None,
        "checks": [
            {
                "rule": c.rule,
                "key": c.key,
                "passed": c.passed,
                "current": c.current,
                "baseline": c.baseline,
                "delta": c.delta,
                "message": c.message,
            }
            for c in verdict.checks
        ],
    }
    return JSONResponse(body, status_code=status)


def _gate_result(document: dict[str, Any], fmt: OutputFormat, status: int) -> Response:
    headers = {"X-Evaluation-Kept": "false"}
    if fmt is OutputFormat.JSON:
        return JSONResponse(document, status_code=status, headers=headers)
    return text_answer({k: v for k, v in document.items() if k not in ("id", "evaluation")}, fmt, status, headers)


@router.post(
    "/evaluations",
    status_code=201,
    response_model=EvaluationResponse,
    summary="Evaluate uploaded predictions for a gate, without keeping them (a read-only token will do)",
    responses={
        201: {"description": "the result, given this once: no evaluation is stored"},
        202: {"description": "the job to poll; once done, its result_location gives the result once"},
        403: {"model": ErrorResponse, "description": "a benchmark's test set"},
        408: {"model": ErrorResponse, "description": "the upload took longer than KITTI_EVAL_BODY_TIMEOUT_S to arrive"},
        413: {"model": ErrorResponse, "description": "the upload is larger than KITTI_EVAL_MAX_UPLOAD_MB"},
        503: {"model": ErrorResponse, "description": "every evaluation slot is taken; see Retry-After"},
    },
)
async def create_gate_evaluation(
    service: ServiceDep,
    caller: ReaderCaller,
    fmt: FormatDep,
    options: EvalOptionsForm,
    predictions: Annotated[UploadFile, File(description="as POST /v1/evaluations' predictions")],
    gt: Annotated[str | None, Form(description="name of a registered ground truth, e.g. demo")] = None,
    gt_file: Annotated[UploadFile | None, File(description="instead of gt: as POST /v1/evaluations' gt_file")] = None,
    wait: Annotated[
        float | None,
        Query(ge=0, le=3600, description="as POST /v1/evaluations' wait: 201 with the result, else 202 with the job"),
    ] = None,
    idempotency_key: Annotated[
        str | None, Header(alias="Idempotency-Key", description=IDEMPOTENCY_DESCRIPTION, max_length=1000)
    ] = None,
) -> Response:
    """Evaluate `predictions` as `POST /v1/evaluations` does, with the same options, keeping nothing: no evaluation
    is stored (none shows in any list), the predictions are not kept, and the result is given to the caller once
    (in this answer, or from the job's `result_location`), then deleted; unread, it is deleted after ten
    minutes. For a gate with a read-only token: the rules are the client's to check on the document."""
    key = parse_key(idempotency_key)
    gt_in = FileIn(gt_file.file, gt_file.filename) if gt_file is not None else None
    job = await service.accept(
        lambda: service.gate_evaluations.accept(
            FileIn(predictions.file, predictions.filename),
            gt or None,
            gt_in,
            options,
            caller,
            enqueue=service.enqueue_evaluation(caller, "gate"),
            idempotency_key=key,
        )
    )
    ended = await service.outcome(job.id, wait)
    if ended.state != "done":
        return await still_pending(service.jobs, ended)
    assert ended.result_id is not None
    document = await anyio.to_thread.run_sync(service.gate_evaluations.take, ended.result_id, caller)
    return _gate_result(document, fmt, 201)


@router.get(
    "/evaluations/{result_id}",
    response_model=EvaluationResponse,
    summary="The result of an evaluation for a gate, once (then it is deleted)",
    responses={404: {"model": ErrorResponse, "description": "not yours, read already, or older than ten minutes"}},
)
def get_gate_evaluation(service: ServiceDep, caller: ReaderCaller, fmt: FormatDep, result_id: str) -> Response:
    """The result of a gate evaluation of yours, once: read, it is deleted."""
    return _gate_result(service.gate_evaluations.take(result_id, caller), fmt, 200)
