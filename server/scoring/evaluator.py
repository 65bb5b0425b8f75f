"""The service's scoring, which users' evaluations and benchmark submissions share: request options to an
:class:`~kitti_eval.core.protocol.EvalConfig`, the calls of ``evaluate`` and the documents they make (a sealed
ground truth's withheld details), the frame listing, the labels.

Evaluations run on several threads at once: the library's kernels are compiled ``nogil`` and keep no
state, so that is safe.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from kitti_eval.analysis.decomposition import decompose_plan, errors_document
from kitti_eval.analysis.diagnostics import frame_stats, frames_document
from kitti_eval.analysis.frame_question import ASKED, FrameQuestion
from kitti_eval.analysis.ranking import evaluate_resampled
from kitti_eval.core.evaluation import Plan, Totals, plan_evaluation, result_from_counts
from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import DEFAULT_CLASSES, THRESHOLD_SETS, EvalConfig, config_from_options
from kitti_eval.core.result import ValueKey
from kitti_eval.errors import InputError
from kitti_eval.report.render import json_document

from ..errors import BadRequest, echo

__all__ = [
    "EvalOptions",
    "evaluate_document",
    "evaluated_plan",
    "evaluate_document_resampled",
    "check_image_fields",
    "summarize",
    "sealed_document",
    "frame_listing",
    "check_worst",
    "parse_labels",
    "LABEL_KEY_PATTERN",
    "ERRORS_SET",
    "MAX_RANGE_BINS",
]

LABEL_KEY_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
_LABEL_KEY = re.compile(LABEL_KEY_PATTERN)
_MAX_LABELS = 32
_MAX_LABEL_VALUE = 256
#: most distance bins an evaluation may ask for (``ranges``: one more edge): each bin is evaluated in full again
MAX_RANGE_BINS = 8
#: the threshold set the error decomposition reads (the CLI's ``--errors`` decomposes the strict one)
ERRORS_SET = "strict"


@dataclass(frozen=True)
class EvalOptions:
    """What the client asked for, as given (strings); :meth:`config` validates it."""

    protocol: str = "official"
    classes: str = ",".join(DEFAULT_CLASSES)
    threshold_sets: str = ",".join(THRESHOLD_SETS)
    iou: Sequence[str] = ()
    curves: bool = False
    errors: bool = False
    ranges: str | None = None
    coco: bool = False
    lidar_only: bool = False

    def to_dict(self) -> dict[str, Any]:
        """The options as stored with an evaluation (JSON)."""
        out = dataclasses.asdict(self)
        out["iou"] = list(self.iou)
        return out

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> EvalOptions:
        known = {f.name for f in dataclasses.fields(cls)}
        kwargs = {k: v for k, v in values.items() if k in known}
        if "iou" in kwargs:
            kwargs["iou"] = tuple(kwargs["iou"])
        return cls(**kwargs)

    def config(self) -> EvalConfig:
        """The evaluation these options ask for: the library's reading of them, as for the CLI's flags, within the
        service's bound on distance bins (:data:`MAX_RANGE_BINS`; the CLI has none)."""
        edges = [v for v in (self.ranges or "").split(",") if v.strip()]  # as the library counts them
        if len(edges) > MAX_RANGE_BINS + 1:
            raise BadRequest(
                f"ranges: at most {MAX_RANGE_BINS} distance bins ({MAX_RANGE_BINS + 1} edges, e.g. 0,30,50,inf), "
                f"got {len(edges) - 1}"
            )
        config = config_from_options(
            classes=self.classes,
            protocol=self.protocol,
            threshold_sets=self.threshold_sets,
            iou=self.iou,
            ranges=self.ranges,
            coco=self.coco,
            lidar_only=self.lidar_only,
        )
        if self.errors and ERRORS_SET not in config.threshold_sets:
            raise BadRequest(
                f"errors=true decomposes the {ERRORS_SET} IoU thresholds: add {ERRORS_SET} to threshold_sets"
            )
        return config


def evaluate_document(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig,
    *,
    curves: bool = False,
    errors: bool = False,
    gt_frames_shown: bool = False,
) -> dict[str, Any]:
    """The JSON document ``kitti-eval --format json`` prints for the same inputs, as a dict; with ``errors``,
    what ``--errors`` adds (``errors``, ``errors_r11``, ``tp_errors``), computed as the CLI does: the AP and
    the decomposition from one planned evaluation.

    ``gt_frames_shown``: whether a refusal may name a frame of the ground truth (not for a sealed one, and not
    by default)."""
    return evaluated_plan(gt, dt, config, curves=curves, errors=errors, gt_frames_shown=gt_frames_shown)[0]


def evaluated_plan(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig,
    *,
    curves: bool = False,
    errors: bool = False,
    gt_frames_shown: bool = False,
) -> tuple[dict[str, Any], Plan]:
    """:func:`evaluate_document`'s document and the plan it was computed from (its overlaps and matchings,
    for what an evaluation stores of each frame: :func:`.frame_rows.frame_rows`)."""
    check_image_fields(gt, dt, config, gt_frames_shown=gt_frames_shown)
    plan = plan_evaluation(gt, dt, config)
    result = result_from_counts(plan, plan.counts(), Totals.of(plan), keep_curves=curves)
    extra = errors_document(decompose_plan(plan, oset=ERRORS_SET), full=False) if errors else None
    doc = json_document(result, include_curves=curves, extra=extra)
    return doc, plan


def evaluate_document_resampled(
    gt: Annotations, dt: Annotations, config: EvalConfig, keys: Sequence[ValueKey], weights: npt.NDArray[np.int64]
) -> tuple[dict[str, Any], npt.NDArray[np.float64]]:
    """:func:`evaluate_document`'s document (no curves, no errors) and the mean of ``keys`` under each row of
    frame ``weights`` (:func:`kitti_eval.analysis.ranking.evaluate_resampled`), from one planned evaluation."""
    check_image_fields(gt, dt, config, gt_frames_shown=False)
    result, values = evaluate_resampled(gt, dt, config, keys, weights)
    return json_document(result), values


def check_image_fields(gt: Annotations, dt: Annotations, config: EvalConfig, *, gt_frames_shown: bool) -> None:
    """The library's refusal of boxes without image fields (a LiDAR-only set) unless ``lidar_only``, said in
    the service's terms (the form field, not the CLI's flag), naming the ground truth's first such frame only
    when ``gt_frames_shown`` (never a sealed set's); the predictions' own frames are the client's to know."""
    if config.lidar_only:
        return
    for annos, frame_shown in ((gt, gt_frames_shown), (dt, True)):
        if annos.missing_fields:
            field = "bbox" if "bbox" in annos.missing_fields else next(iter(annos.missing_fields))
            raise InputError(
                f"no '{field}' (an image field) for some boxes; a set without 2D boxes is evaluated with the "
                "form field lidar_only=true (BEV and 3D only)",
                source=annos.source,
                frame=annos.missing_fields[field] if frame_shown else None,
                field=field,
            )


def frame_listing(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig,
    question: FrameQuestion = ASKED,
    *,
    worst: int | None = 20,
) -> dict[str, Any]:
    """TP/FP/FN per frame (the ``worst`` n first, or all), from the same matching as the AP, as
    :func:`kitti_eval.analysis.diagnostics.frames_document`: what an evaluation's and a submission's frame
    listings answer."""
    check_worst(worst)
    return frames_document(frame_stats(gt, dt, config, question), worst=worst)


def check_worst(worst: int | None) -> None:
    """A frame listing's ``worst``: None (every frame) or at least 1."""
    if worst is not None and worst < 1:
        raise BadRequest("worst must be at least 1")


def sealed_document(doc: dict[str, Any]) -> dict[str, Any]:
    """An evaluation document against a sealed ground truth: the aggregates only. The frames without
    predictions (ids of the sealed set) and the warnings (which may name its frames) are withheld."""
    out = dict(doc)
    withheld = len(doc.get("frames_without_predictions") or ())
    out["frames_without_predictions"] = []
    notes = [f"the ground truth is sealed: per-frame details are withheld ({len(doc.get('warnings') or ())} warnings"]
    notes[0] += f", {withheld} frames without predictions)" if withheld else ")"
    out["warnings"] = notes
    return out


def summarize(doc: Mapping[str, Any]) -> dict[str, dict[str, float | None]]:
    """R40 AP at moderate difficulty with the strict thresholds (or the first set), per class and metric."""
    oset = "strict" if "strict" in doc["ap"] else next(iter(doc["ap"]))
    by_class = doc["ap"][oset]["R40"]
    return {
        cls: {metric: values.get("moderate") for metric, values in metrics.items()} for cls, metrics in by_class.items()
    }


def parse_labels(fixed: Mapping[str, str | None], extra: Sequence[str]) -> dict[str, str]:
    """Labels from the named form fields (model, commit, epoch) and repeated ``label=key=value`` fields."""
    labels = {k: v for k, v in fixed.items() if v not in (None, "")}
    for item in extra:
        key, sep, value = item.partition("=")
        if not sep:
            raise BadRequest(f"label {echo(item)}: expected key=value")
        key = key.strip()
        if key in labels:
            raise BadRequest(f"label {echo(key)} is given twice")
        labels[key] = value
    if len(labels) > _MAX_LABELS:
        raise BadRequest(f"at most {_MAX_LABELS} labels")
    for key, value in labels.items():
        if not _LABEL_KEY.fullmatch(key):
            raise BadRequest(f"label key {echo(key)}: 1-64 letters, digits, '_', '.' or '-'")
        if len(value) > _MAX_LABEL_VALUE or not value.isprintable():
            raise BadRequest(
                f"label {echo(key)}: the value must be printable and at most {_MAX_LABEL_VALUE} characters"
            )
    return labels
