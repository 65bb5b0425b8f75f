"""kitti-eval's node in mmengine's registry tree, so that an OpenMMLab config can name its metric::

    val_evaluator = dict(type="kitti_eval.KittiMetric", ann_file="data/kitti/kitti_infos_val.pkl")

mmengine imports ``<scope>.registry`` itself when a config names a type ``<scope>.<Name>`` of another scope;
the metric class is imported from :mod:`kitti_eval.compat.mmdet3d_evaluator` when first asked for. Without
mmengine installed, ``METRICS`` is None and nothing else happens.
"""

from __future__ import annotations

from typing import Any

__all__ = ["METRICS"]

METRICS: Any = None

try:
    from mmengine.registry import METRICS as _MMENGINE_METRICS
    from mmengine.registry import Registry
except ImportError:  # mmengine is optional
    pass
else:
    METRICS = Registry(
        "metric", parent=_MMENGINE_METRICS, scope="kitti_eval", locations=["kitti_eval.compat.mmdet3d_evaluator"]
    )
