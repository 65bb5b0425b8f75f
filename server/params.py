"""What the JSON routes and the web pages take from a request alike: the service (:data:`ServiceDep`); which phase
a benchmark's route addresses: without a phase, its current one (:data:`CurrentPhase`), a route of one of its
submissions the phase the submission is in (:data:`SubmissionPhase`; a benchmark made with ``benchmark add`` is one
phase: its own row, :mod:`kitti_eval_server.benchmarks.phases`); the bounds of a query's values
(:data:`MAX_SCORE`)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .benchmarks import Benchmarks
from .benchmarks.phases import current_row, submission_row
from .service import Service

__all__ = [
    "get_service",
    "ServiceDep",
    "CurrentPhase",
    "SubmissionPhase",
    "current_phase",
    "submission_phase",
    "MAX_SCORE",
]

#: scores are finite numbers; a threshold beyond this bound selects all or nothing
MAX_SCORE = 1e9


def get_service(request: Request) -> Service:
    service: Service = request.app.state.service
    return service


ServiceDep = Annotated[Service, Depends(get_service)]


def _benchmarks(request: Request) -> Benchmarks:
    found: Benchmarks = request.app.state.benchmarks
    return found


def current_phase(name: str, request: Request) -> str:
    """The row of the benchmark's current phase (the benchmark's own for one made with ``benchmark add``)."""
    return current_row(_benchmarks(request).catalog, name)


def submission_phase(name: str, submission_id: str, request: Request) -> str:
    """The row of the phase a submission of the benchmark is in (else the current phase's: the route's own
    refusal follows)."""
    return submission_row(_benchmarks(request).catalog, name, submission_id)


#: a benchmark's name in a route without a phase: the row of its current phase
CurrentPhase = Annotated[str, Depends(current_phase)]
#: a benchmark's name in a route of one of its submissions: the row of the submission's phase
SubmissionPhase = Annotated[str, Depends(submission_phase)]
