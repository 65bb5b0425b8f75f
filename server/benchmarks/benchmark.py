"""A stored benchmark (a phase's row) with its rules read from the row: its settings (:mod:`.phase_settings`), its
state (:mod:`.lifecycle`), the part of the test set its board shows. Above :mod:`.phase_settings`, which uses the
checks of :mod:`.rules` below both."""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from datetime import datetime, timezone

from ..scoring.evaluator import EvalOptions
from ..store import BenchmarkRecord
from .lifecycle import PhaseState, has_opened, state_of
from .phase_settings import PhaseSettings
from .rules import PHASE_SEPARATOR

__all__ = ["Benchmark"]


@dataclass(frozen=True)
class Benchmark(BenchmarkRecord):
    """A stored benchmark with its rules read from its row."""

    @classmethod
    def from_record(cls, record: BenchmarkRecord) -> Benchmark:
        return cls(**{f.name: getattr(record, f.name) for f in fields(record)})

    @functools.cached_property
    def settings(self) -> PhaseSettings:
        """Its settings, as its row keeps them (:mod:`.phase_settings`: one type, read by one rule)."""
        return PhaseSettings.of_row(self)

    @property
    def key(self) -> list[str]:
        return list(self.settings.key)

    @property
    def columns(self) -> list[str]:
        return list(self.settings.columns)

    @property
    def quota(self) -> tuple[int, float]:
        return self.settings.quota

    @property
    def open_to_all(self) -> bool:
        """Every signed-in account may take part, not only the members of its test set's project."""
        return self.settings.open_to_all

    @property
    def split_percent(self) -> float | None:
        return self.settings.split_percent

    def has_opened(self, now: datetime | None = None) -> bool:
        """Its period has begun (``opens_at`` has passed), whether or not it was closed since."""
        return has_opened(self.opens_at, now)

    def state(self, now: datetime | None = None) -> PhaseState:
        """Its state (:func:`.lifecycle.state_of`: scheduled, open, closed or revealed)."""
        return state_of(self, now)

    def is_closed(self, now: datetime | None = None) -> bool:
        """Closed (by hand, or its ``closes_at`` has passed) or revealed."""
        return self.state(now) in (PhaseState.CLOSED, PhaseState.REVEALED)

    def is_open(self, now: datetime | None = None) -> bool:
        """Taking submissions: in the state ``open``."""
        return self.state(now) is PhaseState.OPEN

    # -- phases and teams (a benchmark defined by a file, :mod:`.phases`; one made with ``add`` is one phase) --
    @property
    def shown_name(self) -> str:
        """The benchmark's name, as its participants address it (a later phase's row is ``NAME~PHASE``)."""
        return self.name.split(PHASE_SEPARATOR, 1)[0]

    @property
    def is_later_phase(self) -> bool:
        """The row of a phase after the first: listed as a phase of its benchmark, not as a benchmark."""
        return PHASE_SEPARATOR in self.name

    @property
    def phase_name(self) -> str:
        return self.settings.phase

    @property
    def late_submissions(self) -> bool:
        """Taking submissions after its close: scored for their participants, never published nor ranked."""
        return self.settings.late_submissions

    @property
    def open_labels(self) -> bool:
        """A phase on a ground truth that is not sealed (a labelled validation set): no split, and its
        participants see their whole result."""
        return bool(self.config.get("open_labels", False))

    @property
    def team_size(self) -> int:
        """The most members a team may have (1: no teams). Kept on the benchmark's first row."""
        return self.settings.team_size

    def takes_late(self, now: datetime | None = None) -> bool:
        """Closed, and taking late submissions (never ranked)."""
        now = now or datetime.now(timezone.utc)
        return self.late_submissions and self.has_opened(now) and self.state(now) is PhaseState.CLOSED

    @property
    def board_part(self) -> str:
        """The part of the test set whose scores the board shows: ``all`` (no split), ``public`` (the public
        part) or ``private`` (after the reveal). Its JSON field is ``board``; "phase" is the competition's."""
        if self.split_percent is None:
            return "all"
        return "private" if self.revealed else "public"

    def options(self) -> EvalOptions:
        settings = self.settings
        return EvalOptions(protocol=settings.protocol, classes=settings.classes, threshold_sets=settings.threshold_sets)
