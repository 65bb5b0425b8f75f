"""Two stored evaluations compared: the library's comparison (:mod:`kitti_eval.analysis.bootstrap`, the CLI's
``compare``) of their documents, with the records' ids and labels, and a note when their ground truths
differ (which only the service knows)."""

from __future__ import annotations

from typing import Any

from kitti_eval.analysis.result_diff import compare_documents, render_comparison

from ..schemas import iso
from ..store import EvaluationRecord

__all__ = ["compare", "render_comparison_markdown"]

_OTHER_GROUND_TRUTH = "the evaluations used different ground truth; the deltas compare different sets"


def _side(record: EvaluationRecord) -> dict[str, Any]:
    return {
        "id": record.id,
        "created_at": iso(record.created_at),
        "ground_truth": {"name": record.gt_name, "sha256": record.gt_sha256},
        "labels": dict(record.labels),
    }


def _name(record: EvaluationRecord) -> str:
    label = record.labels.get("model") or record.id[:8]
    extra = [f"{k} {record.labels[k]}" for k in ("commit", "epoch") if k in record.labels]
    return f"{label} ({', '.join(extra)})" if extra else label


def _column_names(base: EvaluationRecord, other: EvaluationRecord) -> tuple[str, str]:
    """The comparison's column headers, as ``kitti-eval compare`` heads them with the files' names: each
    evaluation's name, with its id's first characters when the two names are the same."""
    a, b = _name(base), _name(other)
    return (f"{a} {base.id[:8]}", f"{b} {other.id[:8]}") if a == b else (a, b)


def compare(base: EvaluationRecord, other: EvaluationRecord) -> dict[str, Any]:
    """The comparison document ``kitti-eval compare --format json`` prints for the two results (A = base,
    B = other), plus ``base`` and ``other``: the records' ids, dates, ground truths and labels."""
    assert base.result is not None and other.result is not None
    doc = compare_documents(base.result, other.result).to_dict()
    if base.gt_sha256 != other.gt_sha256:
        doc["notes"].insert(0, _OTHER_GROUND_TRUTH)
    return {"base": _side(base), "other": _side(other), **doc}


def render_comparison_markdown(base: EvaluationRecord, other: EvaluationRecord) -> str:
    """``kitti-eval compare --format markdown`` of the two, under a title naming them (for a PR comment)."""
    assert base.result is not None and other.result is not None
    comparison = compare_documents(base.result, other.result, names=_column_names(base, other))
    table = render_comparison(comparison, "markdown")
    gt_note = f"> note: {_OTHER_GROUND_TRUTH}\n" if base.gt_sha256 != other.gt_sha256 else ""
    return f"## KITTI evaluation: {_name(base)} → {_name(other)}\n\n{table}{gt_note}"
