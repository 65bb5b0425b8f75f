"""The limits on one input: its bytes (a pickle after decompression, an archive's unpacked txt files), its
frames and its boxes (per frame and in all), and the overlaps an evaluation may compute (per frame and in all),
from the environment (the service reads the same variables) or the defaults.

The overlap budget is checked where every evaluation is planned (:mod:`kitti_eval.core.budget`, whose settings
are listed here too); the box limits on the path every format's frames take (:class:`BoxLimits`, passed by every
loader)."""

from __future__ import annotations

from ..core.budget import (
    DEFAULT_MAX_FRAME_PAIRS,
    DEFAULT_MAX_PAIRS,
    MAX_FRAME_PAIRS_ENV,
    MAX_PAIRS_ENV,
    overlap_budget,
    positive_setting,
    setting_name,
)
from ..core.frames import BoxLimits

__all__ = [
    "MAX_INPUT_ENV",
    "MAX_FRAMES_ENV",
    "MAX_FRAME_BOXES_ENV",
    "MAX_BOXES_ENV",
    "MAX_FRAME_PAIRS_ENV",
    "MAX_PAIRS_ENV",
    "DEFAULT_MAX_INPUT_MB",
    "DEFAULT_MAX_FRAMES",
    "DEFAULT_MAX_FRAME_BOXES",
    "DEFAULT_MAX_BOXES",
    "DEFAULT_MAX_FRAME_PAIRS",
    "DEFAULT_MAX_PAIRS",
    "BoxLimits",
    "input_limits",
    "box_limits",
    "overlap_budget",
    "resolve",
]

#: the environment variables that set the limits on one input (the service reads the same ones)
MAX_INPUT_ENV = "KITTI_EVAL_MAX_UNPACKED_MB"
MAX_FRAMES_ENV = "KITTI_EVAL_MAX_FRAMES"
MAX_FRAME_BOXES_ENV = "KITTI_EVAL_MAX_BOXES_PER_FRAME"
MAX_BOXES_ENV = "KITTI_EVAL_MAX_BOXES"
DEFAULT_MAX_INPUT_MB = 512
DEFAULT_MAX_FRAMES = 200_000
#: boxes of one frame (ground truth or predictions, DontCare included): KITTI's largest frames hold 21 labels and
#: 65 detections in the KITTI-val-sized reference case; KITTI-format exports of larger datasets stay in the
#: hundreds (Waymo's busiest frames, ~400 labels; OpenPCDet and mmdetection3d keep at most 500 detections a
#: frame after NMS); a benchmark's own rule is stricter (1,000 a frame, :mod:`kitti_eval.io.submission_rules`)
DEFAULT_MAX_FRAME_BOXES = 10_000
#: boxes of one input: KITTI val has ~150,000 detections (40 a frame), nuScenes val in KITTI format about 1.8
#: million (6,019 frames, up to 300 detections a frame); Waymo val (39,987 frames) fits at up to 125 a frame
#: and needs a larger limit at more. Reading txt holds a few hundred bytes a box at its peak
#: (docs/service/operations.md has the figures)
DEFAULT_MAX_BOXES = 5_000_000


def input_limits() -> tuple[int, int]:
    """``(max_bytes, max_frames)`` for one input, from :data:`MAX_INPUT_ENV` / :data:`MAX_FRAMES_ENV` or the
    defaults (512 MB, 200,000 frames; KITTI val is 22 MB and 3,769 frames).

    ``max_bytes`` caps a pickle after decompression and the unpacked txt files of an archive; ``max_frames``
    caps the frames of one input (a pickle's top-level list is refused before it is built, other layouts
    before a frame beyond the cap is converted). Every loader uses these unless given its own.
    """
    return positive_setting(MAX_INPUT_ENV, DEFAULT_MAX_INPUT_MB, 1 << 20), positive_setting(
        MAX_FRAMES_ENV, DEFAULT_MAX_FRAMES
    )


def box_limits(per_frame: int | None = None, per_input: int | None = None) -> BoxLimits:
    """The box limits of one input: ``per_frame`` and ``per_input`` where given, else from
    :data:`MAX_FRAME_BOXES_ENV` / :data:`MAX_BOXES_ENV`, else the defaults (10,000 boxes a frame, 5 million
    in all). Every loader checks them as it reads, before anything that grows with the boxes."""
    return BoxLimits(
        per_frame=positive_setting(MAX_FRAME_BOXES_ENV, DEFAULT_MAX_FRAME_BOXES) if per_frame is None else per_frame,
        per_input=positive_setting(MAX_BOXES_ENV, DEFAULT_MAX_BOXES) if per_input is None else per_input,
        per_frame_setting=setting_name(MAX_FRAME_BOXES_ENV),
        per_input_setting=setting_name(MAX_BOXES_ENV),
    )


def resolve(max_bytes: int | None, max_frames: int | None) -> tuple[int, int]:
    """``(max_bytes, max_frames)`` with each None replaced by :func:`input_limits`' value."""
    if max_bytes is not None and max_frames is not None:
        return max_bytes, max_frames
    env_bytes, env_frames = input_limits()
    return (env_bytes if max_bytes is None else max_bytes), (env_frames if max_frames is None else max_frames)
