"""The paired bootstrap over frames: 95% intervals of B - A for every value (see :mod:`.compare`).

A resample draws frames with replacement (the same draw for both prediction sets: paired). Nothing is
re-matched: each frame's counts are step functions of the score threshold (:func:`frame_events_many`),
so a resample's AP is a weighted sweep over those steps, with the score thresholds chosen again from the
resampled true positives exactly as the devkit chooses them. With every frame drawn once this
reproduces :func:`kitti_eval.evaluate`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ..core.ap import average_precisions, envelope
from ..core.arrays import kernel_input
from ..core.evaluation import Plan, Slot, evaluate, plan_evaluation
from ..core.frames import Annotations
from ..core.kernel_cache import njit
from ..core.matching import FrameEvents, default_workers, threshold_step
from ..core.protocol import N_SAMPLE_PTS, EvalConfig, Metric
from ..core.result import EvalResult
from .gate import ValueKey

__all__ = ["resampled_ap", "resampled_values", "paired_intervals", "frame_weights", "paired_bootstrap"]


@njit(cache=True, nogil=True)
def _resampled_curves(
    valid: np.ndarray,
    tp_score: np.ndarray,
    tp_frame: np.ndarray,
    ev_score: np.ndarray,
    ev_frame: np.ndarray,
    ev_delta: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray:
    """(B, 2, 41): precision and orientation similarity / (TP + FP) at each score threshold (zeros past the
    last; NaN where nothing is detected) for each row of frame weights (B, F), before max-interpolation."""
    n_b = weights.shape[0]
    out = np.zeros((n_b, 2, N_SAMPLE_PTS))
    for b in range(n_b):
        w = weights[b]
        n_gt = 0
        for f in range(valid.shape[0]):
            n_gt += w[f] * valid[f]
        n_tp = 0
        for k in range(tp_score.shape[0]):
            n_tp += w[tp_frame[k]]
        if n_gt == 0 or n_tp == 0:
            continue
        # the devkit's score thresholds over the resampled true positives (each repeated by its weight)
        thresholds = np.empty(N_SAMPLE_PTS)
        n_thr = 0
        current = 0.0
        i = 0
        for k in range(tp_score.shape[0]):
            for _ in range(w[tp_frame[k]]):
                take, current = threshold_step(i, n_tp, n_gt, current, N_SAMPLE_PTS)
                if take and n_thr < N_SAMPLE_PTS:
                    thresholds[n_thr] = tp_score[k]
                    n_thr += 1
                i += 1
        tp = 0.0
        fp = 0.0
        sim = 0.0
        e = 0
        for t in range(n_thr):
            while e < ev_score.shape[0] and ev_score[e] >= thresholds[t]:
                ww = w[ev_frame[e]]
                if ww != 0:
                    tp += ww * ev_delta[e, 0]
                    fp += ww * ev_delta[e, 1]
                    sim += ww * ev_delta[e, 3]
                e += 1
            out[b, 0, t] = tp / (tp + fp) if tp + fp > 0 else np.nan
            out[b, 1, t] = sim / (tp + fp) if tp + fp > 0 else np.nan
    return out


def resampled_ap(events: FrameEvents, weights: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """AP of one matching under frame weights.

    Parameters
    ----------
    events : the matching's per-frame steps
    weights : (B, F) non-negative integers, how often each frame is drawn in each of B resamples

    Returns
    -------
    (B, 4) float64: precision AP R11, R40 and orientation AP R11, R40, in percent (the curves interpolated
    and averaged by :mod:`kitti_eval.core.ap`, as every AP is)
    """
    w = kernel_input(weights, np.int64)
    if w.ndim != 2 or w.shape[1] != events.valid.shape[0] or (w < 0).any():
        raise ValueError(f"Expected `weights` with shape (B, {events.valid.shape[0]}) of counts >= 0, got {w.shape}")
    curves = envelope(
        _resampled_curves(
            events.valid, events.tp_score, events.tp_frame, events.ev_score, events.ev_frame, events.ev_delta, w
        )
    )
    return np.stack(
        [
            average_precisions(curves[:, 0], "R11"),
            average_precisions(curves[:, 0], "R40"),
            average_precisions(curves[:, 1], "R11"),
            average_precisions(curves[:, 1], "R40"),
        ],
        axis=1,
    )


def frame_weights(n_frames: int, n_resamples: int, seed: int) -> npt.NDArray[np.int64]:
    """(B, F) bootstrap draws: each row counts how often each frame is drawn among F draws with replacement."""
    rng = np.random.default_rng(seed)
    if n_frames == 0:
        return np.zeros((n_resamples, 0), dtype=np.int64)
    return rng.multinomial(n_frames, np.full(n_frames, 1.0 / n_frames), size=n_resamples).astype(np.int64)


def _resampled_values(plan: Plan, weights: np.ndarray, workers: int | None) -> dict[ValueKey, np.ndarray]:
    """Every value of the result under each resample: {key: (B,)} (keys the protocol evaluates)."""
    return resampled_values(plan.slots, plan.events(workers=workers), weights, workers)


def resampled_values(
    slots: Sequence[Slot], events: Sequence[FrameEvents], weights: np.ndarray, workers: int | None = None
) -> dict[ValueKey, np.ndarray]:
    """Every value of a result under each resample, {key: (B,)}, from its slots and its jobs' events (of the
    whole set, or joined from its parts)."""
    n_workers = default_workers() if workers is None else max(1, workers)
    if n_workers > 1 and len(events) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            per_job = list(pool.map(lambda ev: resampled_ap(ev, weights), events))
    else:
        per_job = [resampled_ap(ev, weights) for ev in events]
    out: dict[ValueKey, np.ndarray] = {}
    for cls, difficulty, metric, oset, job, with_aos in slots:
        if job is None:
            continue
        for r, col in (("R11", 0), ("R40", 1)):
            out[ValueKey(cls, metric.value, difficulty.label, r, oset)] = per_job[job][:, col]
            if metric is Metric.BBOX and with_aos:
                out[ValueKey(cls, "aos", difficulty.label, r, oset)] = per_job[job][:, col + 2]
    return out


def paired_bootstrap(
    gt: Annotations,
    dt_a: Annotations,
    dt_b: Annotations,
    config: EvalConfig | None = None,
    *,
    resamples: int = 1000,
    seed: int = 0,
    workers: int | None = None,
) -> tuple[EvalResult, EvalResult, dict[ValueKey, tuple[float, float]]]:
    """Evaluate A and B, and a 95% interval of B - A for every value from ``resamples`` paired resamples."""
    if resamples < 1:
        raise ValueError("resamples must be >= 1")
    plan_a, plan_b = plan_evaluation(gt, dt_a, config), plan_evaluation(gt, dt_b, config)
    weights = frame_weights(gt.num_frames, resamples, seed)
    intervals = paired_intervals(
        _resampled_values(plan_a, weights, workers), _resampled_values(plan_b, weights, workers)
    )
    return evaluate(gt, dt_a, config, workers=workers), evaluate(gt, dt_b, config, workers=workers), intervals


def paired_intervals(
    values_a: Mapping[ValueKey, np.ndarray], values_b: Mapping[ValueKey, np.ndarray]
) -> dict[ValueKey, tuple[float, float]]:
    """95% intervals of B - A per value from the paired resamples (values either lacks are left out)."""
    intervals: dict[ValueKey, tuple[float, float]] = {}
    for key, va in values_a.items():
        vb = values_b.get(key)
        if vb is None:
            continue
        delta = vb - va
        if np.isnan(delta).any():
            continue
        lo, hi = np.percentile(delta, [2.5, 97.5])
        intervals[key] = (float(lo), float(hi))
    return intervals
