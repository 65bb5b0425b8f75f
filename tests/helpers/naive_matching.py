"""Slow, literal twin of the matching kernels: the devkit's statistics per frame and per threshold."""

from __future__ import annotations

import math

NO_DETECTION = -10000000.0


def thresholds_naive(scores, n_gt, n_sample_pts=41):
    scores = sorted(scores, reverse=True)
    out, current = [], 0.0
    for i, s in enumerate(scores):
        left = (i + 1) / n_gt
        right = (i + 2) / n_gt if i < len(scores) - 1 else left
        if (right - current) < (current - left) and i < len(scores) - 1:
            continue
        out.append(s)
        current += 1.0 / (n_sample_pts - 1.0)
    return out


def statistics_naive(frame, min_overlap, compute_fp, thresh=0.0, compute_aos=False):
    """One frame: frame = dict(ov[j][i], ig[i], idet[j], dc[i], score[j], gt_alpha[i], dt_alpha[j])."""
    ov, ig, idet, dc = frame["ov"], frame["ig"], frame["idet"], frame["dc"]
    score = frame["score"]
    nd, ng = len(idet), len(ig)
    assigned = [False] * nd
    below = [compute_fp and score[j] < thresh for j in range(nd)]
    tp = fp = fn = 0
    tp_scores, deltas = [], []
    for i in range(ng):
        if ig[i] == -1:
            continue
        det_idx, valid, max_ov, took_ignored = -1, NO_DETECTION, 0.0, False
        for j in range(nd):
            if idet[j] == -1 or assigned[j] or below[j]:
                continue
            o = ov[j][i]
            if not compute_fp and o > min_overlap and score[j] > valid:
                det_idx, valid = j, score[j]
            elif compute_fp and o > min_overlap and (o > max_ov or took_ignored) and idet[j] == 0:
                max_ov, det_idx, valid, took_ignored = o, j, 1.0, False
            elif compute_fp and o > min_overlap and valid == NO_DETECTION and idet[j] == 1:
                det_idx, valid, took_ignored = j, 1.0, True
        if valid == NO_DETECTION and ig[i] == 0:
            fn += 1
        elif valid != NO_DETECTION and (ig[i] == 1 or idet[det_idx] == 1):
            assigned[det_idx] = True
        elif valid != NO_DETECTION:
            tp += 1
            tp_scores.append(score[det_idx])
            deltas.append(frame["gt_alpha"][i] - frame["dt_alpha"][det_idx])
            assigned[det_idx] = True
    similarity = 0.0
    if compute_fp:
        for j in range(nd):
            if not (assigned[j] or idet[j] == -1 or idet[j] == 1 or below[j]):
                fp += 1
        stuff = 0
        for i in range(ng):
            if not dc[i]:
                continue
            for j in range(nd):
                if assigned[j] or idet[j] in (-1, 1) or below[j]:
                    continue
                if ov[j][i] > min_overlap:
                    assigned[j] = True
                    stuff += 1
        fp -= stuff
        if compute_aos:
            terms = [0.0] * fp + [(1.0 + math.cos(d)) / 2.0 for d in deltas]
            similarity = sum(terms) if (tp > 0 or fp > 0) else -1.0
    return tp, fp, fn, similarity, tp_scores


def pr_counts_naive(frames, min_overlap, compute_aos):
    n_gt = sum(sum(1 for v in f["ig"] if v == 0) for f in frames)
    scores = []
    for f in frames:
        scores += statistics_naive(f, min_overlap, False)[4]
    thresholds = thresholds_naive(scores, n_gt) if scores else []
    pr = [[0.0] * 4 for _ in thresholds]
    for f in frames:
        for t, thr in enumerate(thresholds):
            tp, fp, fn, sim, _ = statistics_naive(f, min_overlap, True, thr, compute_aos)
            pr[t][0] += tp
            pr[t][1] += fp
            pr[t][2] += fn
            if sim != -1:
                pr[t][3] += sim
    return thresholds, pr, n_gt


def labels_naive(frame, min_overlap, thresh=float("-inf")):
    """One frame's second pass at ``thresh``, literally, keeping who took whom.

    Returns (det_labels, det_refs, gt_labels, gt_refs): labels as the words of ``DET_LABELS`` /
    ``GT_LABELS``; a detection's ref is the ground truth it took or the DontCare row covering it.
    """
    ov, ig, idet, dc, score = frame["ov"], frame["ig"], frame["idet"], frame["dc"], frame["score"]
    nd, ng = len(idet), len(ig)
    below = [score[j] < thresh for j in range(nd)]
    det = [None] * nd
    det_ref = [-1] * nd
    gt = [None] * ng
    gt_ref = [-1] * ng
    for i in range(ng):
        if ig[i] == -1:
            gt[i] = "other_class"
            continue
        det_idx, valid, max_ov, took_ignored = -1, NO_DETECTION, 0.0, False
        for j in range(nd):
            if idet[j] == -1 or det[j] is not None or below[j]:
                continue
            o = ov[j][i]
            if o > min_overlap and (o > max_ov or took_ignored) and idet[j] == 0:
                max_ov, det_idx, valid, took_ignored = o, j, 1.0, False
            elif o > min_overlap and valid == NO_DETECTION and idet[j] == 1:
                det_idx, valid, took_ignored = j, 1.0, True
        if valid == NO_DETECTION:
            gt[i] = "missed" if ig[i] == 0 else "ignored"
        elif ig[i] == 1 or idet[det_idx] == 1:
            det[det_idx], det_ref[det_idx] = "ignored", i
            gt[i], gt_ref[i] = ("ignored" if ig[i] == 1 else "absorbed"), det_idx
        else:
            det[det_idx], det_ref[det_idx] = "tp", i
            gt[i], gt_ref[i] = "matched", det_idx
    for j in range(nd):
        if det[j] is None:
            if idet[j] == -1:
                det[j] = "other_class"
            elif below[j]:
                det[j] = "below_threshold"
            elif idet[j] == 1:
                det[j] = "ignored"
    for i in range(ng):
        if not dc[i]:
            continue
        for j in range(nd):
            if det[j] is None and ov[j][i] > min_overlap:
                det[j], det_ref[j] = "dontcare", i
    det = ["fp" if d is None else d for d in det]
    return det, det_ref, gt, gt_ref
