"""Comparing two sets of predictions: per-value deltas and paired bootstrap intervals over frames.

A resample draws frames with replacement (the same draw for both prediction sets: paired). Nothing is
re-matched: each frame's counts are step functions of the score threshold (:func:`frame_events_many`),
so a resample's AP is a weighted sweep over those steps, with the score thresholds chosen again from the
resampled true positives exactly as the devkit chooses them. With every frame drawn once this
reproduces :func:`kitti_eval.evaluate`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from ._jit import kernel_input
from .errors import InputError
from .evaluation import Plan, evaluate, plan_evaluation
from .frames import Annotations
from .gate import ValueKey
from .matching import FrameEvents, default_workers, frame_events_many, threshold_step
from .metrics import average_precisions, envelope
from .protocol import N_SAMPLE_PTS, EvalConfig, Metric
from .result import EvalResult

__all__ = ["resampled_ap", "frame_weights", "paired_bootstrap", "Comparison", "compare_documents"]


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
    and averaged by :mod:`kitti_eval.metrics`, as every AP is)
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


def _events(plan: Plan, workers: int | None) -> list[FrameEvents]:
    fo = plan.overlaps
    return frame_events_many(
        fo.pair_offsets,
        (fo.bbox, fo.bev, fo.d3),
        plan.gt.offsets,
        plan.dt.offsets,
        plan.ignored_gt,
        plan.ignored_det,
        plan.dontcare,
        plan.dt.score,
        plan.gt.alpha,
        plan.dt.alpha,
        plan.jobs,
        workers=workers,
    )


def _resampled_values(plan: Plan, weights: np.ndarray, workers: int | None) -> dict[ValueKey, np.ndarray]:
    """Every value of the result under each resample: {key: (B,)} (keys the protocol evaluates)."""
    events = _events(plan, workers)
    n_workers = default_workers() if workers is None else max(1, workers)
    if n_workers > 1 and len(events) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            per_job = list(pool.map(lambda ev: resampled_ap(ev, weights), events))
    else:
        per_job = [resampled_ap(ev, weights) for ev in events]
    out: dict[ValueKey, np.ndarray] = {}
    for cls, difficulty, metric, oset, job, with_aos in plan.slots:
        if job is None:
            continue
        for r, col in (("R11", 0), ("R40", 1)):
            out[ValueKey(cls, metric.value, difficulty.label, r, oset)] = per_job[job][:, col]
            if metric is Metric.BBOX and with_aos:
                out[ValueKey(cls, "aos", difficulty.label, r, oset)] = per_job[job][:, col + 2]
    return out


@dataclass(frozen=True)
class Comparison:
    """Two results side by side: per value A, B, B - A, and (with a bootstrap) a 95% interval of B - A."""

    a: Mapping[str, Any]
    b: Mapping[str, Any]
    intervals: Mapping[ValueKey, tuple[float, float]]
    resamples: int
    seed: int | None

    def rows(self) -> list[tuple[ValueKey, float | None, float | None, float | None, tuple[float, float] | None]]:
        from .gate import keys_of

        out = []
        shared = set(self.b.get("classes", ()))
        for key in keys_of(self.a):
            if key.cls not in shared:  # said in the notes
                continue
            va = key.read(self.a)
            try:
                vb = key.read(self.b)
            except InputError:  # a class only A has
                vb = None
            delta = None if va is None or vb is None else vb - va
            out.append((key, va, vb, delta, self.intervals.get(key)))
        return out

    @property
    def notes(self) -> list[str]:
        """What makes the two hard to compare: another protocol, other IoU thresholds, classes in one only."""
        a, b = self.a, self.b
        out = []
        if a.get("protocol") != b.get("protocol"):
            out.append(f"different protocols: {a.get('protocol')} and {b.get('protocol')}")
        only = sorted(set(a.get("classes", ())).symmetric_difference(b.get("classes", ())))
        if only:
            out.append(f"classes in only one of them are not compared: {', '.join(only)}")
        for cls in (c for c in a.get("classes", ()) if c in b.get("classes", ())):
            for oset in (s for s in a.get("threshold_sets", ()) if s in b.get("threshold_sets", ())):
                if a["overlaps"][cls][oset] != b["overlaps"][cls][oset]:
                    out.append(f"{cls}/{oset}: different IoU thresholds")
        return out

    def to_dict(self) -> dict[str, Any]:
        """``values``: every value of A with B's and B - A (and the interval with a bootstrap); ``num_det``
        and ``frames``: B - A of the counts; ``notes``: see :attr:`notes`."""
        shared = [c for c in self.a.get("classes", ()) if c in self.b.get("classes", ())]
        return {
            "schema_version": 1,
            "resamples": self.resamples,
            "seed": self.seed,
            "notes": self.notes,
            "values": [
                {"key": str(k), "a": va, "b": vb, "delta": d, "interval95": list(iv) if iv is not None else None}
                for k, va, vb, d, iv in self.rows()
            ],
            "num_det": {
                c: self.b["num_det"][c] - self.a["num_det"][c]
                for c in shared
                if c in self.a.get("num_det", {}) and c in self.b.get("num_det", {})
            },
            "frames": self.b["frames"] - self.a["frames"] if "frames" in self.a and "frames" in self.b else None,
        }


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
    values_a = _resampled_values(plan_a, weights, workers)
    values_b = _resampled_values(plan_b, weights, workers)
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
    return evaluate(gt, dt_a, config, workers=workers), evaluate(gt, dt_b, config, workers=workers), intervals


def compare_documents(
    a: Mapping[str, Any],
    b: Mapping[str, Any],
    intervals: Mapping[ValueKey, tuple[float, float]] | None = None,
    resamples: int = 0,
    seed: int | None = None,
) -> Comparison:
    return Comparison(a, b, dict(intervals or {}), resamples, seed)


def render_comparison(cmp: Comparison, fmt: str = "table", *, every_value: bool = False) -> str:
    """The comparison as a table (R40 strict values unless ``every_value``), Markdown, or JSON."""
    import json

    if fmt == "json":
        return json.dumps(cmp.to_dict(), indent=2, allow_nan=False) + "\n"
    rows = [r for r in cmp.rows() if every_value or (r[0].recall == "R40" and r[0].oset == "strict")]

    def num(v: float | None, sign: bool = False) -> str:
        return "-" if v is None else (f"{v:+.4f}" if sign else f"{v:.4f}")

    def interval(iv: tuple[float, float] | None) -> str:
        return "" if iv is None else f"[{iv[0]:+.4f}, {iv[1]:+.4f}]"

    def significant(iv: tuple[float, float] | None) -> str:
        return "*" if iv is not None and (iv[0] > 0 or iv[1] < 0) else ""

    if fmt == "markdown":
        out = ["| value | A | B | B − A | 95% interval |", "|---|---:|---:|---:|---|"]
        out += [
            f"| `{k}` | {num(a)} | {num(b)} | {num(d, True)}{significant(iv)} | {interval(iv)} |"
            for k, a, b, d, iv in rows
        ]
        note = (
            f"\n{cmp.resamples} paired bootstrap resamples over frames (seed {cmp.seed}); * : the interval "
            "excludes 0.\n"
            if cmp.resamples
            else "\n"
        )
        return "\n".join(out) + "\n" + note + "".join(f"> note: {n}\n" for n in cmp.notes)
    out = [f"{'value':<34} {'A':>9} {'B':>9} {'B - A':>10}  {'95% interval' if cmp.resamples else ''}"]
    out += [
        f"{str(k):<34} {num(a):>9} {num(b):>9} {num(d, True) + significant(iv):>10}  {interval(iv)}"
        for k, a, b, d, iv in rows
    ]
    if cmp.resamples:
        out.append(
            f"{cmp.resamples} paired bootstrap resamples over frames (seed {cmp.seed}); "
            "* marks an interval that excludes 0"
        )
    return "\n".join(out) + "\n"
