"""Per-value differences between two stored evaluations (``other - base``), as JSON or Markdown."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .schemas import iso
from .store import EvaluationRecord

__all__ = ["compare", "render_comparison_markdown"]

_RECALLS = ("R40", "R11")
_DIFFS = ("easy", "moderate", "hard")


def _delta(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else b - a


def _side(record: EvaluationRecord) -> dict[str, Any]:
    return {"id": record.id, "created_at": iso(record.created_at), "ground_truth":
            {"name": record.gt_name, "sha256": record.gt_sha256}, "labels": dict(record.labels)}


def compare(base: EvaluationRecord, other: EvaluationRecord) -> dict[str, Any]:
    """``delta.ap[set][recall][class][metric][difficulty] = other - base`` (None where either is None).

    Only the threshold sets, classes and metrics both evaluations have are compared; ``notes`` says what
    makes the two hard to compare (other ground truth, protocol or IoU thresholds) and what was left out.
    """
    a, b = base.result, other.result
    assert a is not None and b is not None
    notes: list[str] = []
    if base.gt_sha256 != other.gt_sha256:
        notes.append("the evaluations used different ground truth; the deltas compare different sets")
    if a["protocol"] != b["protocol"]:
        notes.append(f"different protocols: {a['protocol']} and {b['protocol']}")
    classes = [c for c in a["classes"] if c in b["classes"]]
    sets = [s for s in a["threshold_sets"] if s in b["threshold_sets"]]
    left_out = sorted(set(a["classes"]).symmetric_difference(b["classes"]))
    if left_out:
        notes.append(f"classes in only one of them are not compared: {', '.join(left_out)}")
    for cls in classes:
        for oset in sets:
            if a["overlaps"][cls][oset] != b["overlaps"][cls][oset]:
                notes.append(f"{cls}/{oset}: different IoU thresholds")
    ap = {oset: {r: {cls: {m: {d: _delta(a["ap"][oset][r][cls][m][d], b["ap"][oset][r][cls][m][d]) for d in _DIFFS}
                           for m in a["ap"][oset][r][cls] if m in b["ap"][oset][r][cls]}
                     for cls in classes}
                 for r in _RECALLS}
          for oset in sets}
    return {
        "base": _side(base),
        "other": _side(other),
        "classes": classes,
        "threshold_sets": sets,
        "notes": notes,
        "delta": {
            "ap": ap,
            "num_det": {cls: b["num_det"][cls] - a["num_det"][cls] for cls in classes},
            "frames": b["frames"] - a["frames"],
        },
    }


def _cell(a: float | None, b: float | None) -> str:
    if a is None and b is None:
        return "n/a"
    if a is None or b is None:
        return f"{'n/a' if a is None else f'{a:.2f}'} → {'n/a' if b is None else f'{b:.2f}'}"
    return f"{a:.2f} → {b:.2f} ({b - a:+.2f})"


def render_comparison_markdown(base: EvaluationRecord, other: EvaluationRecord,
                               comparison: Mapping[str, Any]) -> str:
    """One table per threshold set (R40): ``base → other (delta)`` for each class, metric and difficulty."""
    a, b = base.result, other.result
    assert a is not None and b is not None

    def name(record: EvaluationRecord) -> str:
        label = record.labels.get("model") or record.id[:8]
        extra = [f"{k} {record.labels[k]}" for k in ("commit", "epoch") if k in record.labels]
        return f"{label} ({', '.join(extra)})" if extra else label

    out = [f"## KITTI evaluation: {name(base)} → {name(other)}", ""]
    for oset in comparison["threshold_sets"]:
        out += [f"### AP R40, {oset} IoU thresholds", "", "| Class | Metric | Easy | Moderate | Hard |",
                "|---|---|---:|---:|---:|"]
        for cls in comparison["classes"]:
            for metric in comparison["delta"]["ap"][oset]["R40"][cls]:
                cells = " | ".join(_cell(a["ap"][oset]["R40"][cls][metric][d], b["ap"][oset]["R40"][cls][metric][d])
                                   for d in _DIFFS)
                out.append(f"| {cls} | {metric} | {cells} |")
        out.append("")
    for note in comparison["notes"]:
        out.append(f"> note: {note}")
    return "\n".join(out).rstrip() + "\n"
