"""``/v1/evaluations``: upload predictions and get AP back; history; comparisons."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, Literal

import anyio.to_thread
from fastapi import APIRouter, Depends, File, Form, Header, Query, UploadFile
from fastapi.responses import JSONResponse, PlainTextResponse, Response

from kitti_eval.core.result import EvalResult
from kitti_eval.report.render import OutputFormat, render

from ..access.deps import FormatDep, ReaderCaller, WriterCaller
from ..errors import BadRequest
from ..evaluations.compare import compare, render_comparison_markdown
from ..idempotency import IDEMPOTENCY_DESCRIPTION, parse_key
from ..params import ServiceDep
from ..schemas import (
    Comparison,
    ErrorResponse,
    EvaluationList,
    EvaluationResponse,
    evaluation_response,
    evaluation_summary,
)
from ..scoring.evaluator import EvalOptions, parse_labels
from ..service import FileIn
from ..store import EvaluationRecord
from .jobs import still_pending

_errors: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "unknown evaluation or ground truth"},
    422: {
        "model": ErrorResponse,
        "description": "invalid request, input (names frame and field) or unsafe pickle; an Idempotency-Key sent "
        "before with another request (idempotency_key_reused)",
    },
}
router = APIRouter(prefix="/v1/evaluations", tags=["evaluations"], responses=_errors)

_TEXT_RESPONSES: dict[str, Any] = {
    "text/plain": {"schema": {"type": "string"}},
    "text/markdown": {"schema": {"type": "string"}},
}
_MEDIA = {OutputFormat.TABLE: "text/plain; charset=utf-8", OutputFormat.MARKDOWN: "text/markdown; charset=utf-8"}


def eval_options_form(
    protocol: Annotated[Literal["official", "openpcdet"], Form()] = "official",
    classes: Annotated[str, Form(description="comma-separated, e.g. Car,Van")] = "Car,Pedestrian,Cyclist",
    threshold_sets: Annotated[str, Form(description="strict, loose or strict,loose")] = "strict,loose",
    iou: Annotated[
        list[str] | None, Form(description="IoU thresholds as the CLI's --iou: CLASS[:SET]=BBOX,BEV,3D; repeatable")
    ] = None,
    curves: Annotated[bool, Form(description="include the 41-point curves in the JSON")] = False,
    errors: Annotated[
        bool,
        Form(
            description="also why AP is lost, as --errors: 'errors', 'errors_r11' and 'tp_errors' in the JSON "
            "(the strict IoU thresholds; see 'kitti-eval errors --help')"
        ),
    ] = False,
    ranges: Annotated[str | None, Form(description="also by distance, e.g. 0,30,50,inf (as --ranges)")] = None,
    coco: Annotated[bool, Form(description="also COCO-style AP over ten IoU thresholds (as --coco)")] = False,
    lidar_only: Annotated[bool, Form(description="BEV and 3D only, for sets without images (as --lidar-only)")] = False,
) -> EvalOptions:
    """An evaluation's options from the form, as the CLI's flags: what ``POST /v1/evaluations`` and a gate's
    evaluation (``POST /v1/gates/evaluations``) take alike."""
    return EvalOptions(
        protocol=protocol,
        classes=classes,
        threshold_sets=threshold_sets,
        iou=tuple(iou or ()),
        curves=curves,
        errors=errors,
        ranges=ranges,
        coco=coco,
        lidar_only=lidar_only,
    )


EvalOptionsForm = Annotated[EvalOptions, Depends(eval_options_form)]


def text_answer(result: Mapping[str, Any], fmt: OutputFormat, status: int, headers: dict[str, str]) -> Response:
    """An evaluation's document (``result``) rendered as the table or Markdown ``fmt`` asks for."""
    text = render(EvalResult.from_dict(result), fmt)
    return PlainTextResponse(text, status_code=status, headers=headers, media_type=_MEDIA[fmt])


def _respond(record: EvaluationRecord, fmt: OutputFormat, status: int = 200) -> Response:
    headers = {"X-Evaluation-Id": record.id, "Location": f"/v1/evaluations/{record.id}"}
    if fmt is OutputFormat.JSON:
        return JSONResponse(evaluation_response(record), status_code=status, headers=headers)
    assert record.result is not None
    return text_answer(record.result, fmt, status, headers)


@router.post(
    "",
    status_code=201,
    response_model=EvaluationResponse,
    summary="Evaluate uploaded predictions",
    responses={
        201: {"content": _TEXT_RESPONSES, "description": "the evaluation, stored"},
        400: {"model": ErrorResponse, "description": "the Idempotency-Key is not 1-255 visible ASCII characters"},
        408: {"model": ErrorResponse, "description": "the upload took longer than KITTI_EVAL_BODY_TIMEOUT_S to arrive"},
        413: {"model": ErrorResponse, "description": "the upload is larger than KITTI_EVAL_MAX_UPLOAD_MB"},
        503: {
            "model": ErrorResponse,
            "description": "every evaluation slot is taken, or too many uploads are arriving; see Retry-After",
        },
    },
)
async def create_evaluation(
    service: ServiceDep,
    caller: WriterCaller,
    fmt: FormatDep,
    options: EvalOptionsForm,
    predictions: Annotated[
        UploadFile,
        File(
            description="an OpenPCDet result.pkl (or .pkl.gz), or a zip/tar of "
            "KITTI result txt files (16 fields, one file per frame)"
        ),
    ],
    gt: Annotated[str | None, Form(description="name of a registered ground truth, e.g. demo")] = None,
    gt_file: Annotated[
        UploadFile | None,
        File(
            description="instead of gt: an infos .pkl[.gz] or a zip/tar of a "
            "label_2 folder, used for this evaluation only"
        ),
    ] = None,
    model: Annotated[str | None, Form(description="label: the model's name")] = None,
    commit: Annotated[str | None, Form(description="label: the code commit")] = None,
    epoch: Annotated[str | None, Form(description="label: the training epoch")] = None,
    label: Annotated[list[str] | None, Form(description="more labels as key=value; repeatable")] = None,
    project: Annotated[
        str | None,
        Form(
            description="accounts mode: the project the evaluation belongs to (default: the ground truth's, "
            "else your only one); ignored in open mode"
        ),
    ] = None,
    wait: Annotated[
        float | None,
        Query(
            ge=0,
            le=3600,
            description="seconds to wait for the result (default KITTI_EVAL_WAIT_S, 600): 201 with the evaluation "
            "when it is done by then, else 202 with the job to poll (GET its Location); 0 answers at once",
        ),
    ] = None,
    idempotency_key: Annotated[
        str | None, Header(alias="Idempotency-Key", description=IDEMPOTENCY_DESCRIPTION, max_length=1000)
    ] = None,
) -> Response:
    """Evaluate `predictions` against a ground truth and store the result with the inputs' sha256 and the
    labels. The JSON is the document `kitti-eval --format json` prints, plus `id` and `evaluation`."""
    checked_key = parse_key(idempotency_key)  # the Idempotency-Key header, checked
    labels = parse_labels({"model": model, "commit": commit, "epoch": epoch}, label or [])
    gt_in = FileIn(gt_file.file, gt_file.filename) if gt_file is not None else None
    job = await service.accept(
        lambda: service.evaluations.accept(
            FileIn(predictions.file, predictions.filename),
            gt or None,
            gt_in,
            options,
            labels,
            caller,
            project or None,
            enqueue=service.enqueue_evaluation(caller),
            idempotency_key=checked_key,
        )
    )
    ended = await service.outcome(job.id, wait)
    if ended.state != "done":
        return await still_pending(service.jobs, ended)
    assert ended.result_id is not None
    record = await anyio.to_thread.run_sync(service.evaluations.get, ended.result_id, caller)
    return _respond(record, fmt, status=201)


@router.get("", response_model=EvaluationList, summary="History, newest first")
def list_evaluations(
    service: ServiceDep,
    caller: ReaderCaller,
    gt: Annotated[str | None, Query(description="only evaluations against this registered ground truth")] = None,
    model: str | None = None,
    commit: str | None = None,
    epoch: str | None = None,
    label: Annotated[list[str] | None, Query(description="key=value; repeatable; all must match")] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000, description="skip this many (at most 10^9)")] = 0,
) -> dict[str, Any]:
    labels = parse_labels({"model": model, "commit": commit, "epoch": epoch}, label or [])
    records = service.evaluations.listed(caller, gt_name=gt, labels=labels, limit=limit + 1, offset=offset)
    more = len(records) > limit
    return {
        "items": [evaluation_summary(r) for r in records[:limit]],
        "limit": limit,
        "offset": offset,
        "next_offset": offset + limit if more else None,
    }


@router.get(
    "/{evaluation_id}",
    response_model=EvaluationResponse,
    summary="One evaluation",
    responses={200: {"content": _TEXT_RESPONSES}},
)
def get_evaluation(service: ServiceDep, caller: ReaderCaller, fmt: FormatDep, evaluation_id: str) -> Response:
    return _respond(service.evaluations.get(evaluation_id, caller), fmt)


@router.get(
    "/{evaluation_id}/compare/{other_id}",
    response_model=Comparison,
    summary="Per-value differences: other minus base",
    responses={200: {"content": {"text/markdown": {"schema": {"type": "string"}}}}},
)
def compare_evaluations(
    service: ServiceDep, caller: ReaderCaller, fmt: FormatDep, evaluation_id: str, other_id: str
) -> Response:
    base, other = service.evaluations.get(evaluation_id, caller), service.evaluations.get(other_id, caller)
    comparison = compare(base, other)
    if fmt is OutputFormat.JSON:
        return JSONResponse(comparison)
    if fmt is OutputFormat.MARKDOWN:
        return PlainTextResponse(render_comparison_markdown(base, other), media_type=_MEDIA[fmt])
    raise BadRequest("a comparison renders as json or markdown")
