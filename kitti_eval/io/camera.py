"""Detections' LiDAR boxes at load time: converted to camera fields with each frame's calibration (taken from
the ground-truth infos) where a frame has no camera fields, and checked against them where it has both."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from ..core.frames import normalize_frame_id, shown_frame_id
from ..errors import InputError
from .calib import calib_from_info, disagreeing_boxes, lidar_to_camera
from .formats import mmdet3d
from .formats._common import Frames
from .formats.openpcdet import entry_frame_id

__all__ = ["calibs_from_object", "camera_fields", "check_agreement"]

_CAMERA_FIELDS = ("location", "dimensions", "rotation_y")
_CAMERA_SET = frozenset(_CAMERA_FIELDS)


class _LazyCalibs(Mapping[str, Any]):
    """{frame id: :class:`kitti_eval.io.calib.Calib`}, each worked out from its entry when first asked for (the
    loader asks for a few frames: those with LiDAR boxes only, and every tenth one to compare both); a
    frame whose calibration cannot be read is missing."""

    def __init__(self, entries: dict[str, Any], build: Callable[[Any], Any]) -> None:
        self._entries, self._build, self._done = entries, build, dict[str, Any]()

    def __getitem__(self, frame_id: str) -> Any:
        if frame_id not in self._done:
            try:
                self._done[frame_id] = self._build(self._entries[frame_id])
            except (TypeError, ValueError, IndexError, AttributeError, InputError) as e:
                raise KeyError(frame_id) from e
        return self._done[frame_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


def calibs_from_object(obj: object) -> Mapping[str, Any]:
    """{frame id: :class:`kitti_eval.io.calib.Calib`} from ground-truth infos (OpenPCDet list, PointPillars
    dict, mmdetection3d 1.x), each read when first used; empty when the object has no calibration. Never
    raises (a frame whose calibration cannot be read is missing)."""
    entries: dict[str, Any] = {}
    try:
        if isinstance(obj, Mapping) and "data_list" in obj:
            for entry in obj["data_list"]:
                if isinstance(entry, Mapping) and "images" in entry:
                    entries[normalize_frame_id(entry["sample_idx"])] = entry
            return _LazyCalibs(entries, mmdet3d.calib)
        items = (
            obj.items()
            if isinstance(obj, Mapping)
            else ((None, e) for e in obj)
            if isinstance(obj, (list, tuple))
            else ()
        )
        for i, (key, info) in enumerate(items):
            if isinstance(info, Mapping) and "calib" in info:
                entries[normalize_frame_id(key if key is not None else entry_frame_id(info, i, ""))] = info
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, InputError):
        return {}
    return _LazyCalibs(entries, calib_from_info)


#: camera/LiDAR agreement is checked on every so many frames that carry both
_CHECK_EVERY = 10


def _numeric_boxes(lidar: Any, location: Any, rotation_y: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(location, rotation_y, boxes_lidar) as float64 when they are numbers of the shapes (N, 3), (N,) and
    (N, 7) with N > 0; None otherwise (from_frames then names what is wrong)."""
    arrays = [np.asarray(v) for v in (location, rotation_y, lidar)]
    if any(a.dtype.kind not in "iuf" for a in arrays):
        return None
    loc, ry, box = arrays
    n = len(box) if box.ndim else 0
    if n == 0 or loc.shape != (n, 3) or ry.shape != (n,) or box.shape != (n, 7):
        return None
    return loc.astype(np.float64), ry.astype(np.float64), box.astype(np.float64)


def camera_fields(frames: Frames, calibs: Mapping[str, Any] | None, source: str, warnings: list[str]) -> Frames:
    """Detections: LiDAR-only frames converted to camera fields; frames with both checked for agreement (a
    disagreement is appended to ``warnings``, the list of the read that called it)."""
    # frames with both camera fields and LiDAR boxes: every CHECK_EVERY-th is collected, then checked in
    # one vectorised call (a broken conversion shows in any sample; checking all costs ~0.1 s on KITTI val)
    both: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    seen_both = 0
    for fid, fields in frames:
        if (type(fields) is not dict and not isinstance(fields, Mapping)) or "boxes_lidar" not in fields:
            yield fid, fields
            continue
        has_camera = fields.keys() >= _CAMERA_SET
        if has_camera:
            seen_both += 1
        calib = None
        if calibs and (not has_camera or (seen_both - 1) % _CHECK_EVERY == 0):  # only where it is used
            try:
                calib = calibs.get(normalize_frame_id(fid))
            except (TypeError, ValueError):
                calib = None
        lidar = fields["boxes_lidar"]
        if has_camera:
            if calib is not None:
                sample = _numeric_boxes(lidar, fields["location"], fields["rotation_y"])
                if sample is not None:
                    both.append((*sample, calib.velo_to_rect))
            yield fid, fields
            continue
        if any(k in fields for k in _CAMERA_FIELDS):
            yield fid, fields  # partial camera fields: from_frames names what is missing
            continue
        arr = np.asarray(lidar)
        if arr.dtype.kind not in "iuf" and arr.size:
            raise InputError(
                f"expected numbers, got dtype {arr.dtype}",
                source=source,
                frame=shown_frame_id(fid),
                field="boxes_lidar",
            )
        if arr.size == 0:
            arr = np.zeros((0, 7))
        if arr.ndim != 2 or arr.shape[1] != 7:
            raise InputError(
                f"expected shape (N, 7), got {arr.shape}", source=source, frame=shown_frame_id(fid), field="boxes_lidar"
            )
        if calib is None:
            raise InputError(
                "LiDAR-only boxes (boxes_lidar without location/dimensions/rotation_y) need the "
                "frame's calibration: pass OpenPCDet (or mmdetection3d) infos as the ground truth",
                source=source,
                frame=shown_frame_id(fid),
                field="boxes_lidar",
            )
        out = dict(fields)
        conv = lidar_to_camera(arr, calib)
        out.update(conv)
        if "alpha" in fields and np.size(fields["alpha"]) == len(arr):
            out["alpha"] = fields["alpha"]
        yield fid, out
    _agreement(both, source, warnings)


def check_agreement(
    location: np.ndarray,
    rotation_y: np.ndarray,
    lidar: np.ndarray,
    offsets: np.ndarray,
    frame_ids: tuple[str, ...],
    calibs: Mapping[str, Any] | None,
    source: str,
    warnings: list[str],
) -> None:
    """:func:`camera_fields`' check of detections whose every frame carries both the camera fields and
    ``boxes_lidar``, over their columns (float64, frame after frame; ``frame_ids`` normalised): the same frames
    sampled (every tenth), the same warning."""
    if not calibs:
        return
    both: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for i in range(0, len(frame_ids), _CHECK_EVERY):
        lo, hi = int(offsets[i]), int(offsets[i + 1])
        calib = calibs.get(frame_ids[i])
        if calib is not None and hi > lo:
            both.append((location[lo:hi], rotation_y[lo:hi], lidar[lo:hi], calib.velo_to_rect))
    _agreement(both, source, warnings)


def _agreement(
    both: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], source: str, warnings: list[str]
) -> None:
    """Check the sampled frames' camera fields against their ``boxes_lidar``: a warning when over 1% of the boxes
    disagree."""
    if not both:
        return
    counts = [len(b[2]) for b in both]
    flags = disagreeing_boxes(
        np.concatenate([b[0] for b in both]),
        np.concatenate([b[1] for b in both]),
        np.concatenate([b[2] for b in both]),
        np.repeat(np.stack([b[3] for b in both]), counts, axis=0),
    )
    checked, bad = len(flags), int(np.count_nonzero(flags))
    bad_frames = int(np.count_nonzero(np.add.reduceat(flags, np.cumsum([0, *counts[:-1]])))) if checked else 0
    if bad > 0.01 * checked:
        warnings.append(
            f"{source}: camera fields and boxes_lidar disagree (location > 0.1 m or yaw > 0.1 rad) "
            f"for {bad} of {checked} boxes checked (every {_CHECK_EVERY}th frame) in {bad_frames} "
            "frames; the camera fields are evaluated"
        )
