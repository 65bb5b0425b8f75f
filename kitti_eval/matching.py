"""Matching detections to ground truth, frame by frame, into precision/recall counts.

This is the KITTI devkit's ``eval_class`` for one (class, difficulty, metric, IoU threshold):

1. **Pass 1** (no false positives): per frame, each non-ignored ground-truth box in file order takes the
   unassigned detection with overlap > threshold and the *highest score*; the scores of true positives
   are collected.
2. **Score thresholds**: from those scores, at most 41 thresholds at recall steps of 1/40
   (:func:`score_thresholds`).
3. **Pass 2**: per frame and threshold, detections below the threshold are dropped, and each
   ground-truth box takes the remaining detection of *highest overlap* (a too-small, "ignored" detection
   only if nothing else qualifies). Unmatched valid ground truth is a false negative; unassigned valid
   detections are false positives unless a DontCare region covers them; AOS sums (1 + cos(dalpha)) / 2
   over true positives.

Ignore codes (computed by :mod:`kitti_eval.evaluation` from the protocol):
``ignored_gt``: 0 = valid, 1 = ignored (neighbour class or outside the difficulty), -1 = other class;
``ignored_det``: 0 = valid, 1 = ignored (too small in 2D), -1 = other class.

The matching in a frame depends only on *which* detections are above the threshold, so each frame is
matched once per distinct set of above-threshold detections rather than once per threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["PRCounts", "pr_counts", "score_thresholds"]

_NO_DETECTION = -10000000.0


@njit(cache=True, nogil=True)
def _score_thresholds(scores_desc: np.ndarray, n_gt: int, n_sample_pts: int) -> np.ndarray:
    """Scores at which recall crosses each 1/(n_sample_pts - 1) step; scores sorted descending."""
    n = scores_desc.shape[0]
    out = np.empty(n, dtype=np.float64)
    k = 0
    current_recall = 0.0
    for i in range(n):
        l_recall = (i + 1) / n_gt
        if i < n - 1:
            r_recall = (i + 2) / n_gt
        else:
            r_recall = l_recall
        if (r_recall - current_recall) < (current_recall - l_recall) and i < n - 1:
            continue
        out[k] = scores_desc[i]
        k += 1
        current_recall += 1.0 / (n_sample_pts - 1.0)
    return out[:k]


@njit(cache=True, nogil=True)
def _match_frame(ov: np.ndarray, base: int, n_gt: int, gts: np.ndarray, dts: np.ndarray, dcs: np.ndarray,
                 ignored_gt: np.ndarray, ignored_det: np.ndarray, score: np.ndarray, gt_alpha: np.ndarray,
                 dt_alpha: np.ndarray, g0: int, d0: int, min_overlap: float, compute_fp: bool, thresh: float,
                 compute_aos: bool, tp_scores: np.ndarray, n_tp_scores: int, assigned: np.ndarray,
                 below: np.ndarray) -> tuple[int, int, int, float, int]:
    """One frame, one threshold. ``gts``/``dts``/``dcs`` are frame-local indices of the relevant rows.

    Returns (tp, fp, fn, similarity, n_tp_scores); in pass 1 (``compute_fp`` False) true-positive scores
    are appended to ``tp_scores`` from position ``n_tp_scores``. ``assigned`` and ``below`` are scratch
    space of at least ``len(dts)`` entries.
    """
    nd = dts.shape[0]
    for a in range(nd):
        assigned[a] = False
        below[a] = compute_fp and score[d0 + dts[a]] < thresh
    tp = 0
    fp = 0
    fn = 0
    similarity = 0.0
    for gi in range(gts.shape[0]):
        i = gts[gi]
        ig = ignored_gt[g0 + i]
        det_a = -1
        valid_detection = _NO_DETECTION
        max_overlap = 0.0
        assigned_ignored_det = False
        for a in range(nd):
            if assigned[a] or below[a]:
                continue
            j = dts[a]
            overlap = ov[base + j * n_gt + i]
            idet = ignored_det[d0 + j]
            s = score[d0 + j]
            if not compute_fp and overlap > min_overlap and s > valid_detection:
                det_a = a
                valid_detection = s
            elif (compute_fp and overlap > min_overlap and (overlap > max_overlap or assigned_ignored_det)
                  and idet == 0):
                max_overlap = overlap
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = False
            elif compute_fp and overlap > min_overlap and valid_detection == _NO_DETECTION and idet == 1:
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = True
        if valid_detection == _NO_DETECTION:
            if ig == 0:
                fn += 1
        elif ig == 1 or ignored_det[d0 + dts[det_a]] == 1:
            assigned[det_a] = True
        else:
            tp += 1
            j = dts[det_a]
            if not compute_fp:
                tp_scores[n_tp_scores] = score[d0 + j]
                n_tp_scores += 1
            if compute_aos:
                similarity += (1.0 + np.cos(gt_alpha[g0 + i] - dt_alpha[d0 + j])) / 2.0
            assigned[det_a] = True
    if compute_fp:
        for a in range(nd):
            if not (assigned[a] or ignored_det[d0 + dts[a]] == 1 or below[a]):
                fp += 1
        nstuff = 0
        for c in range(dcs.shape[0]):
            i = dcs[c]
            for a in range(nd):
                j = dts[a]
                if assigned[a] or ignored_det[d0 + j] == 1 or below[a]:
                    continue
                if ov[base + j * n_gt + i] > min_overlap:
                    assigned[a] = True
                    nstuff += 1
        fp -= nstuff
        if compute_aos and tp == 0 and fp == 0:
            similarity = -1.0
    return tp, fp, fn, similarity, n_tp_scores


@njit(cache=True, nogil=True)
def _candidates(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
                ignored_gt: np.ndarray, ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray,
                min_overlap: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                             np.ndarray, np.ndarray, np.ndarray]:
    """Sort each frame's rows by the part they can play in this matching.

    Returns, as frame-local indices in CSR form (``*_ptr`` has F + 1 entries):
    ``gt_idx``: ground truth that takes part (ignore code != -1); ``det_idx``: detections overlapping one
    of those above the threshold, the only ones that can be matched; ``dc_idx``: DontCare rows. Also
    ``valid``: (F,) valid ground truth per frame, and ``free_fp``: scores of valid detections that can
    match nothing and that no DontCare region covers -- false positives at every threshold up to their
    score, with no need to re-match them.
    """
    n_frames = gt_offsets.shape[0] - 1
    gt_idx = np.empty(gt_offsets[n_frames], dtype=np.int64)
    det_idx = np.empty(dt_offsets[n_frames], dtype=np.int64)
    dc_idx = np.empty(gt_offsets[n_frames], dtype=np.int64)
    free_fp = np.empty(dt_offsets[n_frames], dtype=np.float64)
    gt_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    det_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    dc_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    valid = np.zeros(n_frames, dtype=np.int64)
    ng_all = 0
    nd_all = 0
    nc_all = 0
    n_free = 0
    for f in range(n_frames):
        g0, g1 = gt_offsets[f], gt_offsets[f + 1]
        d0, d1 = dt_offsets[f], dt_offsets[f + 1]
        n_gt = g1 - g0
        base = pair_offsets[f]
        first_gt = ng_all
        first_dc = nc_all
        for i in range(n_gt):
            code = ignored_gt[g0 + i]
            if code != -1:
                gt_idx[ng_all] = i
                ng_all += 1
                if code == 0:
                    valid[f] += 1
            if dontcare[g0 + i]:
                dc_idx[nc_all] = i
                nc_all += 1
        for j in range(d1 - d0):
            code = ignored_det[d0 + j]
            if code == -1:
                continue
            matchable = False
            for k in range(first_gt, ng_all):
                if ov[base + j * n_gt + gt_idx[k]] > min_overlap:
                    matchable = True
                    break
            if matchable:
                det_idx[nd_all] = j
                nd_all += 1
            elif code == 0:
                covered = False
                for k in range(first_dc, nc_all):
                    if ov[base + j * n_gt + dc_idx[k]] > min_overlap:
                        covered = True
                        break
                if not covered:
                    free_fp[n_free] = score[d0 + j]
                    n_free += 1
        gt_ptr[f + 1] = ng_all
        det_ptr[f + 1] = nd_all
        dc_ptr[f + 1] = nc_all
    return gt_idx, gt_ptr, det_idx, det_ptr, dc_idx, dc_ptr, valid, free_fp[:n_free]


@njit(cache=True, nogil=True)
def _pr_counts(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
               ignored_gt: np.ndarray, ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray,
               gt_alpha: np.ndarray, dt_alpha: np.ndarray, min_overlap: float, compute_aos: bool,
               n_sample_pts: int) -> tuple[np.ndarray, np.ndarray, int]:
    n_frames = gt_offsets.shape[0] - 1
    gt_idx, gt_ptr, det_idx, det_ptr, dc_idx, dc_ptr, valid, free_fp = _candidates(
        pair_offsets, ov, gt_offsets, dt_offsets, ignored_gt, ignored_det, dontcare, score, min_overlap)
    n_valid_gt = 0
    for f in range(n_frames):
        n_valid_gt += valid[f]
    no_dc = dc_idx[:0]
    widest = 0
    for f in range(n_frames):
        widest = max(widest, det_ptr[f + 1] - det_ptr[f])
    assigned = np.empty(widest, dtype=np.bool_)
    below = np.empty(widest, dtype=np.bool_)
    # pass 1: scores of true positives
    tp_scores = np.empty(det_idx.shape[0], dtype=np.float64)
    n_tp = 0
    for f in range(n_frames):
        if det_ptr[f] == det_ptr[f + 1]:
            continue
        g0, d0 = gt_offsets[f], dt_offsets[f]
        _, _, _, _, n_tp = _match_frame(ov, pair_offsets[f], gt_offsets[f + 1] - g0,
                                        gt_idx[gt_ptr[f]:gt_ptr[f + 1]], det_idx[det_ptr[f]:det_ptr[f + 1]],
                                        no_dc, ignored_gt, ignored_det, score, gt_alpha, dt_alpha, g0, d0,
                                        min_overlap, False, 0.0, False, tp_scores, n_tp, assigned, below)
    if n_tp == 0:
        return np.empty(0, dtype=np.float64), np.zeros((0, 4), dtype=np.float64), n_valid_gt
    thresholds = _score_thresholds(-np.sort(-tp_scores[:n_tp]), n_valid_gt, n_sample_pts)
    n_thr = thresholds.shape[0]
    # pass 2: counts at each threshold, matching each frame once per distinct above-threshold set
    pr = np.zeros((n_thr, 4), dtype=np.float64)
    fn_unmatchable = 0
    for f in range(n_frames):
        lo, hi = det_ptr[f], det_ptr[f + 1]
        if lo == hi:
            fn_unmatchable += valid[f]
            continue
        g0, d0 = gt_offsets[f], dt_offsets[f]
        gts = gt_idx[gt_ptr[f]:gt_ptr[f + 1]]
        dts = det_idx[lo:hi]
        dcs = dc_idx[dc_ptr[f]:dc_ptr[f + 1]]
        last_active = -1
        tp = 0
        fp = 0
        fn = valid[f]
        sim = 0.0
        for t in range(n_thr):
            active = 0
            for a in range(hi - lo):
                if score[d0 + dts[a]] >= thresholds[t]:
                    active += 1
            if active != last_active and active > 0:
                tp, fp, fn, sim, _ = _match_frame(ov, pair_offsets[f], gt_offsets[f + 1] - g0, gts, dts, dcs,
                                                  ignored_gt, ignored_det, score, gt_alpha, dt_alpha, g0, d0,
                                                  min_overlap, True, thresholds[t], compute_aos, tp_scores, 0,
                                                  assigned, below)
            last_active = active
            pr[t, 0] += tp
            pr[t, 1] += fp
            pr[t, 2] += fn
            if sim != -1.0:
                pr[t, 3] += sim
    # detections that can match nothing: false positives at every threshold up to their score
    # (thresholds descend: a score s counts from the first threshold t <= s on)
    starts = np.zeros(n_thr + 1, dtype=np.int64)
    for k in range(free_fp.shape[0]):
        lo, hi = 0, n_thr
        while lo < hi:
            mid = (lo + hi) // 2
            if thresholds[mid] <= free_fp[k]:
                hi = mid
            else:
                lo = mid + 1
        starts[lo] += 1
    running = 0
    for t in range(n_thr):
        running += starts[t]
        pr[t, 1] += running
        pr[t, 2] += fn_unmatchable
    return thresholds, pr, n_valid_gt


@dataclass(frozen=True)
class PRCounts:
    """Counts behind one precision/recall curve.

    thresholds : (T,) float64 score thresholds, descending, T <= 41
    tp, fp, fn : (T,) float64 totals over all frames at each threshold
    similarity : (T,) float64 summed orientation similarity of true positives (0 without AOS)
    num_valid_gt : ground-truth boxes that count (the recall denominator)
    """

    thresholds: npt.NDArray[np.float64]
    tp: npt.NDArray[np.float64]
    fp: npt.NDArray[np.float64]
    fn: npt.NDArray[np.float64]
    similarity: npt.NDArray[np.float64]
    num_valid_gt: int


def score_thresholds(scores: npt.ArrayLike, num_gt: int, n_sample_pts: int = 41) -> npt.NDArray[np.float64]:
    """Score thresholds at recall steps of 1/(n_sample_pts - 1), from true-positive scores (any order)."""
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 1:
        raise ValueError(f"Expected `scores` with shape (K,), got {s.shape}")
    if s.size == 0 or num_gt <= 0:
        return np.zeros(0)
    return _score_thresholds(-np.sort(-s), int(num_gt), int(n_sample_pts))


def pr_counts(pair_offsets: npt.NDArray[np.int64], overlaps: npt.NDArray[np.float64],
              gt_offsets: npt.NDArray[np.int64], dt_offsets: npt.NDArray[np.int64],
              ignored_gt: npt.NDArray[np.int8], ignored_det: npt.NDArray[np.int8],
              dontcare: npt.NDArray[np.bool_] | None, score: npt.NDArray[np.float64],
              gt_alpha: npt.NDArray[np.float64], dt_alpha: npt.NDArray[np.float64], min_overlap: float,
              compute_aos: bool, n_sample_pts: int = 41) -> PRCounts:
    """Match every frame and count TP/FP/FN (and orientation similarity) at each score threshold.

    Parameters
    ----------
    pair_offsets : (F + 1,) int64, start of each frame's (detection x ground truth) block in ``overlaps``
    overlaps : (P,) float64; pair (det j, gt i) of frame f at ``pair_offsets[f] + j * n_gt_f + i``
        (frame-local j, i); for DontCare ground truth it is the fraction of the detection covered
    gt_offsets : (F + 1,) int64 ; dt_offsets : (F + 1,) int64
    ignored_gt : (M,) int8 in {0, 1, -1} ; ignored_det : (N,) int8 in {0, 1, -1}
    dontcare : (M,) bool, ground-truth rows that suppress false positives, or None for no suppression
    score : (N,) detection scores ; gt_alpha : (M,) ; dt_alpha : (N,)
    min_overlap : a match needs overlap strictly above this
    compute_aos : also sum orientation similarity
    """
    n_gt = int(gt_offsets[-1])
    if dontcare is None:
        dontcare = np.zeros(n_gt, dtype=np.bool_)
    args = (np.ascontiguousarray(pair_offsets, np.int64), np.ascontiguousarray(overlaps, np.float64),
            np.ascontiguousarray(gt_offsets, np.int64), np.ascontiguousarray(dt_offsets, np.int64),
            np.ascontiguousarray(ignored_gt, np.int8), np.ascontiguousarray(ignored_det, np.int8),
            np.ascontiguousarray(dontcare, np.bool_), np.ascontiguousarray(score, np.float64),
            np.ascontiguousarray(gt_alpha, np.float64), np.ascontiguousarray(dt_alpha, np.float64))
    if args[0].shape != args[2].shape or args[2].shape != args[3].shape:
        raise ValueError("Expected `pair_offsets`, `gt_offsets` and `dt_offsets` with the same shape (F + 1,)")
    if args[4].shape != (n_gt,) or args[6].shape != (n_gt,) or args[8].shape != (n_gt,):
        raise ValueError(f"Expected ground-truth arrays with shape ({n_gt},)")
    n_dt = int(dt_offsets[-1])
    if args[5].shape != (n_dt,) or args[7].shape != (n_dt,) or args[9].shape != (n_dt,):
        raise ValueError(f"Expected detection arrays with shape ({n_dt},)")
    thresholds, pr, n_valid = _pr_counts(*args, float(min_overlap), bool(compute_aos), int(n_sample_pts))
    if thresholds.shape[0] > n_sample_pts:
        raise RuntimeError(f"{thresholds.shape[0]} score thresholds for {n_sample_pts} recall samples")
    return PRCounts(thresholds=thresholds, tp=pr[:, 0].copy(), fp=pr[:, 1].copy(), fn=pr[:, 2].copy(),
                    similarity=pr[:, 3].copy(), num_valid_gt=int(n_valid))
