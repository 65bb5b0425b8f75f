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

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

__all__ = ["PRCounts", "MatchJob", "FrameEvents", "FrameLabels", "pr_counts", "pr_counts_many", "frame_events_many",
           "label_frame", "score_thresholds", "default_workers", "DET_LABELS", "GT_LABELS"]

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
def _match_frame(sub: np.ndarray, o0: int, n_g: int, n_c: int, g_code: np.ndarray, g_alpha: np.ndarray,
                 d_score: np.ndarray, d_code: np.ndarray, d_alpha: np.ndarray, min_overlap: float,
                 compute_fp: bool, thresh: float, compute_aos: bool, tp_scores: np.ndarray, n_tp_scores: int,
                 assigned: np.ndarray, below: np.ndarray) -> tuple[int, int, int, float, int]:
    """One frame, one threshold, on the frame's compacted rows (see :func:`_candidates`).

    ``sub[o0 + a * (n_g + n_c) + k]`` is the overlap of detection ``a`` with ground truth ``k`` (k < n_g)
    or with DontCare region ``k - n_g``. ``g_*`` hold the n_g ground-truth rows, ``d_*`` the detections,
    all in file order. Returns (tp, fp, fn, similarity, n_tp_scores); in pass 1 (``compute_fp`` False)
    true-positive scores are appended to ``tp_scores`` from position ``n_tp_scores``. ``assigned`` and
    ``below`` are scratch space of at least ``len(d_score)`` entries.
    """
    nd = d_score.shape[0]
    width = n_g + n_c
    for a in range(nd):
        assigned[a] = False
        below[a] = compute_fp and d_score[a] < thresh
    tp = 0
    fp = 0
    fn = 0
    similarity = 0.0
    for i in range(n_g):
        det_a = -1
        valid_detection = _NO_DETECTION
        max_overlap = 0.0
        assigned_ignored_det = False
        for a in range(nd):
            if assigned[a] or below[a]:
                continue
            overlap = sub[o0 + a * width + i]
            if not compute_fp and overlap > min_overlap and d_score[a] > valid_detection:
                det_a = a
                valid_detection = d_score[a]
            elif (compute_fp and overlap > min_overlap and (overlap > max_overlap or assigned_ignored_det)
                  and d_code[a] == 0):
                max_overlap = overlap
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = False
            elif compute_fp and overlap > min_overlap and valid_detection == _NO_DETECTION and d_code[a] == 1:
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = True
        if valid_detection == _NO_DETECTION:
            if g_code[i] == 0:
                fn += 1
        elif g_code[i] == 1 or d_code[det_a] == 1:
            assigned[det_a] = True
        else:
            tp += 1
            if not compute_fp:
                tp_scores[n_tp_scores] = d_score[det_a]
                n_tp_scores += 1
            if compute_aos:
                similarity += (1.0 + np.cos(g_alpha[i] - d_alpha[det_a])) / 2.0
            assigned[det_a] = True
    if compute_fp:
        for a in range(nd):
            if not (assigned[a] or d_code[a] == 1 or below[a]):
                fp += 1
        nstuff = 0
        for c in range(n_c):
            for a in range(nd):
                if assigned[a] or d_code[a] == 1 or below[a]:
                    continue
                if sub[o0 + a * width + n_g + c] > min_overlap:
                    assigned[a] = True
                    nstuff += 1
        fp -= nstuff
        if compute_aos and tp == 0 and fp == 0:
            similarity = -1.0
    return tp, fp, fn, similarity, n_tp_scores


@njit(cache=True, nogil=True)
def _first_at_or_below(thresholds: np.ndarray, value: float) -> int:
    """Index of the first of the descending ``thresholds`` that is <= value (len if none)."""
    lo, hi = 0, thresholds.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if thresholds[mid] <= value:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def _rank_descending(values: np.ndarray, out: np.ndarray) -> None:
    """``out[:len(values)]`` = values sorted descending (insertion sort: a frame has a handful)."""
    for a in range(values.shape[0]):
        s = values[a]
        b = a
        while b > 0 and out[b - 1] < s:
            out[b] = out[b - 1]
            b -= 1
        out[b] = s


@njit(cache=True, nogil=True)
def _best_overlaps(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
                   groups: np.ndarray, best: np.ndarray) -> None:
    """Fill ``best`` (G, N), zeros on entry: each detection's largest overlap with each group's rows."""
    n_frames = gt_offsets.shape[0] - 1
    n_groups = groups.shape[0]
    for f in range(n_frames):
        g0, g1 = gt_offsets[f], gt_offsets[f + 1]
        d0, d1 = dt_offsets[f], dt_offsets[f + 1]
        n_gt = g1 - g0
        base = pair_offsets[f]
        for j in range(d1 - d0):
            row = base + j * n_gt
            for i in range(n_gt):
                o = ov[row + i]
                if o > 0.0:
                    for g in range(n_groups):
                        if groups[g, g0 + i] and o > best[g, d0 + j]:
                            best[g, d0 + j] = o


@njit(cache=True, nogil=True)
def _candidates(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
                ignored_gt: np.ndarray, ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray,
                gt_alpha: np.ndarray, dt_alpha: np.ndarray, best_gt: np.ndarray, best_dc: np.ndarray,
                min_overlap: float):  # noqa: ANN202 - a tuple of compact arrays, see the docstring
    """Compact each frame to the rows that can play a part in this matching.

    ``best_gt``/``best_dc`` are each detection's largest overlap with the ground truth taking part
    (ignore code != -1) and with the DontCare rows. Kept, per frame and in file order: the ground truth
    taking part (``g_code``, ``g_alpha``; CSR pointer ``g_ptr``), the detections overlapping one of those
    above the threshold -- the only ones that can be matched (``d_score``, ``d_code``, ``d_alpha``;
    ``d_ptr``) -- the number of DontCare rows (``c_cnt``), and their overlaps as one (detections x (ground
    truth + DontCare)) block per frame in ``sub`` at ``sub_ptr``. Also ``valid``: (F,) valid ground truth
    per frame, and ``free_fp``: scores of valid detections that can match nothing and that no DontCare
    region covers -- false positives at every threshold up to their score, with no need to match them --
    and ``free_frame``, the frame of each.
    """
    n_frames = gt_offsets.shape[0] - 1
    n_gt_all = gt_offsets[n_frames]
    n_dt_all = dt_offsets[n_frames]
    g_code = np.empty(n_gt_all, dtype=np.int8)
    g_alpha = np.empty(n_gt_all, dtype=np.float64)
    d_score = np.empty(n_dt_all, dtype=np.float64)
    d_code = np.empty(n_dt_all, dtype=np.int8)
    d_alpha = np.empty(n_dt_all, dtype=np.float64)
    free_fp = np.empty(n_dt_all, dtype=np.float64)
    free_frame = np.empty(n_dt_all, dtype=np.int64)
    g_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    d_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    c_cnt = np.zeros(n_frames, dtype=np.int64)
    sub_ptr = np.zeros(n_frames + 1, dtype=np.int64)
    valid = np.zeros(n_frames, dtype=np.int64)
    cols = np.empty(max(1, int(np.max(np.diff(gt_offsets))) if n_frames else 1), dtype=np.int64)
    ng = 0
    nd = 0
    n_free = 0
    # first pass: which rows take part, and the size of the overlap blocks
    for f in range(n_frames):
        g0, g1 = gt_offsets[f], gt_offsets[f + 1]
        d0, d1 = dt_offsets[f], dt_offsets[f + 1]
        n_c = 0
        for i in range(g1 - g0):
            code = ignored_gt[g0 + i]
            if code != -1:
                g_code[ng] = code
                g_alpha[ng] = gt_alpha[g0 + i]
                ng += 1
                if code == 0:
                    valid[f] += 1
            if dontcare[g0 + i]:
                n_c += 1
        c_cnt[f] = n_c
        first = nd
        for j in range(d1 - d0):
            code = ignored_det[d0 + j]
            if code == -1:
                continue
            if best_gt[d0 + j] > min_overlap:
                d_score[nd] = score[d0 + j]
                d_code[nd] = code
                d_alpha[nd] = dt_alpha[d0 + j]
                nd += 1
            elif code == 0 and not best_dc[d0 + j] > min_overlap:
                free_fp[n_free] = score[d0 + j]
                free_frame[n_free] = f
                n_free += 1
        g_ptr[f + 1] = ng
        d_ptr[f + 1] = nd
        sub_ptr[f + 1] = sub_ptr[f] + (nd - first) * (g_ptr[f + 1] - g_ptr[f] + n_c)
    # second pass: copy the overlaps of the kept detections with the kept ground truth and DontCare
    sub = np.empty(sub_ptr[n_frames], dtype=np.float64)
    for f in range(n_frames):
        m = d_ptr[f + 1] - d_ptr[f]
        if m == 0:
            continue
        g0, g1 = gt_offsets[f], gt_offsets[f + 1]
        d0, d1 = dt_offsets[f], dt_offsets[f + 1]
        n_gt = g1 - g0
        width = 0
        for i in range(n_gt):
            if ignored_gt[g0 + i] != -1:
                cols[width] = i
                width += 1
        for i in range(n_gt):
            if dontcare[g0 + i]:
                cols[width] = i
                width += 1
        k = sub_ptr[f]
        base = pair_offsets[f]
        for j in range(d1 - d0):
            if ignored_det[d0 + j] != -1 and best_gt[d0 + j] > min_overlap:
                for c in range(width):
                    sub[k] = ov[base + j * n_gt + cols[c]]
                    k += 1
    return (g_code, g_alpha, g_ptr, d_score, d_code, d_alpha, d_ptr, c_cnt, sub, sub_ptr, valid,
            free_fp[:n_free], free_frame[:n_free])


@njit(cache=True, nogil=True)
def _pr_counts(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
               ignored_gt: np.ndarray, ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray,
               gt_alpha: np.ndarray, dt_alpha: np.ndarray, best_gt: np.ndarray, best_dc: np.ndarray,
               min_overlap: float, compute_aos: bool, n_sample_pts: int) -> tuple[np.ndarray, np.ndarray, int]:
    n_frames = gt_offsets.shape[0] - 1
    (g_code, g_alpha, g_ptr, d_score, d_code, d_alpha, d_ptr, c_cnt, sub, sub_ptr, valid,
     free_fp, _) = _candidates(pair_offsets, ov, gt_offsets, dt_offsets, ignored_gt, ignored_det, dontcare, score,
                            gt_alpha, dt_alpha, best_gt, best_dc, min_overlap)
    n_valid_gt = 0
    for f in range(n_frames):
        n_valid_gt += valid[f]
    widest = 0
    for f in range(n_frames):
        widest = max(widest, d_ptr[f + 1] - d_ptr[f])
    assigned = np.empty(widest, dtype=np.bool_)
    below = np.empty(widest, dtype=np.bool_)
    # pass 1: scores of true positives (DontCare plays no part)
    tp_scores = np.empty(d_ptr[n_frames], dtype=np.float64)
    n_tp = 0
    for f in range(n_frames):
        lo, hi = d_ptr[f], d_ptr[f + 1]
        if lo == hi:
            continue
        ga, gb = g_ptr[f], g_ptr[f + 1]
        _, _, _, _, n_tp = _match_frame(sub, sub_ptr[f], gb - ga, c_cnt[f], g_code[ga:gb], g_alpha[ga:gb],
                                        d_score[lo:hi], d_code[lo:hi], d_alpha[lo:hi], min_overlap, False, 0.0,
                                        False, tp_scores, n_tp, assigned, below)
    if n_tp == 0:
        return np.empty(0, dtype=np.float64), np.zeros((0, 4), dtype=np.float64), n_valid_gt
    thresholds = _score_thresholds(-np.sort(-tp_scores[:n_tp]), n_valid_gt, n_sample_pts)
    n_thr = thresholds.shape[0]
    # pass 2: counts at each threshold. A frame's counts change only where another of its detections
    # rises above the threshold, so it is matched once per such step, and the change is recorded there
    # (``delta``) and summed up over the thresholds at the end.
    delta = np.zeros((n_thr, 4), dtype=np.float64)
    ranked = np.empty(widest, dtype=np.float64)
    for f in range(n_frames):
        delta[0, 2] += valid[f]  # above every detection's score, every valid box is missed
        lo, hi = d_ptr[f], d_ptr[f + 1]
        if lo == hi:
            continue
        ga, gb = g_ptr[f], g_ptr[f + 1]
        m = hi - lo
        _rank_descending(d_score[lo:hi], ranked)
        prev_tp, prev_fp, prev_fn, prev_sim = 0.0, 0.0, float(valid[f]), 0.0
        a = 0
        while a < m:
            t = _first_at_or_below(thresholds, ranked[a])
            if t == n_thr:
                break  # this and the remaining detections never reach a threshold
            while a < m and ranked[a] >= thresholds[t]:
                a += 1
            tp, fp, fn, sim, _ = _match_frame(sub, sub_ptr[f], gb - ga, c_cnt[f], g_code[ga:gb], g_alpha[ga:gb],
                                              d_score[lo:hi], d_code[lo:hi], d_alpha[lo:hi], min_overlap, True,
                                              thresholds[t], compute_aos, tp_scores, 0, assigned, below)
            if sim == -1.0:
                sim = 0.0
            delta[t, 0] += tp - prev_tp
            delta[t, 1] += fp - prev_fp
            delta[t, 2] += fn - prev_fn
            delta[t, 3] += sim - prev_sim
            prev_tp, prev_fp, prev_fn, prev_sim = tp, fp, fn, sim
    # detections that can match nothing: false positives from the first threshold at or below their score
    lowest = thresholds[n_thr - 1]
    for k in range(free_fp.shape[0]):
        if free_fp[k] >= lowest:
            delta[_first_at_or_below(thresholds, free_fp[k]), 1] += 1.0
    pr = np.empty((n_thr, 4), dtype=np.float64)
    for c in range(4):
        running = 0.0
        for t in range(n_thr):
            running += delta[t, c]
            pr[t, c] = running
    return thresholds, pr, n_valid_gt


@njit(cache=True, nogil=True)
def _frame_events(pair_offsets: np.ndarray, ov: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray,
                  ignored_gt: np.ndarray, ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray,
                  gt_alpha: np.ndarray, dt_alpha: np.ndarray, best_gt: np.ndarray, best_dc: np.ndarray,
                  min_overlap: float, compute_aos: bool):  # noqa: ANN202 - see the docstring
    """Each frame's part of the counts, as a function of the score threshold, for re-weighting frames.

    Returns ``valid`` (F,) valid ground truth per frame; the pass-1 true positives as ``tp_score``,
    ``tp_frame``; and the events ``ev_score``, ``ev_frame``, ``ev_delta`` (E, 4): when the threshold
    falls to ``ev_score``, frame ``ev_frame``'s (tp, fp, fn, similarity) change by ``ev_delta`` (before
    any event a frame counts (0, 0, valid, 0)). The counts at threshold t of any weighting of the frames
    are the weighted sums of the events with score >= t.
    """
    n_frames = gt_offsets.shape[0] - 1
    (g_code, g_alpha, g_ptr, d_score, d_code, d_alpha, d_ptr, c_cnt, sub, sub_ptr, valid,
     free_fp, free_frame) = _candidates(pair_offsets, ov, gt_offsets, dt_offsets, ignored_gt, ignored_det,
                                        dontcare, score, gt_alpha, dt_alpha, best_gt, best_dc, min_overlap)
    widest = 0
    for f in range(n_frames):
        widest = max(widest, d_ptr[f + 1] - d_ptr[f])
    assigned = np.empty(widest, dtype=np.bool_)
    below = np.empty(widest, dtype=np.bool_)
    ranked = np.empty(widest, dtype=np.float64)
    n_match = d_ptr[n_frames]
    tp_score = np.empty(n_match, dtype=np.float64)
    tp_frame = np.empty(n_match, dtype=np.int64)
    n_ev_max = n_match + free_fp.shape[0]
    ev_score = np.empty(n_ev_max, dtype=np.float64)
    ev_frame = np.empty(n_ev_max, dtype=np.int64)
    ev_delta = np.zeros((n_ev_max, 4), dtype=np.float64)
    n_tp = 0
    n_ev = 0
    for f in range(n_frames):
        lo, hi = d_ptr[f], d_ptr[f + 1]
        if lo == hi:
            continue
        ga, gb = g_ptr[f], g_ptr[f + 1]
        first = n_tp
        _, _, _, _, n_tp = _match_frame(sub, sub_ptr[f], gb - ga, c_cnt[f], g_code[ga:gb], g_alpha[ga:gb],
                                        d_score[lo:hi], d_code[lo:hi], d_alpha[lo:hi], min_overlap, False, 0.0,
                                        False, tp_score, n_tp, assigned, below)
        for k in range(first, n_tp):
            tp_frame[k] = f
        m = hi - lo
        _rank_descending(d_score[lo:hi], ranked)
        prev_tp, prev_fp, prev_fn, prev_sim = 0.0, 0.0, float(valid[f]), 0.0
        a = 0
        while a < m:
            level = ranked[a]
            while a < m and ranked[a] >= level:
                a += 1
            tp, fp, fn, sim, _ = _match_frame(sub, sub_ptr[f], gb - ga, c_cnt[f], g_code[ga:gb], g_alpha[ga:gb],
                                              d_score[lo:hi], d_code[lo:hi], d_alpha[lo:hi], min_overlap, True,
                                              level, compute_aos, tp_score, 0, assigned, below)
            if sim == -1.0:
                sim = 0.0
            ev_score[n_ev] = level
            ev_frame[n_ev] = f
            ev_delta[n_ev, 0] = tp - prev_tp
            ev_delta[n_ev, 1] = fp - prev_fp
            ev_delta[n_ev, 2] = fn - prev_fn
            ev_delta[n_ev, 3] = sim - prev_sim
            n_ev += 1
            prev_tp, prev_fp, prev_fn, prev_sim = tp, fp, fn, sim
    for k in range(free_fp.shape[0]):
        ev_score[n_ev] = free_fp[k]
        ev_frame[n_ev] = free_frame[k]
        ev_delta[n_ev, 1] = 1.0
        n_ev += 1
    return valid, tp_score[:n_tp], tp_frame[:n_tp], ev_score[:n_ev], ev_frame[:n_ev], ev_delta[:n_ev]


@njit(cache=True, nogil=True)
def _pr_counts_many(pair_offsets: np.ndarray, ov_0: np.ndarray, ov_1: np.ndarray, ov_2: np.ndarray,
                    gt_offsets: np.ndarray, dt_offsets: np.ndarray, ignored_gt: np.ndarray,
                    ignored_det: np.ndarray, dontcare: np.ndarray, score: np.ndarray, gt_alpha: np.ndarray,
                    dt_alpha: np.ndarray, best: np.ndarray, job_metric: np.ndarray, job_codes: np.ndarray,
                    job_group: np.ndarray, job_overlap: np.ndarray, job_aos: np.ndarray, job_dontcare: np.ndarray,
                    n_sample_pts: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Independent matchings, one per job (metric, ignore-code row, group, threshold, flags).

    ``best`` (3, G, N): each detection's best overlap per metric with each group of ground-truth rows
    (:func:`_best_overlaps`); group G - 1 is the DontCare rows.
    """
    n_jobs = job_metric.shape[0]
    n_dt = dt_offsets[dt_offsets.shape[0] - 1]
    thr_out = np.zeros((n_jobs, n_sample_pts), dtype=np.float64)
    pr_out = np.zeros((n_jobs, n_sample_pts, 4), dtype=np.float64)
    n_thr = np.zeros(n_jobs, dtype=np.int64)
    n_valid = np.zeros(n_jobs, dtype=np.int64)
    no_dontcare = np.zeros(dontcare.shape[0], dtype=np.bool_)
    no_cover = np.zeros(n_dt, dtype=np.float64)
    dc_group = best.shape[1] - 1
    for c in range(n_jobs):
        m = job_metric[c]
        ov = ov_0 if m == 0 else (ov_1 if m == 1 else ov_2)
        use_dc = job_dontcare[c]
        thresholds, pr, valid = _pr_counts(pair_offsets, ov, gt_offsets, dt_offsets, ignored_gt[job_codes[c]],
                                           ignored_det[job_codes[c]], dontcare if use_dc else no_dontcare, score,
                                           gt_alpha, dt_alpha, best[m, job_group[c]],
                                           best[m, dc_group] if use_dc else no_cover, job_overlap[c], job_aos[c],
                                           n_sample_pts)
        t = thresholds.shape[0]
        n_thr[c] = t
        n_valid[c] = valid
        for k in range(min(t, n_sample_pts)):
            thr_out[c, k] = thresholds[k]
            for q in range(4):
                pr_out[c, k, q] = pr[k, q]
    return thr_out, pr_out, n_thr, n_valid


#: labels of :func:`label_frame`, by code
DET_LABELS = ("tp", "fp", "ignored", "dontcare", "below_threshold", "other_class")
GT_LABELS = ("matched", "missed", "ignored", "absorbed", "other_class")


@njit(cache=True, nogil=True)
def _label_frame(ov: np.ndarray, ig: np.ndarray, idet: np.ndarray, dc: np.ndarray, score: np.ndarray,
                 min_overlap: float, thresh: float):  # noqa: ANN202 - five arrays, see label_frame
    """Pass 2 of the matching on one frame at one score threshold, keeping who matched whom.

    The same steps as :func:`_match_frame` with ``compute_fp`` set, on the frame's whole (detections x
    ground truth) overlap matrix in file order.
    """
    nd, ng = ov.shape
    det_label = np.full(nd, -1, dtype=np.int8)
    det_ref = np.full(nd, -1, dtype=np.int64)
    det_ov = np.full(nd, np.nan, dtype=np.float64)
    gt_label = np.full(ng, -1, dtype=np.int8)
    gt_ref = np.full(ng, -1, dtype=np.int64)
    assigned = np.zeros(nd, dtype=np.bool_)
    below = np.zeros(nd, dtype=np.bool_)
    for a in range(nd):
        below[a] = score[a] < thresh
    for i in range(ng):
        if ig[i] == -1:
            gt_label[i] = 4
            continue
        det_a = -1
        valid_detection = _NO_DETECTION
        max_overlap = 0.0
        assigned_ignored_det = False
        for a in range(nd):
            if idet[a] == -1 or assigned[a] or below[a]:
                continue
            overlap = ov[a, i]
            if overlap > min_overlap and (overlap > max_overlap or assigned_ignored_det) and idet[a] == 0:
                max_overlap = overlap
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = False
            elif overlap > min_overlap and valid_detection == _NO_DETECTION and idet[a] == 1:
                det_a = a
                valid_detection = 1.0
                assigned_ignored_det = True
        if valid_detection == _NO_DETECTION:
            gt_label[i] = 1 if ig[i] == 0 else 2
            continue
        assigned[det_a] = True
        det_ref[det_a] = i
        det_ov[det_a] = ov[det_a, i]
        gt_ref[i] = det_a
        if ig[i] == 1 or idet[det_a] == 1:
            det_label[det_a] = 2
            gt_label[i] = 2 if ig[i] == 1 else 3
        else:
            det_label[det_a] = 0
            gt_label[i] = 0
    for a in range(nd):
        if assigned[a]:
            continue
        if idet[a] == -1:
            det_label[a] = 5
        elif below[a]:
            det_label[a] = 4
        elif idet[a] == 1:
            det_label[a] = 2
        else:
            det_label[a] = 1
    for c in range(ng):
        if not dc[c]:
            continue
        for a in range(nd):
            if assigned[a] or idet[a] != 0 or below[a]:
                continue
            if ov[a, c] > min_overlap:
                assigned[a] = True
                det_label[a] = 3
                det_ref[a] = c
                det_ov[a] = ov[a, c]
    return det_label, det_ref, det_ov, gt_label, gt_ref


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
        return int(np.count_nonzero(self.det_label == 0))

    @property
    def fp(self) -> int:
        return int(np.count_nonzero(self.det_label == 1))

    @property
    def fn(self) -> int:
        return int(np.count_nonzero(self.gt_label == 1))


def label_frame(overlaps: npt.ArrayLike, ignored_gt: npt.ArrayLike, ignored_det: npt.ArrayLike,
                dontcare: npt.ArrayLike | None, score: npt.ArrayLike, min_overlap: float,
                score_threshold: float = -np.inf) -> FrameLabels:
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
    ov = np.ascontiguousarray(overlaps, np.float64)
    ig = np.ascontiguousarray(ignored_gt, np.int8)
    idet = np.ascontiguousarray(ignored_det, np.int8)
    sc = np.ascontiguousarray(score, np.float64)
    n_gt = ig.shape[0] if ig.ndim == 1 else -1
    dc = np.zeros(max(n_gt, 0), dtype=np.bool_) if dontcare is None else np.ascontiguousarray(dontcare, np.bool_)
    if ig.ndim != 1 or idet.ndim != 1 or ov.shape != (idet.shape[0], n_gt):
        raise ValueError(f"Expected `overlaps` (N, M) with `ignored_det` (N,) and `ignored_gt` (M,), got "
                         f"{ov.shape}, {idet.shape} and {ig.shape}")
    if dc.shape != (n_gt,) or sc.shape != idet.shape:
        raise ValueError(f"Expected `dontcare` ({n_gt},) and `score` ({idet.shape[0]},), got {dc.shape} and "
                         f"{sc.shape}")
    return FrameLabels(*_label_frame(ov, ig, idet, dc, sc, float(min_overlap), float(score_threshold)))


@dataclass(frozen=True)
class MatchJob:
    """One matching: which overlaps (index into ``overlaps``), which ignore-code row, the IoU a match must
    exceed, whether to sum orientation similarity, and whether DontCare rows suppress false positives."""

    metric: int
    codes: int
    min_overlap: float
    compute_aos: bool
    dontcare: bool


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
    n_gt = int(np.asarray(gt_offsets)[-1])
    use_dc = dontcare is not None
    dc = dontcare if use_dc else np.zeros(n_gt, dtype=np.bool_)
    (counts,) = pr_counts_many(pair_offsets, [overlaps], gt_offsets, dt_offsets, np.asarray(ignored_gt)[None],
                               np.asarray(ignored_det)[None], dc, score, gt_alpha, dt_alpha,
                               [MatchJob(0, 0, float(min_overlap), bool(compute_aos), use_dc)], n_sample_pts)
    return counts


def default_workers() -> int:
    """Threads used for the matchings: ``$KITTI_EVAL_THREADS``, else the CPUs this process may use."""
    env = os.environ.get("KITTI_EVAL_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True, eq=False)
class _Prepared:
    """Validated inputs of a batch of matchings, with each detection's best overlap per ground-truth group."""

    pair_offsets: np.ndarray
    ov3: list[np.ndarray]
    gt_offsets: np.ndarray
    dt_offsets: np.ndarray
    ig: np.ndarray
    idet: np.ndarray
    dc: np.ndarray
    score: np.ndarray
    gt_alpha: np.ndarray
    dt_alpha: np.ndarray
    best: np.ndarray           # (3, G, N): per metric, per group (DontCare last)
    job_group: list[int]
    hands: list[list[int]]     # job indices per thread, largest jobs dealt first

    def best_of(self, job: MatchJob, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The (N,) best overlaps with the job's ground truth, and with DontCare (zeros without it)."""
        dc_best = self.best[job.metric, -1] if job.dontcare else np.zeros(self.best.shape[2])
        return self.best[job.metric, self.job_group[k]], dc_best

    def pool_map(self, fn, items):  # noqa: ANN001, ANN201 - a thread map over the prepared hands
        if len(self.hands) == 1 or len(items) <= 1:
            return [fn(x) for x in items]
        with ThreadPoolExecutor(max_workers=len(self.hands)) as pool:
            return list(pool.map(fn, items))


def _prepare(pair_offsets: npt.ArrayLike, overlaps: Sequence[npt.ArrayLike], gt_offsets: npt.ArrayLike,
             dt_offsets: npt.ArrayLike, ignored_gt: npt.ArrayLike, ignored_det: npt.ArrayLike,
             dontcare: npt.ArrayLike, score: npt.ArrayLike, gt_alpha: npt.ArrayLike, dt_alpha: npt.ArrayLike,
             jobs: Sequence[MatchJob], workers: int | None) -> _Prepared:
    pair_offsets = np.ascontiguousarray(pair_offsets, np.int64)
    gt_offsets = np.ascontiguousarray(gt_offsets, np.int64)
    dt_offsets = np.ascontiguousarray(dt_offsets, np.int64)
    if not pair_offsets.shape == gt_offsets.shape == dt_offsets.shape or pair_offsets.ndim != 1:
        raise ValueError("Expected `pair_offsets`, `gt_offsets` and `dt_offsets` with the same shape (F + 1,)")
    n_gt, n_dt, n_pairs = int(gt_offsets[-1]), int(dt_offsets[-1]), int(pair_offsets[-1])
    ovs = [np.ascontiguousarray(o, np.float64) for o in overlaps]
    if not 1 <= len(ovs) <= 3 or any(o.shape != (n_pairs,) for o in ovs):
        raise ValueError(f"Expected one to three `overlaps` arrays with shape ({n_pairs},)")
    ig = np.ascontiguousarray(ignored_gt, np.int8)
    idet = np.ascontiguousarray(ignored_det, np.int8)
    if ig.ndim != 2 or ig.shape[1] != n_gt or idet.shape != (ig.shape[0], n_dt):
        raise ValueError(f"Expected `ignored_gt` (K, {n_gt}) and `ignored_det` (K, {n_dt}), "
                         f"got {ig.shape} and {idet.shape}")
    dc = np.ascontiguousarray(dontcare, np.bool_)
    gt_alpha = np.ascontiguousarray(gt_alpha, np.float64)
    score = np.ascontiguousarray(score, np.float64)
    dt_alpha = np.ascontiguousarray(dt_alpha, np.float64)
    if dc.shape != (n_gt,) or gt_alpha.shape != (n_gt,):
        raise ValueError(f"Expected ground-truth arrays with shape ({n_gt},)")
    if score.shape != (n_dt,) or dt_alpha.shape != (n_dt,):
        raise ValueError(f"Expected detection arrays with shape ({n_dt},)")
    for job in jobs:
        if not (0 <= job.metric < len(ovs) and 0 <= job.codes < ig.shape[0]):
            raise ValueError(f"{job} refers to overlaps or ignore codes that were not given")
    ov3 = (ovs + [ovs[0]] * 3)[:3]
    # the ground truth taking part depends only on the ignore-code row (per class, not per difficulty)
    rows = sorted({j.codes for j in jobs})
    group_of_row: dict[int, int] = {}
    masks: dict[bytes, tuple[int, npt.NDArray[np.bool_]]] = {}
    for row in rows:
        mask = ig[row] != -1
        group_of_row[row] = masks.setdefault(mask.tobytes(), (len(masks), mask))[0]
    job_group = [group_of_row[j.codes] for j in jobs]
    groups = (np.stack([m for _, m in masks.values()] + [dc]) if n_gt
              else np.zeros((len(masks) + 1, 0), dtype=np.bool_))
    workers = default_workers() if workers is None else max(1, int(workers))
    metrics_used = sorted({j.metric for j in jobs})
    best = np.zeros((3, groups.shape[0], n_dt if metrics_used else 0), dtype=np.float64)
    # jobs differ a lot in cost (by class): deal them out like cards, largest first, one hand per thread
    row_cost = {row: int(np.count_nonzero(idet[row] != -1)) for row in rows}
    cost = np.array([row_cost[j.codes] for j in jobs], dtype=np.int64)
    hands: list[list[int]] = [[] for _ in range(min(workers, max(1, len(jobs))))]
    for rank, k in enumerate(np.argsort(-cost, kind="stable")):
        hands[rank % len(hands)].append(int(k))
    prep = _Prepared(pair_offsets, ov3, gt_offsets, dt_offsets, ig, idet, dc, score, gt_alpha, dt_alpha, best,
                     job_group, hands)

    def fill_best(m: int) -> None:
        _best_overlaps(pair_offsets, ov3[m], gt_offsets, dt_offsets, groups, best[m])

    prep.pool_map(fill_best, metrics_used)  # the kernels release the GIL: plain threads run them in parallel
    return prep


def pr_counts_many(pair_offsets: npt.NDArray[np.int64], overlaps: Sequence[npt.NDArray[np.float64]],
                   gt_offsets: npt.NDArray[np.int64], dt_offsets: npt.NDArray[np.int64],
                   ignored_gt: npt.NDArray[np.int8], ignored_det: npt.NDArray[np.int8],
                   dontcare: npt.NDArray[np.bool_], score: npt.NDArray[np.float64],
                   gt_alpha: npt.NDArray[np.float64], dt_alpha: npt.NDArray[np.float64],
                   jobs: Sequence[MatchJob], n_sample_pts: int = 41, *, workers: int | None = None,
                   ) -> list[PRCounts]:
    """Run many independent matchings over the same frames, in parallel across jobs.

    Parameters
    ----------
    overlaps : one to three (P,) arrays in the layout of :func:`pr_counts`, e.g. bbox, bev, 3d
    ignored_gt : (K, M) int8, one row of ignore codes per (class, difficulty)
    ignored_det : (K, N) int8, the matching rows for detections
    dontcare : (M,) bool, DontCare ground-truth rows (used by jobs with ``dontcare`` set)
    jobs : what to match; see :class:`MatchJob`
    workers : threads to spread the jobs over (default :func:`default_workers`)
    """
    p = _prepare(pair_offsets, overlaps, gt_offsets, dt_offsets, ignored_gt, ignored_det, dontcare, score,
                 gt_alpha, dt_alpha, jobs, workers)

    def run(hand: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        picked = [jobs[k] for k in hand]
        return _pr_counts_many(
            p.pair_offsets, p.ov3[0], p.ov3[1], p.ov3[2], p.gt_offsets, p.dt_offsets, p.ig, p.idet, p.dc, p.score,
            p.gt_alpha, p.dt_alpha, p.best, np.array([j.metric for j in picked], np.int64),
            np.array([j.codes for j in picked], np.int64), np.array([p.job_group[k] for k in hand], np.int64),
            np.array([j.min_overlap for j in picked], np.float64), np.array([j.compute_aos for j in picked], np.bool_),
            np.array([j.dontcare for j in picked], np.bool_), int(n_sample_pts))

    results = p.pool_map(run, p.hands)
    out: list[PRCounts | None] = [None] * len(jobs)
    for hand, (thr, pr, n_thr, n_valid) in zip(p.hands, results):
        for c, k in enumerate(hand):
            t = int(n_thr[c])
            if t > n_sample_pts:
                raise RuntimeError(f"{t} score thresholds for {n_sample_pts} recall samples")
            out[k] = PRCounts(thresholds=thr[c, :t].copy(), tp=pr[c, :t, 0].copy(), fp=pr[c, :t, 1].copy(),
                              fn=pr[c, :t, 2].copy(), similarity=pr[c, :t, 3].copy(), num_valid_gt=int(n_valid[c]))
    return out  # type: ignore[return-value]


@dataclass(frozen=True)
class FrameEvents:
    """One matching's counts per frame as step functions of the score threshold (see :func:`_frame_events`).

    valid : (F,) valid ground truth per frame
    tp_score, tp_frame : (T,) the true positives that choose the score thresholds, sorted by score, descending
    ev_score, ev_frame : (E,) and ev_delta : (E, 4) changes of a frame's (tp, fp, fn, similarity) as the
        threshold falls to ev_score, sorted by score, descending
    """

    valid: npt.NDArray[np.int64]
    tp_score: npt.NDArray[np.float64]
    tp_frame: npt.NDArray[np.int64]
    ev_score: npt.NDArray[np.float64]
    ev_frame: npt.NDArray[np.int64]
    ev_delta: npt.NDArray[np.float64]
    compute_aos: bool


def frame_events_many(pair_offsets: npt.NDArray[np.int64], overlaps: Sequence[npt.NDArray[np.float64]],
                      gt_offsets: npt.NDArray[np.int64], dt_offsets: npt.NDArray[np.int64],
                      ignored_gt: npt.NDArray[np.int8], ignored_det: npt.NDArray[np.int8],
                      dontcare: npt.NDArray[np.bool_], score: npt.NDArray[np.float64],
                      gt_alpha: npt.NDArray[np.float64], dt_alpha: npt.NDArray[np.float64],
                      jobs: Sequence[MatchJob], *, workers: int | None = None) -> list[FrameEvents]:
    """Per-frame step functions for the same jobs as :func:`pr_counts_many` (arguments alike)."""
    p = _prepare(pair_offsets, overlaps, gt_offsets, dt_offsets, ignored_gt, ignored_det, dontcare, score,
                 gt_alpha, dt_alpha, jobs, workers)

    def run(k: int) -> FrameEvents:
        job = jobs[k]
        best_gt, best_dc = p.best_of(job, k)
        valid, tp_s, tp_f, ev_s, ev_f, ev_d = _frame_events(
            p.pair_offsets, p.ov3[job.metric], p.gt_offsets, p.dt_offsets, p.ig[job.codes], p.idet[job.codes],
            p.dc if job.dontcare else np.zeros_like(p.dc), p.score, p.gt_alpha, p.dt_alpha, best_gt, best_dc,
            job.min_overlap, job.compute_aos)
        order_tp = np.argsort(-tp_s, kind="stable")
        order_ev = np.argsort(-ev_s, kind="stable")
        return FrameEvents(valid, tp_s[order_tp], tp_f[order_tp], ev_s[order_ev], ev_f[order_ev], ev_d[order_ev],
                           job.compute_aos)

    order = [k for hand in p.hands for k in hand] if jobs else []
    out: list[FrameEvents | None] = [None] * len(jobs)
    for k, events in zip(order, p.pool_map(run, order)):
        out[k] = events
    return out  # type: ignore[return-value]
