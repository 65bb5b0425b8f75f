"""Per-frame diagnostics: TP / FP / FN of every frame for one class, metric and difficulty, worst first.

The counts come from the same matching as the AP (each frame's recorded steps, see
:func:`kitti_eval.core.matching.frame_events_many`), read at a score threshold: every detection scoring at
least the threshold takes part, exactly as in the devkit's second pass.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.evaluation import Facts, Plan, plan_evaluation
from ..core.frames import Annotations
from ..core.matching import MatchJob
from ..core.protocol import THRESHOLD_SETS, Difficulty, EvalConfig, Metric
from ..errors import ConfigError
from .frame_question import ASKED, FrameQuestion

__all__ = [
    "FrameQuestion",
    "FrameStats",
    "frame_stats",
    "counts_at",
    "frames_document",
    "render_frames",
    "with_class",
    "parse_slot",
    "slot_job",
    "not_evaluated",
]


@dataclass(frozen=True)
class FrameStats:
    """Counts per frame (arrays of shape (F,), in the ground truth's frame order)."""

    frame_ids: tuple[str, ...]
    tp: npt.NDArray[np.int64]
    fp: npt.NDArray[np.int64]
    fn: npt.NDArray[np.int64]
    cls: str
    metric: str
    difficulty: str
    oset: str
    score_threshold: float

    def worst(self, n: int) -> list[int]:
        """Indices of the ``n`` frames with the most errors (FP + FN), ties by more misses, then frame order."""
        errors = self.fp + self.fn
        order = np.lexsort((np.arange(len(errors)), -self.fn, -errors))
        return [int(i) for i in order[:n] if errors[i] > 0]


def with_class(config: EvalConfig | None, cls: str) -> EvalConfig:
    """``config`` (default: the defaults for ``cls`` alone) with ``cls`` among its classes."""
    config = config or EvalConfig(classes=(cls,))
    if cls in config.classes:
        return config
    return EvalConfig(
        classes=(*config.classes, cls),
        protocol=config.protocol,
        overlaps=dict(config.overlaps),
        difficulty=config.difficulty,
        threshold_sets=config.threshold_sets,
        neighbours=dict(config.neighbours),
        lidar_only=config.lidar_only,
    )


def parse_slot(config: EvalConfig, metric: str, difficulty: str, oset: str) -> tuple[Metric, Difficulty]:
    """The overlap metric (AOS rides on the 2D matching) and difficulty named by the strings."""
    try:
        m = Metric(metric)
        d = Difficulty[difficulty.upper()]
    except (ValueError, KeyError):
        raise ConfigError(f"unknown metric {metric!r} or difficulty {difficulty!r}") from None
    if oset not in THRESHOLD_SETS or oset not in config.threshold_sets:
        raise ConfigError(f"unknown threshold set {oset!r}")
    return (Metric.BBOX if m is Metric.AOS else m), d


def slot_job(plan: Plan, cls: str, metric: Metric, difficulty: Difficulty, oset: str) -> MatchJob:
    """The matching behind one (class, metric, difficulty, threshold set) of ``plan``'s result."""
    job = next(
        (
            s.job
            for s in plan.slots
            if s.cls == cls and s.difficulty is difficulty and s.metric is metric and s.oset == oset
        ),
        None,
    )
    if job is None:
        raise not_evaluated(cls, metric, plan.config)
    return plan.jobs[job]


def not_evaluated(cls: str, metric: Metric, config: EvalConfig) -> ConfigError:
    """The refusal of a (class, metric) that the protocol does not evaluate for this set."""
    return ConfigError(
        f"{cls} is not evaluated in {metric.value} under the {config.protocol.name} "
        "protocol (no detection of it can be scored there)"
    )


def frame_stats(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig | None = None,
    question: FrameQuestion = ASKED,
    *,
    facts: Facts | None = None,
) -> FrameStats:
    """TP, FP and FN of every frame for one (class, metric, difficulty, threshold set) at a score threshold, as
    ``question`` asks (``facts``: the whole set's, when ``gt`` and ``dt`` are a part of it)."""
    q = question
    config = with_class(config, q.cls)
    m, d = parse_slot(config, q.metric, q.difficulty, q.oset)
    plan = plan_evaluation(gt, dt, config, facts=facts)
    job = slot_job(plan, q.cls, m, d, q.oset)
    (events,) = plan.events([job])
    tp, fp, fn = counts_at(events.valid, events.ev_frame, events.ev_score, events.ev_delta, q.score_threshold)
    return FrameStats(plan.gt.frame_ids, tp, fp, fn, q.cls, m.value, d.label, q.oset, float(q.score_threshold))


def counts_at(
    valid: npt.NDArray[np.int64],
    ev_frame: npt.NDArray[np.int64],
    ev_score: npt.NDArray[np.float64],
    ev_delta: npt.NDArray[np.float64],
    score_threshold: float,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """TP, FP and FN per frame at ``score_threshold`` from one matching's steps
    (:class:`~kitti_eval.core.matching.FrameEvents`: ``valid`` per frame, and each step's frame, score and change
    of (tp, fp, fn)): every step scoring at least the threshold counts, as every detection scoring at least it
    takes part in the devkit's second pass."""
    counts = np.zeros((len(valid), 3))
    counts[:, 2] = valid
    on = ev_score >= score_threshold
    np.add.at(counts, ev_frame[on], ev_delta[on, :3])
    tp, fp, fn = (np.rint(counts[:, k]).astype(np.int64) for k in range(3))
    return tp, fp, fn


def frames_document(stats: FrameStats, *, worst: int | None = None) -> dict[str, Any]:
    """The frames (all, or the ``worst`` n) as a JSON-ready dict."""
    rows: Sequence[int] = stats.worst(worst) if worst else range(len(stats.frame_ids))
    return {
        "class": stats.cls,
        "metric": stats.metric,
        "difficulty": stats.difficulty,
        "threshold_set": stats.oset,
        "score_threshold": stats.score_threshold,
        "frames": [
            {"frame": stats.frame_ids[i], "tp": int(stats.tp[i]), "fp": int(stats.fp[i]), "fn": int(stats.fn[i])}
            for i in rows
        ],
    }


def render_frames(stats: FrameStats, fmt: str = "table", *, worst: int | None = None) -> str:
    """The frames (all, or the ``worst`` n) as a table, CSV or JSON."""
    rows: Sequence[int] = stats.worst(worst) if worst else range(len(stats.frame_ids))
    if fmt == "json":
        return json.dumps(frames_document(stats, worst=worst), indent=2) + "\n"
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "tp", "fp", "fn"])
        w.writerows([stats.frame_ids[i], int(stats.tp[i]), int(stats.fp[i]), int(stats.fn[i])] for i in rows)
        return buf.getvalue()
    head = (
        f"{stats.cls} {stats.metric} {stats.difficulty} ({stats.oset} IoU), detections scoring >= "
        f"{stats.score_threshold:g}"
    )
    lines = [head, f"{'frame':<12} {'TP':>4} {'FP':>4} {'FN':>4}"]
    lines += [f"{stats.frame_ids[i]:<12} {stats.tp[i]:>4} {stats.fp[i]:>4} {stats.fn[i]:>4}" for i in rows]
    lines.append(f"{'all frames':<12} {int(stats.tp.sum()):>4} {int(stats.fp.sum()):>4} {int(stats.fn.sum()):>4}")
    return "\n".join(lines) + "\n"
