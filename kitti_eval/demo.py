"""The demo data bundled with the package (``kitti_eval/data/demo``): a synthetic KITTI validation set of
200 frames, made by :func:`kitti_eval.synth.generate` with :data:`DEMO_ARGS`, and a weaker model's predictions
on it, made with :data:`DEMO_WEAKER_ARGS` (``python -m kitti_eval.synth --demo`` writes them again)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["DEMO_ARGS", "DEMO_WEAKER_ARGS", "DEMO_FILES", "demo_paths", "demo_weaker_path"]

#: How the bundled demo under ``kitti_eval/data/demo`` was made: ``generate(**DEMO_ARGS)``.
DEMO_ARGS: dict[str, Any] = {"frames": 200, "seed": 7, "dets_per_frame": 12.0}
#: The weaker model: the same ground truth and the same detector, each found object's ground-plane position off
#: by a further N(0, 0.1 m) (Car 3D AP, moderate, R40: 45.86 against the demo's 60.34)
DEMO_WEAKER_ARGS: dict[str, Any] = {**DEMO_ARGS, "location_noise": 0.1}
#: its ground truth, its predictions and the weaker model's, gzipped pickles in OpenPCDet's layouts
DEMO_FILES = ("kitti_infos_val.pkl.gz", "result.pkl.gz", "result_weaker.pkl.gz")

_ROOT = Path(__file__).resolve().parent / "data" / "demo"


def demo_paths() -> tuple[Path, Path]:
    """(ground truth, predictions) of the bundled demo: gzipped ``kitti_infos_val.pkl`` and ``result.pkl``.

    Made by ``generate(**DEMO_ARGS)`` (200 frames, seed 7, 12 detections a frame).
    """
    return _ROOT / DEMO_FILES[0], _ROOT / DEMO_FILES[1]


def demo_weaker_path() -> Path:
    """A weaker model's predictions on the demo's ground truth (``result_weaker.pkl.gz``), for comparisons and
    gates against a baseline on bundled data: made by ``generate(**DEMO_WEAKER_ARGS)``."""
    return _ROOT / DEMO_FILES[2]
