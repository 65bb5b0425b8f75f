"""mmdetection3d's ``KittiMetric``, computed by kitti-eval: one line of an mmdetection3d 1.x config::

    val_evaluator = dict(type="kitti_eval.KittiMetric", ann_file=data_root + "kitti_infos_val.pkl")
    test_evaluator = val_evaluator

mmengine finds the class through :mod:`kitti_eval.registry` (nothing to import in the config). It logs the
same text and the same keys as mmdetection3d's ``KittiMetric`` (``Kitti metric/pred_instances_3d/KITTI/
Car_3D_AP40_moderate_strict``, ..., rounded to four decimals), computed with exact IoU on the CPU under the
``openpcdet`` protocol (see :mod:`kitti_eval.compat.mmdet3d` for where that differs from mmdetection3d's
evaluator). Arguments: those of mmdetection3d's metric that bear on the numbers (``ann_file``,
``pred_box_type_3d``, ``pcd_limit_range``, ``prefix``, ``collect_device``; ``metric='bbox'``), and kitti-eval's
own: ``classes`` (default: the dataset's), ``protocol`` and further :class:`~kitti_eval.core.protocol.EvalConfig`
options. Writing result or submission files (``pklfile_prefix``, ``submission_prefix``, ``format_only``) is
left to mmdetection3d's metric.

Each data sample's ``pred_instances_3d`` (``bboxes_3d``, ``scores_3d``, ``labels_3d``) becomes KITTI camera
fields as mmdetection3d's metric makes them (:func:`predictions_to_kitti`), with the calibration of its
``sample_idx`` in ``ann_file``, and only those compact arrays are kept until the end of the epoch. The class
exists when mmengine (with torch) can be imported; this module imports without them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.frames import Annotations, normalize_frame_id
from ..core.protocol import EvalConfig, get_protocol
from ..errors import ConfigError, InputError
from ..io.calib import Calib, wrap_angle

__all__ = ["predictions_to_kitti", "adapter_class", "KittiMetric", "DEFAULT_PCD_LIMIT_RANGE"]

#: mmdetection3d's default: predictions whose LiDAR box (bottom centre) lies outside are dropped
DEFAULT_PCD_LIMIT_RANGE = (0.0, -40.0, -3.0, 70.4, 40.0, 0.0)
F64 = npt.NDArray[np.float64]


def _image_boxes(loc: F64, dims: F64, ry: F64, p2: F64) -> F64:
    """(N, 4) x1, y1, x2, y2 spanned by the eight corners of camera boxes (bottom centre, l h w, ry) projected
    through ``p2`` (3x4), unclipped."""
    if not len(loc):
        return np.zeros((0, 4))
    sx = np.array([0.5, 0.5, -0.5, -0.5, 0.5, 0.5, -0.5, -0.5])[None]
    sy = np.array([0.0, 0.0, 0.0, 0.0, -1.0, -1.0, -1.0, -1.0])[None]
    sz = np.array([0.5, -0.5, -0.5, 0.5, 0.5, -0.5, -0.5, 0.5])[None]
    c, s = np.cos(ry)[:, None], np.sin(ry)[:, None]
    ox, oz = sx * dims[:, 0:1], sz * dims[:, 2:3]
    x = loc[:, 0:1] + c * ox + s * oz
    y = loc[:, 1:2] + sy * dims[:, 1:2]
    z = loc[:, 2:3] - s * ox + c * oz
    pts = np.stack([x, y, z, np.ones_like(x)], axis=-1) @ p2.T  # (N, 8, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pts[..., :2] / pts[..., 2:3]
    return np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)


def predictions_to_kitti(
    boxes: npt.ArrayLike,
    scores: npt.ArrayLike,
    labels: npt.ArrayLike,
    calib: Calib,
    classes: Sequence[str],
    *,
    box_type: str = "LiDAR",
    pcd_limit_range: Sequence[float] = DEFAULT_PCD_LIMIT_RANGE,
    frame: str | None = None,
) -> dict[str, np.ndarray]:
    """One frame's mmdetection3d predictions as the KITTI annos dict mmdetection3d's ``KittiMetric`` makes.

    ``boxes`` (N, 7+): LiDAR boxes ``x, y, z`` (bottom centre), ``x_size, y_size, z_size, yaw``
    (``box_type="LiDAR"``), or camera boxes ``x, y, z`` (bottom centre), ``l, h, w, ry`` (``"Camera"``).
    LiDAR boxes become camera boxes as mmdetection3d converts them: location ``lidar2cam @ (x, y, z, 1)``,
    dimensions ``(x_size, z_size, y_size)``, ``ry = -yaw - pi/2`` wrapped to [-pi, pi); alpha is
    ``ry - atan2(-y, x)`` (LiDAR) or ``ry - atan2(x_cam, z_cam)`` (camera). The 2D box spans the projected
    corners; a box is kept if that box reaches into the image and (LiDAR) its ``x, y, z`` lie strictly within
    ``pcd_limit_range``; kept 2D boxes are clipped to ``[0, W] x [0, H]``. In float64 (mmdetection3d: float32).
    """
    where = {"source": "pred_instances_3d", "frame": frame}
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] < 7:
        raise InputError(f"bboxes_3d: expected shape (N, 7), got {b.shape}", field="bboxes_3d", **where)
    b = b[:, :7]
    n = len(b)
    score = np.asarray(scores, dtype=np.float64).reshape(-1)
    label = np.asarray(labels).reshape(-1)
    if len(score) != n or len(label) != n:
        raise InputError(f"{n} boxes but {len(score)} scores and {len(label)} labels", field="scores_3d", **where)
    if label.dtype.kind not in "iu" or (n and (label.min() < 0 or label.max() >= len(classes))):
        raise InputError(f"labels_3d must be class indices 0..{len(classes) - 1}", field="labels_3d", **where)
    if calib.image_shape is None:
        raise InputError("the calibration has no image size (height, width)", field="images", **where)
    height, width = calib.image_shape
    if box_type == "LiDAR":
        pts = np.concatenate([b[:, :3], np.ones((n, 1))], axis=1)
        loc = (pts @ calib.velo_to_rect.T)[:, :3]
        dims = b[:, [3, 5, 4]]
        ry = wrap_angle(-b[:, 6] - np.pi / 2)
        alpha = -np.arctan2(-b[:, 1], b[:, 0]) + ry
        limit = np.asarray(pcd_limit_range, dtype=np.float64)
        inside = np.all((b[:, :3] > limit[:3]) & (b[:, :3] < limit[3:]), axis=1)
    elif box_type == "Camera":
        loc, dims = b[:, :3], b[:, 3:6]
        ry = wrap_angle(b[:, 6])
        alpha = -np.arctan2(loc[:, 0], loc[:, 2]) + ry
        inside = np.ones(n, dtype=bool)
    else:
        raise ConfigError(f"box type {box_type!r}: expected 'LiDAR' or 'Camera'")
    raw = _image_boxes(loc, dims, ry, calib.p2)
    keep = inside & (raw[:, 0] < width) & (raw[:, 1] < height) & (raw[:, 2] > 0) & (raw[:, 3] > 0)
    bbox = raw[keep]
    bbox[:, 2:] = np.minimum(bbox[:, 2:], [width, height])
    bbox[:, :2] = np.maximum(bbox[:, :2], 0.0)
    k = int(keep.sum())
    return {
        "name": np.array([classes[int(c)] for c in label[keep]]) if k else np.zeros(0, dtype="<U1"),
        "truncated": np.zeros(k),
        "occluded": np.zeros(k),
        "alpha": alpha[keep],
        "bbox": bbox,
        "dimensions": dims[keep],
        "location": loc[keep],
        "rotation_y": ry[keep],
        "score": score[keep],
    }


def _numpy(x: Any) -> np.ndarray:
    """A box object's, a tensor's or an array's values as numpy (no torch import: duck typing)."""
    x = getattr(x, "tensor", x)
    for step in ("detach", "cpu", "numpy"):
        f = getattr(x, step, None)
        if callable(f):
            x = f()
    return np.asarray(x)


def _box_type(boxes: Any, default: str) -> str:
    name = type(boxes).__name__
    if name == "LiDARInstance3DBoxes":
        return "LiDAR"
    if name == "CameraInstance3DBoxes":
        return "Camera"
    if name.endswith("Instance3DBoxes"):
        raise ConfigError(f"{name}: kitti_eval.KittiMetric evaluates LiDAR or camera boxes")
    return default


def _read_calibs(ann_file: str) -> dict[str, Calib]:
    """{frame id: calibration of CAM2} of an mmdetection3d 1.x info file, without keeping the file's dicts."""
    from ..io.loaders import calibs_from_object
    from ..io.safe_pickle import load_pickle

    lazy = calibs_from_object(load_pickle(ann_file, source=ann_file))
    try:
        return {fid: lazy[fid] for fid in lazy}
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise InputError(f"a frame's images['CAM2'] calibration cannot be read ({e})", source=ann_file) from None


def adapter_class(base: type, print_log: Callable[..., Any]) -> type:
    """The metric class on mmengine's ``BaseMetric`` (``base``), logging with ``print_log``."""
    from .mmdet3d import ap_dict, result_text

    class KittiMetric(base):
        """mmdetection3d's ``KittiMetric`` on kitti-eval (see :mod:`kitti_eval.compat.mmdet3d_evaluator`)."""

        default_prefix = "Kitti metric"

        def __init__(
            self,
            ann_file: str,
            metric: str | list[str] = "bbox",
            pred_box_type_3d: str = "LiDAR",
            pcd_limit_range: Sequence[float] = DEFAULT_PCD_LIMIT_RANGE,
            prefix: str | None = None,
            pklfile_prefix: str | None = None,
            default_cam_key: str = "CAM2",
            format_only: bool = False,
            submission_prefix: str | None = None,
            collect_device: str = "cpu",
            backend_args: Mapping[str, Any] | None = None,
            classes: Sequence[str] | None = None,
            protocol: str = "openpcdet",
            **options: Any,
        ) -> None:
            super().__init__(collect_device=collect_device, prefix=prefix)
            metrics = [metric] if isinstance(metric, str) else list(metric)
            if metrics != ["bbox"]:
                raise ConfigError(f"kitti_eval.KittiMetric computes metric='bbox' (3D boxes), got {metric!r}")
            if pklfile_prefix is not None or submission_prefix is not None or format_only:
                raise ConfigError(
                    "kitti_eval.KittiMetric evaluates; mmdetection3d's KittiMetric writes result and submission files"
                )
            if default_cam_key != "CAM2":
                raise ConfigError(f"default_cam_key {default_cam_key!r}: KITTI is evaluated on CAM2")
            if backend_args:
                raise ConfigError("ann_file is read from the local disk (backend_args is not supported)")
            if pred_box_type_3d not in ("LiDAR", "Camera"):
                raise ConfigError(f"pred_box_type_3d {pred_box_type_3d!r}: expected 'LiDAR' or 'Camera'")
            limit = tuple(float(v) for v in pcd_limit_range)
            if len(limit) != 6:
                raise ConfigError(f"pcd_limit_range needs six numbers (x, y, z min, then max), got {limit}")
            self.ann_file = str(ann_file)
            self.pred_box_type_3d = pred_box_type_3d
            self.pcd_limit_range = limit
            self._classes = (classes,) if isinstance(classes, str) else tuple(classes) if classes else None
            self._protocol = protocol
            self._options = dict(options)
            if self._classes is not None:
                EvalConfig(
                    classes=self._classes, protocol=get_protocol(protocol), **options
                )  # fails now, not at the end
            self._calibs: dict[str, Calib] | None = None

        def _label_names(self) -> tuple[str, ...]:
            """The names of the model's labels: the dataset's classes (or ``classes`` when there is none)."""
            meta = self.dataset_meta or {}
            if meta.get("classes"):
                return tuple(meta["classes"])
            if self._classes is not None:
                return self._classes
            raise ConfigError("no classes: give classes=... or run with a dataset whose metainfo has 'classes'")

        def _class_names(self) -> tuple[str, ...]:
            """The classes evaluated: ``classes``, by default the dataset's."""
            return self._classes if self._classes is not None else self._label_names()

        def process(self, data_batch: Any, data_samples: Sequence[Mapping[str, Any]]) -> None:
            """Keep each sample's predictions as KITTI camera fields (compact arrays, one entry a sample)."""
            if self._calibs is None:
                self._calibs = _read_calibs(self.ann_file)
            classes = self._label_names()
            for sample in data_samples:
                fid = normalize_frame_id(_numpy(sample["sample_idx"]).reshape(-1)[0].item())
                calib = self._calibs.get(fid)
                if calib is None:
                    raise InputError("no calibration for this sample_idx", source=self.ann_file, frame=fid)
                pred = sample["pred_instances_3d"]
                boxes = pred["bboxes_3d"]
                annos = predictions_to_kitti(
                    _numpy(boxes),
                    _numpy(pred["scores_3d"]),
                    _numpy(pred["labels_3d"]),
                    calib,
                    classes,
                    box_type=_box_type(boxes, self.pred_box_type_3d),
                    pcd_limit_range=self.pcd_limit_range,
                    frame=fid,
                )
                self.results.append((fid, annos))

        def compute_metrics(self, results: list[Any]) -> dict[str, float]:
            """Evaluate every sample's predictions against ``ann_file``; mmdetection3d's keys and text."""
            from ..incremental import KittiMetric as Incremental
            from ..io.loaders import annotations_from_object
            from ..io.safe_pickle import load_pickle

            gt = annotations_from_object(
                load_pickle(self.ann_file, source=self.ann_file),
                "ground_truth",
                source=self.ann_file,
                fmt="mmdet3d_infos",
            )
            dt = Annotations.from_frames("detections", "pred_instances_3d", results)
            metric = Incremental(self._class_names(), self._protocol, **self._options)
            metric.update(gt.subset(dt.frame_ids), dt)
            result = metric.compute()
            for message in result.warnings:
                print_log(message, logger="current", level=logging.WARNING)
            print_log("Results of pred_instances_3d:\n" + result_text(result), logger="current")
            return {f"pred_instances_3d/{k}": float(f"{v:.4f}") for k, v in ap_dict(result).items()}

    KittiMetric.__module__ = __name__
    return KittiMetric


#: the class mmengine builds for ``type="kitti_eval.KittiMetric"``; None without mmengine (or torch)
KittiMetric: type | None = None

try:
    from mmengine.evaluator import BaseMetric as _BaseMetric
    from mmengine.logging import print_log as _print_log
except ImportError:  # mmengine is optional, and its evaluator needs torch
    pass
else:
    KittiMetric = adapter_class(_BaseMetric, _print_log)
    from ..registry import METRICS

    if METRICS is not None:
        METRICS.register_module(name="KittiMetric", module=KittiMetric, force=True)
