"""A drop-in for OpenPCDet's ``get_official_eval_result``: swap one import, keep the calling code.

    # from pcdet.datasets.kitti.kitti_object_eval_python.eval import get_official_eval_result
    from kitti_eval import get_official_eval_result    # or from kitti_eval.compat.openpcdet import ...

Same arguments (lists of per-frame annos dicts, paired by position as OpenPCDet does), same printed text
and ``ret_dict`` keys, computed with the ``openpcdet`` protocol on exact IoU and without a GPU.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..core.evaluation import evaluate
from ..core.frames import Annotations
from ..core.protocol import DIFFICULTIES, METRICS, OPENPCDET, EvalConfig
from ..core.result import EvalResult
from ..errors import ConfigError, InputError
from ..report.render import render_table
from ._common import warn_about

__all__ = ["get_official_eval_result", "ret_dict"]

#: OpenPCDet's class indices.
_CLASS_BY_INDEX = ("Car", "Pedestrian", "Cyclist", "Van", "Person_sitting", "Truck")


def _class_names(current_classes: Any) -> tuple[str, ...]:
    if not isinstance(current_classes, (list, tuple)):
        current_classes = [current_classes]
    names = []
    for c in current_classes:
        if isinstance(c, (int, np.integer)) and not isinstance(c, bool):
            if not 0 <= int(c) < len(_CLASS_BY_INDEX):
                raise ConfigError(f"class index {c} out of range 0..{len(_CLASS_BY_INDEX) - 1}")
            names.append(_CLASS_BY_INDEX[int(c)])
        elif isinstance(c, str):
            names.append(c)
        else:
            raise ConfigError(f"classes must be names or indices, got {c!r}")
    return tuple(names)


def ret_dict(result: EvalResult) -> dict[str, float]:
    """OpenPCDet's ``ret_dict``: strict thresholds, R40, keys like ``Car_3d/moderate_R40``."""
    out: dict[str, float] = {}
    for cls in result.classes:
        by_metric = result.ap["strict"]["R40"][cls]
        if result.aos_evaluated:
            for d in DIFFICULTIES:
                out[f"{cls}_aos/{d}_R40"] = _value(by_metric["aos"][d])
        for metric, key in (("3d", "3d"), ("bev", "bev"), ("bbox", "image")):
            for d in DIFFICULTIES:
                out[f"{cls}_{key}/{d}_R40"] = _value(by_metric[metric][d])
    return out


def _value(v: float | None) -> float:
    return float("nan") if v is None else float(v)


def get_official_eval_result(
    gt_annos: Sequence[Mapping[str, Any]],
    dt_annos: Sequence[Mapping[str, Any]],
    current_classes: Any,
    PR_detail_dict: dict[str, Any] | None = None,  # noqa: N803
) -> tuple[str, dict[str, float]]:
    """Evaluate like OpenPCDet's function of the same name; returns ``(text, ret_dict)``.

    ``gt_annos`` and ``dt_annos`` are lists of per-frame annos dicts paired by position. If
    ``PR_detail_dict`` is given it receives the precision curves under ``bbox``, ``bev``, ``3d``, ``aos``,
    each shaped [class, difficulty, threshold set, 41] as OpenPCDet's.
    """
    if len(gt_annos) != len(dt_annos):
        raise InputError(
            f"{len(gt_annos)} ground-truth frames but {len(dt_annos)} prediction frames; "
            "this function pairs frames by position"
        )
    ids = [f"{i:06d}" for i in range(len(gt_annos))]
    gt = Annotations.from_frames("ground_truth", "gt_annos", zip(ids, gt_annos))
    dt = Annotations.from_frames("detections", "dt_annos", zip(ids, dt_annos))
    config = EvalConfig(classes=_class_names(current_classes), protocol=OPENPCDET)
    result = evaluate(gt, dt, config, keep_curves=PR_detail_dict is not None)
    warn_about(result)
    if PR_detail_dict is not None and result.curves is not None:
        for metric in METRICS:
            arr = np.zeros((len(config.classes), 3, len(config.threshold_sets), 41))
            for j, cls in enumerate(config.classes):
                for k, oset in enumerate(config.threshold_sets):
                    for i, d in enumerate(DIFFICULTIES):
                        curve = result.curves[oset][cls][metric].get(d)
                        if curve is not None:
                            arr[j, i, k] = curve.orientation if metric == "aos" else curve.precision
            PR_detail_dict[metric] = arr
    return render_table(result), ret_dict(result)
