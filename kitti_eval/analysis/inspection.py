"""One frame, several models: every box labelled by the matching that the AP counts.

For a class, metric, difficulty and threshold set, each detection of the frame is a true positive (with
the ground-truth box it matched and their overlap), a false positive (with why: the best overlap it had,
or the box a better detection took), ignored (too small for the difficulty, or matched to a box that does
not count), covered by a DontCare region, below the score threshold, or of another class. Each
ground-truth box is matched, missed, ignored, absorbed (taken by an ignored detection) or of another
class. The labels come from :func:`kitti_eval.core.frame_labels.label_frame`, the devkit's second pass on the
frame, so the frame's TP/FP/FN are its share of the counts behind the AP at that score threshold.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from os import PathLike
from pathlib import PurePath
from typing import Any

import numpy as np

from ..core.evaluation import Facts, Plan, plan_evaluation
from ..core.frame_labels import DET_LABELS, GT_LABELS, label_frame
from ..core.frames import Annotations, normalize_frame_id
from ..core.matching import MatchJob
from ..core.protocol import DEFAULT_METRIC, DEFAULT_OSET, OVERLAP_METRICS, Difficulty, EvalConfig, Metric
from ..errors import ConfigError, InputError
from .diagnostics import parse_slot, slot_job, with_class

__all__ = ["inspect_frame", "render_inspection", "inspection_json", "model_name", "unique_names"]

#: the box fields shown for every box, in this order
_BOX_FIELDS = ("name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y")


def model_name(path: str | PathLike[str]) -> str:
    """A model's display name from its result path: the folder after ``kitti_models`` (OpenPCDet's
    ``output/kitti_models/<model>/...``) when there is one, else the file's stem (``result`` of
    ``result.pkl.gz``)."""
    parts = PurePath(path).parts
    for k, part in enumerate(parts[:-1]):
        if part == "kitti_models":
            return parts[k + 1]
    name = PurePath(path).name
    for suffix in (".gz", ".pkl", ".pickle", ".zip", ".tgz", ".tar"):
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return name or str(path)


def unique_names(names: Sequence[str]) -> list[str]:
    """The names, a repeated one numbered from its second use (``pv_rcnn``, ``pv_rcnn (2)``)."""
    seen: dict[str, int] = {}
    taken = set(names)
    out = []
    for name in names:
        count = seen.get(name, 0) + 1
        seen[name] = count
        if count == 1:
            out.append(name)
            continue
        k = count
        while f"{name} ({k})" in taken:
            k += 1
        taken.add(f"{name} ({k})")
        out.append(f"{name} ({k})")
    return out


def _num(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def _shown(value: float) -> float:
    """A box value as written: inputs are mostly float32, so seven significant digits say all they hold
    (292.71, not 292.7099914550781)."""
    return float(f"{value:.7g}")


def _box(annos: Annotations, row: int, index: int) -> dict[str, Any]:
    out: dict[str, Any] = {"index": index}
    for f in _BOX_FIELDS:
        v = getattr(annos, f)[row]
        out[f] = str(v) if f == "name" else ([_shown(x) for x in v] if np.ndim(v) else _shown(v))
    return out


def _gt_roles(
    plan: Plan,
    cls: str,
    difficulty: Difficulty,
    job: MatchJob,
    g0: int,
    g1: int,
) -> list[tuple[str, str | None]]:
    """(role, reason) of each ground-truth box of the frame: whether and why it counts."""
    gt, config = plan.gt, plan.config
    codes = plan.ignored_gt[job.codes]
    limits, d = config.difficulty, int(difficulty)
    neighbours = set(config.neighbours.get(cls.lower(), ()))
    out: list[tuple[str, str | None]] = []
    for row in range(g0, g1):
        name = str(gt.name[row])
        code = int(codes[row])
        if code == 0:
            out.append(("counts", None))
        elif code == 1 and name.lower() in neighbours:
            out.append(("ignored", f"{name} is a neighbour class of {cls}: neither a hit nor a miss"))
        elif code == 1:
            height = gt.bbox[row, 3] - gt.bbox[row, 1]
            why = []
            if gt.occluded[row] > limits.max_occlusion[d]:
                why.append(f"occlusion {gt.occluded[row]:g} > {limits.max_occlusion[d]:g}")
            if gt.truncated[row] > limits.max_truncation[d]:
                why.append(f"truncation {gt.truncated[row]:.2f} > {limits.max_truncation[d]:g}")
            if height <= limits.min_height[d]:
                why.append(f"2D height {height:.1f} px <= {limits.min_height[d]:g} px")
            if not why:  # outside a distance range (not used here) or another rule of the row
                why.append("outside the set")
            out.append(("ignored", f"harder than {difficulty.label}: " + ", ".join(why)))
        elif plan.dontcare[row]:
            out.append(
                (
                    "dontcare",
                    "covers false positives"
                    if job.dontcare
                    else f"not used in {OVERLAP_METRICS[job.overlap].value} under the {config.protocol.name} protocol",
                )
            )
        else:
            out.append(("other_class", None))
    return out


def _fp_reason(ov: np.ndarray, a: int, codes: np.ndarray, gt_ref: np.ndarray, min_overlap: float) -> str:
    """Why a false positive matched nothing: a better detection took its box, or its overlap was too low."""
    taking_part = np.flatnonzero(codes != -1)
    if taking_part.size == 0:
        return "no ground truth of the class in the frame"
    best = int(taking_part[np.argmax(ov[a, taking_part])])
    o = float(ov[a, best])
    if o > min_overlap and gt_ref[best] >= 0:
        return f"duplicate: ground truth {best} (overlap {o:.3f}) went to detection {int(gt_ref[best])}"
    if o > 0:
        return f"best overlap {o:.3f} with ground truth {best}; a match needs > {min_overlap:g}"
    return "overlaps no ground truth of the class"


def _label_model(
    plan: Plan,
    f: int,
    cls: str,
    metric: Metric,
    difficulty: Difficulty,
    job: MatchJob,
    score_threshold: float | None,
    roles: list[tuple[str, str | None]],
) -> dict[str, Any]:
    gt, dt, fo = plan.gt, plan.dt, plan.overlaps
    g0, g1 = int(gt.offsets[f]), int(gt.offsets[f + 1])
    d0, d1 = int(dt.offsets[f]), int(dt.offsets[f + 1])
    ov = (fo.bbox, fo.bev, fo.d3)[job.overlap][fo.pair_offsets[f] : fo.pair_offsets[f + 1]].reshape(d1 - d0, g1 - g0)
    codes = plan.ignored_gt[job.codes][g0:g1]
    det_codes = plan.ignored_det[job.codes][d0:d1]
    dontcare = plan.dontcare[g0:g1] if job.dontcare else None
    thr = -math.inf if score_threshold is None else float(score_threshold)
    labels = label_frame(ov, codes, det_codes, dontcare, dt.score[d0:d1], job.min_overlap, thr)
    min_height = plan.config.difficulty.min_height[int(difficulty)]
    detections = []
    for a in range(d1 - d0):
        row = d0 + a
        box = _box(dt, row, a)
        box["score"] = _shown(dt.score[row])
        box["boxes_lidar"] = (
            None
            if dt.boxes_lidar is None or np.isnan(dt.boxes_lidar[row]).any()
            else [_shown(x) for x in dt.boxes_lidar[row]]
        )
        label = DET_LABELS[labels.det_label[a]]
        ref = int(labels.det_ref[a])
        reason = None
        if label == "fp":
            reason = _fp_reason(ov, a, codes, labels.gt_ref, job.min_overlap)
        elif label == "ignored" and det_codes[a] == 1:
            height = abs(dt.bbox[row, 3] - dt.bbox[row, 1])
            reason = f"2D height {height:.1f} px < {min_height:g} px for {difficulty.label}"
            if ref >= 0:
                reason += f"; took ground truth {ref}, which is then no miss"
        elif label == "ignored":
            reason = f"matched ground truth {ref}, which does not count ({roles[ref][1]})"
        elif label == "dontcare":
            reason = f"inside DontCare region {ref}"
        elif label == "below_threshold":
            reason = f"score below {thr:g}"
        box.update(
            label=label,
            gt=ref if label in ("tp", "ignored") and ref >= 0 else None,
            iou=_num(labels.det_overlap[a]) if ref >= 0 else None,
            reason=reason,
        )
        if label == "dontcare":
            box["dontcare_region"] = ref
        if label == "tp" and plan.compute_aos and metric is Metric.BBOX:
            box["orientation_similarity"] = (1.0 + math.cos(gt.alpha[g0 + ref] - dt.alpha[row])) / 2.0
        detections.append(box)
    ground_truth = []
    for i in range(g1 - g0):
        label = GT_LABELS[labels.gt_label[i]]
        if roles[i][0] == "dontcare":
            label = "dontcare"
        ref = int(labels.gt_ref[i])
        ground_truth.append(
            {
                "index": i,
                "label": label,
                "detection": ref if ref >= 0 else None,
                "iou": _num(labels.det_overlap[ref]) if ref >= 0 else None,
            }
        )
    return {
        "source": dt.source,
        "detections": detections,
        "ground_truth": ground_truth,
        "missed": [g["index"] for g in ground_truth if g["label"] == "missed"],
        "counts": {"tp": labels.tp, "fp": labels.fp, "fn": labels.fn},
    }


def inspect_frame(
    gt: Annotations,
    models: Sequence[tuple[str, Annotations]],
    frame_id: str | int,
    config: EvalConfig | None = None,
    *,
    cls: str = "Car",
    metric: str = DEFAULT_METRIC,
    difficulty: str = "moderate",
    oset: str = DEFAULT_OSET,
    score_threshold: float | None = None,
    facts: Sequence[Facts | None] | None = None,
) -> dict[str, Any]:
    """Every box of one frame, for each of ``models`` (name, detections), labelled by the matching.

    Each model is matched against ``gt`` exactly as :func:`kitti_eval.evaluate` matches it (the same
    protocol, ignore rules and thresholds); ``score_threshold`` drops detections scoring below it (default:
    none dropped). ``facts``: per model, what its whole set decides (:class:`~kitti_eval.core.evaluation.Facts`)
    when its detections are a part of it (e.g. the frame alone); None: its own. Returns a JSON-ready dict: the
    frame's ground truth with its role for the class, and per model the labelled detections, the ground truth's
    labels, the missed boxes and the counts.
    """
    if not models:
        raise ConfigError("no predictions to inspect")
    if facts is not None and len(facts) != len(models):
        raise ConfigError(f"facts for {len(facts)} of {len(models)} models")
    names = [name for name, _ in models]
    if len(set(names)) != len(names):
        raise ConfigError(f"model names repeat: {names}")
    config = with_class(config, cls)
    m, d = parse_slot(config, metric, difficulty, oset)
    fid = normalize_frame_id(frame_id)
    f = gt.frame_index().get(fid)
    if f is None:
        raise InputError("no such frame in the ground truth", source=gt.source, frame=fid)
    out: dict[str, Any] = {
        "frame": fid,
        "class": cls,
        "metric": metric,
        "difficulty": d.label,
        "threshold_set": oset,
        "min_overlap": config.overlap(cls, oset, m),
        "score_threshold": score_threshold,
        "protocol": config.protocol.name,
    }
    g0, g1 = int(gt.offsets[f]), int(gt.offsets[f + 1])
    reports: dict[str, Any] = {}
    roles: list[tuple[str, str | None]] = []
    for k, (name, dt) in enumerate(models):
        plan = plan_evaluation(gt, dt, config, facts=None if facts is None else facts[k])
        job = slot_job(plan, cls, m, d, oset)
        roles = _gt_roles(plan, cls, d, job, g0, g1)
        reports[name] = _label_model(plan, f, cls, m, d, job, score_threshold, roles)
    out["ground_truth"] = [
        {**_box(gt, g0 + i, i), "role": role, "reason": reason} for i, (role, reason) in enumerate(roles)
    ]
    out["models"] = reports
    return out


def inspection_json(report: dict[str, Any]) -> str:
    """The report as indented JSON, each box's number lists (bbox, dimensions, ...) on one line."""
    text = json.dumps(report, indent=2)
    return re.sub(r"\[\s+([-\d.eE+,\s]+?)\s+\]", lambda m: "[" + re.sub(r",\s+", ", ", m.group(1)) + "]", text) + "\n"


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, list):
        return " ".join(f"{x:.{digits}f}" for x in v)
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    widths = [max(len(h), *(len(r[k]) for r in rows)) if rows else len(h) for k, h in enumerate(header)]
    line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()  # noqa: E731
    return [line(header), *(line(r) for r in rows)]


def render_inspection(report: dict[str, Any]) -> str:
    """The report as readable text: the ground truth, then per model its detections and misses."""
    thr = report["score_threshold"]
    head = (
        f"frame {report['frame']}: {report['class']} {report['metric']} {report['difficulty']} "
        f"({report['threshold_set']} IoU > {report['min_overlap']:g}, {report['protocol']} protocol)"
        + ("" if thr is None else f", detections scoring >= {thr:g}")
    )
    lines = [head, "", f"ground truth ({len(report['ground_truth'])} boxes)"]
    lines += _table(
        ["#", "name", "role", "trunc", "occ", "bbox", "dims (l h w)", "location", "ry", "why"],
        [
            [
                str(g["index"]),
                g["name"],
                g["role"],
                _fmt(g["truncated"]),
                _fmt(g["occluded"], 0),
                _fmt(g["bbox"], 1),
                _fmt(g["dimensions"]),
                _fmt(g["location"]),
                _fmt(g["rotation_y"]),
                g["reason"] or "",
            ]
            for g in report["ground_truth"]
        ],
    )
    for name, model in report["models"].items():
        c = model["counts"]
        lines += ["", f"{name} ({model['source']}): TP {c['tp']}  FP {c['fp']}  FN {c['fn']}"]
        lines += _table(
            ["#", "name", "score", "label", "gt", "iou", "bbox", "dims (l h w)", "location", "ry", "why"],
            [
                [
                    str(det["index"]),
                    det["name"],
                    _fmt(det["score"], 3),
                    det["label"],
                    _fmt(det["gt"]),
                    _fmt(det["iou"], 3),
                    _fmt(det["bbox"], 1),
                    _fmt(det["dimensions"]),
                    _fmt(det["location"]),
                    _fmt(det["rotation_y"]),
                    det["reason"] or "",
                ]
                for det in model["detections"]
            ],
        )
        missed = ", ".join(str(i) for i in model["missed"]) or "none"
        lines.append(f"missed ground truth: {missed}")
    return "\n".join(lines) + "\n"
