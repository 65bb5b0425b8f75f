"""Orchestration: overlaps once, then one match per (class, difficulty, metric, IoU threshold).

Step 1 computes the overlaps of every detection with every ground-truth box of its own frame, for the
three overlap metrics at once. Step 2 derives, per class and difficulty, which boxes count (the protocol's
rules, vectorised here), matches, and reduces the counts to curves and AP. No I/O, no printing.
"""

from __future__ import annotations

import time

import numpy as np
import numpy.typing as npt

from .frames import Annotations, dimension_order_warnings
from .geometry import frame_overlaps
from .matching import MatchJob, pr_counts_many
from .metrics import Curve, average_precision, curve_from_counts
from .protocol import (
    ALL_METRICS,
    DONTCARE,
    INVALID_ALPHA,
    MISSING_COORD,
    NEIGHBOURS,
    OVERLAP_METRICS,
    RECALL_MODES,
    Difficulty,
    DifficultyLimits,
    EvalConfig,
    Metric,
    Protocol,
)
from .result import EvalResult

__all__ = ["evaluate", "ignore_codes", "aos_enabled", "scored_metrics"]


def ignore_codes(gt: Annotations, dt: Annotations, cls: str, difficulty: Difficulty,
                 limits: DifficultyLimits) -> tuple[npt.NDArray[np.int8], npt.NDArray[np.int8]]:
    """The devkit's ``cleanData``: which boxes count for ``cls`` at ``difficulty``.

    Ground truth: 0 = counts, 1 = ignored (a neighbour class such as Van for Car, or the class itself but
    too occluded, truncated, or with 2D height ``y2 - y1 <= min_height``), -1 = another class.
    Detections: 1 = too small (``|y2 - y1| < min_height``, whatever the class: such a detection can still
    absorb a ground-truth box), else 0 for the class, -1 for others.
    """
    d = int(difficulty)
    own = gt.is_class(cls)
    neighbour = gt.is_class(*NEIGHBOURS.get(cls.lower(), ()))
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    hard = ((gt.occluded > limits.max_occlusion[d]) | (gt.truncated > limits.max_truncation[d])
            | (height <= limits.min_height[d]))
    ig = np.full(gt.num_boxes, -1, dtype=np.int8)
    ig[neighbour | (own & hard)] = 1
    ig[own & ~hard] = 0
    idet = np.full(dt.num_boxes, -1, dtype=np.int8)
    idet[dt.is_class(cls)] = 0
    idet[np.abs(dt.bbox[:, 3] - dt.bbox[:, 1]) < limits.min_height[d]] = 1
    return ig, idet


def aos_enabled(dt: Annotations, protocol: Protocol) -> bool:
    """Whether orientation similarity is computed at all.

    official: no detection anywhere has alpha == -10. openpcdet: the first detection of the first frame
    that has any is not -10 (and False when there are no detections).
    """
    if protocol.aos_rule == "all_valid":
        return not bool(np.any(dt.alpha == INVALID_ALPHA))
    if dt.num_boxes == 0:
        return False
    return bool(dt.alpha[0] != INVALID_ALPHA)


def scored_metrics(dt: Annotations, cls: str) -> dict[Metric, bool]:
    """The devkit evaluates a class in a metric only if some detection of it can be scored there.

    2D: a detection with x1 >= 0; BEV: with x and z given (not -1000) and w, l > 0; 3D: also y given and
    h > 0.
    """
    sel = dt.is_class(cls)
    x, y, z = dt.location.T
    ell, h, w = dt.dimensions.T
    ground = sel & (x != MISSING_COORD) & (z != MISSING_COORD) & (w > 0) & (ell > 0)
    return {
        Metric.BBOX: bool(np.any(sel & (dt.bbox[:, 0] >= 0))),
        Metric.BEV: bool(np.any(ground)),
        Metric.THREE_D: bool(np.any(ground & (y != MISSING_COORD) & (h > 0))),
    }


def _dontcare_rows(gt: Annotations, protocol: Protocol) -> npt.NDArray[np.bool_]:
    if gt.num_boxes == 0:
        return np.zeros(0, dtype=np.bool_)
    if protocol.dontcare_case_insensitive:
        return gt.is_class(DONTCARE)
    return gt.name == DONTCARE


def evaluate(gt: Annotations, dt: Annotations, config: EvalConfig | None = None, *,
             keep_curves: bool = False, workers: int | None = None) -> EvalResult:
    """Evaluate detections against ground truth.

    Parameters
    ----------
    gt : ground truth (DontCare rows included); its frames define the evaluated set
    dt : detections; matched to ``gt`` by frame id. A ground-truth frame without detections counts as
        empty and is listed in ``frames_without_predictions``; a detection frame unknown to ``gt`` raises
        :class:`~kitti_eval.errors.InputError`.
    config : classes, protocol, IoU thresholds (default: Car, Pedestrian, Cyclist; official protocol)
    keep_curves : keep the 41-point curves in the result
    workers : threads for the matchings (default: the CPUs available, or ``$KITTI_EVAL_THREADS``)
    """
    clock = time.perf_counter
    timings: dict[str, float] = {}
    t0 = clock()
    config = config or EvalConfig()
    protocol = config.protocol
    if gt.kind != "ground_truth" or dt.kind != "detections":
        raise ValueError("evaluate(gt, dt): expected ground truth then detections")
    dt, missing = dt.aligned_to(gt.frame_ids)
    warnings = dimension_order_warnings(gt) + dimension_order_warnings(dt)
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        warnings.append(f"{len(missing)} of {gt.num_frames} frames have no predictions and count as empty: "
                        f"{shown}")
    dontcare = _dontcare_rows(gt, protocol)
    t1 = clock()
    timings["align"] = t1 - t0
    fo = frame_overlaps(dt.bbox, dt.boxes_camera, dt.offsets, gt.bbox, gt.boxes_camera, gt.offsets, dontcare)
    t0 = clock()
    timings["overlaps"] = t0 - t1
    compute_aos = aos_enabled(dt, protocol)

    # step 1: the matchings needed, one per (class, difficulty, metric, distinct IoU threshold)
    ig_rows: list[npt.NDArray[np.int8]] = []
    idet_rows: list[npt.NDArray[np.int8]] = []
    jobs: list[MatchJob] = []
    job_of: dict[tuple[int, Metric, float], int] = {}
    slots: list[tuple[str, Difficulty, Metric, str, int | None, bool]] = []
    num_gt: dict[str, dict[str, int]] = {}
    num_det: dict[str, int] = {}
    for cls in config.classes:
        scored = scored_metrics(dt, cls)
        evaluated = {m: (scored[m] or not protocol.skip_undetected) for m in OVERLAP_METRICS}
        with_aos = evaluated[Metric.BBOX] and compute_aos
        num_det[cls] = int(np.sum(dt.is_class(cls)))
        num_gt[cls] = {}
        for difficulty in Difficulty:
            ig, idet = ignore_codes(gt, dt, cls, difficulty, config.difficulty)
            num_gt[cls][difficulty.label] = int(np.sum(ig == 0))
            row = len(ig_rows)
            ig_rows.append(ig)
            idet_rows.append(idet)
            for metric in OVERLAP_METRICS:
                for oset in config.threshold_sets:
                    job = None
                    if evaluated[metric]:
                        thr = config.overlap(cls, oset, metric)
                        job = job_of.get((row, metric, thr))
                        if job is None:
                            job = job_of[(row, metric, thr)] = len(jobs)
                            jobs.append(MatchJob(metric=OVERLAP_METRICS.index(metric), codes=row, min_overlap=thr,
                                                 compute_aos=metric is Metric.BBOX and with_aos,
                                                 dontcare=metric in protocol.dontcare_metrics))
                    slots.append((cls, difficulty, metric, oset, job, with_aos))
    counts = pr_counts_many(fo.pair_offsets, (fo.bbox, fo.bev, fo.d3), gt.offsets, dt.offsets,
                            np.stack(ig_rows), np.stack(idet_rows), dontcare, dt.score, gt.alpha, dt.alpha,
                            jobs, workers=workers) if jobs else []
    t1 = clock()
    timings["matching"] = t1 - t0
    job_curves = [curve_from_counts(c) for c in counts]

    # step 2: curves to AP
    ap: dict[str, dict[str, dict[str, dict[str, dict[str, float | None]]]]] = {
        oset: {r: {cls: {m.value: {} for m in ALL_METRICS} for cls in config.classes} for r in RECALL_MODES}
        for oset in config.threshold_sets}
    curves: dict[str, dict[str, dict[str, dict[str, Curve]]]] = {
        oset: {cls: {m.value: {} for m in ALL_METRICS} for cls in config.classes} for oset in config.threshold_sets}
    for cls, difficulty, metric, oset, job, with_aos in slots:
        curve = None if job is None else job_curves[job]
        targets = [(metric, curve, "precision")]
        if metric is Metric.BBOX:
            targets.append((Metric.AOS, curve if with_aos else None, "orientation"))
        for m, curve_, attr in targets:
            for r in RECALL_MODES:
                ap[oset][r][cls][m.value][difficulty.label] = (
                    None if curve_ is None else average_precision(getattr(curve_, attr), r))
            if curve_ is not None:
                curves[oset][cls][m.value][difficulty.label] = curve_
    timings["ap"] = clock() - t1
    return EvalResult(
        protocol=protocol.name,
        classes=tuple(config.classes),
        threshold_sets=tuple(config.threshold_sets),
        overlaps={cls: {oset: {m.value: config.overlap(cls, oset, m) for m in OVERLAP_METRICS}
                        for oset in config.threshold_sets} for cls in config.classes},
        ap=ap,
        num_gt=num_gt,
        num_det=num_det,
        frames=gt.num_frames,
        frames_without_predictions=tuple(missing),
        aos_evaluated=compute_aos,
        warnings=tuple(warnings),
        curves=curves if keep_curves else None,
        timings=timings,
    )
