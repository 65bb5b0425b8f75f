"""Read ground truth and detections: the library's public loading functions, over :mod:`kitti_eval.io.reading`.

Each function takes the options of :class:`~kitti_eval.io.reading.LoadOptions` as keywords (``fmt``,
``max_bytes``, ``max_frames``, ``calibs``, ``keep_lidar``, ``known_frames``). ``warnings``, where a function
takes it, is a list that the read's warnings are appended to; the functions of
:mod:`kitti_eval.io.reading` return them instead (:attr:`~kitti_eval.io.reading.Loaded.warnings`).
The formats themselves are in :mod:`kitti_eval.io.formats`, one module each.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import IO, Any

from ..core.frames import Annotations, Kind
from .archives import ArchiveLimits
from .camera import calibs_from_object
from .formats import FORMATS, PICKLE_FORMATS, describe_format, detect_format
from .formats.kitti_txt import (
    KITTI_TXT_FIELDS,
    extract_txt_archive,
    input_kind,
    is_archive,
    load_kitti_txt_dir,
    parse_kitti_txt,
)
from .limits import DEFAULT_MAX_FRAMES, DEFAULT_MAX_INPUT_MB, MAX_FRAMES_ENV, MAX_INPUT_ENV, input_limits
from .reading import (
    Loaded,
    LoadOptions,
    apply_split,
    read_annotations,
    read_ground_truth_and_calibs,
    read_object,
    read_pair,
    read_pickle,
    read_split,
)

__all__ = [
    "load_ground_truth",
    "load_detections",
    "load_annotations",
    "load_kitti_txt_dir",
    "parse_kitti_txt",
    "annotations_from_object",
    "annotations_from_pickle",
    "detect_format",
    "describe_format",
    "PICKLE_FORMATS",
    "KITTI_TXT_FIELDS",
    "FORMATS",
    "load_pair",
    "load_ground_truth_and_calibs",
    "read_split",
    "apply_split",
    "calibs_from_object",
    "extract_txt_archive",
    "is_archive",
    "input_kind",
    "input_limits",
    "ArchiveLimits",
    "LoadOptions",
    "MAX_INPUT_ENV",
    "MAX_FRAMES_ENV",
    "DEFAULT_MAX_INPUT_MB",
    "DEFAULT_MAX_FRAMES",
]

PathLike = str | os.PathLike[str]


def _told(loaded: Loaded, warnings: list[str] | None) -> Annotations:
    if warnings is not None:
        warnings.extend(loaded.warnings)
    return loaded.annotations


def load_ground_truth(path: PathLike, *, warnings: list[str] | None = None, **options: Any) -> Annotations:
    """Ground truth from a KITTI ``label_2``-style txt folder (or a zip/tar of one) or an infos/annos pickle."""
    return _told(read_annotations(path, "ground_truth", LoadOptions(**options)), warnings)


def load_detections(path: PathLike, *, warnings: list[str] | None = None, **options: Any) -> Annotations:
    """Detections from a KITTI txt folder (16 fields; or a zip/tar of one) or a ``result.pkl``-style pickle.

    ``calibs`` converts LiDAR-only boxes and checks boxes that carry both; what the check finds is appended
    to ``warnings``. The other options: see :class:`~kitti_eval.io.reading.LoadOptions`.
    """
    return _told(read_annotations(path, "detections", LoadOptions(**options)), warnings)


def load_annotations(path: PathLike, kind: Kind, *, warnings: list[str] | None = None, **options: Any) -> Annotations:
    """A folder is read as KITTI txt files, a zip/tar as an archived txt folder, a file as a pickle."""
    return _told(read_annotations(path, kind, LoadOptions(**options)), warnings)


def annotations_from_object(
    obj: object, kind: Kind, *, source: str, warnings: list[str] | None = None, **options: Any
) -> Annotations:
    """Annotations from an already unpickled object (e.g. an upload passed through ``load_pickle``)."""
    return _told(read_object(obj, kind, source, LoadOptions(**options)), warnings)


def annotations_from_pickle(
    path_or_fileobj: PathLike | IO[bytes],
    kind: Kind,
    *,
    source: str,
    warnings: list[str] | None = None,
    **options: Any,
) -> Annotations:
    """Annotations from a pickle given as a path or a binary file object (e.g. an upload; gzip or not), through
    the restricted unpickler: what :func:`~kitti_eval.io.safe_pickle.load_pickle` then
    :func:`annotations_from_object` give, with ``max_bytes`` and ``max_frames`` applied to both, but a
    result.pkl of the usual layout read from its bytes without building its objects
    (:mod:`kitti_eval.io.pickle_columns`)."""
    return _told(read_pickle(path_or_fileobj, kind, source, LoadOptions(**options)), warnings)


def load_ground_truth_and_calibs(
    gt_path: PathLike, *, warnings: list[str] | None = None, **options: Any
) -> tuple[Annotations, Mapping[str, Any]]:
    """Ground truth and, from an infos pickle, its calibration per frame (read once; empty for txt)."""
    loaded, calibs = read_ground_truth_and_calibs(gt_path, LoadOptions(**options))
    return _told(loaded, warnings), calibs


def load_pair(
    gt_path: PathLike,
    pred_path: PathLike,
    *,
    gt_format: str | None = None,
    pred_format: str | None = None,
    split: PathLike | None = None,
    warnings: list[str] | None = None,
    **options: Any,
) -> tuple[Annotations, Annotations]:
    """Ground truth and predictions (see :func:`kitti_eval.io.reading.read_pair`); the options (``max_bytes``,
    ``max_frames``, ``keep_lidar``) are the predictions', the limits apply to both."""
    pair = read_pair(
        gt_path, pred_path, gt_format=gt_format, options=LoadOptions(fmt=pred_format, **options), split=split
    )
    if warnings is not None:
        warnings.extend(pair.warnings)
    return pair.gt, pair.dt
