"""Slow, obvious twins of the kernels, for tests only: pure Python loops and shapely polygons.

Coordinate frame as in :mod:`kitti_eval.core.geometry`: a camera box is ``x, y, z, l, h, w, ry`` with the
bottom centre at (x, y, z), y down; in bird's-eye view a rectangle of the (x, z) plane with length axis
(cos ry, -sin ry) and width axis (sin ry, cos ry).
"""

from __future__ import annotations

import math

import numpy as np
from shapely.geometry import Polygon


def _check(criterion: str) -> None:
    if criterion not in ("union", "first"):
        raise ValueError(f"unknown criterion {criterion!r}")


def iou_2d_naive(a, b, criterion: str = "union") -> np.ndarray:
    _check(criterion)
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    out = np.zeros((len(a), len(b)))
    for i, (ax1, ay1, ax2, ay2) in enumerate(a.tolist()):
        for j, (bx1, by1, bx2, by2) in enumerate(b.tolist()):
            iw = min(ax2, bx2) - max(ax1, bx1)
            ih = min(ay2, by2) - max(ay1, by1)
            if iw <= 0 or ih <= 0:
                continue
            inter = iw * ih
            area_a = (ax2 - ax1) * (ay2 - ay1)
            area_b = (bx2 - bx1) * (by2 - by1)
            denom = area_a if criterion == "first" else area_a + area_b - inter
            out[i, j] = inter / denom if denom > 0 else 0.0
    return out


def bev_polygon(box) -> Polygon:
    """The bird's-eye-view rectangle of one camera box, as a shapely polygon in (x, z)."""
    x, _, z, l, _, w, ry = (float(v) for v in box)
    u = (math.cos(ry), -math.sin(ry))
    v = (math.sin(ry), math.cos(ry))
    hl, hw = abs(l) / 2, abs(w) / 2
    corners = [
        (x + sl * hl * u[0] + sw * hw * v[0], z + sl * hl * u[1] + sw * hw * v[1])
        for sl, sw in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ]
    return Polygon(corners)


def _bev_inter(a, b) -> float:
    pa, pb = bev_polygon(a), bev_polygon(b)
    if pa.area == 0 or pb.area == 0:
        return 0.0
    return pa.intersection(pb).area


def iou_bev_naive(a, b, criterion: str = "union") -> np.ndarray:
    _check(criterion)
    a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 7)
    out = np.zeros((len(a), len(b)))
    for i, ba in enumerate(a):
        for j, bb in enumerate(b):
            inter = _bev_inter(ba, bb)
            area_a = abs(ba[3]) * abs(ba[5])
            area_b = abs(bb[3]) * abs(bb[5])
            denom = area_a if criterion == "first" else area_a + area_b - inter
            out[i, j] = inter / denom if denom > 0 else 0.0
    return out


def iou_3d_naive(a, b, criterion: str = "union") -> np.ndarray:
    _check(criterion)
    a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 7)
    out = np.zeros((len(a), len(b)))
    for i, ba in enumerate(a):
        for j, bb in enumerate(b):
            ya, ha, yb, hb = ba[1], ba[4], bb[1], bb[4]
            dy = max(0.0, min(ya, yb) - max(ya - ha, yb - hb))
            inter = _bev_inter(ba, bb) * dy
            vol_a = abs(ba[3]) * abs(ba[5]) * max(ha, 0.0)
            vol_b = abs(bb[3]) * abs(bb[5]) * max(hb, 0.0)
            denom = vol_a if criterion == "first" else vol_a + vol_b - inter
            out[i, j] = inter / denom if denom > 0 else 0.0
    return out


def resampled_curves_naive(events, weights) -> np.ndarray:
    """The paired bootstrap's curves (``kitti_eval.analysis.bootstrap._resampled_curves``) one resample at a
    time: the devkit's threshold rule stepped over every repeated true positive, then one sweep of the events
    per resample."""
    from kitti_eval.core.matching import threshold_step
    from kitti_eval.core.protocol import N_SAMPLE_PTS

    weights = np.asarray(weights, dtype=np.int64)
    out = np.zeros((weights.shape[0], 2, N_SAMPLE_PTS))
    for b, w in enumerate(weights.tolist()):
        n_gt = sum(wf * int(v) for wf, v in zip(w, events.valid.tolist()))
        repeated = [float(s) for s, f in zip(events.tp_score.tolist(), events.tp_frame.tolist()) for _ in range(w[f])]
        if n_gt == 0 or not repeated:
            continue
        thresholds, current = [], 0.0
        for i, score in enumerate(repeated):
            take, current = threshold_step(i, len(repeated), n_gt, current, N_SAMPLE_PTS)
            if take and len(thresholds) < N_SAMPLE_PTS:
                thresholds.append(score)
        tp = fp = sim = 0.0
        e = 0
        n_e = len(events.ev_score)
        for t, thr in enumerate(thresholds):
            while e < n_e and events.ev_score[e] >= thr:
                ww = w[int(events.ev_frame[e])]
                if ww != 0:
                    tp += ww * float(events.ev_delta[e, 0])
                    fp += ww * float(events.ev_delta[e, 1])
                    sim += ww * float(events.ev_delta[e, 3])
                e += 1
            out[b, 0, t] = tp / (tp + fp) if tp + fp > 0 else math.nan
            out[b, 1, t] = sim / (tp + fp) if tp + fp > 0 else math.nan
    return out
