"""The one exception tree of kitti_eval: library code raises these, the CLI and server decide what to show."""

from __future__ import annotations

__all__ = ["KittiEvalError", "InputError", "UnsafePickleError", "UnknownFormatError", "ConfigError"]


class KittiEvalError(Exception):
    """Base of every error kitti_eval raises on purpose."""


class InputError(KittiEvalError):
    """Ground truth or predictions are malformed; names the source, frame and field where known."""

    def __init__(
        self, message: str, *, source: str | None = None, frame: str | None = None, field: str | None = None
    ) -> None:
        self.source = source
        self.frame = frame
        self.field = field
        where = []
        if source:
            where.append(source)
        if frame is not None:
            where.append(f"frame {frame}")
        if field:
            where.append(f"field '{field}'")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.message = message


class UnsafePickleError(InputError):
    """A pickle refers to something other than numpy arrays and plain containers; it was not loaded."""


class UnknownFormatError(InputError):
    """A file is none of the formats read (a pickle, a zip or tar of KITTI txt files, a txt folder)."""


class ConfigError(KittiEvalError):
    """An evaluation option (class, threshold, protocol) is invalid."""
