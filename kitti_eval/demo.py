"""The demo data bundled with the package (``kitti_eval/data/demo``): a synthetic KITTI validation set of
200 frames, made by :func:`kitti_eval.synth.generate` with :data:`DEMO_ARGS` (``python -m kitti_eval.synth
--demo`` writes it again)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["DEMO_ARGS", "DEMO_FILES", "demo_paths"]

#: How the bundled demo under ``kitti_eval/data/demo`` was made: ``generate(**DEMO_ARGS)``.
DEMO_ARGS: dict[str, Any] = {"frames": 200, "seed": 7, "dets_per_frame": 12.0}
#: its ground truth and its predictions, gzipped pickles in OpenPCDet's layouts
DEMO_FILES = ("kitti_infos_val.pkl.gz", "result.pkl.gz")


def demo_paths() -> tuple[Path, Path]:
    """(ground truth, predictions) of the bundled demo: gzipped ``kitti_infos_val.pkl`` and ``result.pkl``.

    Made by ``generate(**DEMO_ARGS)`` (200 frames, seed 7, 12 detections a frame).
    """
    root = Path(__file__).resolve().parent / "data" / "demo"
    return root / DEMO_FILES[0], root / DEMO_FILES[1]
