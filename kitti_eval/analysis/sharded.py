"""A set given as many files (shards), evaluated in bounded memory: in this process or on a Dask cluster.

The evaluation is two map-reduce phases over parts of the set (a part: one ground-truth file and the
predictions of its frames):

1. per part, pass 1 of every matching the set could need (:meth:`Plan.first_passes`): the true-positive
   scores and valid ground truth per job, and the part's facts (which metrics some detection can be scored
   in, the orientation rule's inputs, box counts, frames without predictions). Reduced: the set's
   :class:`~kitti_eval.core.evaluation.Facts` decide the jobs, and each job's score thresholds come from all
   of its true-positive scores, exactly as for the set in one piece;
2. per part, pass 2 of those jobs at those thresholds (:meth:`Plan.second_passes`), reduced by summing the
   counts; :func:`~kitti_eval.core.evaluation.result_from_counts` turns them into the result.

Memory is bounded by the largest part plus the true-positive scores (a few bytes per ground-truth box);
each part is read twice. The numbers equal :func:`~kitti_eval.core.evaluation.evaluate` on the whole set
(the summed orientation similarity may differ in the last bits: it is added in another order).

Frames are matched by id across files: when there are as many prediction files as ground-truth files,
the i-th of each are tried as a part, and if some prediction file holds frames of another ground-truth
file, every file's frame ids are read first and each part takes the prediction files that hold its
frames. A frame in two files of the same kind is an error naming both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.evaluation import Facts, Totals, plan_evaluation, result_from_counts, scored_metrics
from ..core.frames import (
    Annotations,
    UnsizedBoxes,
    dimension_order_warnings,
    dimension_samples,
    merge_dimension_samples,
    size_warnings,
    unsized_boxes,
)
from ..core.matching import PRCounts, score_thresholds
from ..core.protocol import (
    INVALID_ALPHA,
    OVERLAP_METRICS,
    EvalConfig,
    Metric,
    did_you_mean,
)
from ..core.result import EvalResult
from ..errors import ConfigError, InputError
from .frame_question import ASKED, FrameQuestion

__all__ = ["Part", "evaluate_sharded", "frame_stats_sharded", "paired_bootstrap_sharded", "parts_of"]

#: a map over parts: ``mapper(fn, items)`` returns ``[fn(x) for x in items]`` in order (Dask's client.map,
#: a process pool, or the built-in map)
Mapper = Callable[[Callable[[Any], Any], Sequence[Any]], list[Any]]


@dataclass(frozen=True)
class Part:
    """One unit of work: a ground-truth file and the prediction files that hold its frames (the frames of
    those files that are not in this ground truth belong to other parts)."""

    gt: str
    preds: tuple[str, ...]
    #: prediction files that are known to hold only this part's frames (no filtering, and a frame outside
    #: the ground truth means the files are not paired by position)
    paired: bool = False
    gt_format: str | None = None
    pred_format: str | None = None


class _NotPaired(Exception):
    """A prediction file paired by position holds frames of another ground-truth file."""


# ----------------------------------------------------------------------------------------------- loading


def _load_part(part: Part) -> tuple[Annotations, Annotations, list[str]]:
    """The part's ground truth, its predictions and the warnings of reading them."""
    from ..io.reading import LoadOptions, read_annotations, read_ground_truth_and_calibs

    loaded_gt, calibs = read_ground_truth_and_calibs(part.gt, LoadOptions(fmt=part.gt_format))
    loaded = [read_annotations(p, "detections", LoadOptions(fmt=part.pred_format, calibs=calibs)) for p in part.preds]
    gt = loaded_gt.annotations
    pieces = [piece.annotations for piece in loaded]
    warnings = [*loaded_gt.warnings, *(w for piece in loaded for w in piece.warnings)]
    wanted = gt.frame_index()
    if part.paired:
        for piece in pieces:
            if any(fid not in wanted for fid in piece.frame_ids):
                raise _NotPaired(piece.source)
        if len(pieces) == 1:
            return gt, pieces[0], warnings
    return gt, _concat("detections", pieces, wanted), warnings


def _concat(kind: str, pieces: Sequence[Annotations], wanted: Mapping[str, int] | None) -> Annotations:
    """The frames of ``pieces`` (those in ``wanted``, if given) as one set."""

    def frames() -> Iterator[tuple[object, Mapping[str, Any]]]:
        for piece in pieces:
            for fid in piece.frame_ids:
                if wanted is None or fid in wanted:
                    yield fid, piece.frame(fid)

    if not pieces:  # a ground-truth file none of whose frames has predictions
        source = "predictions"
    else:
        source = pieces[0].source if len(pieces) == 1 else f"{pieces[0].source} (+{len(pieces) - 1} more)"
    return Annotations.from_frames(kind, source, frames(), max_frames=None)  # type: ignore[arg-type]


def _frame_ids(path: str, kind: str, fmt: str | None) -> tuple[str, ...]:
    from ..io.reading import LoadOptions, read_annotations

    return read_annotations(path, kind, LoadOptions(fmt=fmt)).annotations.frame_ids  # type: ignore[arg-type]


def parts_of(
    gt_paths: Sequence[str | Path],
    pred_paths: Sequence[str | Path],
    *,
    gt_format: str | None = None,
    pred_format: str | None = None,
    mapper: Mapper | None = None,
) -> list[Part]:
    """The parts of a set from its files, after reading every file's frame ids (see the module docstring).

    Raises InputError for a frame in two files of one kind (naming both) or a predicted frame that is in no
    ground-truth file.
    """
    run = mapper or _serial
    gts, preds = [str(p) for p in gt_paths], [str(p) for p in pred_paths]
    gt_ids = run(_Ids("ground_truth", gt_format), gts)
    pred_ids = run(_Ids("detections", pred_format), preds)
    owner: dict[str, int] = {}
    for g, ids in enumerate(gt_ids):
        for fid in ids:
            other = owner.setdefault(fid, g)
            if other != g:
                raise InputError(f"frame {fid} is in two ground-truth files: {gts[other]} and {gts[g]}", frame=fid)
    seen: dict[str, int] = {}
    takes: list[list[str]] = [[] for _ in gts]
    for p, ids in enumerate(pred_ids):
        owners: set[int] = set()
        for fid in ids:
            other = seen.setdefault(fid, p)
            if other != p:
                raise InputError(f"frame {fid} is in two prediction files: {preds[other]} and {preds[p]}", frame=fid)
            home = owner.get(fid)
            if home is None:
                raise InputError("predictions for a frame that is not in the ground truth", source=preds[p], frame=fid)
            owners.add(home)
        for home in sorted(owners):
            takes[home].append(preds[p])
    return [Part(gt, tuple(t), False, gt_format, pred_format) for gt, t in zip(gts, takes)]


@dataclass(frozen=True)
class _Ids:
    kind: str
    fmt: str | None

    def __call__(self, path: str) -> tuple[str, ...]:
        return _frame_ids(path, self.kind, self.fmt)


def _serial(fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
    return [fn(x) for x in items]


# ------------------------------------------------------------------------------------------------ phase 1


@dataclass
class _Summary1:
    """What phase 1 keeps of one part (no boxes: a few bytes per ground-truth box)."""

    gt_ids: tuple[str, ...]
    pred_ids: tuple[str, ...]
    missing: tuple[str, ...]
    tp_scores: list[np.ndarray]  # per job of the superset plan
    n_valid: list[int]
    scored: dict[str, dict[Metric, bool]]
    any_invalid_alpha: bool
    first_alpha: float | None  # of the first detection of the part's first frame with detections
    num_gt: dict[str, dict[str, int]]
    num_det: dict[str, int]
    range_num_gt: list[dict[str, dict[str, int]]]
    present: dict[str, bool]  # per class: any ground truth or detection of it
    names: set[str]
    gt_dims: dict[str, tuple[int, np.ndarray]]
    dt_dims: dict[str, tuple[int, np.ndarray]]
    gt_unsized: UnsizedBoxes
    dt_unsized: UnsizedBoxes
    load_warnings: list[str]
    seconds: float = 0.0


@dataclass(frozen=True)
class _Phase1:
    config: EvalConfig

    def __call__(self, part: Part) -> _Summary1:
        from ..core.evaluation import range_num_gt

        t0 = time.perf_counter()
        gt, dt, warnings = _load_part(part)
        plan = plan_evaluation(gt, dt, self.config, facts=Facts.every_job(self.config))
        passes = plan.first_passes()
        aligned = plan.dt
        first = int(np.argmax(aligned.counts > 0)) if aligned.num_boxes else -1
        return _Summary1(
            gt_ids=gt.frame_ids,
            pred_ids=dt.frame_ids,
            missing=plan.missing,
            tp_scores=[s for s, _ in passes],
            n_valid=[n for _, n in passes],
            scored={c: scored_metrics(aligned, c) for c in self.config.classes},
            any_invalid_alpha=bool(np.any(aligned.alpha == INVALID_ALPHA)),
            first_alpha=float(aligned.alpha[aligned.offsets[first]]) if first >= 0 else None,
            num_gt=plan.num_gt,
            num_det=plan.num_det,
            range_num_gt=range_num_gt(plan),
            present={c: bool(gt.is_class(c).any() or dt.is_class(c).any()) for c in self.config.classes},
            names=set(np.unique(gt.name).tolist()) | set(np.unique(dt.name).tolist()),
            gt_dims=dimension_samples(gt),
            dt_dims=dimension_samples(aligned),
            gt_unsized=unsized_boxes(gt),
            dt_unsized=unsized_boxes(aligned),
            load_warnings=warnings,
            seconds=time.perf_counter() - t0,
        )


# ------------------------------------------------------------------------------------------------ phase 2


@dataclass(frozen=True)
class _Phase2:
    config: EvalConfig
    facts: Facts
    thresholds: tuple[np.ndarray, ...]  # per job of the plan made with ``facts``
    #: also each job's per-frame steps (for the bootstrap), from the same loaded part
    events: bool = False

    def __call__(self, part: Part) -> tuple[list[np.ndarray], list[Any] | None]:
        gt, dt, _ = _load_part(part)
        plan = plan_evaluation(gt, dt, self.config, facts=self.facts)
        counts = plan.second_passes(self.thresholds)
        return [np.stack([c.tp, c.fp, c.fn, c.similarity]) for c in counts], plan.events() if self.events else None


# ------------------------------------------------------------------------------------------------ driver


def _empty(kind: str, source: str = "") -> Annotations:
    """No frames: a plan of it has the jobs and slots (which depend on the config and facts only)."""
    return Annotations.from_frames(kind, source or kind, [])  # type: ignore[arg-type]


def evaluate_sharded(
    gt_paths: Sequence[str | Path],
    pred_paths: Sequence[str | Path],
    config: EvalConfig | None = None,
    *,
    gt_format: str | None = None,
    pred_format: str | None = None,
    keep_curves: bool = False,
    mapper: Mapper | None = None,
    source: tuple[str, str] | None = None,
) -> EvalResult:
    """Evaluate the set made of ``gt_paths`` and ``pred_paths`` (any formats the loaders read) part by part.

    ``mapper`` runs each phase over the parts (default: one after another in this process; see
    :mod:`kitti_eval.analysis.cluster` for Dask). ``source``: names of the two inputs for messages
    (default: the first file of each).
    """
    return _evaluate(gt_paths, pred_paths, config, gt_format, pred_format, keep_curves, mapper, source)[0]


def _evaluate(
    gt_paths: Sequence[str | Path],
    pred_paths: Sequence[str | Path],
    config: EvalConfig | None,
    gt_format: str | None,
    pred_format: str | None,
    keep_curves: bool,
    mapper: Mapper | None,
    source: tuple[str, str] | None,
    events: bool = False,
) -> tuple[EvalResult, Any, list[Any] | None]:
    """:func:`evaluate_sharded`, the plan of its jobs and slots, and (with ``events``) each job's per-frame
    steps over the whole set."""
    config = config or EvalConfig()
    run = mapper or _serial
    if not gt_paths:
        raise InputError("no ground-truth files")
    if not pred_paths:
        raise InputError("no prediction files")
    clock = time.perf_counter
    t0 = clock()
    parts, first = _run_parts(run, _Phase1(config), gt_paths, pred_paths, gt_format, pred_format)
    t1 = clock()
    gt_name, pred_name = source or (str(gt_paths[0]), str(pred_paths[0]))
    facts, totals = _reduce_facts(first, config, gt_name, pred_name, gt_paths)
    template = plan_evaluation(_empty("ground_truth"), _empty("detections"), config, facts=facts)
    superset = plan_evaluation(_empty("ground_truth"), _empty("detections"), config, facts=Facts.every_job(config))
    index = {(j.codes, j.overlap, j.min_overlap): k for k, j in enumerate(superset.jobs)}
    thresholds, n_valid = [], []
    for job in template.jobs:
        k = index[(job.codes, job.overlap, job.min_overlap)]
        n = sum(s.n_valid[k] for s in first)
        scores = np.concatenate([s.tp_scores[k] for s in first]) if first else np.zeros(0)
        thresholds.append(score_thresholds(scores, n))
        n_valid.append(n)
    del first
    t2 = clock()
    second = run(_Phase2(config, facts, tuple(thresholds), events), parts)
    sums = [np.zeros((4, len(t))) for t in thresholds]
    for counts, _ in second:
        for k, c in enumerate(counts):
            sums[k] += c
    counts_ = [
        PRCounts(thresholds=t, tp=s[0], fp=s[1], fn=s[2], similarity=s[3], num_valid_gt=n)
        for t, s, n in zip(thresholds, sums, n_valid)
    ]
    t3 = clock()
    timings = {"phase1": t1 - t0, "reduce": t2 - t1, "phase2": t3 - t2}
    result = result_from_counts(template, counts_, totals, keep_curves=keep_curves, timings=timings)
    joined = _join_events([steps for _, steps in second], len(template.jobs)) if events else None
    return result, template, joined


# ------------------------------------------------------------------------------------------- bootstrap


def _join_events(parts: Sequence[Sequence[Any]], n_jobs: int) -> list[Any]:
    """Each job's per-frame steps over the whole set, from its parts' (in ground-truth file order)."""
    from ..core.matching import FrameEvents

    out = []
    for k in range(n_jobs):
        pieces = [p[k] for p in parts]
        offsets = np.cumsum([0, *(len(e.valid) for e in pieces[:-1])])
        tp_score = np.concatenate([e.tp_score for e in pieces])
        tp_frame = np.concatenate([e.tp_frame + o for e, o in zip(pieces, offsets)])
        ev_score = np.concatenate([e.ev_score for e in pieces])
        ev_frame = np.concatenate([e.ev_frame + o for e, o in zip(pieces, offsets)])
        ev_delta = np.concatenate([e.ev_delta for e in pieces])
        tp_order = np.argsort(-tp_score, kind="stable")
        ev_order = np.argsort(-ev_score, kind="stable")
        out.append(
            FrameEvents(
                valid=np.concatenate([e.valid for e in pieces]),
                tp_score=tp_score[tp_order],
                tp_frame=tp_frame[tp_order],
                ev_score=ev_score[ev_order],
                ev_frame=ev_frame[ev_order],
                ev_delta=np.ascontiguousarray(ev_delta[ev_order]),
                compute_aos=pieces[0].compute_aos if pieces else False,
            )
        )
    return out


def paired_bootstrap_sharded(
    gt_paths: Sequence[str | Path],
    preds_a: Sequence[str | Path],
    preds_b: Sequence[str | Path],
    config: EvalConfig | None = None,
    *,
    resamples: int = 1000,
    seed: int = 0,
    gt_format: str | None = None,
    pred_format: str | None = None,
    mapper: Mapper | None = None,
) -> tuple[EvalResult, EvalResult, dict[Any, tuple[float, float]]]:
    """:func:`kitti_eval.analysis.bootstrap.paired_bootstrap` of two prediction sets over a ground truth given
    in shards: both evaluated part by part, then each job's per-frame steps joined from the parts (a few numbers
    per detection, not its box) and resampled as for the set in one piece (same frames, same draws)."""
    from .bootstrap import frame_weights, paired_intervals, resampled_values

    if resamples < 1:
        raise ValueError("resamples must be >= 1")
    values = []
    results = []
    weights = None
    for preds in (preds_a, preds_b):
        result, template, events = _evaluate(
            gt_paths, preds, config, gt_format, pred_format, False, mapper, None, events=True
        )
        assert events is not None
        if weights is None:
            weights = frame_weights(result.frames, resamples, seed)
        values.append(resampled_values(template.slots, events, weights))
        results.append(result)
    return results[0], results[1], paired_intervals(values[0], values[1])


def _run_parts(
    run: Mapper,
    phase: Callable[[Part], Any],
    gt_paths: Sequence[str | Path],
    pred_paths: Sequence[str | Path],
    gt_format: str | None,
    pred_format: str | None,
) -> tuple[list[Part], list[Any]]:
    """``phase`` over the parts: the files paired by position when that holds, else as :func:`parts_of` says."""
    if len(gt_paths) == len(pred_paths):
        parts = [Part(str(g), (str(p),), True, gt_format, pred_format) for g, p in zip(gt_paths, pred_paths)]
        try:
            return parts, run(phase, parts)
        except _NotPaired:
            pass
    parts = parts_of(gt_paths, pred_paths, gt_format=gt_format, pred_format=pred_format, mapper=run)
    return parts, run(phase, parts)


@dataclass(frozen=True)
class _FramesPhase:
    config: EvalConfig
    question: FrameQuestion

    def __call__(self, part: Part) -> tuple[Any, bool]:
        from .diagnostics import frame_stats

        gt, dt, _ = _load_part(part)
        stats = frame_stats(gt, dt, self.config, self.question, facts=Facts.every_job(self.config))
        metric = self.question.metric
        overlap = Metric.BBOX if metric == Metric.AOS.value else Metric(metric)
        return stats, scored_metrics(dt, self.question.cls)[overlap]


def frame_stats_sharded(
    gt_paths: Sequence[str | Path],
    pred_paths: Sequence[str | Path],
    config: EvalConfig | None = None,
    question: FrameQuestion = ASKED,
    *,
    gt_format: str | None = None,
    pred_format: str | None = None,
    mapper: Mapper | None = None,
) -> Any:
    """:func:`kitti_eval.analysis.diagnostics.frame_stats` of a set given in shards: each part's frames (a
    frame's counts depend on its own boxes only), in ground-truth file order; only three counts a frame are
    kept."""
    from .diagnostics import FrameStats, parse_slot, with_class

    cls, metric = question.cls, question.metric
    config = with_class(config, cls)
    parse_slot(config, metric, question.difficulty, question.oset)  # bad names fail before any file is read
    _, out = _run_parts(
        mapper or _serial,
        _FramesPhase(config, question),
        gt_paths,
        pred_paths,
        gt_format,
        pred_format,
    )
    _check_unique([stats.frame_ids for stats, _ in out], [str(p) for p in gt_paths], "ground-truth")
    if config.protocol.skip_undetected and not any(scored for _, scored in out):
        raise ConfigError(
            f"{cls} is not evaluated in {metric} under the {config.protocol.name} protocol (no detection of it "
            "can be scored there)"
        )
    first = out[0][0]
    return FrameStats(
        tuple(fid for stats, _ in out for fid in stats.frame_ids),
        np.concatenate([stats.tp for stats, _ in out]),
        np.concatenate([stats.fp for stats, _ in out]),
        np.concatenate([stats.fn for stats, _ in out]),
        first.cls,
        first.metric,
        first.difficulty,
        first.oset,
        first.score_threshold,
    )


def _reduce_facts(
    first: Sequence[_Summary1],
    config: EvalConfig,
    gt_name: str,
    pred_name: str,
    gt_paths: Sequence[str | Path],
) -> tuple[Facts, Totals]:
    """The set's facts and totals from the parts' summaries (in ground-truth file order)."""
    _check_unique([s.gt_ids for s in first], [str(p) for p in gt_paths], "ground-truth")
    _check_unique([s.pred_ids for s in first], None, "prediction")
    protocol = config.protocol
    scored = {c: {m: any(s.scored[c][m] for s in first) for m in OVERLAP_METRICS} for c in config.classes}
    if protocol.aos_rule == "all_valid":
        compute_aos = not any(s.any_invalid_alpha for s in first)
    else:
        alphas = [s.first_alpha for s in first if s.first_alpha is not None]
        compute_aos = bool(alphas) and alphas[0] != INVALID_ALPHA
    num_gt = {c: {d: sum(s.num_gt[c][d] for s in first) for d in first[0].num_gt[c]} for c in config.classes}
    num_det = {c: sum(s.num_det[c] for s in first) for c in config.classes}
    ranges = tuple(
        {c: {d: sum(s.range_num_gt[r][c][d] for s in first) for d in num_gt[c]} for c in config.classes}
        for r in range(len(config.ranges))
    )
    missing = tuple(fid for s in first for fid in s.missing)
    frames = sum(len(s.gt_ids) for s in first)
    warnings = list(dict.fromkeys(w for s in first for w in s.load_warnings))  # each file's, once
    unsized = [UnsizedBoxes(), UnsizedBoxes()]
    for s in first:
        unsized = [unsized[0].merged(s.gt_unsized), unsized[1].merged(s.dt_unsized)]
    warnings += size_warnings(_empty("ground_truth", gt_name), unsized=unsized[0])
    warnings += size_warnings(_empty("detections", pred_name), unsized=unsized[1])
    warnings += dimension_order_warnings(
        _empty("ground_truth", gt_name), samples=merge_dimension_samples(s.gt_dims for s in first)
    )
    warnings += dimension_order_warnings(
        _empty("detections", pred_name), samples=merge_dimension_samples(s.dt_dims for s in first)
    )
    names = sorted(set().union(*(s.names for s in first)))
    for c in config.classes:
        if not any(s.present[c] for s in first):
            warnings.append(
                f"class {c!r} has neither ground truth nor detections, so every AP of it is n/a{did_you_mean(c, names)}"
            )
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        warnings.append(f"{len(missing)} of {frames} frames have no predictions and count as empty: {shown}")
    totals = Totals(num_gt, num_det, frames, missing, tuple(warnings), compute_aos, ranges)
    return Facts(scored, compute_aos), totals


def _check_unique(ids: Iterable[tuple[str, ...]], names: Sequence[str] | None, what: str) -> None:
    seen: dict[str, int] = {}
    for k, part in enumerate(ids):
        for fid in part:
            other = seen.setdefault(fid, k)
            if other != k:
                where = f": {names[other]} and {names[k]}" if names else ""
                raise InputError(f"frame {fid} is in two {what} files{where}", frame=fid)
