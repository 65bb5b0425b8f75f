"""Renderings of an :class:`EvalResult`: OpenPCDet's text table, versioned JSON, Markdown."""

from __future__ import annotations

import enum
import json
import math
from collections.abc import Mapping
from typing import Any

from ..core.protocol import DIFFICULTIES, METRICS
from ..core.result import EvalResult

__all__ = ["OutputFormat", "render", "render_table", "render_json", "json_document", "render_markdown"]


class OutputFormat(str, enum.Enum):
    TABLE = "table"
    JSON = "json"
    MARKDOWN = "markdown"

    def __str__(self) -> str:
        return self.value


_ROW_LABELS = (("bbox", "bbox AP:"), ("bev", "bev  AP:"), ("3d", "3d   AP:"))


def _num(value: float | None, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def render_table(result: EvalResult) -> str:
    """OpenPCDet's printed table, line for line.

    Per class and threshold set: an ``AP@`` (R11) block then an ``AP_R40@`` block; the header triple is
    the IoU thresholds for bbox, bev and 3d; each row holds easy, moderate, hard. AOS rows appear when
    AOS was evaluated. Values the protocol does not evaluate print as ``n/a``. Distance ranges, when asked
    for, follow as the same blocks with the range in the header (``Car AP_R40@0.70, 0.70, 0.70 (0-30m):``).
    """
    lines = _blocks(result, result.ap, "")
    for rng in result.ranges:
        lines += _blocks(result, rng["ap"], f" ({rng['label']})")
    if result.coco is not None:
        lines += _coco_blocks(result)
    return "\n".join(lines) + "\n"


def _coco_blocks(result: EvalResult) -> list[str]:
    """``Car coco AP@0.50:0.05:0.95:`` (R11) and ``Car coco AP_R40@...`` blocks."""
    from ..core.protocol import coco_thresholds

    assert result.coco is not None
    lines: list[str] = []
    for cls in result.classes:
        t = coco_thresholds(cls)
        span = f"{t[0]:.2f}:{(t[-1] - t[0]) / (len(t) - 1):.2f}:{t[-1]:.2f}"
        for recall, tag in (("R11", "AP"), ("R40", "AP_R40")):
            lines.append(f"{cls} coco {tag}@{span}:")
            lines += _rows(result.coco[recall][cls], result.aos_evaluated)
    return lines


def _rows(by_metric: Any, with_aos: bool) -> list[str]:
    """The bbox / bev / 3d rows (4 decimals) and the aos row (2 decimals) of one block: easy, moderate, hard."""
    lines = [label + ", ".join(_num(by_metric[metric][d], 4) for d in DIFFICULTIES) for metric, label in _ROW_LABELS]
    if with_aos:
        lines.append("aos  AP:" + ", ".join(_num(by_metric["aos"][d], 2) for d in DIFFICULTIES))
    return lines


def _blocks(result: EvalResult, ap: Any, suffix: str) -> list[str]:
    lines: list[str] = []
    for cls in result.classes:
        for oset in result.threshold_sets:
            ious = result.overlaps[cls][oset]
            triple = f"{ious['bbox']:.2f}, {ious['bev']:.2f}, {ious['3d']:.2f}"
            for recall, tag in (("R11", "AP"), ("R40", "AP_R40")):
                lines.append(f"{cls} {tag}@{triple}{suffix}:")
                lines += _rows(ap[oset][recall][cls], result.aos_evaluated)
    return lines


def _json_key(key: object) -> str:
    """A dict key as ``json.dumps`` writes it (JSON's keys are strings)."""
    if isinstance(key, str):
        return str.__str__(key)
    if key is None or isinstance(key, bool):
        return json.dumps(key)
    if isinstance(key, float):
        return float.__repr__(key)
    return int.__repr__(key) if isinstance(key, int) else str(key)


def _finite_or_none(obj: object) -> object:
    """``obj`` as ``json.loads(json.dumps(obj))`` would give it back, with every non-finite number None (JSON
    has no NaN): tuples as lists, keys as strings, a float's or a string's subclass as the plain type."""
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {_json_key(k): _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, str) and type(obj) is not str:
        return str.__str__(obj)
    return obj


def json_document(
    result: EvalResult, *, include_curves: bool = False, extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The versioned JSON document (see :meth:`EvalResult.to_dict`) as a dict, with the keys of ``extra`` added
    (e.g. the error decomposition's): what :func:`render_json` writes and ``json.loads`` of it would give back,
    each non-finite number None, without the text in between."""
    doc = {**result.to_dict(include_curves=include_curves), **(extra or {})}
    finite: dict[str, Any] = _finite_or_none(doc)  # type: ignore[assignment]  # a dict's copy is a dict
    return finite


def render_json(result: EvalResult, *, include_curves: bool = False, extra: Mapping[str, Any] | None = None) -> str:
    """The versioned JSON document (see :meth:`EvalResult.to_dict`), with the keys of ``extra`` added (e.g.
    the error decomposition's): :func:`json_document`, written."""
    return (
        json.dumps(json_document(result, include_curves=include_curves, extra=extra), indent=2, allow_nan=False) + "\n"
    )


def render_markdown(result: EvalResult) -> str:
    """GitHub-flavoured Markdown tables (one per threshold set and recall mode), for CI job summaries."""
    out: list[str] = [f"## KITTI evaluation ({result.protocol} protocol, {result.frames} frames)", ""]
    for oset in result.threshold_sets:
        for recall in ("R40", "R11"):
            out.append(f"### AP {recall}, {oset} IoU thresholds")
            out.append("")
            out.append("| Class | Metric | IoU | Easy | Moderate | Hard |")
            out.append("|---|---|---:|---:|---:|---:|")
            for cls in result.classes:
                for metric in METRICS:
                    iou = result.overlaps[cls][oset]["bbox" if metric == "aos" else metric]
                    vals = " | ".join(_num(result.ap[oset][recall][cls][metric][d], 2) for d in DIFFICULTIES)
                    out.append(f"| {cls} | {metric} | {iou:.2f} | {vals} |")
            out.append("")
    for rng in result.ranges:
        out.append(f"### AP R40 by distance {rng['label']}, strict IoU thresholds")
        out.append("")
        out.append("| Class | Metric | Easy | Moderate | Hard |")
        out.append("|---|---|---:|---:|---:|")
        for cls in result.classes:
            for metric in METRICS:
                vals = (
                    " | ".join(_num(rng["ap"]["strict"]["R40"][cls][metric][d], 2) for d in DIFFICULTIES)
                    if "strict" in rng["ap"]
                    else ""
                )
                out.append(f"| {cls} | {metric} | {vals} |")
        out.append("")
    if result.coco is not None:
        out.append("### COCO-style AP R40 (mean over ten IoU thresholds)")
        out.append("")
        out.append("| Class | Metric | Easy | Moderate | Hard |")
        out.append("|---|---|---:|---:|---:|")
        for cls in result.classes:
            for metric in METRICS:
                vals = " | ".join(_num(result.coco["R40"][cls][metric][d], 2) for d in DIFFICULTIES)
                out.append(f"| {cls} | {metric} | {vals} |")
        out.append("")
    gt_line = ", ".join(f"{cls} {result.num_gt[cls]['moderate']}" for cls in result.classes)
    out.append(f"Ground truth boxes that count (moderate): {gt_line}.")
    for w in result.warnings:
        out.append(f"\n> warning: {w}")
    return "\n".join(out) + "\n"


def render(
    result: EvalResult, fmt: OutputFormat | str, *, include_curves: bool = False, extra: Mapping[str, Any] | None = None
) -> str:
    """``result`` in ``fmt``; ``extra``: keys added to the JSON document (the other formats ignore it)."""
    fmt = OutputFormat(fmt)
    if fmt is OutputFormat.JSON:
        return render_json(result, include_curves=include_curves, extra=extra)
    if fmt is OutputFormat.MARKDOWN:
        return render_markdown(result)
    return render_table(result)
