"""Seeded synthetic KITTI validation sets, in OpenPCDet's exact structures.

:func:`generate` returns ``(infos, results)``: a ``kitti_infos_val.pkl`` list and a ``result.pkl`` list as
OpenPCDet writes them (keys, key order, dtypes, the float64 empty-frame template of ``result.pkl``). The
writers put them on disk as pickles or as KITTI txt folders (``label_2/`` with 15 fields, ``pred/`` with
the 16 fields OpenPCDet's ``--save_to_file`` writes).

Geometry is self-consistent and uses KITTI's standard calibration (frame 000000 of the training set): the
2D box of every object is its 3D box's eight corners projected through ``P2`` and clipped to the image
(``[0, W - 1] x [0, H - 1]``, as OpenPCDet clips), truncation is the clipped fraction of that projection,
``alpha = rotation_y - arctan2(x, z)``, and the LiDAR boxes come from the inverse calibration.

Ground truth is written with KITTI's two decimals; detections are rounded to ``pred_decimals`` (four, the
precision of OpenPCDet's txt output, so the pickle and the txt route hold the same numbers) before their 2D
box and alpha are derived from them. Ground truth and detections draw from independent streams of the seed:
the same seed gives the same ground truth whatever the detection settings.

Command line::

    python -m kitti_eval.synth --frames 3769 --seed 0 --dets-per-frame 40 --out DIR [--txt] [--gzip]
        [--detector-seed N] [--location-noise METRES]
"""

from __future__ import annotations

import argparse
import gzip
import pickle
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .core.protocol import KITTI_CLASSES
from .demo import DEMO_ARGS, DEMO_WEAKER_ARGS, demo_paths, demo_weaker_path
from .io.calib import camera_to_lidar, rect_to_velo, wrap_angle

__all__ = [
    "generate",
    "write_infos",
    "write_results",
    "write_label_dir",
    "write_result_dir",
    "box_corners_image",
    "IMAGE_SHAPE",
    "main",
]

F64 = npt.NDArray[np.float64]

#: (H, W) of every synthetic frame, as in ``info['image']['image_shape']``.
IMAGE_SHAPE = (375, 1242)


# KITTI training calibration of frame 000000 (also the golden cases' calib.txt), parsed to float32 as
# OpenPCDet's Calibration does.
_P2 = np.array(
    [
        7.215377e02,
        0.0,
        6.095593e02,
        4.485728e01,
        0.0,
        7.215377e02,
        1.728540e02,
        2.163791e-01,
        0.0,
        0.0,
        1.0,
        2.745884e-03,
    ],
    dtype=np.float32,
).reshape(3, 4)
_R0 = np.array(
    [
        9.999239e-01,
        9.837760e-03,
        -7.445048e-03,
        -9.869795e-03,
        9.999421e-01,
        -4.278459e-03,
        7.402527e-03,
        4.351614e-03,
        9.999631e-01,
    ],
    dtype=np.float32,
).reshape(3, 3)
_V2C = np.array(
    [
        7.533745e-03,
        -9.999714e-01,
        -6.166020e-04,
        -4.069766e-03,
        1.480249e-02,
        7.280733e-04,
        -9.998902e-01,
        -7.631618e-02,
        9.998621e-01,
        7.523790e-03,
        1.480755e-02,
        -2.717806e-01,
    ],
    dtype=np.float32,
).reshape(3, 4)


_RECT_TO_LIDAR = rect_to_velo(_R0, _V2C)

# Ground-truth classes: name, share of objects (KITTI train label counts), mean (l, h, w) and its spread (m),
# probability that the detector finds a near, unoccluded one, and the detector class (index into _PRED_NAMES).
_GT_NAMES = KITTI_CLASSES  # the arrays below follow its order
_GT_SHARE = np.array([28742, 2914, 1094, 4487, 222, 1627, 511, 973], dtype=np.float64)
_GT_LHW = np.array(
    [
        [3.88, 1.53, 1.63],
        [5.08, 2.21, 1.90],
        [10.1, 3.25, 2.58],
        [0.84, 1.76, 0.66],
        [0.80, 1.27, 0.59],
        [1.76, 1.74, 0.60],
        [16.1, 3.53, 2.54],
        [3.58, 1.91, 1.51],
    ]
)
_GT_LHW_SD = np.array(
    [
        [0.43, 0.14, 0.10],
        [0.48, 0.30, 0.15],
        [2.9, 0.45, 0.20],
        [0.23, 0.11, 0.14],
        [0.20, 0.12, 0.10],
        [0.18, 0.09, 0.12],
        [5.0, 0.18, 0.15],
        [2.0, 0.6, 0.4],
    ]
)
_GT_FIND = np.array([0.97, 0.45, 0.15, 0.90, 0.40, 0.88, 0.05, 0.10])
_GT_AS = np.array([0, 0, 0, 1, 1, 2, 0, 0])
_VEHICLE = np.array([True, True, True, False, False, True, True, False])  # mostly aligned with the road

_PRED_NAMES = np.array(["Car", "Pedestrian", "Cyclist"])  # dtype <U10, like np.array(class_names)
_PRED_SHARE_FP = np.array([0.55, 0.30, 0.15])
_PRED_YAW_SD = np.array([0.05, 0.30, 0.15])
_PRED_LHW = _GT_LHW[[0, 3, 5]]


# ------------------------------------------------------------------------------------------------ geometry


def box_corners_image(
    location: npt.ArrayLike,
    dimensions: npt.ArrayLike,
    rotation_y: npt.ArrayLike,
    image_shape: tuple[int, int] = IMAGE_SHAPE,
) -> tuple[F64, F64, F64]:
    """Project camera boxes into the image through the standard ``P2``.

    Parameters
    ----------
    location : (N, 3) bottom centres x, y, z (camera frame, metres)
    dimensions : (N, 3) l, h, w
    rotation_y : (N,) yaw about the camera y axis
    image_shape : (H, W)

    Returns
    -------
    bbox : (N, 4) x1, y1, x2, y2 of the eight projected corners, clipped to ``[0, W-1] x [0, H-1]``
    raw : (N, 4) the same box before clipping
    min_depth : (N,) the smallest depth of a corner (a box is in front of the camera when it is > 0)
    """
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=np.float64).reshape(-1)
    c, s = np.cos(ry), np.sin(ry)
    p = _P2.astype(np.float64)
    n = len(ry)
    lo = np.full((n, 2), np.inf)
    hi = np.full((n, 2), -np.inf)
    min_depth = np.full(n, np.inf)
    for sx in (-0.5, 0.5):  # one corner at a time: no (N, 8, 3) temporaries
        for sy in (0.0, -1.0):
            for sz in (-0.5, 0.5):
                ox, oz = sx * dims[:, 0], sz * dims[:, 2]
                x = loc[:, 0] + c * ox + s * oz
                y = loc[:, 1] + sy * dims[:, 1]
                z = loc[:, 2] - s * ox + c * oz
                d = p[2, 0] * x + p[2, 1] * y + p[2, 2] * z + p[2, 3]
                with np.errstate(divide="ignore", invalid="ignore"):
                    u = (p[0, 0] * x + p[0, 1] * y + p[0, 2] * z + p[0, 3]) / d
                    v = (p[1, 0] * x + p[1, 1] * y + p[1, 2] * z + p[1, 3]) / d
                np.minimum(lo[:, 0], u, out=lo[:, 0])
                np.minimum(lo[:, 1], v, out=lo[:, 1])
                np.maximum(hi[:, 0], u, out=hi[:, 0])
                np.maximum(hi[:, 1], v, out=hi[:, 1])
                np.minimum(min_depth, d, out=min_depth)
    raw = np.concatenate([lo, hi], axis=1)
    h, w = image_shape
    bbox = np.empty_like(raw)
    bbox[:, [0, 2]] = np.clip(raw[:, [0, 2]], 0, w - 1)
    bbox[:, [1, 3]] = np.clip(raw[:, [1, 3]], 0, h - 1)
    return bbox, raw, min_depth


def _round(a: F64, decimals: int | None) -> F64:
    return a if decimals is None else np.round(a, decimals) + 0.0  # + 0.0 turns -0.0 into 0.0


def _visible(bbox: F64, raw: F64, min_depth: F64) -> tuple[npt.NDArray[np.bool_], F64]:
    """Whether a projected box can be seen, and its truncation (clipped fraction of the projected area)."""
    area = (raw[:, 2] - raw[:, 0]) * (raw[:, 3] - raw[:, 1])
    inside = (bbox[:, 2] - bbox[:, 0]) * (bbox[:, 3] - bbox[:, 1])
    ok = (min_depth > 0.1) & (bbox[:, 2] - bbox[:, 0] >= 2.0) & (bbox[:, 3] - bbox[:, 1] >= 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        trunc = np.where(ok, 1.0 - inside / np.where(ok, area, 1.0), 1.0)
    return ok & (trunc <= 0.85), np.clip(trunc, 0.0, 1.0)


def _rank_in_frame(frame: npt.NDArray[np.int64], keep: npt.NDArray[np.bool_], n_frames: int) -> npt.NDArray[np.int64]:
    """For rows sorted by frame: how many kept rows of the same frame come before each row."""
    k = keep.astype(np.int64)
    before = np.cumsum(k) - k
    first = np.searchsorted(frame, np.arange(n_frames))
    starts = np.concatenate([before, [0]])[first]
    return before - starts[frame]


def _earlier_pairs(frame: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """For rows sorted by frame: every pair (i, j) of rows of one frame with i < j."""
    n = len(frame)
    start = np.searchsorted(frame, frame)  # first row of each row's frame
    before = np.arange(n) - start  # rows of the same frame before each row
    j = np.repeat(np.arange(n), before)
    first_pair = np.cumsum(before) - before
    i = np.repeat(start, before) + np.arange(len(j)) - np.repeat(first_pair, before)
    return i, j


def _bev_overlap(
    loc: F64, dims: F64, ry: F64, i: npt.NDArray[np.int64], j: npt.NDArray[np.int64], margin: float
) -> npt.NDArray[np.bool_]:
    """Whether the bird's-eye rectangles of boxes i and j, grown by ``margin``, overlap (separating axes)."""
    dx, dz = loc[j, 0] - loc[i, 0], loc[j, 2] - loc[i, 2]
    c, s = np.cos(ry), np.sin(ry)
    sides = [(c[k], s[k], dims[k, 0] / 2 + margin / 2, dims[k, 2] / 2 + margin / 2) for k in (i, j)]
    overlap = np.ones(len(i), dtype=bool)
    for ck, sk, _, _ in sides:
        for ax, az in ((ck, -sk), (sk, ck)):  # the length and width axes of each box, in (x, z)
            reach = sum(hl * np.abs(cm * ax - sm * az) + hw * np.abs(sm * ax + cm * az) for cm, sm, hl, hw in sides)
            overlap &= np.abs(dx * ax + dz * az) < reach
    return overlap


# ------------------------------------------------------------------------------------------ ground truth


def _sample_objects(
    rng: np.random.Generator,
    cls: npt.NDArray[np.int64],
    lhw: F64,
    lhw_sd: F64,
    vehicle: npt.NDArray[np.bool_],
    z_beta: tuple[float, float],
) -> tuple[F64, F64, F64]:
    n = len(cls)
    z = 4.0 + 66.0 * rng.beta(*z_beta, n)
    x = z * np.tan(rng.uniform(-0.76, 0.76, n))
    y = np.clip(rng.normal(1.70, 0.09, n), 1.45, 1.95)
    mean = lhw[cls]
    dims = np.maximum(mean * np.exp(rng.normal(0.0, 1.0, (n, 3)) * lhw_sd[cls] / mean), 0.25)
    aligned = vehicle & (rng.random(n) < 0.75)
    ry = np.where(
        aligned,
        np.where(rng.random(n) < 0.5, -np.pi / 2, np.pi / 2) + rng.normal(0, 0.15, n),
        rng.uniform(-np.pi, np.pi, n),
    )
    return np.stack([x, y, z], axis=1), dims, wrap_angle(ry)


def _ground_truth(
    rng: np.random.Generator, frames: int, gt_per_frame: float, dontcare_per_frame: float, empty_gt_frac: float
) -> dict[str, np.ndarray]:
    """Flat arrays of all ground-truth objects (frame-major, DontCare last in each frame)."""
    empty = rng.random(frames) < empty_gt_frac
    want = np.where(empty, 0, rng.poisson(gt_per_frame, frames))
    n_dc = np.where(empty, 0, rng.poisson(dontcare_per_frame, frames))
    # oversample candidates, keep the first `want` of each frame that are visible and clear of the others
    n_cand = want + np.ceil(0.5 * want).astype(np.int64) + 3 * (want > 0)
    frame = np.repeat(np.arange(frames), n_cand)
    cls = rng.choice(len(_GT_NAMES), size=len(frame), p=_GT_SHARE / _GT_SHARE.sum())
    loc, dims, ry = _sample_objects(rng, cls, _GT_LHW, _GT_LHW_SD, _VEHICLE[cls], (1.3, 2.4))
    loc, dims, ry = np.round(loc, 2) + 0.0, np.round(dims, 2), np.round(ry, 2) + 0.0
    bbox, raw, depth = box_corners_image(loc, dims, ry)
    ok, trunc = _visible(bbox, raw, depth)
    i, j = _earlier_pairs(frame)
    pick = ok[i] & ok[j]
    i, j = i[pick], j[pick]
    ok[j[_bev_overlap(loc, dims, ry, i, j, margin=0.3)]] = False  # a later candidate yields to an earlier one
    keep = ok & (_rank_in_frame(frame, ok, frames) < want[frame])
    frame, cls, loc, dims, ry, bbox, trunc = (
        frame[keep],
        cls[keep],
        loc[keep],
        dims[keep],
        ry[keep],
        bbox[keep],
        trunc[keep],
    )
    n = len(frame)
    z = loc[:, 2]
    occ = np.digitize(0.75 * (z - 4.0) / 66.0 + rng.random(n), [0.7, 1.05, 1.42]).astype(np.float64)
    trunc = np.round(trunc, 2) + 0.0
    bbox = np.round(bbox, 2) + 0.0
    alpha = np.round(wrap_angle(ry - np.arctan2(loc[:, 0], z)), 2) + 0.0
    face = dims[:, 1] * np.maximum(dims[:, 0], dims[:, 2])
    points = 6.0e4 * face / z**2 * (1.0 - 0.25 * occ) * (1.0 - trunc) * rng.lognormal(0.0, 0.35, n)
    # DontCare regions: small boxes around the horizon
    dc_frame = np.repeat(np.arange(frames), n_dc)
    m = len(dc_frame)
    x1 = rng.uniform(0.0, 1180.0, m)
    yc = rng.normal(182.0, 10.0, m)
    hh = rng.uniform(10.0, 50.0, m)
    dc_bbox = np.stack(
        [x1, yc - hh / 2, np.minimum(x1 + rng.uniform(8.0, 140.0, m), IMAGE_SHAPE[1] - 1.0), yc + hh / 2], axis=1
    )
    dc_bbox = np.round(np.clip(dc_bbox, 0.0, [IMAGE_SHAPE[1] - 1.0, IMAGE_SHAPE[0] - 1.0] * 2), 2) + 0.0
    # concatenate objects and DontCare, DontCare last within each frame
    order = np.argsort(np.concatenate([frame * 2, dc_frame * 2 + 1]), kind="stable")
    names = np.array(_GT_NAMES + ("DontCare",))
    minus = np.full(m, -1.0)

    def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a, b])[order]

    return {
        "frame": cat(frame, dc_frame),
        "name": cat(names[cls], np.full(m, "DontCare", dtype=names.dtype)),
        "truncated": cat(trunc, minus),
        "occluded": cat(occ, minus),
        "alpha": cat(alpha, np.full(m, -10.0)),
        "bbox": cat(bbox, dc_bbox),
        "dimensions": cat(dims, np.full((m, 3), -1.0)),
        "location": cat(loc, np.full((m, 3), -1000.0)),
        "rotation_y": cat(ry, np.full(m, -10.0)),
        "num_points_in_gt": cat(np.floor(points).astype(np.int32), np.full(m, -1, np.int32)),
        "cls": cat(cls, np.full(m, -1)),
        "counts": np.bincount(frame, minlength=frames) + n_dc,
    }


def _difficulty(bbox: npt.NDArray[np.float32], trunc: F64, occ: F64) -> npt.NDArray[np.int32]:
    """OpenPCDet's ``Object3d.get_kitti_obj_level`` (height = y2 - y1 + 1); -1 when no level applies."""
    height = bbox[:, 3].astype(np.float64) - bbox[:, 1].astype(np.float64) + 1
    out = np.full(len(height), -1, dtype=np.int32)
    hard = (height >= 25) & (trunc <= 0.5) & (occ <= 2)
    moderate = (height >= 25) & (trunc <= 0.3) & (occ <= 1)
    easy = (height >= 40) & (trunc <= 0.15) & (occ <= 0)
    out[hard] = 2
    out[moderate] = 1
    out[easy] = 0
    return out


# ------------------------------------------------------------------------------------------- detections


def _detections(
    rng: np.random.Generator,
    gt: dict[str, np.ndarray],
    frames: int,
    dets_per_frame: float,
    empty_pred_frac: float,
    decimals: int | None,
    location_noise: float = 0.0,
) -> dict[str, np.ndarray]:
    """Flat arrays of the detections of ``frames`` frames (frame-major, by descending score in a frame).

    ``gt`` holds the labelled objects (no DontCare) of these frames, ``frame`` counted from 0;
    ``location_noise``: a further N(0, it) metres on x and z of each true positive.
    """
    g_frame, g_cls = gt["frame"], gt["cls"]
    g_loc, g_dims, g_ry = gt["location"], gt["dimensions"], gt["rotation_y"]
    g_occ, g_trunc = gt["occluded"], gt["truncated"]
    empty = rng.random(frames) < empty_pred_frac
    z = g_loc[:, 2]
    p_find = _GT_FIND[g_cls] * np.clip(1.08 - z / 150.0, 0.3, 1.0) * (1 - 0.08 * g_occ) * (1 - 0.5 * g_trunc)
    found = (rng.random(len(g_cls)) < p_find) & ~empty[g_frame]
    n_tp = int(found.sum())
    live = max(frames - int(empty.sum()), 1)
    if n_tp > dets_per_frame * frames:  # fewer detections wanted than objects found: drop some
        found &= rng.random(len(found)) < dets_per_frame * frames / n_tp
        n_tp = int(found.sum())
    idx = np.flatnonzero(found)
    # true positives: jittered copies of ground truth
    t_frame, t_loc, t_dims, t_ry, z = g_frame[idx], g_loc[idx], g_dims[idx], g_ry[idx], z[idx]
    t_cls = _GT_AS[g_cls[idx]]
    wrong = rng.random(len(idx)) < 0.03
    t_cls = np.where(wrong, (t_cls + rng.integers(1, 3, len(idx))) % 3, t_cls)
    # location error grows with distance, and is smaller for small objects
    sd_xz = (0.02 + 0.0035 * z) * (0.6 + 0.4 * np.minimum(t_dims[:, 2] / 1.63, 1.0))
    err = rng.normal(0.0, 1.0, (len(idx), 3)) * np.stack([sd_xz, 0.02 + 0.001 * z, sd_xz], axis=1)
    t_loc = t_loc + err
    if location_noise > 0:
        t_loc[:, [0, 2]] += rng.normal(0.0, location_noise, (len(idx), 2))
    t_dims = t_dims * np.exp(rng.normal(0.0, 0.045, (len(idx), 3)))
    flip = rng.random(len(idx)) < 0.04
    t_ry = t_ry + rng.normal(0.0, 1.0, len(idx)) * (_PRED_YAW_SD[t_cls] + 0.002 * z) + np.pi * flip
    miss = np.hypot(err[:, 0], err[:, 2]) / (0.15 + 0.1 * t_dims[:, 2])
    logit = 2.6 - 1.0 * miss - 0.025 * z - 0.3 * g_occ[idx] - 0.8 * flip - 1.5 * wrong + rng.normal(0.0, 0.7, len(idx))
    # false positives: near-duplicates of objects, and boxes anywhere in the scene
    lam = max((dets_per_frame * frames - n_tp) / live, 0.0)
    n_fp = np.where(empty, 0, rng.poisson(lam, frames))
    n_cand = n_fp + np.ceil(0.25 * n_fp).astype(np.int64) + 2 * (n_fp > 0)  # some will not be visible
    f_frame = np.repeat(np.arange(frames), n_cand)
    n_gt = np.bincount(g_frame, minlength=frames)
    g_start = np.concatenate([[0], np.cumsum(n_gt)])[:-1]
    near = (rng.random(len(f_frame)) < 0.3) & (n_gt[f_frame] > 0)
    src = g_start[f_frame] + (rng.random(len(f_frame)) * n_gt[f_frame]).astype(np.int64)
    f_cls = rng.choice(3, size=len(f_frame), p=_PRED_SHARE_FP)
    f_loc, f_dims, f_ry = _sample_objects(rng, f_cls, _PRED_LHW, 0.1 * _PRED_LHW, f_cls == 0, (1.2, 2.0))
    src = np.where(near, src, 0)
    if len(g_frame):
        shift = rng.normal(0.0, 1.0, (len(f_frame), 3)) * np.stack(
            [1.0 + 0.02 * g_loc[src, 2], np.full(len(src), 0.1), 1.0 + 0.02 * g_loc[src, 2]], axis=1
        )
        f_cls = np.where(near, _GT_AS[g_cls[src]], f_cls)
        f_loc = np.where(near[:, None], g_loc[src] + shift, f_loc)
        f_dims = np.where(near[:, None], g_dims[src] * np.exp(rng.normal(0.0, 0.15, (len(src), 3))), f_dims)
        f_ry = np.where(near, g_ry[src] + rng.normal(0.0, 0.5, len(src)), f_ry)
    f_logit = np.where(near, rng.normal(-2.0, 0.8, len(f_frame)), rng.normal(-2.8, 1.0, len(f_frame)))
    # together: round the 3D box, then derive everything else from the rounded numbers
    frame = np.concatenate([t_frame, f_frame])
    cls = np.concatenate([t_cls, f_cls])
    loc = _round(np.concatenate([t_loc, f_loc]), decimals)
    dims = _round(np.concatenate([t_dims, f_dims]), decimals)
    ry = _round(wrap_angle(np.concatenate([t_ry, f_ry])), decimals)
    score = _round(np.clip(1.0 / (1.0 + np.exp(-np.concatenate([logit, f_logit]))), 1e-3, 0.999), decimals)
    bbox, raw, depth = box_corners_image(loc, dims, ry)
    ok, _ = _visible(bbox, raw, depth)
    ok &= np.all(dims > 0, axis=1)
    fp_ok = ok[len(t_frame) :]  # a view: keep the first n_fp visible false positives of each frame
    fp_ok &= _rank_in_frame(f_frame, fp_ok, frames) < n_fp[f_frame]
    order = np.lexsort((-score, frame))
    order = order[ok[order]]
    loc, dims, ry = loc[order], dims[order], ry[order]
    return {
        "frame": frame[order],
        "name": _PRED_NAMES[cls[order]],
        "alpha": _round(ry - np.arctan2(loc[:, 0], loc[:, 2]), decimals),
        "bbox": _round(bbox[order], decimals),
        "dimensions": dims,
        "location": loc,
        "rotation_y": ry,
        "score": score[order],
        "boxes_lidar": camera_to_lidar(loc, dims, ry, _RECT_TO_LIDAR),
        "counts": np.bincount(frame[order], minlength=frames),
    }


# -------------------------------------------------------------------------------------- OpenPCDet dicts


def _calib() -> dict[str, np.ndarray]:
    """OpenPCDet's ``calib`` entry: P2 and Tr_velo_to_cam float64 (float32 values), R0_rect float32."""
    p2 = np.concatenate([_P2, np.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)
    r0 = np.zeros((4, 4), dtype=np.float32)
    r0[:3, :3] = _R0
    r0[3, 3] = 1.0
    v2c = np.concatenate([_V2C, np.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)
    return {"P2": p2, "R0_rect": r0, "Tr_velo_to_cam": v2c}


def _empty_gt_annos() -> dict[str, np.ndarray]:
    return {
        "name": np.zeros(0),
        "truncated": np.zeros(0),
        "occluded": np.zeros(0),
        "alpha": np.zeros(0),
        "bbox": np.zeros((0, 4), np.float32),
        "dimensions": np.zeros((0, 3)),
        "location": np.zeros((0, 3), np.float32),
        "rotation_y": np.zeros(0),
        "score": np.zeros(0),
        "difficulty": np.zeros(0, np.int32),
        "index": np.zeros(0, np.int32),
        "gt_boxes_lidar": np.zeros((0, 7)),
        "num_points_in_gt": np.zeros(0, np.int32),
    }


def _empty_prediction(frame_id: str) -> dict[str, Any]:
    """OpenPCDet's ``get_template_prediction(0)`` plus ``frame_id``: float64 zeros, ``name`` included."""
    return {
        "name": np.zeros(0),
        "truncated": np.zeros(0),
        "occluded": np.zeros(0),
        "alpha": np.zeros(0),
        "bbox": np.zeros((0, 4)),
        "dimensions": np.zeros((0, 3)),
        "location": np.zeros((0, 3)),
        "rotation_y": np.zeros(0),
        "score": np.zeros(0),
        "boxes_lidar": np.zeros((0, 7)),
        "frame_id": frame_id,
    }


_GT_FIELDS = (
    "name",
    "truncated",
    "occluded",
    "alpha",
    "bbox",
    "dimensions",
    "location",
    "rotation_y",
    "score",
    "difficulty",
    "index",
    "gt_boxes_lidar",
    "num_points_in_gt",
)
_DET_FIELDS = ("alpha", "bbox", "dimensions", "location", "rotation_y", "score", "boxes_lidar")


def _build_infos(gt: dict[str, np.ndarray], frames: int) -> list[dict[str, Any]]:
    counts = gt["counts"]
    ends = np.cumsum(counts)
    starts = ends - counts
    real = gt["cls"] >= 0
    bbox = gt["bbox"].astype(np.float32)
    cols = {
        "name": gt["name"],
        "truncated": gt["truncated"],
        "occluded": gt["occluded"],
        "alpha": gt["alpha"],
        "bbox": bbox,
        "dimensions": gt["dimensions"],
        "location": gt["location"].astype(np.float32),
        "rotation_y": gt["rotation_y"],
        "score": np.full(len(real), -1.0),
        "difficulty": _difficulty(bbox, gt["truncated"], gt["occluded"]),
        "index": np.where(real, np.arange(len(real)) - np.repeat(starts, counts), -1).astype(np.int32),
        "num_points_in_gt": gt["num_points_in_gt"],
    }
    # gt_boxes_lidar has no DontCare rows: (num_obj, 7), from the float32 locations as OpenPCDet's
    lidar = camera_to_lidar(
        cols["location"][real].astype(np.float64), gt["dimensions"][real], gt["rotation_y"][real], _RECT_TO_LIDAR
    )
    n_real = np.bincount(gt["frame"][real], minlength=frames)
    real_ends = np.cumsum(n_real)
    # np.array(list_of_names) in OpenPCDet: the width of a frame's longest name
    width = np.zeros(frames, dtype=np.int64)
    if len(real):
        nonempty = counts > 0
        width[nonempty] = np.maximum.reduceat(np.char.str_len(gt["name"]), starts[nonempty])
    infos: list[dict[str, Any]] = []
    for f in range(frames):
        idx = f"{f:06d}"
        lo, hi = int(starts[f]), int(ends[f])
        if hi > lo:
            annos = {
                k: (
                    cols[k][lo:hi].copy()
                    if k != "gt_boxes_lidar"
                    else lidar[real_ends[f] - n_real[f] : real_ends[f]].copy()
                )
                for k in _GT_FIELDS
            }
            annos["name"] = annos["name"].astype(f"<U{width[f]}")
        else:
            annos = _empty_gt_annos()
        infos.append(
            {
                "point_cloud": {"num_features": 4, "lidar_idx": idx},
                "image": {"image_idx": idx, "image_shape": np.array(IMAGE_SHAPE, dtype=np.int32)},
                "calib": _calib(),
                "annos": annos,
            }
        )
    return infos


def _build_results(det: dict[str, np.ndarray], first: int, numpy_frame_ids: bool) -> list[dict[str, Any]]:
    """Result dicts of the frames ``first ..`` of a chunk (float32, views of one array per field)."""
    counts = det["counts"]
    ends = np.cumsum(counts)
    cols = {k: det[k].astype(np.float32) for k in _DET_FIELDS}
    results: list[dict[str, Any]] = []
    for f, (n, hi) in enumerate(zip(counts.tolist(), ends.tolist())):
        text = f"{first + f:06d}"
        fid: str = np.str_(text) if numpy_frame_ids else text
        if n == 0:
            results.append(_empty_prediction(fid))
            continue
        lo = hi - n
        d: dict[str, Any] = {"name": det["name"][lo:hi], "truncated": np.zeros(n), "occluded": np.zeros(n)}
        for k in _DET_FIELDS:
            d[k] = cols[k][lo:hi]
        d["frame_id"] = fid
        results.append(d)
    return results


#: Detections are made this many frames at a time (bounds the memory; part of what a seed means).
_CHUNK = 2048


def generate(
    frames: int,
    seed: int = 0,
    *,
    dets_per_frame: float = 10.0,
    gt_per_frame: float = 6.5,
    dontcare_per_frame: float = 1.5,
    empty_gt_frac: float = 0.02,
    empty_pred_frac: float = 0.02,
    pred_decimals: int | None = 4,
    numpy_frame_ids: bool = True,
    detector_seed: int | None = None,
    location_noise: float = 0.0,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """A synthetic KITTI validation set: ``(infos, results)`` as OpenPCDet's pickles hold them.

    Parameters
    ----------
    frames : number of frames, ids ``000000`` .. in order (positional alignment, as OpenPCDet's)
    seed : the whole output is a function of the arguments (and of numpy's random streams)
    dets_per_frame : mean detections a frame over all frames (found objects plus false positives)
    gt_per_frame : mean labelled objects (DontCare not counted) of a frame that is not empty, Poisson
    dontcare_per_frame : mean DontCare regions of a frame that is not empty, Poisson
    empty_gt_frac : share of frames whose label file is empty (no objects, no DontCare)
    empty_pred_frac : share of frames without detections (OpenPCDet's empty template)
    pred_decimals : detections are rounded to this many decimals (None: full float32)
    numpy_frame_ids : ``frame_id`` as ``numpy.str_`` (what OpenPCDet's collate produces) or plain ``str``
    detector_seed : the detections' own seed (default: drawn from ``seed``): the same ground truth with
        another draw of the same detector, e.g. two training runs of one model
    location_noise : a further error of every found object's ground-plane position (x and z), N(0, this)
        metres: a less precise detector (0: none, and the same detections as without it)

    Returns
    -------
    infos : list of ``kitti_infos_val.pkl`` dicts (``point_cloud``, ``image``, ``calib``, ``annos``)
    results : list of ``result.pkl`` dicts, frame by frame, detections by descending score; the arrays
        of a frame are views into one array per field and chunk of frames
    """
    if frames < 0:
        raise ValueError(f"Expected `frames` >= 0, got {frames}")
    for name, value in (
        ("dets_per_frame", dets_per_frame),
        ("gt_per_frame", gt_per_frame),
        ("dontcare_per_frame", dontcare_per_frame),
    ):
        if not value >= 0:
            raise ValueError(f"Expected `{name}` >= 0, got {value}")
    if not location_noise >= 0:
        raise ValueError(f"Expected `location_noise` >= 0, got {location_noise}")
    for name, value in (("empty_gt_frac", empty_gt_frac), ("empty_pred_frac", empty_pred_frac)):
        if not 0 <= value <= 1:
            raise ValueError(f"Expected `{name}` in [0, 1], got {value}")
    gt_seq, det_seq = np.random.SeedSequence(seed).spawn(2)
    gt = _ground_truth(np.random.default_rng(gt_seq), frames, gt_per_frame, dontcare_per_frame, empty_gt_frac)
    infos = _build_infos(gt, frames)
    rng = np.random.default_rng(det_seq if detector_seed is None else detector_seed)
    keys = ("cls", "location", "dimensions", "rotation_y", "occluded", "truncated")
    real = gt["cls"] >= 0
    objects = {k: gt[k][real] for k in keys}
    objects["frame"] = gt["frame"][real]
    del gt
    results: list[dict[str, Any]] = []
    for first in range(0, frames, _CHUNK):
        last = min(first + _CHUNK, frames)
        lo, hi = np.searchsorted(objects["frame"], [first, last])
        chunk = {k: v[lo:hi] for k, v in objects.items()}
        chunk["frame"] = chunk["frame"] - first
        det = _detections(rng, chunk, last - first, dets_per_frame, empty_pred_frac, pred_decimals, location_noise)
        results += _build_results(det, first, numpy_frame_ids)
    return infos, results


# ------------------------------------------------------------------------------------------------ writers


def _dump(path: str | Path, obj: object) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.name.endswith(".gz"):  # mtime 0: the same data gives the same bytes
        fh: Any = gzip.GzipFile(path, "wb", compresslevel=6, mtime=0)
    else:
        fh = open(path, "wb")
    with fh:
        pickle.dump(obj, fh, protocol=4)  # OpenPCDet's default protocol on Python 3.8-3.13


def write_infos(path: str | Path, infos: Sequence[dict[str, Any]]) -> None:
    """Pickle an infos list (gzip-compressed when ``path`` ends with ``.gz``)."""
    _dump(path, list(infos))


def write_results(path: str | Path, results: Sequence[dict[str, Any]]) -> None:
    """Pickle a result list (gzip-compressed when ``path`` ends with ``.gz``)."""
    _dump(path, list(results))


_GT_LINE = "%s %.2f %d %.2f %.2f %.2f %.2f %.2f %.2f %.2f %.2f %.2f %.2f %.2f %.2f"
_DC_LINE = "DontCare -1 -1 -10 %.2f %.2f %.2f %.2f -1 -1 -1 -1000 -1000 -1000 -10"
_DET_LINE = "%s -1 -1 %.4f" + " %.4f" * 11 + " %.4f"


def write_label_dir(directory: str | Path, infos: Sequence[dict[str, Any]]) -> None:
    """KITTI ``label_2`` files ``<image_idx>.txt``: 15 fields, dims h w l, two decimals, DontCare last."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    for info in infos:
        a = info["annos"]
        lines = []
        num = np.concatenate(
            [
                np.asarray(a["truncated"], np.float64)[:, None],
                np.asarray(a["occluded"], np.float64)[:, None],
                np.asarray(a["alpha"], np.float64)[:, None],
                np.asarray(a["bbox"], np.float64).reshape(-1, 4),
                np.asarray(a["dimensions"], np.float64).reshape(-1, 3)[:, [1, 2, 0]],
                np.asarray(a["location"], np.float64).reshape(-1, 3),
                np.asarray(a["rotation_y"], np.float64)[:, None],
            ],
            axis=1,
        ).tolist()
        for name, row in zip(np.asarray(a["name"]).tolist(), num):
            if name == "DontCare":
                lines.append(_DC_LINE % tuple(row[3:7]))
            else:
                lines.append(_GT_LINE % (name, row[0], int(row[1]), *row[2:]))
        (out / f"{info['image']['image_idx']}.txt").write_text("".join(s + "\n" for s in lines))


def write_result_dir(directory: str | Path, results: Sequence[dict[str, Any]]) -> None:
    """OpenPCDet's ``--save_to_file`` txt: one ``<frame_id>.txt`` per frame (empty without detections)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    for r in results:
        num = np.concatenate(
            [
                np.asarray(r["alpha"], np.float64)[:, None],
                np.asarray(r["bbox"], np.float64).reshape(-1, 4),
                np.asarray(r["dimensions"], np.float64).reshape(-1, 3)[:, [1, 2, 0]],
                np.asarray(r["location"], np.float64).reshape(-1, 3),
                np.asarray(r["rotation_y"], np.float64)[:, None],
                np.asarray(r["score"], np.float64)[:, None],
            ],
            axis=1,
        ).tolist()
        names = np.asarray(r["name"]).tolist() if len(num) else []
        text = "".join(_DET_LINE % (name, *row) + "\n" for name, row in zip(names, num))
        (out / f"{r['frame_id']}.txt").write_text(text)


# ---------------------------------------------------------------------------------------- command line


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m kitti_eval.synth", description="Write a synthetic KITTI validation set."
    )
    parser.add_argument("--frames", type=int, default=3769)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dets-per-frame", type=float, default=10.0)
    parser.add_argument("--gt-per-frame", type=float, default=6.5)
    parser.add_argument("--dontcare-per-frame", type=float, default=1.5)
    parser.add_argument(
        "--detector-seed",
        type=int,
        help="the detections' own seed: the same ground truth (--seed) with another draw of the same detector",
    )
    parser.add_argument(
        "--location-noise",
        type=float,
        default=0.0,
        metavar="METRES",
        help="a further error of each found object's ground-plane position: a less precise detector",
    )
    parser.add_argument("--out", type=Path, help="output folder")
    parser.add_argument("--txt", action="store_true", help="also write label_2/ and pred/ txt folders")
    parser.add_argument("--gzip", action="store_true", help="write kitti_infos_val.pkl.gz and result.pkl.gz")
    parser.add_argument(
        "--demo", action="store_true", help="(re)write the bundled demo files (kitti_eval/data/demo); ignores the rest"
    )
    args = parser.parse_args(argv)
    if args.frames < 0:
        parser.error("--frames must be >= 0")
    if args.out is None and not args.demo:
        parser.error("the following arguments are required: --out")
    t0 = time.perf_counter()
    if args.demo:
        infos, results = generate(**DEMO_ARGS)
        gt_path, pred_path = demo_paths()
        write_results(demo_weaker_path(), generate(**DEMO_WEAKER_ARGS)[1])  # the weaker model's, same ground truth
    else:
        infos, results = generate(
            args.frames,
            args.seed,
            dets_per_frame=args.dets_per_frame,
            gt_per_frame=args.gt_per_frame,
            dontcare_per_frame=args.dontcare_per_frame,
            detector_seed=args.detector_seed,
            location_noise=args.location_noise,
        )
        ext = ".pkl.gz" if args.gzip else ".pkl"
        gt_path, pred_path = args.out / f"kitti_infos_val{ext}", args.out / f"result{ext}"
    write_infos(gt_path, infos)
    write_results(pred_path, results)
    if args.txt and not args.demo:
        write_label_dir(args.out / "label_2", infos)
        write_result_dir(args.out / "pred", results)
    n_gt = sum(len(i["annos"]["name"]) for i in infos)
    n_dc = sum(int(np.sum(i["annos"]["index"] < 0)) for i in infos)
    n_det = sum(len(r["name"]) for r in results)
    sys.stderr.write(
        f"synth: {len(infos)} frames, {n_gt - n_dc} objects + {n_dc} DontCare, "
        f"{n_det} detections -> {gt_path.parent} ({time.perf_counter() - t0:.1f} s)\n"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
