"""LiDAR boxes (OpenPCDet convention) to KITTI camera boxes and back, with one frame's calibration (numpy).

OpenPCDet ``boxes_lidar`` rows are ``x, y, z, dx, dy, dz, heading``: the geometric centre in the Velodyne
frame, ``dx`` = l, ``dy`` = w, ``dz`` = h, heading about z. The camera box is the bottom centre
``R0_rect @ Tr_velo_to_cam @ [x, y, z - h/2, 1]``, dimensions ``(l, h, w)``, ``ry = -heading - pi/2``
(wrapped to [-pi, pi]), ``alpha = ry - arctan2(x_cam, z_cam)``, and the 2D box is the projection of the
eight corners through ``P2``, clipped to ``[0, W-1] x [0, H-1]`` (what OpenPCDet writes).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "Calib",
    "calib_from_info",
    "lidar_to_camera",
    "camera_lidar_disagreement",
    "disagreeing_boxes",
    "wrap_angle",
    "rect_to_velo",
    "camera_to_lidar",
]

F64 = npt.NDArray[np.float64]


def _as4x4(m: Any, what: str) -> F64:
    a = np.asarray(m, dtype=np.float64)
    if a.shape == (4, 4):
        return a
    if a.shape in ((3, 3), (3, 4)):
        out = np.eye(4)
        out[: a.shape[0], : a.shape[1]] = a
        return out
    raise ValueError(f"{what} has shape {a.shape}, expected 3x3, 3x4 or 4x4")


@dataclass(frozen=True)
class Calib:
    """One frame's calibration: ``velo_to_rect`` = R0_rect @ Tr_velo_to_cam (4x4), ``P2`` (3x4), (H, W)."""

    velo_to_rect: F64
    p2: F64
    image_shape: tuple[int, int] | None


def calib_from_info(info: Mapping[str, Any]) -> Calib:
    """The calibration of an OpenPCDet info dict (``calib`` with P2, R0_rect, Tr_velo_to_cam; ``image``)."""
    c = info["calib"]
    r0 = _as4x4(c["R0_rect"], "R0_rect")
    tr = _as4x4(c["Tr_velo_to_cam"], "Tr_velo_to_cam")
    p2 = _as4x4(c["P2"], "P2")[:3]
    shape = None
    image = info.get("image")
    if isinstance(image, Mapping) and image.get("image_shape") is not None:
        hw = np.asarray(image["image_shape"]).reshape(-1)
        shape = (int(hw[0]), int(hw[1]))
    return Calib(r0 @ tr, p2, shape)


def wrap_angle(a: npt.ArrayLike) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def _project_corners(loc: F64, dims: F64, ry: F64, p2: F64) -> F64:
    """(N, 4) x1, y1, x2, y2 of the 8 corners of camera boxes projected through P2 (unclipped)."""
    sx = np.array([0.5, 0.5, -0.5, -0.5, 0.5, 0.5, -0.5, -0.5])
    sy = np.array([0.0, 0.0, 0.0, 0.0, -1.0, -1.0, -1.0, -1.0])
    sz = np.array([0.5, -0.5, -0.5, 0.5, 0.5, -0.5, -0.5, 0.5])
    c, s = np.cos(ry)[:, None], np.sin(ry)[:, None]
    ox, oz = sx[None] * dims[:, 0:1], sz[None] * dims[:, 2:3]
    x = loc[:, 0:1] + c * ox + s * oz
    y = loc[:, 1:2] + sy[None] * dims[:, 1:2]
    z = loc[:, 2:3] - s * ox + c * oz
    pts = np.stack([x, y, z, np.ones_like(x)], axis=-1)  # (N, 8, 4)
    img = pts @ p2.T  # (N, 8, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = img[..., :2] / img[..., 2:3]
    return np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1) if len(loc) else np.zeros((0, 4))


def lidar_to_camera(boxes_lidar: npt.ArrayLike, calib: Calib) -> dict[str, F64]:
    """Camera-frame fields (``location``, ``dimensions``, ``rotation_y``, ``alpha``, ``bbox``) of (N, 7)
    OpenPCDet LiDAR boxes, float64."""
    b = np.asarray(boxes_lidar, dtype=np.float64).reshape(-1, 7)
    pts = np.stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 5] / 2, np.ones(len(b))], axis=1)
    loc = (pts @ calib.velo_to_rect.T)[:, :3]
    dims = b[:, [3, 5, 4]]  # dx, dz, dy = l, h, w
    ry = wrap_angle(-b[:, 6] - np.pi / 2)
    alpha = ry - np.arctan2(loc[:, 0], loc[:, 2])
    bbox = _project_corners(loc, dims, ry, calib.p2)
    if calib.image_shape is not None:
        h, w = calib.image_shape
        bbox[:, [0, 2]] = np.clip(bbox[:, [0, 2]], 0, w - 1)
        bbox[:, [1, 3]] = np.clip(bbox[:, [1, 3]], 0, h - 1)
    return {"location": loc, "dimensions": dims, "rotation_y": ry, "alpha": alpha, "bbox": bbox}


def rect_to_velo(r0_rect: npt.ArrayLike, velo_to_cam: npt.ArrayLike) -> F64:
    """(4, 4) camera (rectified) -> LiDAR: the inverse of ``R0_rect @ Tr_velo_to_cam`` ((3, 3) and (3, 4)), in
    closed form.

    The rigid inverse ``[A^-1, -A^-1 t]`` (A^-1 by its adjugate, as A is only nearly orthonormal) is worked
    out on Python floats, one IEEE operation at a time in a fixed order, so every machine gets the same bits.
    ``np.linalg.inv`` and ``@`` go through LAPACK and BLAS kernels that differ by CPU (FMA, blocking) and
    change the last bit of some LiDAR boxes from one machine to another.
    """
    r0 = np.asarray(r0_rect, dtype=np.float64)[:3, :3].tolist()
    v = np.asarray(velo_to_cam, dtype=np.float64)[:3, :4].tolist()
    a = [[r0[i][0] * v[0][j] + r0[i][1] * v[1][j] + r0[i][2] * v[2][j] for j in range(3)] for i in range(3)]
    t = [r0[i][0] * v[0][3] + r0[i][1] * v[1][3] + r0[i][2] * v[2][3] for i in range(3)]
    cof = [
        [
            a[(j + 1) % 3][(i + 1) % 3] * a[(j + 2) % 3][(i + 2) % 3]
            - a[(j + 1) % 3][(i + 2) % 3] * a[(j + 2) % 3][(i + 1) % 3]
            for j in range(3)
        ]
        for i in range(3)
    ]
    det = a[0][0] * cof[0][0] + a[0][1] * cof[1][0] + a[0][2] * cof[2][0]
    inv = [[cof[i][j] / det for j in range(3)] for i in range(3)]
    out = np.eye(4)
    for i in range(3):
        out[i, :3] = inv[i]
        out[i, 3] = -(inv[i][0] * t[0] + inv[i][1] * t[1] + inv[i][2] * t[2])
    return out


def camera_to_lidar(location: F64, dimensions: F64, rotation_y: F64, rect_to_velo: F64) -> F64:
    """(N, 7) OpenPCDet LiDAR boxes (x, y, z of the geometric centre, l, w, h, heading = -(ry + pi/2)) of
    float64 camera boxes, with the (4, 4) camera -> LiDAR matrix of :func:`rect_to_velo`: the inverse of
    :func:`lidar_to_camera`."""
    m = rect_to_velo
    loc, dims = location, dimensions
    out = np.empty((len(loc), 7))
    for r in range(3):  # elementwise, not `loc @ m.T`: a BLAS call with 3 columns is slower, and threaded
        out[:, r] = m[r, 0] * loc[:, 0] + m[r, 1] * loc[:, 1] + m[r, 2] * loc[:, 2] + m[r, 3]
    out[:, 2] += dims[:, 1] / 2
    out[:, 3:6] = dims[:, [0, 2, 1]]
    out[:, 6] = -(rotation_y + np.pi / 2)
    return out


def disagreeing_boxes(
    location: npt.ArrayLike,
    rotation_y: npt.ArrayLike,
    boxes_lidar: npt.ArrayLike,
    velo_to_rect: npt.ArrayLike,
    *,
    max_distance: float = 0.1,
    max_yaw: float = 0.1,
) -> npt.NDArray[np.bool_]:
    """(N,) which boxes' camera fields and LiDAR box disagree (location by more than ``max_distance`` metres
    in any coordinate, or yaw by more than ``max_yaw`` radians); ``velo_to_rect`` is (4, 4) or one (N, 4, 4)
    per box, so a whole set is checked in one call."""
    b = np.asarray(boxes_lidar, dtype=np.float64).reshape(-1, 7)
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=np.float64).reshape(-1)
    m = np.asarray(velo_to_rect, dtype=np.float64)
    pts = np.stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 5] / 2, np.ones(len(b))], axis=1)
    conv = pts @ m.T if m.ndim == 2 else np.einsum("nij,nj->ni", m, pts)
    far = np.abs(loc - conv[:, :3]).max(axis=1, initial=0.0) > max_distance
    turned = np.abs(wrap_angle(ry - wrap_angle(-b[:, 6] - np.pi / 2))) > max_yaw
    return far | turned


def camera_lidar_disagreement(
    location: npt.ArrayLike,
    rotation_y: npt.ArrayLike,
    boxes_lidar: npt.ArrayLike,
    calib: Calib,
    *,
    max_distance: float = 0.1,
    max_yaw: float = 0.1,
) -> int:
    """How many boxes of one frame disagree (see :func:`disagreeing_boxes`)."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    if len(loc) != len(np.asarray(boxes_lidar).reshape(-1, 7)):
        return len(loc)
    return int(
        np.count_nonzero(
            disagreeing_boxes(
                loc, rotation_y, boxes_lidar, calib.velo_to_rect, max_distance=max_distance, max_yaw=max_yaw
            )
        )
    )
