"""The limits on one input: its bytes (a pickle after decompression, an archive's unpacked txt files) and its
frames, from the environment (the service reads the same variables) or the defaults."""

from __future__ import annotations

import os

from ..errors import ConfigError

__all__ = ["MAX_INPUT_ENV", "MAX_FRAMES_ENV", "DEFAULT_MAX_INPUT_MB", "DEFAULT_MAX_FRAMES", "input_limits", "resolve"]

#: the environment variables that set the limits on one input (the service reads the same ones)
MAX_INPUT_ENV = "KITTI_EVAL_MAX_UNPACKED_MB"
MAX_FRAMES_ENV = "KITTI_EVAL_MAX_FRAMES"
DEFAULT_MAX_INPUT_MB = 512
DEFAULT_MAX_FRAMES = 200_000


def input_limits() -> tuple[int, int]:
    """``(max_bytes, max_frames)`` for one input, from :data:`MAX_INPUT_ENV` / :data:`MAX_FRAMES_ENV` or the
    defaults (512 MB, 200,000 frames; KITTI val is 22 MB and 3,769 frames).

    ``max_bytes`` caps a pickle after decompression and the unpacked txt files of an archive; ``max_frames``
    caps the frames of one input (a pickle's top-level list is refused before it is built, other layouts
    before a frame beyond the cap is converted). Every loader uses these unless given its own.
    """
    out = []
    for env, default, unit in ((MAX_INPUT_ENV, DEFAULT_MAX_INPUT_MB, 1 << 20), (MAX_FRAMES_ENV, DEFAULT_MAX_FRAMES, 1)):
        raw = os.environ.get(env, "").strip()
        try:
            value = float(raw) if raw else default
        except ValueError:
            value = -1
        if not value > 0 or value == float("inf"):
            raise ConfigError(f"{env}={raw!r}: expected a number > 0")
        out.append(int(value * unit))
    return out[0], out[1]


def resolve(max_bytes: int | None, max_frames: int | None) -> tuple[int, int]:
    """``(max_bytes, max_frames)`` with each None replaced by :func:`input_limits`' value."""
    if max_bytes is not None and max_frames is not None:
        return max_bytes, max_frames
    env_bytes, env_frames = input_limits()
    return (env_bytes if max_bytes is None else max_bytes), (env_frames if max_frames is None else max_frames)
