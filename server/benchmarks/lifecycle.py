"""A phase's life: the one place its state is decided, and the changes of state it allows.

A phase (a benchmark's row, :mod:`.phases`) is in one of four states, computed by :func:`state_of` from its
row (``opens_at``, ``closes_at``, ``closed``, ``revealed``) and the time:

- ``scheduled``: its ``opens_at`` is still to come;
- ``open``: it has opened, and neither its ``closes_at`` has passed nor was it closed by hand;
- ``closed``: its ``closes_at`` has passed, or it was closed by hand (a phase closed by hand before it opens is
  closed too: reopening it makes it scheduled again);
- ``revealed``: its private ranking is out. Final: nothing changes it back.

The changes it allows (:data:`TRANSITIONS`): scheduled -> open (time, or an earlier ``opens_at``), open ->
closed (time, ``close`` or an earlier ``closes_at``), closed -> open (``reopen`` or a later ``closes_at``, only
before the reveal: a revealed phase is never anything else), closed -> revealed (``reveal``), and a scheduled
phase closed by hand and reopened. Every surface that changes a phase's row (the close, reopen and reveal routes
and admin commands, applying the benchmark file) asks :func:`check_change` first, and every surface that reads a
phase's state (submissions, teams, views, pages) asks :func:`state_of`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from datetime import datetime, timezone
from enum import Enum
from typing import Any, Protocol, TypeVar

from ..errors import Conflict

__all__ = ["PhaseState", "TRANSITIONS", "state_of", "check_change", "PhaseTimes"]


class PhaseState(str, Enum):
    SCHEDULED = "scheduled"
    OPEN = "open"
    CLOSED = "closed"
    REVEALED = "revealed"


class PhaseTimes(Protocol):
    """What a phase's state is computed from (a :class:`~.store.BenchmarkRecord`)."""

    @property
    def opens_at(self) -> datetime: ...

    @property
    def closes_at(self) -> datetime | None: ...

    @property
    def closed(self) -> bool: ...

    @property
    def revealed(self) -> bool: ...


R = TypeVar("R", bound=PhaseTimes)

#: (before, after): the changes of state a phase may go through (a state may always stay as it is)
TRANSITIONS: frozenset[tuple[PhaseState, PhaseState]] = frozenset(
    {
        (PhaseState.SCHEDULED, PhaseState.OPEN),
        (PhaseState.SCHEDULED, PhaseState.CLOSED),  # closed by hand before it opens
        (PhaseState.OPEN, PhaseState.CLOSED),
        (PhaseState.CLOSED, PhaseState.OPEN),
        (PhaseState.CLOSED, PhaseState.REVEALED),
    }
)

#: the columns of a phase's row its state is computed from
STATE_COLUMNS = ("opens_at", "closes_at", "closed", "revealed")


def has_opened(opens_at: datetime, now: datetime | None = None) -> bool:
    """A period that begins at ``opens_at`` has begun at ``now`` (default: the present)."""
    return opens_at <= (now or datetime.now(timezone.utc))


def past_closing(closes_at: datetime | None, now: datetime | None = None) -> bool:
    """A period that ends at ``closes_at`` (None: never) has ended at ``now`` (default: the present)."""
    return closes_at is not None and closes_at <= (now or datetime.now(timezone.utc))


def state_of(phase: PhaseTimes, now: datetime | None = None) -> PhaseState:
    """The phase's state at ``now`` (default: the present)."""
    now = now or datetime.now(timezone.utc)
    if phase.revealed:
        return PhaseState.REVEALED
    if phase.closed or past_closing(phase.closes_at, now):
        return PhaseState.CLOSED
    if not has_opened(phase.opens_at, now):
        return PhaseState.SCHEDULED
    return PhaseState.OPEN


def _refusal(
    name: str, before: PhaseState, after: PhaseState, phase: PhaseTimes, columns: set[str], now: datetime
) -> str:
    if before is PhaseState.REVEALED and columns <= {"closed", "revealed"}:
        return "revealed benchmarks stay closed: the private part's scores are out"
    if before is PhaseState.REVEALED:
        return (
            f"the phase {name!r} is revealed (its private ranking is out): it stays closed and its dates no longer "
            "change"
        )
    if after is PhaseState.REVEALED and now < phase.opens_at:
        return (
            f"the phase {name!r} has not opened yet (it opens at {phase.opens_at.isoformat()}): there is no ranking "
            "to reveal"
        )
    if after is PhaseState.REVEALED:
        return (
            f"the phase {name!r} is open: the private ranking is revealed once the phase is closed (close it first, "
            "or wait for its closes_at)"
        )
    if after is PhaseState.SCHEDULED:
        return f"the phase {name!r} has opened (it is {before.value}): it does not go back to being scheduled"
    return f"the phase {name!r} does not go from {before.value} to {after.value}"


def _unclosed_before_opening(before: PhaseState, after: PhaseState) -> bool:
    """A phase closed by hand before it opened, reopened: scheduled again (checked against its opens_at)."""
    return before is PhaseState.CLOSED and after is PhaseState.SCHEDULED


def check_change(
    name: str, phase: R, changes: Mapping[str, Any], *, now: datetime | None = None
) -> tuple[PhaseState, PhaseState]:
    """The phase's state before and after its row takes ``changes`` (columns of the row; those its state is not
    computed from are ignored), or :class:`.Conflict` naming ``name`` when the machine does not allow the change.
    A revealed phase takes no change of its dates nor of its state."""
    now = now or datetime.now(timezone.utc)
    before = state_of(phase, now)
    relevant = {k: v for k, v in changes.items() if k in STATE_COLUMNS}
    after = state_of(dataclasses.replace(phase, **relevant), now) if relevant else before  # type: ignore[type-var]
    moved = {k for k, v in relevant.items() if getattr(phase, k) != v}
    # a revealed phase stays closed and revealed; asked to reopen, or given dates, it refuses (even when its row
    # would not change: a reopen of a phase closed by its closes_at and revealed is no less refused)
    undoing = {k for k, v in relevant.items() if not (k in ("closed", "revealed") and v is True)}
    refused = (
        (before is PhaseState.REVEALED and bool(undoing))
        or (before != after and (before, after) not in TRANSITIONS and not _unclosed_before_opening(before, after))
        or (after is PhaseState.REVEALED and before is not PhaseState.REVEALED and now < phase.opens_at)
    )
    if before is PhaseState.CLOSED and after is PhaseState.SCHEDULED and phase.opens_at <= now:
        refused = True  # it had opened: moving its opens_at later does not make it scheduled again
    if refused:
        raise Conflict(_refusal(name, before, after, phase, undoing | moved, now))
    return before, after
