"""Orchestration: overlaps once, then one match per (class, difficulty, metric, IoU threshold).

Step 1 computes the overlaps of every detection with every ground-truth box of its own frame, for the
three overlap metrics at once. Step 2 derives, per class and difficulty, which boxes count (the protocol's
rules, vectorised here), matches, and reduces the counts to curves and AP. No I/O, no printing.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .ap import Curve, average_precision, curve_from_counts
from .budget import check_overlap_budget
from .frames import Annotations, dimension_order_warnings, size_warnings
from .geometry import FrameOverlaps, frame_overlaps
from .matching import (
    FrameEvents,
    MatchingInputs,
    MatchJob,
    PRCounts,
    first_passes,
    frame_events_many,
    pr_counts_many,
    second_passes,
)
from .protocol import (
    ALL_METRICS,
    DONTCARE,
    INVALID_ALPHA,
    MISSING_COORD,
    NEIGHBOURS,
    OVERLAP_INDEX,
    OVERLAP_METRICS,
    RECALL_MODES,
    Difficulty,
    DifficultyLimits,
    EvalConfig,
    Metric,
    Protocol,
    coco_thresholds,
    did_you_mean,
)
from .result import EvalResult

__all__ = [
    "evaluate",
    "plan_evaluation",
    "Plan",
    "Facts",
    "Totals",
    "result_from_counts",
    "ap_tables",
    "ignore_codes",
    "aos_enabled",
    "scored_metrics",
]


def ignore_codes(
    gt: Annotations,
    dt: Annotations,
    cls: str,
    difficulty: Difficulty,
    limits: DifficultyLimits,
    neighbours: Mapping[str, tuple[str, ...]] = NEIGHBOURS,
) -> tuple[npt.NDArray[np.int8], npt.NDArray[np.int8]]:
    """The devkit's ``cleanData``: which boxes count for ``cls`` at ``difficulty``.

    Ground truth: 0 = counts, 1 = ignored (a neighbour class such as Van for Car, or the class itself but
    too occluded, truncated, or with 2D height ``y2 - y1 <= min_height``), -1 = another class.
    Detections: 1 = too small (``|y2 - y1| < min_height``, whatever the class: such a detection can still
    absorb a ground-truth box), else 0 for the class, -1 for others.
    """
    d = int(difficulty)
    own = gt.is_class(cls)
    neighbour = gt.is_class(*neighbours.get(cls.lower(), ()))
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    hard = (
        (gt.occluded > limits.max_occlusion[d])
        | (gt.truncated > limits.max_truncation[d])
        | (height <= limits.min_height[d])
    )
    ig = np.full(gt.num_boxes, -1, dtype=np.int8)
    ig[neighbour | (own & hard)] = 1
    ig[own & ~hard] = 0
    idet = np.full(dt.num_boxes, -1, dtype=np.int8)
    idet[dt.is_class(cls)] = 0
    idet[np.abs(dt.bbox[:, 3] - dt.bbox[:, 1]) < limits.min_height[d]] = 1
    return ig, idet


def in_range_codes(
    ignored_gt: npt.NDArray[np.int8],
    ignored_det: npt.NDArray[np.int8],
    gt_inside: npt.NDArray[np.bool_],
    dt_inside: npt.NDArray[np.bool_],
) -> tuple[npt.NDArray[np.int8], npt.NDArray[np.int8]]:
    """Ignore codes within a distance range (:class:`~kitti_eval.core.protocol.DistanceRange`): ground truth
    outside it that takes part becomes ignored (1), and so does a counting detection (0) outside it."""
    ig = ignored_gt.copy()
    ig[(ig != -1) & ~gt_inside] = 1
    idet = ignored_det.copy()
    idet[(idet == 0) & ~dt_inside] = 1
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


def _absent_class_warnings(gt: Annotations, dt: Annotations, config: EvalConfig) -> list[str]:
    """A requested class with neither ground truth nor detections is n/a everywhere: usually a typo."""
    absent = [c for c in config.classes if not gt.is_class(c).any() and not dt.is_class(c).any()]
    if not absent:
        return []
    present = sorted(set(np.unique(gt.name).tolist()) | set(np.unique(dt.name).tolist()))
    return [
        f"class {c!r} has neither ground truth nor detections, so every AP of it is n/a{did_you_mean(c, present)}"
        for c in absent
    ]


def _dontcare_rows(gt: Annotations, protocol: Protocol) -> npt.NDArray[np.bool_]:
    if gt.num_boxes == 0:
        return np.zeros(0, dtype=np.bool_)
    if protocol.dontcare_case_insensitive:
        return gt.is_class(DONTCARE)
    return gt.name == DONTCARE


@dataclass(frozen=True)
class Facts:
    """What the whole set decides for each part of it (see :mod:`kitti_eval.analysis.sharded`): per class, the
    metrics in which some detection can be scored (:func:`scored_metrics`), and whether AOS is computed
    (:func:`aos_enabled`)."""

    scored: Mapping[str, Mapping[Metric, bool]]
    compute_aos: bool

    @classmethod
    def every_job(cls, config: EvalConfig) -> Facts:
        """Every metric of every class scored, no AOS: the superset of the jobs any set can have."""
        return cls({c: dict.fromkeys(OVERLAP_METRICS, True) for c in config.classes}, False)


class Slot(NamedTuple):
    """One (class, difficulty, metric, threshold set) of the result: the matching behind it (an index into
    ``Plan.jobs``; None where the protocol does not evaluate it) and whether AOS rides on it."""

    cls: str
    difficulty: Difficulty
    metric: Metric
    oset: str
    job: int | None
    with_aos: bool


@dataclass(frozen=True, eq=False)
class Plan:
    """Everything an evaluation computes before matching: aligned inputs, overlaps, and the matchings.

    ``jobs`` are the distinct matchings (one per class, difficulty, metric and IoU threshold); ``slots``
    map every (class, difficulty, metric, threshold set) of the result to its job (None where the
    protocol does not evaluate it) and say whether AOS rides on it.
    """

    gt: Annotations
    dt: Annotations
    config: EvalConfig
    missing: tuple[str, ...]
    warnings: tuple[str, ...]
    dontcare: npt.NDArray[np.bool_]
    overlaps: FrameOverlaps
    compute_aos: bool
    ignored_gt: npt.NDArray[np.int8]  # (K, M), one row per (class, difficulty)
    ignored_det: npt.NDArray[np.int8]  # (K, N)
    jobs: tuple[MatchJob, ...]
    slots: tuple[Slot, ...]
    #: per distance range of the config, the slots of that range's matchings (same layout as ``slots``)
    range_slots: tuple[tuple[Slot, ...], ...]
    #: the row of ``ignored_gt`` holding the whole set's codes of each (class, difficulty)
    code_rows: dict[tuple[str, Difficulty], int]
    #: with ``config.coco``: the job of each (class, difficulty, metric) at each COCO threshold (None where
    #: the protocol does not evaluate it), and whether AOS rides on the bbox ones
    coco_jobs: dict[tuple[str, Difficulty, Metric], tuple[tuple[int | None, ...], bool]]
    num_gt: dict[str, dict[str, int]]
    num_det: dict[str, int]
    timings: dict[str, float]

    def _matching_inputs(self) -> MatchingInputs:
        """The arrays every matching of the plan shares (see :func:`kitti_eval.core.matching.pr_counts`)."""
        fo = self.overlaps
        return MatchingInputs(
            fo.pair_offsets,
            (fo.bbox, fo.bev, fo.d3),
            self.gt.offsets,
            self.dt.offsets,
            self.ignored_gt,
            self.ignored_det,
            self.dontcare,
            self.dt.score,
            self.gt.alpha,
            self.dt.alpha,
        )

    def counts(self, jobs: Sequence[MatchJob] | None = None, *, workers: int | None = None) -> list[PRCounts]:
        """The TP/FP/FN counts of ``jobs`` (default: every job of the plan) at their score thresholds."""
        jobs = self.jobs if jobs is None else jobs
        return pr_counts_many(self._matching_inputs(), jobs, workers=workers) if jobs else []

    def first_passes(self, *, workers: int | None = None) -> list[tuple[np.ndarray, int]]:
        """Per job: pass 1's true-positive scores and the valid ground truth (phase 1 over a part of a set)."""
        return first_passes(self._matching_inputs(), self.jobs, workers=workers) if self.jobs else []

    def second_passes(self, thresholds: Sequence[np.ndarray], *, workers: int | None = None) -> list[PRCounts]:
        """Per job: the counts at the whole set's ``thresholds`` (phase 2 over a part of a set)."""
        if not self.jobs:
            return []
        return second_passes(self._matching_inputs(), self.jobs, thresholds, workers=workers)

    def events(self, jobs: Sequence[MatchJob] | None = None, *, workers: int | None = None) -> list[FrameEvents]:
        """Each frame's share of ``jobs``' counts as step functions of the score threshold (default: every job)."""
        jobs = self.jobs if jobs is None else jobs
        return frame_events_many(self._matching_inputs(), jobs, workers=workers) if jobs else []


def plan_evaluation(
    gt: Annotations, dt: Annotations, config: EvalConfig | None = None, *, facts: Facts | None = None
) -> Plan:
    """Align detections to the ground truth's frames, compute overlaps, and list the matchings needed.

    ``facts``: the whole set's (when ``gt`` and ``dt`` are a part of it), instead of this part's own.
    """
    config = config or EvalConfig()
    protocol = config.protocol
    if gt.kind != "ground_truth" or dt.kind != "detections":
        raise ValueError("evaluate(gt, dt): expected ground truth then detections")
    if not config.lidar_only:
        for annos in (gt, dt):
            if annos.missing_fields:
                fname = "bbox" if "bbox" in annos.missing_fields else next(iter(annos.missing_fields))
                frame = annos.missing_fields[fname]
                raise InputError(
                    f"no '{fname}' (an image field) for some boxes; a set without 2D boxes is "
                    "evaluated with --lidar-only (BEV and 3D)",
                    source=annos.source,
                    frame=frame,
                    field=fname,
                )
    dt, missing = dt.aligned_to(gt.frame_ids)
    warnings = size_warnings(gt) + size_warnings(dt) + dimension_order_warnings(gt) + dimension_order_warnings(dt)
    warnings += _absent_class_warnings(gt, dt, config)
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        warnings.append(f"{len(missing)} of {gt.num_frames} frames have no predictions and count as empty: {shown}")
    dontcare = _dontcare_rows(gt, protocol)
    check_overlap_budget(dt.counts, gt.counts, gt.frame_ids, source=dt.source)
    t0 = time.perf_counter()
    fo = frame_overlaps(dt.bbox, dt.boxes_camera, dt.offsets, gt.bbox, gt.boxes_camera, gt.offsets, dontcare)
    overlap_seconds = time.perf_counter() - t0
    compute_aos = aos_enabled(dt, protocol) if facts is None else facts.compute_aos
    ig_rows: list[npt.NDArray[np.int8]] = []
    idet_rows: list[npt.NDArray[np.int8]] = []
    jobs: list[MatchJob] = []
    job_of: dict[tuple[int, Metric, float], int] = {}
    slots: list[Slot] = []
    num_gt: dict[str, dict[str, int]] = {}
    num_det: dict[str, int] = {}
    range_slots: list[list[Slot]] = [[] for _ in config.ranges]

    code_rows: dict[tuple[str, Difficulty], int] = {}

    coco_jobs: dict[tuple[str, Difficulty, Metric], tuple[tuple[int | None, ...], bool]] = {}

    def job_for(row: int, metric: Metric, thr: float, with_aos: bool) -> int:
        job = job_of.get((row, metric, thr))
        if job is None:
            job = job_of[(row, metric, thr)] = len(jobs)
            jobs.append(
                MatchJob(
                    overlap=OVERLAP_INDEX[metric],
                    codes=row,
                    min_overlap=thr,
                    compute_aos=metric is Metric.BBOX and with_aos,
                    dontcare=metric in protocol.dontcare_metrics,
                )
            )
        return job

    def add_jobs(
        ig: npt.NDArray[np.int8],
        idet: npt.NDArray[np.int8],
        cls: str,
        difficulty: Difficulty,
        evaluated: dict[Metric, bool],
        with_aos: bool,
        into: list[Slot],
    ) -> int:
        row = len(ig_rows)
        ig_rows.append(ig)
        idet_rows.append(idet)
        for metric in OVERLAP_METRICS:
            for oset in config.threshold_sets:
                job = job_for(row, metric, config.overlap(cls, oset, metric), with_aos) if evaluated[metric] else None
                into.append(Slot(cls, difficulty, metric, oset, job, with_aos))
        return row

    for cls in config.classes:
        scored = scored_metrics(dt, cls) if facts is None else facts.scored[cls]
        evaluated = {m: (scored[m] or not protocol.skip_undetected) for m in OVERLAP_METRICS}
        if config.lidar_only:
            evaluated[Metric.BBOX] = False  # no image: BEV and 3D only
        with_aos = evaluated[Metric.BBOX] and compute_aos
        num_det[cls] = int(np.sum(dt.is_class(cls)))
        num_gt[cls] = {}
        for difficulty in Difficulty:
            ig, idet = ignore_codes(gt, dt, cls, difficulty, config.difficulty, config.neighbours)
            num_gt[cls][difficulty.label] = int(np.sum(ig == 0))
            row = code_rows[(cls, difficulty)] = add_jobs(ig, idet, cls, difficulty, evaluated, with_aos, slots)
            if config.coco:
                for metric in OVERLAP_METRICS:
                    coco_jobs[(cls, difficulty, metric)] = (
                        tuple(
                            job_for(row, metric, thr, with_aos) if evaluated[metric] else None
                            for thr in coco_thresholds(cls)
                        ),
                        with_aos,
                    )
            for k, rng in enumerate(config.ranges):
                ig_r, idet_r = in_range_codes(
                    ig, idet, rng.contains(gt.ground_distance), rng.contains(dt.ground_distance)
                )
                add_jobs(ig_r, idet_r, cls, difficulty, evaluated, with_aos, range_slots[k])
    return Plan(
        gt=gt,
        dt=dt,
        config=config,
        missing=tuple(missing),
        warnings=tuple(warnings),
        dontcare=dontcare,
        overlaps=fo,
        compute_aos=compute_aos,
        ignored_gt=np.stack(ig_rows),
        ignored_det=np.stack(idet_rows),
        jobs=tuple(jobs),
        slots=tuple(slots),
        range_slots=tuple(tuple(r) for r in range_slots),
        code_rows=code_rows,
        coco_jobs=coco_jobs,
        num_gt=num_gt,
        num_det=num_det,
        timings={"overlaps": overlap_seconds},
    )


def evaluate(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig | None = None,
    *,
    keep_curves: bool = False,
    workers: int | None = None,
) -> EvalResult:
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
    t0 = clock()
    plan = plan_evaluation(gt, dt, config)
    t1 = clock()
    counts = plan.counts(workers=workers)
    t2 = clock()
    timings = {"align": t1 - t0 - plan.timings["overlaps"], "overlaps": plan.timings["overlaps"], "matching": t2 - t1}
    return result_from_counts(plan, counts, Totals.of(plan), keep_curves=keep_curves, timings=timings)


@dataclass(frozen=True)
class Totals:
    """What a result reports besides AP, for the whole set: counts of boxes and frames, the frames without
    predictions, warnings, whether AOS was computed, and the valid ground truth of each distance range."""

    num_gt: dict[str, dict[str, int]]
    num_det: dict[str, int]
    frames: int
    missing: tuple[str, ...]
    warnings: tuple[str, ...]
    compute_aos: bool
    range_num_gt: tuple[dict[str, dict[str, int]], ...]

    @classmethod
    def of(cls, plan: Plan) -> Totals:
        return cls(
            plan.num_gt,
            plan.num_det,
            plan.gt.num_frames,
            plan.missing,
            plan.warnings,
            plan.compute_aos,
            tuple(range_num_gt(plan)),
        )


def range_num_gt(plan: Plan) -> list[dict[str, dict[str, int]]]:
    """Per distance range of the config: the valid ground truth of each class and difficulty inside it."""
    out = []
    for rng in plan.config.ranges:
        inside = rng.contains(plan.gt.ground_distance)
        out.append(
            {
                cls: {
                    d.label: int(np.sum((plan.ignored_gt[plan.code_rows[(cls, d)]] == 0) & inside)) for d in Difficulty
                }
                for cls in plan.config.classes
            }
        )
    return out


def result_from_counts(
    plan: Plan,
    counts: Sequence[PRCounts],
    totals: Totals,
    *,
    keep_curves: bool = False,
    timings: Mapping[str, float] | None = None,
) -> EvalResult:
    """The result from the counts of every job of ``plan`` (whose jobs and slots are the whole set's; its
    data may be any part of the set, or none) and the set's ``totals``."""
    t2 = time.perf_counter()
    job_curves = [curve_from_counts(c) for c in counts]
    ap, curves = ap_tables(plan, job_curves)
    config = plan.config
    by_range = []
    for rng, slots, range_gt in zip(config.ranges, plan.range_slots, totals.range_num_gt):
        range_ap, _ = ap_tables(plan, job_curves, slots)
        by_range.append({"label": rng.label, "min": rng.lo, "max": rng.hi, "ap": range_ap, "num_gt": range_gt})
    coco = _coco_table(plan, job_curves) if config.coco else None
    timings = {**(timings or {}), "ap": time.perf_counter() - t2}
    return EvalResult(
        protocol=config.protocol.name,
        classes=tuple(config.classes),
        threshold_sets=tuple(config.threshold_sets),
        overlaps={
            cls: {
                oset: {m.value: config.overlap(cls, oset, m) for m in OVERLAP_METRICS} for oset in config.threshold_sets
            }
            for cls in config.classes
        },
        ap=ap,
        num_gt=totals.num_gt,
        num_det=totals.num_det,
        frames=totals.frames,
        frames_without_predictions=totals.missing,
        aos_evaluated=totals.compute_aos,
        warnings=totals.warnings,
        curves=curves if keep_curves else None,
        timings=timings,
        ranges=tuple(by_range),
        coco=coco,
    )


def _coco_table(plan: Plan, job_curves: list[Curve]) -> dict:
    """``coco[recall][class][metric][difficulty]``: the mean AP over the class's COCO IoU thresholds."""
    out: dict[str, dict[str, dict[str, dict[str, float | None]]]] = {
        r: {cls: {m.value: {} for m in ALL_METRICS} for cls in plan.config.classes} for r in RECALL_MODES
    }
    for (cls, difficulty, metric), (jobs, with_aos) in plan.coco_jobs.items():
        targets = [(metric, "precision", True)]
        if metric is Metric.BBOX:
            targets.append((Metric.AOS, "orientation", with_aos))
        for m, attr, wanted in targets:
            for r in RECALL_MODES:
                picked = [j for j in jobs if j is not None]
                if not wanted or len(picked) < len(jobs):
                    value = None
                else:
                    value = sum(average_precision(getattr(job_curves[j], attr), r) for j in picked) / len(picked)
                out[r][cls][m.value][difficulty.label] = value
    return out


def ap_tables(
    plan: Plan,
    job_curves: list[Curve],
    slots: Sequence[Slot] | None = None,
) -> tuple[dict, dict]:
    """``ap[set][recall][class][metric][difficulty]`` and ``curves[set][class][metric][difficulty]`` from the
    curve of every job of ``plan`` (for ``slots``: the whole set by default, or one distance range's)."""
    config = plan.config
    ap: dict[str, dict[str, dict[str, dict[str, dict[str, float | None]]]]] = {
        oset: {r: {cls: {m.value: {} for m in ALL_METRICS} for cls in config.classes} for r in RECALL_MODES}
        for oset in config.threshold_sets
    }
    curves: dict[str, dict[str, dict[str, dict[str, Curve]]]] = {
        oset: {cls: {m.value: {} for m in ALL_METRICS} for cls in config.classes} for oset in config.threshold_sets
    }
    for cls, difficulty, metric, oset, job, with_aos in plan.slots if slots is None else slots:
        curve = None if job is None else job_curves[job]
        targets = [(metric, curve, "precision")]
        if metric is Metric.BBOX:
            targets.append((Metric.AOS, curve if with_aos else None, "orientation"))
        for m, curve_, attr in targets:
            for r in RECALL_MODES:
                ap[oset][r][cls][m.value][difficulty.label] = (
                    None if curve_ is None else average_precision(getattr(curve_, attr), r)
                )
            if curve_ is not None:
                curves[oset][cls][m.value][difficulty.label] = curve_
    return ap, curves
