"""Response models: they document the JSON in OpenAPI; the routes build the same shapes as plain dicts."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from .store import EvaluationRecord, GroundTruthRecord

__all__ = [
    "ErrorBody",
    "ErrorResponse",
    "EvaluationMeta",
    "EvaluationResponse",
    "EvaluationSummary",
    "EvaluationList",
    "GroundTruthOut",
    "GroundTruthList",
    "Comparison",
    "Health",
    "evaluation_meta",
    "evaluation_response",
    "evaluation_summary",
    "ground_truth_out",
]

APValues = dict[str, dict[str, dict[str, dict[str, dict[str, float | None]]]]]
ErrorValues = dict[str, dict[str, dict[str, dict[str, float | None] | None]]]


class ErrorBody(BaseModel):
    code: str = Field(description="machine-readable, e.g. invalid_input, unsafe_pickle, payload_too_large, busy")
    message: str = Field(
        description="what went wrong, naming the file, frame and field where known; at most 1000 characters "
        "(a longer one is cut and says how long it was)"
    )
    frame: str | None = Field(None, description="the frame at fault, for input errors")
    field: str | None = Field(None, description="the field at fault, for input errors")


class ErrorResponse(BaseModel):
    error: ErrorBody


class GroundTruthRef(BaseModel):
    name: str | None = Field(description="registered name; null for a ground truth uploaded with the request")
    sha256: str


class PredictionsRef(BaseModel):
    filename: str
    sha256: str
    size: int
    format: str = Field(description="pickle, zip or tar")


class EvaluationMeta(BaseModel):
    created_at: datetime
    ground_truth: GroundTruthRef
    predictions: PredictionsRef
    labels: dict[str, str]
    duration_ms: float
    project: str | None = Field(None, description="accounts mode: the project it belongs to")


class EvaluationResponse(BaseModel):
    """The document ``kitti-eval --format json`` prints, plus ``id`` and ``evaluation`` (the record)."""

    model_config = ConfigDict(extra="allow")

    id: str
    schema_version: int
    protocol: str
    classes: list[str]
    threshold_sets: list[str]
    metrics: list[str]
    difficulties: list[str]
    overlaps: dict[str, dict[str, dict[str, float]]]
    ap: APValues = Field(description="ap[set][R11|R40][class][bbox|bev|3d|aos][easy|moderate|hard], percent")
    num_gt: dict[str, dict[str, int]]
    num_det: dict[str, int]
    frames: int
    frames_without_predictions: list[str]
    aos_evaluated: bool
    warnings: list[str]
    errors: ErrorValues | None = Field(
        None,
        description="with errors=true: errors[class][bbox|bev|3d|aos][easy|moderate|hard][type], the AP points "
        "(R40, strict IoU thresholds) fixing each error type alone adds: classification, localization, both, "
        "duplicate, background, missed; orientation for aos. As kitti-eval --errors",
    )
    errors_r11: ErrorValues | None = Field(None, description="with errors=true: the same in R11 AP points")
    tp_errors: dict[str, dict[str, dict[str, float | None] | None]] | None = Field(
        None,
        description="with errors=true: tp_errors[class][easy|moderate|hard][translation|scale|orientation], "
        "the mean errors of the 3D matching's true positives (metres, 1 - IoU, radians) over recall >= 0.1",
    )
    evaluation: EvaluationMeta


class EvaluationSummary(BaseModel):
    id: str
    evaluation: EvaluationMeta
    protocol: str
    summary: dict[str, dict[str, float | None]] = Field(
        description="R40 AP at moderate difficulty, strict thresholds: summary[class][metric]"
    )


class EvaluationList(BaseModel):
    items: list[EvaluationSummary]
    limit: int
    offset: int
    next_offset: int | None


class GroundTruthOut(BaseModel):
    name: str
    sha256: str
    format: str
    filename: str
    size_bytes: int
    frames: int
    boxes: int = Field(description="boxes including DontCare rows")
    created_at: datetime
    project: str | None = Field(None, description="the project whose members use it; null: everyone")
    sealed: bool = Field(False, description="a sealed test set: aggregate results only, no per-frame view")


class GroundTruthList(BaseModel):
    items: list[GroundTruthOut]


class Comparison(BaseModel):
    """``kitti-eval compare --format json`` of the two results (A = base, B = other), with the records."""

    base: dict[str, Any]
    other: dict[str, Any]
    schema_version: int
    resamples: int
    seed: int | None
    notes: list[str]
    values: list[dict[str, Any]] = Field(
        description="every value both have: key Class/metric/difficulty/"
        "recall/set, a, b, delta = b - a (null where either is)"
    )
    num_det: dict[str, int] = Field(description="detections per class, other - base")
    frames: int | None


class Health(BaseModel):
    status: str


def iso(value: datetime) -> str:
    """UTC, ISO 8601 with a Z, as pydantic writes it."""
    return value.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def evaluation_meta(record: EvaluationRecord) -> dict[str, Any]:
    meta = {
        "created_at": iso(record.created_at),
        "ground_truth": {"name": record.gt_name, "sha256": record.gt_sha256},
        "predictions": {
            "filename": record.pred_filename,
            "sha256": record.pred_sha256,
            "size": record.pred_size,
            "format": record.pred_format,
        },
        "labels": dict(record.labels),
        "duration_ms": record.duration_ms,
    }
    if record.project is not None:
        meta["project"] = record.project
    return meta


def evaluation_response(record: EvaluationRecord) -> dict[str, Any]:
    assert record.result is not None
    return {"id": record.id, **record.result, "evaluation": evaluation_meta(record)}


def evaluation_summary(record: EvaluationRecord) -> dict[str, Any]:
    return {
        "id": record.id,
        "evaluation": evaluation_meta(record),
        "protocol": record.protocol,
        "summary": dict(record.summary),
    }


def ground_truth_out(record: GroundTruthRecord) -> dict[str, Any]:
    return {
        "name": record.name,
        "sha256": record.sha256,
        "format": record.format,
        "filename": record.filename,
        "size_bytes": record.size_bytes,
        "frames": record.frames,
        "boxes": record.boxes,
        "created_at": iso(record.created_at),
        "project": record.project,
        "sealed": record.sealed,
    }
