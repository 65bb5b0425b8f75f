"""What a frame listing asks (:class:`FrameQuestion`), with its defaults: one definition for the library
(:func:`kitti_eval.analysis.diagnostics.frame_stats`), the command line and the service. A light module (no
kernels), so that the command line's options read their defaults from it before anything is compiled."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.protocol import DEFAULT_METRIC, DEFAULT_OSET

__all__ = ["FrameQuestion", "ASKED"]


@dataclass(frozen=True)
class FrameQuestion:
    """The class, the overlap metric (``aos``: the 2D matching), the difficulty, the IoU threshold set, and the
    score from which detections count."""

    cls: str = "Car"
    metric: str = DEFAULT_METRIC
    difficulty: str = "moderate"
    oset: str = DEFAULT_OSET
    score_threshold: float = 0.0


#: the defaults of every frame listing, and of a frame view's class, metric, difficulty and set
ASKED = FrameQuestion()
