"""The one exception tree of kitti_eval: library code raises these, the CLI and server decide what to show."""

from __future__ import annotations

__all__ = [
    "KittiEvalError",
    "InputError",
    "UnsafePickleError",
    "UnknownFormatError",
    "ArchiveError",
    "WorkLimitError",
    "InvalidSubmissionError",
    "ConfigError",
    "ServiceError",
    "ServiceUnreachable",
    "QuotaExceeded",
    "SubmissionRefused",
]


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


class ArchiveError(InputError):
    """A zip or tar was refused as a whole: unreadable, or past a limit (members, unpacked bytes), or unsafe
    (absolute paths, ``..``, links); nothing of it was loaded."""


class WorkLimitError(InputError):
    """An input asks for more work than a limit allows (boxes in a frame or in a file, overlaps of a frame or
    of a set: :mod:`kitti_eval.io.limits`); refused before that work is done, naming the frame, the count and
    the limit."""


class InvalidSubmissionError(InputError):
    """A benchmark submission that can be read but breaks the rules (:mod:`kitti_eval.io.submission`):
    ``problems``, the validator's sentences in the order found (``more``: those past its limit, not listed);
    :meth:`lines` as ``kitti-eval validate`` prints them."""

    def __init__(self, problems: list[str], more: int = 0) -> None:
        self.problems = list(problems)
        self.more = more
        lines = self.lines()
        shown = "; ".join(lines[:3]) + (" ..." if len(lines) > 3 else "")
        super().__init__(f"the submission breaks the rules: {shown}")

    def lines(self) -> list[str]:
        return [*self.problems, *([f"... and {self.more} more problems"] if self.more else [])]


class ConfigError(KittiEvalError):
    """An evaluation option (class, threshold, protocol) is invalid."""


class ServiceError(KittiEvalError):
    """A service refused a request (:mod:`kitti_eval.client`): its status, error code and message, and the
    details its error response added (``frame`` and ``field`` of an input error, for one)."""

    def __init__(
        self, message: str, *, status: int | None = None, code: str | None = None, details: dict | None = None
    ) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        self.code = code
        self.details = dict(details or {})

    @property
    def refused_input(self) -> bool:
        """Whether the files sent were refused (unreadable, unsafe, breaking the rules), not the request."""
        return self.code in _INPUT_CODES


#: the error codes of the service's 422 that are about the files sent
_INPUT_CODES = frozenset(
    {
        "invalid_input",
        "unsafe_pickle",
        "invalid_archive",
        "unknown_format",
        "invalid_submission",
        "payload_too_large",
        "over_work_limit",
    }
)


class ServiceUnreachable(ServiceError):
    """The service did not answer (or answered only that it is away: 502, 503, 504) within the client's retry
    time."""


class QuotaExceeded(ServiceError):
    """A benchmark's quota is used; ``retry_at`` (ISO 8601, UTC) is when the next submission is accepted."""

    @property
    def retry_at(self) -> str | None:
        value = self.details.get("retry_at")
        return str(value) if value is not None else None


class SubmissionRefused(ServiceError):
    """A submission breaks the benchmark's rules; ``problems`` are the sentences ``kitti-eval validate`` prints
    (found before sending it, or by the service)."""

    def __init__(self, message: str, problems: list[str], **kw: object) -> None:
        super().__init__(message, **kw)  # type: ignore[arg-type]
        self.problems = list(problems)

    @property
    def refused_input(self) -> bool:
        return True
