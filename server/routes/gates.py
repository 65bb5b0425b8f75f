"""``/v1/gates``: the CLI's gate rules against stored evaluations, so CI can gate with one request."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Query
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

from ..access.deps import ReaderCaller
from ..errors import BadRequest, NotFound
from ..params import ServiceDep
from ..schemas import ErrorResponse
from ..scoring.evaluator import parse_labels

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
