"""One frame's boxes labelled as the devkit's second pass sees them at a score threshold (tp, fp, ignored,
DontCare, below the threshold, another class; matched, missed, ...): what the frame listings and the frame view
show, from the same kernels as the AP counts (:mod:`kitti_eval.core.matching`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .arrays import kernel_input
from .matching import IGNORED, OTHER_CLASS, VALID, Frames, find_candidates, frame_taken

__all__ = ["FrameLabels", "label_frame", "DET_LABELS", "GT_LABELS"]

DET_LABELS = ("tp", "fp", "ignored", "dontcare", "below_threshold", "other_class")
GT_LABELS = ("matched", "missed", "ignored", "absorbed", "other_class")
DET_TP, DET_FP, DET_IGNORED, DET_DONTCARE, DET_BELOW_THRESHOLD, DET_OTHER_CLASS = range(len(DET_LABELS))
GT_MATCHED, GT_MISSED, GT_IGNORED, GT_ABSORBED, GT_OTHER_CLASS = range(len(GT_LABELS))


@dataclass(frozen=True)
class FrameLabels:
    """What the matching made of each box of one frame (codes index :data:`DET_LABELS` / :data:`GT_LABELS`).

    det_label : (N,) int8 ; det_ref : (N,) int64, the ground-truth row a detection matched (tp, ignored) or
        the DontCare row that covers it (dontcare), else -1 ; det_overlap : (N,) float64, that overlap (NaN
        without one) ; gt_label : (M,) int8 ; gt_ref : (M,) int64, the detection that took the box, else -1
    """

    det_label: npt.NDArray[np.int8]
    det_ref: npt.NDArray[np.int64]
    det_overlap: npt.NDArray[np.float64]
    gt_label: npt.NDArray[np.int8]
    gt_ref: npt.NDArray[np.int64]

    @property
    def tp(self) -> int:
        return int(np.count_nonzero(self.det_label == DET_TP))

    @property
    def fp(self) -> int:
        return int(np.count_nonzero(self.det_label == DET_FP))

    @property
    def fn(self) -> int:
        return int(np.count_nonzero(self.gt_label == GT_MISSED))


def label_frame(
    overlaps: npt.ArrayLike,
    ignored_gt: npt.ArrayLike,
    ignored_det: npt.ArrayLike,
    dontcare: npt.ArrayLike | None,
    score: npt.ArrayLike,
    min_overlap: float,
    score_threshold: float = -np.inf,
) -> FrameLabels:
    """Label every box of one frame as the devkit's second pass sees it at ``score_threshold``.

    Parameters
    ----------
    overlaps : (N, M) float64, detection j (rows) against ground-truth box i (columns) of the frame, in
        file order; for DontCare rows the fraction of the detection covered
    ignored_gt : (M,) int8 in {0, 1, -1} ; ignored_det : (N,) int8 in {0, 1, -1} (see the module docstring)
    dontcare : (M,) bool, ground-truth rows that suppress false positives, or None for none
    score : (N,) detection scores ; min_overlap : a match needs overlap strictly above this
    score_threshold : detections scoring below it take no part (default: all take part)

    The counts (``tp``, ``fp``, ``fn``) are the frame's share of the precision/recall counts at that
    threshold.
    """
    ov = kernel_input(overlaps, np.float64)
    ig = kernel_input(ignored_gt, np.int8)
    idet = kernel_input(ignored_det, np.int8)
    sc = kernel_input(score, np.float64)
    n_gt = ig.shape[0] if ig.ndim == 1 else -1
    dc = np.zeros(max(n_gt, 0), dtype=np.bool_) if dontcare is None else kernel_input(dontcare, np.bool_)
    if ig.ndim != 1 or idet.ndim != 1 or ov.shape != (idet.shape[0], n_gt):
        raise ValueError(
            f"Expected `overlaps` (N, M) with `ignored_det` (N,) and `ignored_gt` (M,), got "
            f"{ov.shape}, {idet.shape} and {ig.shape}"
        )
    if dc.shape != (n_gt,) or sc.shape != idet.shape:
        raise ValueError(f"Expected `dontcare` ({n_gt},) and `score` ({idet.shape[0]},), got {dc.shape} and {sc.shape}")
    return _labels(ov, ig, idet, dc, sc, float(min_overlap), float(score_threshold))


def _labels(
    ov: np.ndarray, ig: np.ndarray, idet: np.ndarray, dc: np.ndarray, score: np.ndarray, min_overlap: float, thr: float
) -> FrameLabels:
    """The frame compacted as for an evaluation, pass 2 (:func:`frame_pass2`, the one the AP counts come
    from), and each box's label read off what every detection took."""
    nd, ng = ov.shape
    part, dcs = np.flatnonzero(ig != OTHER_CLASS), np.flatnonzero(dc)
    best_gt = ov[:, part].max(axis=1, initial=0.0)
    best_dc = ov[:, dcs].max(axis=1, initial=0.0)
    frames = Frames(np.array([0, nd * ng]), np.array([0, ng]), np.array([0, nd]), score, np.zeros(ng), np.zeros(nd))
    c = find_candidates(frames, ov.reshape(-1), ig, idet, dc, best_gt, best_dc, min_overlap)
    taken = frame_taken(c, min_overlap, thr)
    cand = np.flatnonzero((idet != OTHER_CLASS) & (best_gt > min_overlap))
    det_label = np.full(nd, DET_FP, dtype=np.int8)
    det_ref = np.full(nd, -1, dtype=np.int64)
    det_ov = np.full(nd, np.nan)
    gt_label = np.where(ig == OTHER_CLASS, GT_OTHER_CLASS, np.where(ig == VALID, GT_MISSED, GT_IGNORED)).astype(np.int8)
    gt_ref = np.full(ng, -1, dtype=np.int64)
    det_label[idet == IGNORED] = DET_IGNORED
    for a, t in zip(cand.tolist(), taken.tolist()):
        if t >= 0:  # took ground truth part[t]
            i = int(part[t])
            det_ref[a], det_ov[a], gt_ref[i] = i, ov[a, i], a
            if ig[i] == VALID and idet[a] == VALID:
                det_label[a], gt_label[i] = DET_TP, GT_MATCHED
            else:
                det_label[a] = DET_IGNORED
                gt_label[i] = GT_IGNORED if ig[i] == IGNORED else GT_ABSORBED
        elif t <= -2:  # a DontCare region covers it
            det_label[a], det_ref[a], det_ov[a] = DET_DONTCARE, dcs[-2 - t], ov[a, dcs[-2 - t]]
    rest = np.setdiff1d(np.flatnonzero(idet == VALID), cand)  # valid but matching nothing: FP or under DontCare
    for a in rest.tolist():
        covering = np.flatnonzero(ov[a, dcs] > min_overlap)
        if len(covering) and score[a] >= thr:
            det_label[a], det_ref[a], det_ov[a] = DET_DONTCARE, dcs[covering[0]], ov[a, dcs[covering[0]]]
    det_label[(score < thr) & (idet != OTHER_CLASS)] = DET_BELOW_THRESHOLD
    det_label[idet == OTHER_CLASS] = DET_OTHER_CLASS
    return FrameLabels(det_label, det_ref, det_ov, gt_label, gt_ref)
