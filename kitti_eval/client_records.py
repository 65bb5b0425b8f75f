"""What the service answers, as the client's records (an evaluation, a job, a submission, a quota) and the ids and
paths it addresses them by: the parts of :mod:`kitti_eval.client` that its submission flow uses too."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .client_http import shown as _shown

if TYPE_CHECKING:
    from .core.result import EvalResult

__all__ = ["Evaluation", "Job", "Submission", "Quota"]

#: how long one POST asks the service to wait for its result before answering 202 with the job
_POST_WAIT_S = 20.0

# ------------------------------------------------------------------------------------------ results

_ID = re.compile(r"^[A-Za-z0-9_-]{1,128}$")


def _id(value: object) -> str:
    """An id the service gave, as it may go into a path and a sentence (else the answer is not the service's)."""
    text = str(value)
    if not _ID.match(text):
        raise ValueError(f"not an id: {_shown(text)[:80]!r}")
    return text


@dataclass(frozen=True)
class Evaluation:
    """One stored evaluation: its id, the labels and inputs the service recorded (``meta``), and ``document``,
    the JSON document ``kitti-eval --format json`` prints for the same files."""

    id: str
    document: dict[str, Any]
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Evaluation:
        doc = {k: v for k, v in body.items() if k not in ("id", "evaluation")}
        return cls(id=_id(body["id"]), document=doc, meta=dict(body.get("evaluation") or {}))

    def result(self) -> EvalResult:
        """The document as the library's result (without curves)."""
        from .core.result import EvalResult

        return EvalResult.from_dict(self.document)

    def render(self, fmt: str = "json") -> str:
        """What ``kitti-eval --format FMT`` prints for the same files: the document as it came for ``json``
        (with its curves and error decomposition when they were asked for), else rendered from :meth:`result`."""
        from .report.render import OutputFormat, render

        if OutputFormat(fmt) is OutputFormat.JSON:
            return json.dumps(self.document, indent=2, allow_nan=False) + "\n"
        return render(self.result(), fmt)


@dataclass(frozen=True)
class Job:
    """An accepted evaluation's or submission's job, as ``GET /v1/jobs/{id}`` says it is."""

    id: str
    kind: str
    state: str
    position: int | None = None
    attempts: int = 0
    result_location: str | None = None
    error: dict[str, Any] | None = None

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Job:
        return cls(
            id=_id(body["id"]),
            kind=_shown(body.get("kind", "")),
            state=_shown(body["state"]),
            position=body.get("position"),
            attempts=int(body.get("attempts") or 0),
            result_location=body.get("result_location"),
            error=body.get("error"),
        )

    @property
    def ended(self) -> bool:
        return self.state in ("done", "failed", "cancelled")


@dataclass(frozen=True)
class Submission:
    """One of your submissions as the service shows it to you: ``status`` (``queued``, ``scored``, ``failed``),
    ``scores`` (the board's columns, on the part of the test set the board shows: ``scored_on``), and ``view``,
    everything the service answered. ``reused``: :meth:`Client.submit` sent the key an earlier call saved for
    the same file (the answer is the submission that call made, counted once)."""

    id: str
    benchmark: str
    status: str
    scores: dict[str, float | None] | None
    scored_on: str | None
    view: dict[str, Any]
    reused: bool = False

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> Submission:
        return cls(
            id=_id(body["id"]),
            benchmark=_shown(body.get("benchmark", "")),
            status=_shown(body.get("status", "")),
            scores=body.get("scores"),
            scored_on=body.get("scored_on"),
            view=dict(body),
        )

    def result(self) -> EvalResult | None:
        """The scored document on the part shown, as the library's result (None before it is scored)."""
        from .core.result import EvalResult

        doc = self.view.get("result")
        return EvalResult.from_dict(doc) if doc else None


@dataclass(frozen=True)
class Quota:
    """A benchmark's quota as it stands for you: ``submissions`` in any ``days``, ``used`` and ``left``, and
    ``next_at`` (ISO 8601) when none is left: when the next submission is accepted."""

    submissions: int
    days: float
    used: int
    left: int
    next_at: str | None = None


def _at(benchmark: str, phase: str | None) -> str:
    """The path of a benchmark's phase: its own routes address its current phase."""
    return f"/v1/benchmarks/{benchmark}" if phase is None else f"/v1/benchmarks/{benchmark}/phases/{phase}"
