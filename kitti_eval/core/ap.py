"""From match counts to curves and average precision: pure functions over small arrays."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .matching import PRCounts
from .protocol import N_SAMPLE_PTS, RECALL_SAMPLE_INDICES

__all__ = ["Curve", "curve_from_counts", "envelope", "average_precision", "average_precisions"]


@dataclass(frozen=True)
class Curve:
    """The 41-point curves of one (class, metric, difficulty, threshold set).

    precision : (41,) max-interpolated precision, ``p[i] = max(p[i:])``; zeros past the last threshold
    recall : (41,) recall at each score threshold, interpolated the same way
    orientation : (41,) AOS similarity / (TP + FP), interpolated; zeros when AOS is not computed
    thresholds : (T,) the score thresholds behind samples 0..T-1
    num_valid_gt : the recall denominator
    """

    precision: npt.NDArray[np.float64]
    recall: npt.NDArray[np.float64]
    orientation: npt.NDArray[np.float64]
    thresholds: npt.NDArray[np.float64]
    num_valid_gt: int

    def __post_init__(self) -> None:
        for name in ("precision", "recall", "orientation"):
            if getattr(self, name).shape != (N_SAMPLE_PTS,):
                raise ValueError(f"Expected `{name}` with shape ({N_SAMPLE_PTS},), got {getattr(self, name).shape}")


def envelope(values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``out[..., i] = max(values[..., i:])`` along the last axis: the devkit's max-interpolation (a NaN
    makes every earlier sample NaN, as numpy's max does)."""
    return np.maximum.accumulate(values[..., ::-1], axis=-1)[..., ::-1].copy()


def curve_from_counts(counts: PRCounts, n_sample_pts: int = N_SAMPLE_PTS) -> Curve:
    """Precision, recall and orientation similarity at each threshold, then their max envelopes."""
    t = counts.thresholds.shape[0]
    precision = np.zeros(n_sample_pts)
    recall = np.zeros(n_sample_pts)
    orientation = np.zeros(n_sample_pts)
    if t:
        with np.errstate(divide="ignore", invalid="ignore"):
            recall[:t] = counts.tp / (counts.tp + counts.fn)
            precision[:t] = counts.tp / (counts.tp + counts.fp)
            orientation[:t] = counts.similarity / (counts.tp + counts.fp)
    return Curve(
        precision=envelope(precision),
        recall=envelope(recall),
        orientation=envelope(orientation),
        thresholds=counts.thresholds.copy(),
        num_valid_gt=counts.num_valid_gt,
    )


def average_precision(values: Sequence[float] | npt.NDArray[np.float64], recall: str) -> float:
    """AP in percent from a 41-point curve: R40 averages samples 1..40, R11 samples 0, 4, ..., 40.

    Summed in sample order, as the reference evaluators do.
    """
    return float(average_precisions(np.asarray(values, dtype=np.float64)[None], recall)[0])


def average_precisions(curves: npt.NDArray[np.float64], recall: str) -> npt.NDArray[np.float64]:
    """:func:`average_precision` of each row of ``curves`` (B, 41): the same sums, in the same order."""
    idx = RECALL_SAMPLE_INDICES[recall]
    total = np.zeros(curves.shape[0])
    for i in idx:
        total = total + curves[:, i]
    return total / len(idx) * 100.0
