"""Overlap of KITTI boxes: 2D image IoU, bird's-eye-view (BEV) rotated-rectangle IoU and 3D IoU, in float64.

Coordinate frame: KITTI rectified camera (x right, y down, z forward). A camera box is a row of seven numbers
``x, y, z, l, h, w, ry``: ``(x, y, z)`` is the **bottom** centre (the box spans ``y - h`` .. ``y``
vertically), ``l, h, w`` are length, height and width in metres and ``ry`` is the yaw about the camera y
axis. In bird's-eye view a box is the rectangle of the (x, z) plane centred at ``(x, z)`` whose length axis
is ``(cos ry, -sin ry)`` and width axis ``(sin ry, cos ry)``, with sides ``|l|`` and ``|w|`` (a KITTI
DontCare line carries ``l = h = w = -1``). An image box is a row ``x1, y1, x2, y2`` in pixels.

Two criteria: ``"union"`` is intersection over union; ``"first"`` is intersection over the size of the
*first* box (the fraction of ``a`` covered by ``b``), which is how a detection is scored against a DontCare
region. A zero denominator gives 0, never NaN.

The BEV intersection is exact polygon clipping (Sutherland-Hodgman with inclusive side tests) done in the
frame of the smaller rectangle, where that rectangle is axis-aligned and its corners are exact; so
identical boxes give a BEV IoU of exactly 1 (3D: 1 to an ulp), boxes that share an edge or touch give 0 (to
rounding), and the precision of a tiny box does not depend on how far it is from the camera. The result is
bitwise symmetric: ``iou_bev(a, b) == iou_bev(b, a).T``. Intersections are clamped to the geometric bounds
(an intersection area or height is never larger than either box's), so no overlap exceeds 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .arrays import kernel_input
from .kernel_cache import njit

__all__ = ["FrameOverlaps", "iou_2d", "iou_bev", "iou_3d", "frame_overlaps"]

_CRITERIA = ("union", "first")


# --------------------------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True)
def _overlap_2d(ax1, ay1, ax2, ay2, bx1, by1, bx2, by2, first):  # pragma: no cover - compiled
    """KITTI devkit ``boxoverlap``, in its arithmetic order (bit-for-bit)."""
    iw = min(ax2, bx2) - max(ax1, bx1)
    ih = min(ay2, by2) - max(ay1, by1)
    if iw <= 0.0 or ih <= 0.0:
        return 0.0
    inter = iw * ih
    area_a = (ax2 - ax1) * (ay2 - ay1)
    if first:
        denom = area_a
    else:
        area_b = (bx2 - bx1) * (by2 - by1)
        denom = area_a + area_b - inter
    if denom > 0.0:
        return inter / denom
    return 0.0


@njit(cache=True, nogil=True)
def _iou_2d_kernel(a, b, first):  # pragma: no cover - compiled
    n = a.shape[0]
    m = b.shape[0]
    out = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            out[i, j] = _overlap_2d(a[i, 0], a[i, 1], a[i, 2], a[i, 3], b[j, 0], b[j, 1], b[j, 2], b[j, 3], first)
    return out


@njit(cache=True, nogil=True)
def _clip_half_plane(px, pz, n, qx, qz, sign, bound):  # pragma: no cover - compiled
    """Clip polygon ``(px, pz)[:n]`` to ``sign * x <= bound`` into ``(qx, qz)``; return the vertex count.

    Inclusive: a vertex on the line is kept, and a crossing point is added only where the signed distance
    changes sign strictly, so no division can be by zero and points on the line are never duplicated.
    A crossing point gets its x set exactly on the line. (Called with x and z swapped for the z sides.)
    Output has at most 2 n vertices.
    """
    if n == 0:
        return 0
    m = 0
    prev_x = px[n - 1]
    prev_z = pz[n - 1]
    prev_d = bound - sign * prev_x
    on_line = sign * bound
    for k in range(n):
        cur_x = px[k]
        cur_z = pz[k]
        cur_d = bound - sign * cur_x
        if (prev_d > 0.0 and cur_d < 0.0) or (prev_d < 0.0 and cur_d > 0.0):
            t = prev_d / (prev_d - cur_d)
            qx[m] = on_line
            qz[m] = prev_z + t * (cur_z - prev_z)
            m += 1
        if cur_d >= 0.0:
            qx[m] = cur_x
            qz[m] = cur_z
            m += 1
        prev_x = cur_x
        prev_z = cur_z
        prev_d = cur_d
    return m


@njit(cache=True, nogil=True)
def _polygon_area(px, pz, n):  # pragma: no cover - compiled
    """Shoelace area (absolute) of ``(px, pz)[:n]``, taken relative to the first vertex."""
    if n < 3:
        return 0.0
    x0 = px[0]
    z0 = pz[0]
    s = 0.0
    for k in range(1, n - 1):
        s += (px[k] - x0) * (pz[k + 1] - z0) - (px[k + 1] - x0) * (pz[k] - z0)
    return 0.5 * abs(s)


@njit(cache=True, nogil=True)
def _rect_inter_local(xp, zp, lp, wp, rp, xq, zq, lq, wq, rq, buf):  # pragma: no cover - compiled
    """Intersection area of rectangles P and Q, clipped in P's frame (P axis-aligned at the origin).

    ``buf`` is a (4, 64) scratch array.
    """
    cp = np.cos(rp)
    sp = np.sin(rp)
    dx = xq - xp
    dz = zq - zp
    # Q's centre in P's (length, width) axes
    cx = dx * cp - dz * sp
    cz = dx * sp + dz * cp
    theta = rq - rp
    ct = np.cos(theta)
    st = np.sin(theta)
    hlq = 0.5 * abs(lq)
    hwq = 0.5 * abs(wq)
    ex = hlq * ct
    ez = -hlq * st
    fx = hwq * st
    fz = hwq * ct
    ax = buf[0]
    az = buf[1]
    bx = buf[2]
    bz = buf[3]
    # counter-clockwise in the (x, z) plane
    ax[0] = cx + ex + fx
    az[0] = cz + ez + fz
    ax[1] = cx - ex + fx
    az[1] = cz - ez + fz
    ax[2] = cx - ex - fx
    az[2] = cz - ez - fz
    ax[3] = cx + ex - fx
    az[3] = cz + ez - fz
    hlp = 0.5 * abs(lp)
    hwp = 0.5 * abs(wp)
    n = _clip_half_plane(ax, az, np.int64(4), bx, bz, 1.0, hlp)  # int64, not a literal: one compiled version
    n = _clip_half_plane(bx, bz, n, ax, az, -1.0, hlp)
    n = _clip_half_plane(az, ax, n, bz, bx, 1.0, hwp)
    n = _clip_half_plane(bz, bx, n, az, ax, -1.0, hwp)
    return _polygon_area(ax, az, n)


@njit(cache=True, nogil=True)
def _bev_inter(xa, za, la, wa, ra, area_a, rad_a, xb, zb, lb, wb, rb, area_b, rad_b, buf):  # pragma: no cover
    """BEV intersection area of boxes a and b, clamped to [0, min(area_a, area_b)].

    ``area`` is ``|l| * |w|`` and ``rad`` the bounding-circle radius ``0.5 * hypot(l, w)`` of each box.
    """
    if area_a <= 0.0 or area_b <= 0.0:
        return 0.0
    dx = xb - xa
    dz = zb - za
    reach = (rad_a + rad_b) * (1.0 + 1e-9)
    if dx * dx + dz * dz > reach * reach:
        return 0.0
    # clip in the frame of the smaller box (ties broken on the box values, so the result is symmetric)
    a_is_frame = area_a < area_b
    if area_a == area_b:
        if xa != xb:
            a_is_frame = xa < xb
        elif za != zb:
            a_is_frame = za < zb
        elif ra != rb:
            a_is_frame = ra < rb
        else:
            a_is_frame = abs(la) <= abs(lb)
    if a_is_frame:
        inter = _rect_inter_local(xa, za, la, wa, ra, xb, zb, lb, wb, rb, buf)
    else:
        inter = _rect_inter_local(xb, zb, lb, wb, rb, xa, za, la, wa, ra, buf)
    return min(inter, area_a, area_b)


@njit(cache=True, nogil=True)
def _box_stats(boxes):  # pragma: no cover - compiled
    """Per box: BEV area ``|l| |w|``, bounding-circle radius, volume ``|l| |w| max(h, 0)``."""
    n = boxes.shape[0]
    area = np.empty(n)
    rad = np.empty(n)
    vol = np.empty(n)
    for i in range(n):
        l_ = abs(boxes[i, 3])
        w_ = abs(boxes[i, 5])
        area[i] = l_ * w_
        rad[i] = 0.5 * np.sqrt(l_ * l_ + w_ * w_)
        vol[i] = l_ * w_ * max(boxes[i, 4], 0.0)
    return area, rad, vol


@njit(cache=True, nogil=True)
def _height_overlap(ya, ha, yb, hb):  # pragma: no cover - compiled
    """Overlap of the vertical spans ``[y - h, y]``, clamped to [0, min(max(h_a, 0), max(h_b, 0))]."""
    ov = min(ya, yb) - max(ya - ha, yb - hb)
    return max(0.0, min(ov, ha, hb))


@njit(cache=True, nogil=True)
def _ratio(inter, size_a, size_b, first):  # pragma: no cover - compiled
    if first:
        denom = size_a
    else:
        denom = size_a + size_b - inter
    if denom > 0.0:
        return inter / denom
    return 0.0


@njit(cache=True, nogil=True)
def _iou_rot_kernel(a, b, first, three_d):  # pragma: no cover - compiled
    n = a.shape[0]
    m = b.shape[0]
    out = np.zeros((n, m))
    area_a, rad_a, vol_a = _box_stats(a)
    area_b, rad_b, vol_b = _box_stats(b)
    buf = np.empty((4, 64))
    for i in range(n):
        for j in range(m):
            if three_d:
                dy = _height_overlap(a[i, 1], a[i, 4], b[j, 1], b[j, 4])
                if dy <= 0.0:
                    continue
            inter = _bev_inter(
                a[i, 0],
                a[i, 2],
                a[i, 3],
                a[i, 5],
                a[i, 6],
                area_a[i],
                rad_a[i],
                b[j, 0],
                b[j, 2],
                b[j, 3],
                b[j, 5],
                b[j, 6],
                area_b[j],
                rad_b[j],
                buf,
            )
            if inter <= 0.0:
                continue
            if three_d:
                out[i, j] = _ratio(inter * dy, vol_a[i], vol_b[j], first)
            else:
                out[i, j] = _ratio(inter, area_a[i], area_b[j], first)
    return out


@njit(cache=True, nogil=True)
def _frame_overlaps_kernel(
    dt_bbox, dt_boxes, dt_off, gt_bbox, gt_boxes, gt_off, gt_first, pair_off
):  # pragma: no cover - compiled
    n_pairs = pair_off[pair_off.shape[0] - 1]
    out_bbox = np.zeros(n_pairs)
    out_bev = np.zeros(n_pairs)
    out_3d = np.zeros(n_pairs)
    area_d, rad_d, vol_d = _box_stats(dt_boxes)
    area_g, rad_g, vol_g = _box_stats(gt_boxes)
    buf = np.empty((4, 64))
    for f in range(dt_off.shape[0] - 1):
        d0 = dt_off[f]
        d1 = dt_off[f + 1]
        g0 = gt_off[f]
        g1 = gt_off[f + 1]
        n_gt = g1 - g0
        for j in range(d0, d1):
            base = pair_off[f] + (j - d0) * n_gt - g0
            dx1 = dt_bbox[j, 0]
            dy1 = dt_bbox[j, 1]
            dx2 = dt_bbox[j, 2]
            dy2 = dt_bbox[j, 3]
            xd = dt_boxes[j, 0]
            zd = dt_boxes[j, 2]
            rd = rad_d[j]
            for i in range(g0, g1):
                k = base + i
                first = gt_first[i]
                # 2D: the devkit's arithmetic; the cheap rejection is inlined here
                if (
                    min(dx2, gt_bbox[i, 2]) - max(dx1, gt_bbox[i, 0]) > 0.0
                    and min(dy2, gt_bbox[i, 3]) - max(dy1, gt_bbox[i, 1]) > 0.0
                ):
                    out_bbox[k] = _overlap_2d(
                        dx1, dy1, dx2, dy2, gt_bbox[i, 0], gt_bbox[i, 1], gt_bbox[i, 2], gt_bbox[i, 3], first
                    )
                # BEV and 3D share one intersection; pairs whose bounding circles miss are 0
                ex = gt_boxes[i, 0] - xd
                ez = gt_boxes[i, 2] - zd
                reach = (rd + rad_g[i]) * (1.0 + 1e-9)
                if ex * ex + ez * ez > reach * reach:
                    continue
                inter = _bev_inter(
                    xd,
                    zd,
                    dt_boxes[j, 3],
                    dt_boxes[j, 5],
                    dt_boxes[j, 6],
                    area_d[j],
                    rd,
                    gt_boxes[i, 0],
                    gt_boxes[i, 2],
                    gt_boxes[i, 3],
                    gt_boxes[i, 5],
                    gt_boxes[i, 6],
                    area_g[i],
                    rad_g[i],
                    buf,
                )
                if inter <= 0.0:
                    continue
                out_bev[k] = _ratio(inter, area_d[j], area_g[i], first)
                dy = _height_overlap(dt_boxes[j, 1], dt_boxes[j, 4], gt_boxes[i, 1], gt_boxes[i, 4])
                if dy > 0.0:
                    out_3d[k] = _ratio(inter * dy, vol_d[j], vol_g[i], first)
    return out_bbox, out_bev, out_3d


# ------------------------------------------------------------------------------------------ validation


def _as_rows(value: object, name: str, width: int) -> npt.NDArray[np.float64]:
    """``value`` as a C-contiguous float64 (N, width) array (an empty array of any shape is (0, width))."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"Expected `{name}` to hold numbers, got dtype {arr.dtype}")
    if arr.size == 0 and arr.ndim == 1:
        arr = arr.reshape(0, width)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(f"Expected `{name}` with shape (N, {width}), got {arr.shape}")
    out = kernel_input(arr, np.float64)
    if not np.isfinite(out).all():
        row = int(np.argwhere(~np.isfinite(out))[0][0])
        raise ValueError(f"Expected finite values in `{name}`, got {out[row].tolist()} in row {row}")
    return out


def _criterion(criterion: str) -> bool:
    if criterion not in _CRITERIA:
        raise ValueError(f"Expected `criterion` to be one of {list(_CRITERIA)}, got {criterion!r}")
    return criterion == "first"


def _offsets(value: object, name: str, n_rows: int, n_rows_name: str) -> npt.NDArray[np.int64]:
    arr = np.asarray(value)
    if arr.ndim != 1 or arr.shape[0] < 1:
        raise ValueError(f"Expected `{name}` with shape (F + 1,), got {arr.shape}")
    if arr.dtype.kind not in "iu":
        raise ValueError(f"Expected `{name}` to hold integers, got dtype {arr.dtype}")
    out = kernel_input(arr, np.int64)
    if out[0] != 0:
        raise ValueError(f"Expected `{name}` to start at 0, got {int(out[0])}")
    steps = np.diff(out)
    if (steps < 0).any():
        f = int(np.argmax(steps < 0))
        raise ValueError(
            f"Expected `{name}` to be non-decreasing, got {int(out[f])} then {int(out[f + 1])} at frame {f}"
        )
    if out[-1] != n_rows:
        raise ValueError(f"Expected `{name}` to end at the {n_rows} rows of `{n_rows_name}`, got {int(out[-1])}")
    return out


# -------------------------------------------------------------------------------------------- public API


def iou_2d(a: npt.ArrayLike, b: npt.ArrayLike, criterion: str = "union") -> npt.NDArray[np.float64]:
    """Overlap of image boxes, computed exactly like the KITTI devkit's ``boxoverlap``.

    Parameters
    ----------
    a : (N, 4) array_like
        Image boxes ``x1, y1, x2, y2`` (pixels).
    b : (M, 4) array_like
        Image boxes ``x1, y1, x2, y2`` (pixels).
    criterion : {"union", "first"}
        ``"union"``: intersection / (area_a + area_b - intersection); ``"first"``: intersection / area_a.

    Returns
    -------
    (N, M) float64
        Overlap of ``a[i]`` and ``b[j]``; 0 where the boxes do not overlap with positive width and height.
        Bit-for-bit the devkit's double arithmetic (``iw = min(x2) - max(x1)``, ``ih`` likewise,
        ``inter = iw * ih``, areas as ``(x2 - x1) * (y2 - y1)``).
    """
    first = _criterion(criterion)
    a_ = _as_rows(a, "a", 4)
    b_ = _as_rows(b, "b", 4)
    return _iou_2d_kernel(a_, b_, first)


def iou_bev(a: npt.ArrayLike, b: npt.ArrayLike, criterion: str = "union") -> npt.NDArray[np.float64]:
    """Bird's-eye-view overlap of camera boxes: exact intersection of rotated rectangles in the (x, z) plane.

    Parameters
    ----------
    a : (N, 7) array_like
        Camera boxes ``x, y, z, l, h, w, ry`` (KITTI rectified camera frame; bottom centre; metres).
    b : (M, 7) array_like
        Camera boxes, as ``a``.
    criterion : {"union", "first"}
        ``"union"``: inter / (area_a + area_b - inter); ``"first"``: inter / area_a, with
        ``area = |l| * |w|``.

    Returns
    -------
    (N, M) float64
        Overlap of ``a[i]`` and ``b[j]`` in [0, 1]; 0 where a denominator is 0.
    """
    first = _criterion(criterion)
    a_ = _as_rows(a, "a", 7)
    b_ = _as_rows(b, "b", 7)
    return _iou_rot_kernel(a_, b_, first, False)


def iou_3d(a: npt.ArrayLike, b: npt.ArrayLike, criterion: str = "union") -> npt.NDArray[np.float64]:
    """3D overlap of camera boxes: BEV intersection times the overlap of the vertical spans ``[y - h, y]``.

    Parameters
    ----------
    a : (N, 7) array_like
        Camera boxes ``x, y, z, l, h, w, ry`` (KITTI rectified camera frame, y down; ``(x, y, z)`` is the
        bottom centre, so a box spans ``y - h`` .. ``y``; metres).
    b : (M, 7) array_like
        Camera boxes, as ``a``.
    criterion : {"union", "first"}
        ``"union"``: inter_vol / (vol_a + vol_b - inter_vol); ``"first"``: inter_vol / vol_a, with
        ``vol = |l| * |w| * max(h, 0)`` and
        ``inter_vol = bev_inter * max(0, min(y_a, y_b) - max(y_a - h_a, y_b - h_b))``.

    Returns
    -------
    (N, M) float64
        Overlap of ``a[i]`` and ``b[j]`` in [0, 1]; 0 where a denominator is 0.
    """
    first = _criterion(criterion)
    a_ = _as_rows(a, "a", 7)
    b_ = _as_rows(b, "b", 7)
    return _iou_rot_kernel(a_, b_, first, True)


@dataclass(frozen=True, eq=False)
class FrameOverlaps:
    """Overlaps of every (detection, ground truth) pair within each frame, flat.

    Frame ``f`` with ``n_dt_f`` detections and ``n_gt_f`` ground-truth boxes owns the row-major
    ``(n_dt_f, n_gt_f)`` block ``values[pair_offsets[f]:pair_offsets[f + 1]]``: the pair (detection ``j``,
    ground truth ``i``), both counted from the start of the frame, is at
    ``pair_offsets[f] + j * n_gt_f + i``.

    Attributes
    ----------
    pair_offsets : (F + 1,) int64
    bbox : (P,) float64
        2D image-box overlap (devkit arithmetic).
    bev : (P,) float64
        Bird's-eye-view overlap.
    d3 : (P,) float64
        3D overlap.

    Each value is the IoU, except for ground truth flagged ``gt_first`` (DontCare regions) where it is the
    intersection over the detection's area (volume for 3D).
    """

    pair_offsets: npt.NDArray[np.int64]
    bbox: npt.NDArray[np.float64]
    bev: npt.NDArray[np.float64]
    d3: npt.NDArray[np.float64]


def frame_overlaps(
    dt_bbox: npt.ArrayLike,
    dt_boxes: npt.ArrayLike,
    dt_offsets: npt.ArrayLike,
    gt_bbox: npt.ArrayLike,
    gt_boxes: npt.ArrayLike,
    gt_offsets: npt.ArrayLike,
    gt_first: npt.ArrayLike,
) -> FrameOverlaps:
    """2D, BEV and 3D overlaps of all detection/ground-truth pairs of the same frame, for ``F`` frames.

    Parameters
    ----------
    dt_bbox : (N, 4) array_like
        Detections' image boxes ``x1, y1, x2, y2`` (pixels).
    dt_boxes : (N, 7) array_like
        Detections' camera boxes ``x, y, z, l, h, w, ry`` (KITTI rectified camera frame, bottom centre).
    dt_offsets : (F + 1,) integer array_like
        CSR offsets: frame ``f`` owns detections ``dt_offsets[f]:dt_offsets[f + 1]``.
    gt_bbox : (M, 4) array_like
        Ground truth's image boxes.
    gt_boxes : (M, 7) array_like
        Ground truth's camera boxes.
    gt_offsets : (F + 1,) integer array_like
        CSR offsets of the ground truth, same frames as ``dt_offsets``.
    gt_first : (M,) bool array_like
        True where a ground-truth box is scored with the ``"first"`` criterion (intersection over the
        detection's area or volume): DontCare regions.

    Returns
    -------
    FrameOverlaps
        ``pair_offsets`` (F + 1,) and ``bbox``, ``bev``, ``d3`` (P,) float64, with
        ``P = sum_f n_dt_f * n_gt_f``; see :class:`FrameOverlaps` for the layout.
    """
    dt_bbox_ = _as_rows(dt_bbox, "dt_bbox", 4)
    dt_boxes_ = _as_rows(dt_boxes, "dt_boxes", 7)
    gt_bbox_ = _as_rows(gt_bbox, "gt_bbox", 4)
    gt_boxes_ = _as_rows(gt_boxes, "gt_boxes", 7)
    if dt_bbox_.shape[0] != dt_boxes_.shape[0]:
        raise ValueError(
            f"Expected `dt_bbox` and `dt_boxes` with the same number of rows, got "
            f"{dt_bbox_.shape[0]} and {dt_boxes_.shape[0]}"
        )
    if gt_bbox_.shape[0] != gt_boxes_.shape[0]:
        raise ValueError(
            f"Expected `gt_bbox` and `gt_boxes` with the same number of rows, got "
            f"{gt_bbox_.shape[0]} and {gt_boxes_.shape[0]}"
        )
    first = np.asarray(gt_first)
    if first.size == 0 and first.ndim == 1:
        first = first.astype(np.bool_)
    if first.dtype != np.bool_:
        raise ValueError(f"Expected `gt_first` to be boolean, got dtype {first.dtype}")
    if first.shape != (gt_boxes_.shape[0],):
        raise ValueError(f"Expected `gt_first` with shape ({gt_boxes_.shape[0]},), got {first.shape}")
    first = kernel_input(first, np.bool_)
    dt_off = _offsets(dt_offsets, "dt_offsets", dt_boxes_.shape[0], "dt_boxes")
    gt_off = _offsets(gt_offsets, "gt_offsets", gt_boxes_.shape[0], "gt_boxes")
    if dt_off.shape != gt_off.shape:
        raise ValueError(
            f"Expected `dt_offsets` and `gt_offsets` with the same shape (F + 1,), got "
            f"{dt_off.shape} and {gt_off.shape}"
        )
    pair_off = np.zeros(dt_off.shape[0], dtype=np.int64)
    np.cumsum(np.diff(dt_off) * np.diff(gt_off), out=pair_off[1:])
    bbox, bev, d3 = _frame_overlaps_kernel(dt_bbox_, dt_boxes_, dt_off, gt_bbox_, gt_boxes_, gt_off, first, pair_off)
    return FrameOverlaps(pair_offsets=pair_off, bbox=bbox, bev=bev, d3=d3)
