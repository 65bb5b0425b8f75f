"""The overlap budget: the detection x ground-truth pairs whose overlaps an evaluation computes, per frame and
per set, refused past their limits before any overlap is computed (:func:`check_overlap_budget`, called by
:func:`kitti_eval.core.evaluation.plan_evaluation`, the path every evaluation takes).

The overlaps of every pair of a frame are computed and kept (2D, BEV and 3D, float64) while the evaluation runs:
about 30 bytes a pair, so a frame of 8,000 boxes on each side needs about 2 GB. The limits come from the
environment (the CLI's flags and the service set the same variables), read when an evaluation is planned.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ..errors import ConfigError, WorkLimitError

__all__ = [
    "MAX_FRAME_PAIRS_ENV",
    "MAX_PAIRS_ENV",
    "DEFAULT_MAX_FRAME_PAIRS",
    "DEFAULT_MAX_PAIRS",
    "overlap_budget",
    "check_overlap_budget",
    "setting_name",
    "set_by_flags",
]

#: the environment variables of the budget: pairs of one frame, pairs of one evaluation (or one part of it)
MAX_FRAME_PAIRS_ENV = "KITTI_EVAL_MAX_FRAME_PAIRS"
MAX_PAIRS_ENV = "KITTI_EVAL_MAX_PAIRS"
#: 4 million pairs (2,000 boxes on each side, ~120 MB of overlaps): KITTI's largest frames need about 1,400
#: (21 ground-truth boxes, 65 detections), a Waymo-sized frame exported to KITTI format about 200,000 (400
#: objects, 500 detections, the usual cap after NMS)
DEFAULT_MAX_FRAME_PAIRS = 4_000_000
#: 100 million pairs (~3 GB of overlaps): KITTI val needs about 1.2 million (3,769 frames, ~8 ground-truth
#: boxes and ~40 detections a frame), nuScenes val in KITTI format about 75 million (6,019 frames, ~40 objects,
#: up to 300 detections)
DEFAULT_MAX_PAIRS = 100_000_000


#: the command-line flag that set each setting of this process, while its command runs (:func:`set_by_flags`)
_FLAGS: dict[str, str] = {}


def setting_name(env: str) -> str:
    """How a refusal names the setting ``env``: the flag that set it (``--max-boxes``) when the command line did,
    else the environment variable."""
    return _FLAGS.get(env, env)


@contextlib.contextmanager
def set_by_flags(flags: Mapping[str, str]) -> Iterator[None]:
    """While the block runs, the settings ``flags`` maps (variable -> flag) were given as those flags: the
    refusals name the flag."""
    before = dict(_FLAGS)
    _FLAGS.update(flags)
    try:
        yield
    finally:
        _FLAGS.clear()
        _FLAGS.update(before)


def positive_setting(env: str, default: float, unit: int = 1) -> int:
    """A limit from the environment variable ``env`` (a number > 0, times ``unit``), or ``default``; anything
    else is a :class:`ConfigError` naming the variable. Every limit on input and work is read through it."""
    raw = os.environ.get(env, "").strip()
    try:
        value = float(raw) if raw else default
    except ValueError:
        value = -1
    if not value > 0 or value == float("inf"):
        raise ConfigError(f"{env}={raw!r}: expected a number > 0")
    return int(value * unit)


def overlap_budget() -> tuple[int, int]:
    """``(max_frame_pairs, max_pairs)`` from :data:`MAX_FRAME_PAIRS_ENV` / :data:`MAX_PAIRS_ENV` or the
    defaults."""
    return positive_setting(MAX_FRAME_PAIRS_ENV, DEFAULT_MAX_FRAME_PAIRS), positive_setting(
        MAX_PAIRS_ENV, DEFAULT_MAX_PAIRS
    )


def check_overlap_budget(
    dt_counts: npt.NDArray[np.int64],
    gt_counts: npt.NDArray[np.int64],
    frame_ids: Sequence[str],
    *,
    source: str,
    budget: tuple[int, int] | None = None,
) -> int:
    """Refuse an evaluation whose frames (``dt_counts[f] x gt_counts[f]`` pairs, frame ``frame_ids[f]``) need more
    overlaps than ``budget`` (``(per frame, per set)``; None: :func:`overlap_budget`) allows, naming the first
    frame past it; returns the pairs in all."""
    per_frame, per_set = overlap_budget() if budget is None else budget
    pairs = np.asarray(dt_counts, dtype=np.int64) * np.asarray(gt_counts, dtype=np.int64)
    over = pairs > per_frame
    if over.any():
        f = int(np.argmax(over))
        raise WorkLimitError(
            f"{int(dt_counts[f])} detections x {int(gt_counts[f])} ground-truth boxes = {int(pairs[f])} overlaps "
            f"in one frame, more than the limit of {per_frame} ({setting_name(MAX_FRAME_PAIRS_ENV)})",
            source=source,
            frame=frame_ids[f],
        )
    total = np.cumsum(pairs)
    if len(total) and total[-1] > per_set:
        f = int(np.argmax(total > per_set))
        raise WorkLimitError(
            f"{int(total[-1])} detection x ground-truth overlaps in all, more than the limit of {per_set} for one "
            f"evaluation ({setting_name(MAX_PAIRS_ENV)}); the limit is passed at this frame",
            source=source,
            frame=frame_ids[f],
        )
    return int(total[-1]) if len(total) else 0
