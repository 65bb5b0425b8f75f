"""kitti-eval: exact KITTI 3D object detection evaluation on a CPU.

>>> from kitti_eval import evaluate, load_ground_truth, load_detections
>>> result = evaluate(load_ground_truth("kitti_infos_val.pkl"), load_detections("result.pkl"))  # doctest: +SKIP
>>> result.get("Car", "3d", "moderate")                                                           # doctest: +SKIP

Heavy modules (numba kernels) are imported on first use, so ``import kitti_eval`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

from .core.protocol import OFFICIAL, OPENPCDET, EvalConfig, Metric, Protocol
from .errors import ConfigError, InputError, KittiEvalError, UnsafePickleError

__version__ = "0.1.0"

_LAZY = {
    "evaluate": "kitti_eval.core.evaluation",
    "EvalResult": "kitti_eval.core.result",
    "Annotations": "kitti_eval.core.frames",
    "load_ground_truth": "kitti_eval.io.loaders",
    "load_detections": "kitti_eval.io.loaders",
    "get_official_eval_result": "kitti_eval.compat.openpcdet",
    "KittiMetric": "kitti_eval.incremental",
}

__all__ = [
    "evaluate",
    "EvalConfig",
    "EvalResult",
    "Annotations",
    "Metric",
    "Protocol",
    "OFFICIAL",
    "OPENPCDET",
    "load_ground_truth",
    "load_detections",
    "get_official_eval_result",
    "KittiMetric",
    "KittiEvalError",
    "InputError",
    "UnsafePickleError",
    "ConfigError",
    "__version__",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'kitti_eval' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
