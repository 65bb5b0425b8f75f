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

Ignore codes (computed by :mod:`kitti_eval.core.evaluation` from the protocol; named VALID, IGNORED, OTHER_CLASS):
``ignored_gt``: 0 = valid, 1 = ignored (neighbour class or outside the difficulty), -1 = other class;
``ignored_det``: 0 = valid, 1 = ignored (too small in 2D), -1 = other class.

The matching in a frame depends only on *which* detections are above the threshold, so each frame is
matched once per distinct set of above-threshold detections rather than once per threshold.

The public wrappers (:func:`pr_counts`, :func:`pr_counts_many`, :func:`frame_events_many`, ...) take the
frames' arrays as one :class:`MatchingInputs` and check them; the kernels under them take the checked arrays
one by one. The kernels that :mod:`kitti_eval.analysis.decomposition` and :mod:`kitti_eval.core.frame_labels`
reuse have public names (:func:`find_candidates`, :func:`frame_pass1`, :func:`frame_pass2`, :func:`frame_taken`,
:func:`best_overlaps`, :func:`rank_descending`, :func:`widest_step`) and validate nothing; they stay in this
module with the kernels they call. One frame's boxes labelled by the matching are :mod:`.frame_labels`; the
threads the matchings use, :mod:`.cpus`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

from .arrays import kernel_input
from .cpus import default_workers
from .kernel_cache import njit

_T = TypeVar("_T")

__all__ = [
    "PRCounts",
    "MatchJob",
    "FrameEvents",
    "pr_counts",
    "pr_counts_many",
    "first_passes",
    "second_passes",
    "frame_events_many",
    "score_thresholds",
    "MatchingInputs",
    "checked_inputs",
    "checked_layout",
    # the kernels the error decomposition (kitti_eval.analysis.decomposition) builds on: checked arrays in
    # (checked_inputs), nothing validated
    "Frames",
    "Candidates",
    "best_overlaps",
    "find_candidates",
    "frame_taken",
    "frame_pass1",
    "frame_pass2",
    "rank_descending",
    "widest_step",
    "threshold_step",
]

_NO_DETECTION = -10000000.0

#: ignore codes of ground truth and detections (numba compiles these module constants in)
VALID, IGNORED, OTHER_CLASS = 0, 1, -1


@njit(cache=True, nogil=True, inline="always")
def threshold_step(i: int, n: int, n_gt: int, current_recall: float, n_sample_pts: int) -> tuple[bool, float]:
    """The devkit's rule for score thresholds: whether the ``i``-th of ``n`` true-positive scores (sorted
    descending, so taking it as the threshold gives recall ``(i + 1) / n_gt``) becomes a threshold, and the
    recall the next one must reach. A score becomes one where recall gets at least as close to the next
    1/(n_sample_pts - 1) step as the following score would; the last score always does."""
    l_recall = (i + 1) / n_gt
    r_recall = (i + 2) / n_gt if i < n - 1 else l_recall
    if (r_recall - current_recall) < (current_recall - l_recall) and i < n - 1:
        return False, current_recall
    return True, current_recall + 1.0 / (n_sample_pts - 1.0)


@njit(cache=True, nogil=True)
def _score_thresholds(scores_desc: np.ndarray, n_gt: int, n_sample_pts: int) -> np.ndarray:
    """The score thresholds (see :func:`threshold_step`) of true-positive scores sorted descending."""
    n = scores_desc.shape[0]
    out = np.empty(n, dtype=np.float64)
    k = 0
    current_recall = 0.0
    for i in range(n):
        take, current_recall = threshold_step(i, n, n_gt, current_recall, n_sample_pts)
        if take:
            out[k] = scores_desc[i]
            k += 1
    return out[:k]


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
def rank_descending(values: np.ndarray, out: np.ndarray) -> None:
    """``out[:len(values)]`` = values sorted descending (insertion sort: a frame has a handful)."""
    for a in range(values.shape[0]):
        s = values[a]
        b = a
        while b > 0 and out[b - 1] < s:
            out[b] = out[b - 1]
            b -= 1
        out[b] = s


@njit(cache=True, nogil=True)
def best_overlaps(
    pair_offsets: np.ndarray,
    ov: np.ndarray,
    gt_offsets: np.ndarray,
    dt_offsets: np.ndarray,
    groups: np.ndarray,
    best: np.ndarray,
    arg: np.ndarray,
) -> None:
    """Fill ``best`` (G, N), zeros on entry: each detection's largest overlap with each group's rows; and, when
    ``arg`` is (G, N) too (not (0, 0)), the row of that box (the first in file order on ties)."""
    with_arg = arg.shape[0] > 0
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
                            if with_arg:
                                arg[g, d0 + j] = g0 + i


class Frames(NamedTuple):
    """The frames every matching of one evaluation shares (CSR offsets; see :func:`pr_counts`)."""

    pair_offsets: np.ndarray  # (F + 1,) int64: start of each frame's (detections x ground truth) block
    gt_offsets: np.ndarray  # (F + 1,) int64
    dt_offsets: np.ndarray  # (F + 1,) int64
    score: np.ndarray  # (N,) float64 detection scores
    gt_alpha: np.ndarray  # (M,) float64
    dt_alpha: np.ndarray  # (N,) float64


class Candidates(NamedTuple):
    """One matching's rows, compacted per frame to those that can play a part (made by :func:`find_candidates`).

    Per frame and in file order: the ground truth taking part (``g_code``: 0 valid, 1 ignored; ``g_alpha``;
    CSR pointer ``g_ptr``); the detections overlapping one of those above the threshold, the only ones
    that can be matched (``d_score``, ``d_code``, ``d_alpha``; ``d_ptr``); the number of DontCare rows
    (``c_cnt``); their overlaps as one (detections x (ground truth + DontCare)) block per frame in ``sub``
    at ``sub_ptr``. ``valid``: (F,) valid ground truth per frame. ``free_fp``: scores of valid detections
    that can match nothing and that no DontCare region covers -- false positives at every threshold up to
    their score, with no need to match them -- and ``free_frame``, the frame of each.
    """

    g_code: np.ndarray
    g_alpha: np.ndarray
    g_ptr: np.ndarray
    d_score: np.ndarray
    d_code: np.ndarray
    d_alpha: np.ndarray
    d_ptr: np.ndarray
    c_cnt: np.ndarray
    sub: np.ndarray
    sub_ptr: np.ndarray
    valid: np.ndarray
    free_fp: np.ndarray
    free_frame: np.ndarray


@njit(cache=True, nogil=True)
def find_candidates(
    fr: Frames,
    ov: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_det: np.ndarray,
    dontcare: np.ndarray,
    best_gt: np.ndarray,
    best_dc: np.ndarray,
    min_overlap: float,
) -> Candidates:
    """Compact each frame to the rows that can play a part in one matching (see :class:`Candidates`).

    ``ov``: the (P,) overlaps of the metric; ``ignored_gt``/``ignored_det``: the job's ignore codes;
    ``dontcare``: the DontCare rows that suppress false positives (all False for none); ``best_gt``/
    ``best_dc``: each detection's largest overlap with the ground truth taking part (ignore code != -1)
    and with those DontCare rows.
    """
    pair_offsets, gt_offsets, dt_offsets = fr.pair_offsets, fr.gt_offsets, fr.dt_offsets
    score, gt_alpha, dt_alpha = fr.score, fr.gt_alpha, fr.dt_alpha
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
    widest_gt = 1
    for f in range(n_frames):
        widest_gt = max(widest_gt, gt_offsets[f + 1] - gt_offsets[f])
    cols = np.empty(widest_gt, dtype=np.int64)
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
            if code != OTHER_CLASS:
                g_code[ng] = code
                g_alpha[ng] = gt_alpha[g0 + i]
                ng += 1
                if code == VALID:
                    valid[f] += 1
            if dontcare[g0 + i]:
                n_c += 1
        c_cnt[f] = n_c
        first = nd
        for j in range(d1 - d0):
            code = ignored_det[d0 + j]
            if code == OTHER_CLASS:
                continue
            if best_gt[d0 + j] > min_overlap:
                d_score[nd] = score[d0 + j]
                d_code[nd] = code
                d_alpha[nd] = dt_alpha[d0 + j]
                nd += 1
            elif code == VALID and not best_dc[d0 + j] > min_overlap:
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
            if ignored_gt[g0 + i] != OTHER_CLASS:
                cols[width] = i
                width += 1
        for i in range(n_gt):
            if dontcare[g0 + i]:
                cols[width] = i
                width += 1
        k = sub_ptr[f]
        base = pair_offsets[f]
        for j in range(d1 - d0):
            if ignored_det[d0 + j] != OTHER_CLASS and best_gt[d0 + j] > min_overlap:
                for c in range(width):
                    sub[k] = ov[base + j * n_gt + cols[c]]
                    k += 1
    return Candidates(
        g_code,
        g_alpha,
        g_ptr,
        d_score,
        d_code,
        d_alpha,
        d_ptr,
        c_cnt,
        sub,
        sub_ptr,
        valid,
        free_fp[:n_free],
        free_frame[:n_free],
    )


@njit(cache=True, nogil=True, inline="always")
def _frame_rows(c: Candidates, f: int) -> tuple[int, int, int, int, int, int]:
    """Where frame ``f`` lies in ``c``: first ground-truth row and count, first detection row and count, and
    its overlap block's start and row width (ground truth + DontCare regions)."""
    ga, d0 = c.g_ptr[f], c.d_ptr[f]
    n_g = c.g_ptr[f + 1] - ga
    return ga, n_g, d0, c.d_ptr[f + 1] - d0, c.sub_ptr[f], n_g + c.c_cnt[f]


@njit(cache=True, nogil=True, inline="always")
def frame_pass1(c: Candidates, f: int, min_overlap: float, tp_scores: np.ndarray, assigned: np.ndarray) -> int:
    """Pass 1 on frame ``f``: each ground-truth box in file order takes the unassigned detection of highest
    score with overlap > ``min_overlap``. Writes the scores of the valid matches (true positives) to
    ``tp_scores`` and returns how many. ``assigned`` (out, int64, one per detection of the frame): the
    ground-truth row (frame-local, compacted) a detection was taken by, else -1.
    """
    ga, n_g, d0, nd, o0, width = _frame_rows(c, f)
    for a in range(nd):
        assigned[a] = -1
    n_tp = 0
    for i in range(n_g):
        det_a = -1
        best = _NO_DETECTION
        for a in range(nd):
            if assigned[a] < 0 and c.sub[o0 + a * width + i] > min_overlap and c.d_score[d0 + a] > best:
                det_a = a
                best = c.d_score[d0 + a]
        if det_a >= 0:
            assigned[det_a] = i
            if c.g_code[ga + i] == VALID and c.d_code[d0 + det_a] == VALID:
                tp_scores[n_tp] = best
                n_tp += 1
    return n_tp


@njit(cache=True, nogil=True, inline="always")
def frame_pass2(
    c: Candidates, f: int, min_overlap: float, thresh: float, compute_aos: bool, taken: np.ndarray, below: np.ndarray
) -> tuple[int, int, int, float]:
    """Pass 2 on frame ``f`` at score threshold ``thresh``: detections below it take no part; each
    ground-truth box takes the remaining detection of highest overlap (a too-small, ignored detection only
    if nothing else qualifies). Returns (tp, fp, fn, summed orientation similarity): unmatched valid ground
    truth is a miss, unassigned valid detections are false positives unless a DontCare region covers them.

    ``taken`` (out, int64, one per detection of the frame): the ground-truth row (frame-local, compacted) a
    detection took, ``-2 - k`` if DontCare region ``k`` covers it, else -1. ``below``: scratch space.
    """
    ga, n_g, d0, nd, o0, width = _frame_rows(c, f)
    for a in range(nd):
        taken[a] = -1
        below[a] = c.d_score[d0 + a] < thresh
    tp = 0
    fn = 0
    similarity = 0.0
    for i in range(n_g):
        det_a = -1
        max_overlap = 0.0
        det_ignored = False
        for a in range(nd):
            if taken[a] != -1 or below[a]:
                continue
            overlap = c.sub[o0 + a * width + i]
            if overlap <= min_overlap:
                continue
            if c.d_code[d0 + a] == VALID and (overlap > max_overlap or det_ignored):
                max_overlap = overlap
                det_a = a
                det_ignored = False
            elif det_a < 0 and c.d_code[d0 + a] == IGNORED:
                det_a = a
                det_ignored = True
        if det_a < 0:
            fn += int(c.g_code[ga + i] == VALID)
            continue
        taken[det_a] = i
        if c.g_code[ga + i] == VALID and c.d_code[d0 + det_a] == VALID:
            tp += 1
            if compute_aos:
                similarity += (1.0 + np.cos(c.g_alpha[ga + i] - c.d_alpha[d0 + det_a])) / 2.0
    fp = 0
    for a in range(nd):
        fp += int(not (taken[a] != -1 or below[a] or c.d_code[d0 + a] == IGNORED))
    for k in range(c.c_cnt[f]):  # false positives that a DontCare region covers do not count
        for a in range(nd):
            if (
                not (taken[a] != -1 or below[a] or c.d_code[d0 + a] == IGNORED)
                and c.sub[o0 + a * width + n_g + k] > min_overlap
            ):
                taken[a] = -2 - k
                fp -= 1
    return tp, fp, fn, similarity


@njit(cache=True, nogil=True)
def widest_step(ptr: np.ndarray) -> int:
    """The largest step of a CSR pointer (at least 1)."""
    out = 1
    for f in range(ptr.shape[0] - 1):
        out = max(out, ptr[f + 1] - ptr[f])
    return out


@njit(cache=True, nogil=True)
def _pass1(c: Candidates, min_overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """The scores of pass 1's true positives over every frame, in frame order, and the frame of each."""
    assigned = np.empty(widest_step(c.d_ptr), dtype=np.int64)
    tp_scores = np.empty(c.d_ptr[c.d_ptr.shape[0] - 1], dtype=np.float64)
    tp_frames = np.empty(tp_scores.shape[0], dtype=np.int64)
    n_tp = 0
    for f in range(c.valid.shape[0]):
        k = frame_pass1(c, f, min_overlap, tp_scores[n_tp:], assigned)
        tp_frames[n_tp : n_tp + k] = f
        n_tp += k
    return tp_scores[:n_tp], tp_frames[:n_tp]


@njit(cache=True, nogil=True)
def _pass2(c: Candidates, thresholds: np.ndarray, min_overlap: float, compute_aos: bool) -> np.ndarray:
    """(T, 4) totals of (tp, fp, fn, similarity) over every frame at each of the descending ``thresholds``.

    A frame's counts change only where another of its detections rises above the threshold, so it is
    matched once per such step; the change is recorded there and summed over the thresholds at the end.
    """
    n_thr = thresholds.shape[0]
    widest = widest_step(c.d_ptr)
    taken = np.empty(widest, dtype=np.int64)
    below = np.empty(widest, dtype=np.bool_)
    ranked = np.empty(widest, dtype=np.float64)
    delta = np.zeros((n_thr, 4), dtype=np.float64)
    for f in range(c.valid.shape[0]):
        delta[0, 2] += c.valid[f]  # above every detection's score, every valid box is missed
        d0, m = c.d_ptr[f], c.d_ptr[f + 1] - c.d_ptr[f]
        rank_descending(c.d_score[d0 : d0 + m], ranked)
        prev_tp, prev_fp, prev_fn, prev_sim = 0.0, 0.0, float(c.valid[f]), 0.0
        a = 0
        while a < m:
            t = _first_at_or_below(thresholds, ranked[a])
            if t == n_thr:
                break  # this and the remaining detections never reach a threshold
            while a < m and ranked[a] >= thresholds[t]:
                a += 1
            tp, fp, fn, sim = frame_pass2(c, f, min_overlap, thresholds[t], compute_aos, taken, below)
            delta[t, 0] += tp - prev_tp
            delta[t, 1] += fp - prev_fp
            delta[t, 2] += fn - prev_fn
            delta[t, 3] += sim - prev_sim
            prev_tp, prev_fp, prev_fn, prev_sim = tp, fp, fn, sim
    for k in range(c.free_fp.shape[0]):  # detections that can match nothing
        if n_thr and c.free_fp[k] >= thresholds[n_thr - 1]:
            delta[_first_at_or_below(thresholds, c.free_fp[k]), 1] += 1.0
    for t in range(1, n_thr):
        for q in range(4):
            delta[t, q] += delta[t - 1, q]
    return delta


@njit(cache=True, nogil=True)
def _events(c: Candidates, min_overlap: float, compute_aos: bool):  # noqa: ANN202 - see the docstring
    """Each frame's part of the counts as a function of the score threshold, for re-weighting frames.

    Returns the events ``ev_score``, ``ev_frame``, ``ev_delta`` (E, 4): when the threshold falls to
    ``ev_score``, frame ``ev_frame``'s (tp, fp, fn, similarity) change by ``ev_delta`` (before any event a
    frame counts (0, 0, valid, 0)). The counts at threshold t of any weighting of the frames are the
    weighted sums of the events with score >= t.
    """
    widest = widest_step(c.d_ptr)
    taken = np.empty(widest, dtype=np.int64)
    below = np.empty(widest, dtype=np.bool_)
    ranked = np.empty(widest, dtype=np.float64)
    n_ev_max = c.d_ptr[c.d_ptr.shape[0] - 1] + c.free_fp.shape[0]
    ev_score = np.empty(n_ev_max, dtype=np.float64)
    ev_frame = np.empty(n_ev_max, dtype=np.int64)
    ev_delta = np.zeros((n_ev_max, 4), dtype=np.float64)
    n_ev = 0
    for f in range(c.valid.shape[0]):
        d0, m = c.d_ptr[f], c.d_ptr[f + 1] - c.d_ptr[f]
        rank_descending(c.d_score[d0 : d0 + m], ranked)
        prev_tp, prev_fp, prev_fn, prev_sim = 0.0, 0.0, float(c.valid[f]), 0.0
        a = 0
        while a < m:
            level = ranked[a]
            while a < m and ranked[a] >= level:
                a += 1
            tp, fp, fn, sim = frame_pass2(c, f, min_overlap, level, compute_aos, taken, below)
            ev_score[n_ev] = level
            ev_frame[n_ev] = f
            ev_delta[n_ev, 0] = tp - prev_tp
            ev_delta[n_ev, 1] = fp - prev_fp
            ev_delta[n_ev, 2] = fn - prev_fn
            ev_delta[n_ev, 3] = sim - prev_sim
            n_ev += 1
            prev_tp, prev_fp, prev_fn, prev_sim = tp, fp, fn, sim
    for k in range(c.free_fp.shape[0]):
        ev_score[n_ev] = c.free_fp[k]
        ev_frame[n_ev] = c.free_frame[k]
        ev_delta[n_ev, 1] = 1.0
        n_ev += 1
    return ev_score[:n_ev], ev_frame[:n_ev], ev_delta[:n_ev]


#: labels of :func:`label_frame`, by code
@njit(cache=True, nogil=True)
def frame_taken(c: Candidates, min_overlap: float, thresh: float) -> np.ndarray:
    """Pass 2 on the one frame of ``c``: what each of its detections took (see :func:`frame_pass2`)."""
    n = max(c.d_ptr[1], 1)
    taken = np.empty(n, dtype=np.int64)
    below = np.empty(n, dtype=np.bool_)
    frame_pass2(c, 0, min_overlap, thresh, False, taken, below)
    return taken[: c.d_ptr[1]]


@dataclass(frozen=True)
class MatchJob:
    """One matching: which overlap arrays (``overlap``: position in the list the matching is given; the
    evaluation gives bbox, BEV, 3D, so ``protocol.OVERLAP_INDEX[metric]``), which ignore-code row, the IoU
    a match must exceed, whether to sum orientation similarity, and whether DontCare rows suppress false
    positives."""

    overlap: int
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


def pr_counts(inputs: MatchingInputs, min_overlap: float, compute_aos: bool, n_sample_pts: int = 41) -> PRCounts:
    """Match every frame and count TP/FP/FN (and orientation similarity) at each score threshold: one matching.

    Parameters
    ----------
    inputs : the frames' arrays (:class:`MatchingInputs`) with one overlap array and one row of ignore codes,
        ``ignored_gt`` (M,) and ``ignored_det`` (N,) (or (1, M) and (1, N)); ``dontcare`` None for no
        suppression of false positives
    min_overlap : a match needs overlap strictly above this
    compute_aos : also sum orientation similarity
    """
    job = MatchJob(0, 0, float(min_overlap), bool(compute_aos), inputs.dontcare is not None)
    (counts,) = pr_counts_many(inputs.one_matching(), [job], n_sample_pts)
    return counts


class MatchingInputs(NamedTuple):
    """The arrays every matching over one set of frames shares, what :func:`pr_counts_many`,
    :func:`frame_events_many`, :func:`first_passes` and :func:`second_passes` take before the jobs.
    :func:`checked_inputs` makes them the kernels' arrays (the kernels take them one by one, unpacked).

    ``pair_offsets`` (F + 1,) int64: the start of each frame's (detection x ground truth) block in each
    overlap array; ``overlaps``: one to three (P,) float64 arrays (bbox, BEV, 3D), pair (det j, gt i) of
    frame f at ``pair_offsets[f] + j * n_gt_f + i`` (frame-local j, i), for DontCare ground truth the
    fraction of the detection covered; ``gt_offsets`` and ``dt_offsets`` (F + 1,) int64; ``ignored_gt``
    (K, M) and ``ignored_det`` (K, N) int8 in {0, 1, -1}: one row of ignore codes per (class, difficulty)
    (see the module docstring); ``dontcare`` (M,) bool, the ground-truth rows that suppress false positives,
    None for none; ``score`` (N,) the detections' scores; ``gt_alpha`` (M,) and ``dt_alpha`` (N,), None
    where no orientation is used (zeros).
    """

    # array-likes as given; numpy arrays once checked (Any: a NamedTuple cannot be generic on Python 3.10)
    pair_offsets: Any
    overlaps: Sequence[Any]
    gt_offsets: Any
    dt_offsets: Any
    ignored_gt: Any
    ignored_det: Any
    dontcare: Any
    score: Any
    gt_alpha: Any = None
    dt_alpha: Any = None

    def one_matching(self) -> MatchingInputs:
        """These inputs as one matching's: one overlap array and one row of ignore codes, ``ignored_gt`` (M,)
        and ``ignored_det`` (N,) rows made (1, M) and (1, N) (ValueError for more than one overlap array)."""
        if len(self.overlaps) != 1:
            raise ValueError(f"Expected one `overlaps` array for one matching, got {len(self.overlaps)}")
        ig, idet = np.asarray(self.ignored_gt), np.asarray(self.ignored_det)
        return self._replace(
            ignored_gt=ig[None] if ig.ndim == 1 else ig, ignored_det=idet[None] if idet.ndim == 1 else idet
        )


def checked_layout(
    pair_offsets: npt.ArrayLike, overlaps: Sequence[npt.ArrayLike], gt_offsets: npt.ArrayLike, dt_offsets: npt.ArrayLike
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """The frames' CSR offsets and the overlap arrays as kernel arrays, checked against each other."""
    po = kernel_input(pair_offsets, np.int64)
    go = kernel_input(gt_offsets, np.int64)
    do = kernel_input(dt_offsets, np.int64)
    if not po.shape == go.shape == do.shape or po.ndim != 1:
        raise ValueError("Expected `pair_offsets`, `gt_offsets` and `dt_offsets` with the same shape (F + 1,)")
    n_pairs = int(po[-1])
    ovs = [kernel_input(o, np.float64) for o in overlaps]
    if not 1 <= len(ovs) <= 3 or any(o.shape != (n_pairs,) for o in ovs):
        raise ValueError(f"Expected one to three `overlaps` arrays with shape ({n_pairs},)")
    return po, ovs, go, do


def checked_inputs(inputs: MatchingInputs) -> MatchingInputs:
    """``inputs`` as the kernels take them (:func:`kitti_eval.core.arrays.kernel_input`), every shape checked
    (ValueError naming the arrays); None ``dontcare``, ``gt_alpha``, ``dt_alpha`` become zeros."""
    po, ovs, go, do = checked_layout(inputs.pair_offsets, inputs.overlaps, inputs.gt_offsets, inputs.dt_offsets)
    n_gt, n_dt = int(go[-1]), int(do[-1])
    ig = kernel_input(inputs.ignored_gt, np.int8)
    idet = kernel_input(inputs.ignored_det, np.int8)
    if ig.ndim != 2 or ig.shape[1] != n_gt or idet.shape != (ig.shape[0], n_dt):
        raise ValueError(
            f"Expected `ignored_gt` (K, {n_gt}) and `ignored_det` (K, {n_dt}), got {ig.shape} and {idet.shape}"
        )

    def array(value: npt.ArrayLike | None, n: int, dtype: type) -> np.ndarray:
        return np.zeros(n, dtype=dtype) if value is None else kernel_input(value, dtype)

    dc = array(inputs.dontcare, n_gt, np.bool_)
    gt_alpha = array(inputs.gt_alpha, n_gt, np.float64)
    score = kernel_input(inputs.score, np.float64)
    dt_alpha = array(inputs.dt_alpha, n_dt, np.float64)
    if dc.shape != (n_gt,) or gt_alpha.shape != (n_gt,):
        raise ValueError(f"Expected ground-truth arrays with shape ({n_gt},)")
    if score.shape != (n_dt,) or dt_alpha.shape != (n_dt,):
        raise ValueError(f"Expected detection arrays with shape ({n_dt},)")
    return MatchingInputs(po, ovs, go, do, ig, idet, dc, score, gt_alpha, dt_alpha)


@dataclass(frozen=True, eq=False)
class _Prepared:
    """Validated inputs of a batch of matchings, with each detection's best overlap per ground-truth group."""

    frames: Frames
    ov3: list[np.ndarray]
    ig: np.ndarray
    idet: np.ndarray
    dc: np.ndarray
    best: np.ndarray  # (3, G, N): per metric, per group (DontCare last)
    job_group: list[int]
    hands: list[list[int]]  # job indices per thread, largest jobs dealt first

    def candidates(self, job: MatchJob, k: int) -> Candidates:
        """Job ``k``'s rows that can play a part (see :class:`Candidates`)."""
        if job.dontcare:
            dc, dc_best = self.dc, self.best[job.overlap, -1]
        else:
            dc, dc_best = np.zeros_like(self.dc), np.zeros(self.best.shape[2])
        return find_candidates(
            self.frames,
            self.ov3[job.overlap],
            self.ig[job.codes],
            self.idet[job.codes],
            dc,
            self.best[job.overlap, self.job_group[k]],
            dc_best,
            float(job.min_overlap),
        )

    def pool_map(self, fn, items):  # noqa: ANN001, ANN201 - a thread map over the prepared hands
        if len(self.hands) == 1 or len(items) <= 1:
            return [fn(x) for x in items]
        with ThreadPoolExecutor(max_workers=len(self.hands)) as pool:
            return list(pool.map(fn, items))

    def map_jobs(self, fn: Callable[[int], _T]) -> list[_T]:
        """``[fn(0), fn(1), ...]`` over the jobs, each thread running one hand in the order it was dealt."""
        out: list[Any] = [None] * sum(len(hand) for hand in self.hands)
        results = self.pool_map(lambda hand: [fn(k) for k in hand], self.hands)
        for hand, values in zip(self.hands, results):
            for k, value in zip(hand, values):
                out[k] = value
        return out


#: ``arg`` of :func:`best_overlaps` when only the overlaps are wanted
_NO_ARG = np.zeros((0, 0), dtype=np.int64)


def _prepare(inputs: MatchingInputs, jobs: Sequence[MatchJob], workers: int | None) -> _Prepared:
    checked = checked_inputs(inputs)
    pair_offsets, ovs, gt_offsets, dt_offsets, ig, idet, dc, score, gt_alpha, dt_alpha = checked
    n_gt, n_dt = int(gt_offsets[-1]), int(dt_offsets[-1])
    for job in jobs:
        if not (0 <= job.overlap < len(ovs) and 0 <= job.codes < ig.shape[0]):
            raise ValueError(f"{job} refers to overlaps or ignore codes that were not given")
    ov3 = ([*ovs] + [ovs[0]] * 3)[:3]
    # the ground truth taking part depends only on the ignore-code row (per class, not per difficulty)
    rows = sorted({j.codes for j in jobs})
    group_of_row: dict[int, int] = {}
    masks: dict[bytes, tuple[int, npt.NDArray[np.bool_]]] = {}
    for row in rows:
        mask = ig[row] != -1
        group_of_row[row] = masks.setdefault(mask.tobytes(), (len(masks), mask))[0]
    job_group = [group_of_row[j.codes] for j in jobs]
    groups = np.stack([m for _, m in masks.values()] + [dc]) if n_gt else np.zeros((len(masks) + 1, 0), dtype=np.bool_)
    workers = default_workers() if workers is None else max(1, int(workers))
    metrics_used = sorted({j.overlap for j in jobs})
    best = np.zeros((3, groups.shape[0], n_dt if metrics_used else 0), dtype=np.float64)
    # jobs differ a lot in cost (by class): deal them out like cards, largest first, one hand per thread
    row_cost = {row: int(np.count_nonzero(idet[row] != -1)) for row in rows}
    cost = np.array([row_cost[j.codes] for j in jobs], dtype=np.int64)
    hands: list[list[int]] = [[] for _ in range(min(workers, max(1, len(jobs))))]
    for rank, k in enumerate(np.argsort(-cost, kind="stable")):
        hands[rank % len(hands)].append(int(k))
    frames = Frames(pair_offsets, gt_offsets, dt_offsets, score, gt_alpha, dt_alpha)
    prep = _Prepared(frames, ov3, ig, idet, dc, best, job_group, hands)

    def fill_best(m: int) -> None:
        best_overlaps(pair_offsets, ov3[m], gt_offsets, dt_offsets, groups, best[m], _NO_ARG)

    prep.pool_map(fill_best, metrics_used)  # the kernels release the GIL: plain threads run them in parallel
    return prep


def pr_counts_many(
    inputs: MatchingInputs, jobs: Sequence[MatchJob], n_sample_pts: int = 41, *, workers: int | None = None
) -> list[PRCounts]:
    """Run many independent matchings over the same frames, in parallel across jobs.

    Parameters
    ----------
    inputs : the frames' arrays (:class:`MatchingInputs`): one to three overlap arrays, one row of ignore
        codes per (class, difficulty), the DontCare rows (used by jobs with ``dontcare`` set)
    jobs : what to match; see :class:`MatchJob`
    workers : threads to spread the jobs over (default :func:`default_workers`)
    """
    p = _prepare(inputs, jobs, workers)

    def count(k: int) -> PRCounts:
        c = p.candidates(jobs[k], k)
        tp_scores, n_valid = _first_pass(c, jobs[k])
        return _second_pass(c, jobs[k], score_thresholds(tp_scores, n_valid, n_sample_pts), n_valid, n_sample_pts)

    return p.map_jobs(count)


def first_passes(
    inputs: MatchingInputs, jobs: Sequence[MatchJob], *, workers: int | None = None
) -> list[tuple[np.ndarray, int]]:
    """Phase 1 of :func:`pr_counts_many` alone: per job, the
    scores of pass 1's true positives and the number of valid ground-truth boxes. Over parts of a set,
    these are what the whole set's score thresholds come from (:func:`score_thresholds` of the concatenated
    scores and the summed counts)."""
    p = _prepare(inputs, jobs, workers)
    return p.map_jobs(lambda k: _first_pass(p.candidates(jobs[k], k), jobs[k]))


def second_passes(
    inputs: MatchingInputs,
    jobs: Sequence[MatchJob],
    thresholds: Sequence[np.ndarray],
    *,
    n_sample_pts: int = 41,
    workers: int | None = None,
) -> list[PRCounts]:
    """Phase 2 of :func:`pr_counts_many` alone: per job, the counts at the given score thresholds (those of
    the whole set); over parts of a set they add up to the whole set's counts."""
    p = _prepare(inputs, jobs, workers)

    def count(k: int) -> PRCounts:
        c = p.candidates(jobs[k], k)
        return _second_pass(c, jobs[k], np.asarray(thresholds[k], np.float64), int(c.valid.sum()), n_sample_pts)

    return p.map_jobs(count)


def _first_pass(c: Candidates, job: MatchJob) -> tuple[np.ndarray, int]:
    tp_scores, _ = _pass1(c, float(job.min_overlap))
    return tp_scores, int(c.valid.sum())


def _second_pass(c: Candidates, job: MatchJob, thresholds: np.ndarray, n_valid: int, n_sample_pts: int) -> PRCounts:
    """Pass 2 at each score threshold (from pass 1's true positives, of this set or a larger one)."""
    if len(thresholds) > n_sample_pts:
        raise RuntimeError(f"{len(thresholds)} score thresholds for {n_sample_pts} recall samples")
    pr = _pass2(c, thresholds, float(job.min_overlap), bool(job.compute_aos)) if len(thresholds) else np.zeros((0, 4))
    return PRCounts(
        thresholds=thresholds,
        tp=pr[:, 0].copy(),
        fp=pr[:, 1].copy(),
        fn=pr[:, 2].copy(),
        similarity=pr[:, 3].copy(),
        num_valid_gt=n_valid,
    )


@dataclass(frozen=True)
class FrameEvents:
    """One matching's counts per frame as step functions of the score threshold (see :func:`_events`).

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


def frame_events_many(
    inputs: MatchingInputs, jobs: Sequence[MatchJob], *, workers: int | None = None
) -> list[FrameEvents]:
    """Per-frame step functions for the same jobs as :func:`pr_counts_many` (arguments alike)."""
    p = _prepare(inputs, jobs, workers)

    def run(k: int) -> FrameEvents:
        job = jobs[k]
        c = p.candidates(job, k)
        tp_s, tp_f = _pass1(c, float(job.min_overlap))
        ev_s, ev_f, ev_d = _events(c, float(job.min_overlap), bool(job.compute_aos))
        order_tp = np.argsort(-tp_s, kind="stable")
        order_ev = np.argsort(-ev_s, kind="stable")
        return FrameEvents(
            c.valid, tp_s[order_tp], tp_f[order_tp], ev_s[order_ev], ev_f[order_ev], ev_d[order_ev], job.compute_aos
        )

    return p.map_jobs(run)
