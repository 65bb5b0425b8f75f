"""Slow, literal twin of the error decomposition: every rule of kitti_eval/analysis/decomposition.py written
out per frame in plain Python, every AP from the literal matcher (naive_matching.pr_counts_naive)."""

from __future__ import annotations

import math

import numpy as np
from naive_matching import NO_DETECTION, pr_counts_naive, statistics_naive, thresholds_naive

from kitti_eval.core.ap import average_precision, curve_from_counts
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.matching import PRCounts
from kitti_eval.core.protocol import Metric

TYPES = ("classification", "localization", "both", "duplicate", "background", "missed")
BACKGROUND = 0.1


def _frames(plan, job):
    """The job's frames as dicts of lists, with names, DontCare flags and boxes for the rules."""
    fo, gt, dt = plan.overlaps, plan.gt, plan.dt
    ov_all = (fo.bbox, fo.bev, fo.d3)[job.overlap]
    ig_all, idet_all = plan.ignored_gt[job.codes], plan.ignored_det[job.codes]
    out = []
    for f in range(gt.num_frames):
        g0, g1 = int(gt.offsets[f]), int(gt.offsets[f + 1])
        d0, d1 = int(dt.offsets[f]), int(dt.offsets[f + 1])
        ng, nd = g1 - g0, d1 - d0
        p0 = int(fo.pair_offsets[f])
        ov = [[float(ov_all[p0 + j * ng + i]) for i in range(ng)] for j in range(nd)]
        is_dc = [bool(plan.dontcare[g0 + i]) for i in range(ng)]
        out.append(
            dict(
                ov=ov,
                ig=[int(ig_all[g0 + i]) for i in range(ng)],
                idet=[int(idet_all[d0 + j]) for j in range(nd)],
                dc=[is_dc[i] and job.dontcare for i in range(ng)],
                is_dc=is_dc,
                score=[float(dt.score[d0 + j]) for j in range(nd)],
                gt_alpha=[float(gt.alpha[g0 + i]) for i in range(ng)],
                dt_alpha=[float(dt.alpha[d0 + j]) for j in range(nd)],
                gt_name=[str(gt.name[g0 + i]).lower() for i in range(ng)],
                dt_name=[str(dt.name[d0 + j]).lower() for j in range(nd)],
            )
        )
    return out


def pass1_naive(frame, t):
    """Who took whom in pass 1 (every detection taking part): taken[j] = the box that took detection j."""
    taken = [-1] * len(frame["idet"])
    for i, code in enumerate(frame["ig"]):
        if code == -1:
            continue
        best_j, best_score = -1, NO_DETECTION
        for j, dcode in enumerate(frame["idet"]):
            if dcode != -1 and taken[j] < 0 and frame["ov"][j][i] > t and frame["score"][j] > best_score:
                best_j, best_score = j, frame["score"][j]
        if best_j >= 0:
            taken[best_j] = i
    return taken


def _best(frame, j, wanted):
    """(largest overlap of detection j with the boxes i where wanted(i), that box or -1)."""
    best, arg = 0.0, -1
    for i in range(len(frame["ig"])):
        if wanted(i) and frame["ov"][j][i] > best:
            best, arg = frame["ov"][j][i], i
    return best, arg


def labels_naive(frame, t, neighbours):
    """Every box's error type in one frame, by the module's rules in their order."""
    taken = pass1_naive(frame, t)
    n_dt = len(frame["idet"])
    det_type, target = [None] * n_dt, [-1] * n_dt
    for j in range(n_dt):
        own, own_arg = _best(frame, j, lambda i: frame["ig"][i] != -1)
        other, _ = _best(frame, j, lambda i: frame["ig"][i] == -1 and not frame["is_dc"][i])
        covered, _ = _best(frame, j, lambda i: frame["dc"][i])
        name = frame["dt_name"][j]
        kin_names = {name} | set(neighbours.get(name, ()))
        kin, _ = _best(
            frame, j, lambda i, kin_names=kin_names: frame["gt_name"][i] in kin_names and not frame["is_dc"][i]
        )
        target[j] = own_arg
        code = frame["idet"][j]
        if code == -1:
            if name != "dontcare" and kin <= t and own > t:
                det_type[j] = "incoming"
            continue
        if code != 0 or taken[j] >= 0 or covered > t:
            continue
        if own > t:
            det_type[j] = "duplicate"
        elif other > t:
            det_type[j] = "classification"
        elif own >= BACKGROUND:
            det_type[j] = "localization"
        elif other >= BACKGROUND:
            det_type[j] = "both"
        else:
            det_type[j] = "background"
    gt_taken = [i in taken for i in range(len(frame["ig"]))]
    pointed = {target[j] for j in range(n_dt) if det_type[j] in ("localization", "incoming")}
    missed = [frame["ig"][i] == 0 and not gt_taken[i] and i not in pointed for i in range(len(frame["ig"]))]
    orientation = []
    for j in range(n_dt):
        i = taken[j]
        flipped = False
        if i >= 0 and frame["idet"][j] == 0 and frame["ig"][i] == 0:
            d = (frame["dt_alpha"][j] - frame["gt_alpha"][i]) % (2 * math.pi)
            flipped = min(d, 2 * math.pi - d) > math.pi / 2
        orientation.append(flipped)
    return dict(det_type=det_type, target=target, gt_taken=gt_taken, missed=missed, orientation=orientation)


def fixed_frames(frames, labels, kinds):
    """The frames after fixing ``kinds``: copies, never the inputs."""
    claims = []  # (score, frame, detection) of localization / incoming fixes, settled by score then file order
    for f, (frame, lab) in enumerate(zip(frames, labels)):
        for j, kind in enumerate(lab["det_type"]):
            if (kind == "localization" and "localization" in kinds) or (
                kind == "incoming" and "classification" in kinds
            ):
                claims.append((-frame["score"][j], f, j))
    claims.sort()
    won, claimed = set(), set()
    for _, f, j in claims:
        g = labels[f]["target"][j]
        if not labels[f]["gt_taken"][g] and (f, g) not in claimed:
            claimed.add((f, g))
            won.add((f, j))
    out = []
    for f, (frame, lab) in enumerate(zip(frames, labels)):
        new = {k: [list(r) for r in v] if k == "ov" else list(v) for k, v in frame.items()}
        for j, kind in enumerate(lab["det_type"]):
            if kind in ("duplicate", "classification", "both", "background") and kind in kinds:
                new["idet"][j] = -1
            elif kind == "localization" and "localization" in kinds:
                if (f, j) in won:
                    new["ov"][j] = [0.0] * len(new["ov"][j])
                    new["ov"][j][lab["target"][j]] = 1.0
                else:
                    new["idet"][j] = -1
            elif kind == "incoming" and "classification" in kinds and (f, j) in won:
                new["idet"][j] = 0
            if lab["orientation"][j] and "orientation" in kinds:
                new["dt_alpha"][j] += math.pi
        for i, gone in enumerate(lab["missed"]):
            if gone and "missed" in kinds:
                new["ig"][i] = -1
        out.append(new)
    return out


def ap_naive(frames, t, compute_aos):
    """{R40, R11, aos_R40, aos_R11} of the frames, from the literal matcher."""
    thresholds, pr, n_gt = pr_counts_naive(frames, t, compute_aos)
    a = np.array(pr, dtype=float).reshape(-1, 4)
    counts = PRCounts(np.array(thresholds, dtype=float), a[:, 0], a[:, 1], a[:, 2], a[:, 3], n_gt)
    curve = curve_from_counts(counts)
    out = {r: average_precision(curve.precision, r) for r in ("R40", "R11")}
    out.update({f"aos_{r}": average_precision(curve.orientation, r) for r in ("R40", "R11")})
    return out


def decompose_naive(gt, dt, config=None, oset="strict"):
    """{(class, metric, difficulty): {"ap": {...}, type: {recall: AP after fixing it}, "all": ...}}."""
    plan = plan_evaluation(gt, dt, config)
    neighbours = {k.lower(): tuple(n.lower() for n in v) for k, v in plan.config.neighbours.items()}
    out = {}
    for slot in plan.slots:
        if slot.oset != oset or slot.job is None:
            continue
        job = plan.jobs[slot.job]
        frames = _frames(plan, job)
        labels = [labels_naive(f, job.min_overlap, neighbours) for f in frames]
        with_aos = slot.with_aos and slot.metric is Metric.BBOX
        kinds = TYPES + (("orientation",) if with_aos else ())
        fixed = {"ap": ap_naive(frames, job.min_overlap, with_aos)}
        for k in kinds:
            fixed[k] = ap_naive(fixed_frames(frames, labels, {k}), job.min_overlap, with_aos)
        fixed["all"] = ap_naive(fixed_frames(frames, labels, set(kinds)), job.min_overlap, with_aos)
        metric = slot.metric.value
        out[(slot.cls, metric, slot.difficulty.label)] = {
            k: {r: v[r] for r in ("R40", "R11")} for k, v in fixed.items()
        }
        if with_aos:
            out[(slot.cls, "aos", slot.difficulty.label)] = {
                k: {r: v[f"aos_{r}"] for r in ("R40", "R11")} for k, v in fixed.items()
            }
    return out


def tp_errors_naive(frame, t, thresh, dt_boxes, gt_boxes):
    """Pass 2 at ``thresh`` on one frame, literally, and the summed (tp, translation, scale, orientation) of
    its true positives; boxes are the frame's (x, y, z, l, h, w, ry) rows."""
    ov, ig, idet, score = frame["ov"], frame["ig"], frame["idet"], frame["score"]
    taken = [False] * len(idet)
    sums = [0.0, 0.0, 0.0, 0.0]
    for i in range(len(ig)):
        if ig[i] == -1:
            continue
        best_j, max_ov, took_ignored = -1, 0.0, False
        for j in range(len(idet)):
            if idet[j] == -1 or taken[j] or score[j] < thresh or ov[j][i] <= t:
                continue
            if idet[j] == 0 and (ov[j][i] > max_ov or took_ignored):
                best_j, max_ov, took_ignored = j, ov[j][i], False
            elif best_j < 0 and idet[j] == 1:
                best_j, took_ignored = j, True
        if best_j < 0:
            continue
        taken[best_j] = True
        if ig[i] == 0 and idet[best_j] == 0:
            d, g = dt_boxes[best_j], gt_boxes[i]
            inter = min(d[3], g[3]) * min(d[4], g[4]) * min(d[5], g[5])
            turn = (d[6] - g[6]) % (2 * math.pi)
            sums[0] += 1
            sums[1] += math.hypot(d[0] - g[0], d[2] - g[2])
            sums[2] += 1 - inter / (d[3] * d[4] * d[5] + g[3] * g[4] * g[5] - inter)
            sums[3] += min(turn, 2 * math.pi - turn)
    return sums


__all__ = [
    "decompose_naive",
    "pass1_naive",
    "labels_naive",
    "tp_errors_naive",
    "statistics_naive",
    "thresholds_naive",
]
