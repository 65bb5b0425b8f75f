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
from ..core.cpus import default_workers
from ..core.evaluation import Plan, Slot, evaluate, plan_evaluation
from ..core.frames import Annotations
from ..core.kernel_cache import njit
from ..core.matching import FrameEvents, threshold_step
from ..core.protocol import N_SAMPLE_PTS, EvalConfig, Metric
from ..core.result import EvalResult, ValueKey

__all__ = [
    "resampled_ap",
    "resampled_values",
    "paired_intervals",
    "interval95",
    "frame_weights",
    "paired_bootstrap",
]


#: resamples swept together over a matching's events (one pass over the events per block)
_BLOCK = 32


@njit(cache=True, nogil=True)
def _resampled_thresholds(
    valid: np.ndarray,
    tp_score: np.ndarray,
    tp_frame: np.ndarray,
    weights: np.ndarray,
    thresholds: np.ndarray,
    n_thr: np.ndarray,
) -> None:
    """Into ``thresholds[b, :n_thr[b]]``: the devkit's score thresholds over the true positives of resample b
    (each repeated by its frame's weight). The rule (:func:`threshold_step`) is monotone in the index of the
    true positive: false up to the next threshold, true from it on (its two recalls grow with the index, and
    so does their rounding), so each threshold is found by bisection instead of a step per true positive;
    the takes, and the recall targets they update, are the ones the step-by-step loop makes."""
    n_b, n_f = weights.shape
    n_k = tp_score.shape[0]
    before = np.empty(n_k + 1, np.int64)  # before[k]: the repeated true positives ahead of the k-th
    for b in range(n_b):
        w = weights[b]
        n_gt = 0
        for f in range(n_f):
            n_gt += w[f] * valid[f]
        before[0] = 0
        for k in range(n_k):
            before[k + 1] = before[k] + w[tp_frame[k]]
        n_tp = int(before[n_k])
        n_thr[b] = 0
        if n_gt == 0 or n_tp == 0:
            continue
        current = 0.0
        i = 0
        m = 0
        while m < N_SAMPLE_PTS and i < n_tp:
            lo, hi = i, n_tp - 1  # the last one is always taken
            while lo < hi:
                mid = (lo + hi) // 2
                take, _ = threshold_step(mid, n_tp, n_gt, current, N_SAMPLE_PTS)
                if take:
                    hi = mid
                else:
                    lo = mid + 1
            _, current = threshold_step(lo, n_tp, n_gt, current, N_SAMPLE_PTS)
            thresholds[b, m] = tp_score[np.searchsorted(before, lo, side="right") - 1]
            m += 1
            i = lo + 1
        n_thr[b] = m


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
    last; NaN where nothing is detected) for each row of frame weights (B, F), before max-interpolation.

    The events (sorted by score, descending) are swept once per block of resamples: each resample keeps its
    own sums and records them when the sweep passes its next threshold. Each resample adds the same terms in
    the same order as a sweep of its own would, so the numbers are the same; the events are read once a
    block rather than once a resample (reading them was most of the time)."""
    n_b, n_f = weights.shape
    out = np.zeros((n_b, 2, N_SAMPLE_PTS))
    thresholds = np.empty((n_b, N_SAMPLE_PTS))
    n_thr = np.zeros(n_b, np.int64)
    _resampled_thresholds(valid, tp_score, tp_frame, weights, thresholds, n_thr)
    block = np.zeros((n_f, _BLOCK))  # the block's weights, a frame's in one row
    tp = np.zeros(_BLOCK)
    fp = np.zeros(_BLOCK)
    sim = np.zeros(_BLOCK)
    t = np.zeros(_BLOCK, np.int64)
    n_e = ev_score.shape[0]
    for b0 in range(0, n_b, _BLOCK):
        nb = min(_BLOCK, n_b - b0)
        for f in range(n_f):
            for r in range(nb):
                block[f, r] = weights[b0 + r, f]
        top = -np.inf  # the highest next threshold of the block
        for r in range(nb):
            tp[r] = 0.0
            fp[r] = 0.0
            sim[r] = 0.0
            t[r] = 0
            if n_thr[b0 + r] > 0:
                top = max(top, thresholds[b0 + r, 0])
        for e in range(n_e + 1):
            s = ev_score[e] if e < n_e else -np.inf
            if s < top:  # some resample's threshold is above this event: record its sums first
                top = -np.inf
                for r in range(nb):
                    b = b0 + r
                    while t[r] < n_thr[b] and s < thresholds[b, t[r]]:
                        den = tp[r] + fp[r]
                        out[b, 0, t[r]] = tp[r] / den if den > 0 else np.nan
                        out[b, 1, t[r]] = sim[r] / den if den > 0 else np.nan
                        t[r] += 1
                    if t[r] < n_thr[b]:
                        top = max(top, thresholds[b, t[r]])
                if top == -np.inf:  # every threshold of the block recorded
                    break
            if e == n_e:
                break
            row = block[ev_frame[e]]
            d_tp, d_fp, d_sim = ev_delta[e, 0], ev_delta[e, 1], ev_delta[e, 3]
            for r in range(nb):
                ww = row[r]
                if ww != 0:
                    tp[r] += ww * d_tp
                    fp[r] += ww * d_fp
                    sim[r] += ww * d_sim
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
        found = interval95(vb - va)
        if found is not None:
            intervals[key] = found
    return intervals


def interval95(values: npt.ArrayLike) -> tuple[float, float] | None:
    """The 2.5th and 97.5th percentiles of resampled values (numpy's default, linear interpolation): every
    95% interval of the paired bootstrap, of a difference (:func:`paired_intervals`) or of one result's value
    (:mod:`.ranking`). None when there are none or one is NaN."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0 or np.isnan(v).any():
        return None
    lo, hi = np.percentile(v, [2.5, 97.5])
    return float(lo), float(hi)
