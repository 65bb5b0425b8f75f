"""A benchmark's phases: a development phase on a labelled validation set, a test phase on a sealed set, each
with its own dates, quota, split and board.

Each phase is stored as a benchmark row of its own, so every rule of a benchmark (the quota, the split and its
reveal, the freeze at the close, the intervals and rank ranges) holds per phase as it is: the first phase is the
benchmark's own row (``NAME``), a later one the row ``NAME~PHASE`` (``~`` is in no name a host can give). The
first row's ``config`` lists the phases in order (``phases``: ``[[phase, row], ...]``); each row's holds its
phase's name (``phase``), the team size, whether it takes late submissions and whether it is on open labels.
A benchmark made with ``benchmark add`` is one phase, named ``main``.

The benchmark's routes without a phase address its current phase (:func:`current_row`): the first phase taking
submissions now; else the last one that has opened; else the first.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Protocol

from ..access.policy import Caller, Policy
from ..errors import ApiError, NotFound, echo
from ..store import BenchmarkRecord, BenchmarkStore
from .benchmark import Benchmark
from .phase_settings import check_phase_name
from .rules import MAIN_PHASE, PHASE_SEPARATOR
from .views import phase_view


class BenchmarkCatalog(Protocol):
    """What the phases read of :class:`.catalog.BenchmarkCatalog` (which reads the phases: named here, not
    imported, so the two modules do not import each other)."""

    benchmark_store: BenchmarkStore
    policy: Policy

    def sees(self, caller: Caller, bench: Benchmark) -> bool: ...

    def get(self, row: str, caller: Caller) -> Benchmark: ...


__all__ = [
    "PhaseOf",
    "phase_list",
    "phase_row",
    "check_phase_name",
    "current_row",
    "current_phase_of",
    "last_phase",
    "row_of",
    "addressed_row",
    "submission_row",
    "phase_views",
    "MAX_BENCHMARK_NAME",
]

#: a benchmark with phases: its name and ``~PHASE`` fit a benchmark row's 64 characters
MAX_BENCHMARK_NAME = 40


def phase_row(benchmark: str, phase: str, *, first: bool) -> str:
    """The row a phase is stored as."""
    return benchmark if first else f"{benchmark}{PHASE_SEPARATOR}{phase}"


@dataclass(frozen=True)
class PhaseOf:
    """Where :meth:`BenchmarkCatalog.create <.catalog.BenchmarkCatalog.create>` stores a phase of a benchmark
    defined by a file: its row, and on the first row the phases in order (its settings, the phase's name among
    them, are :class:`.phase_settings.PhaseSettings`)."""

    row: str
    phases: tuple[tuple[str, str], ...] = ()  # the first row only: (phase, row) in order


def phase_list(first: BenchmarkRecord) -> list[tuple[str, str]]:
    """(phase, row) of a benchmark in order, from its first row."""
    listed = first.config.get("phases")
    if not listed:
        return [(str(first.config.get("phase") or MAIN_PHASE), first.name)]
    return [(str(p), str(r)) for p, r in listed]


def _rows(catalog: BenchmarkCatalog, benchmark: str) -> list[Benchmark]:
    first = catalog.benchmark_store.get_benchmark(benchmark)
    if first is None:
        return []
    rows = []
    for _, row in phase_list(first):
        record = first if row == first.name else catalog.benchmark_store.get_benchmark(row)
        if record is not None:
            rows.append(Benchmark.from_record(record))
    return rows


def _current(rows: list[Benchmark], now: datetime) -> Benchmark:
    for bench in rows:
        if bench.is_open(now):
            return bench
    opened = [b for b in rows if b.has_opened(now)]
    return opened[-1] if opened else rows[0]


def current_row(catalog: BenchmarkCatalog, benchmark: str) -> str:
    """The row the benchmark's routes without a phase address: its current phase's (``benchmark`` itself when
    it has one phase, is a phase's row or is no benchmark: the route's own answer follows)."""
    if PHASE_SEPARATOR in benchmark:
        return benchmark
    rows = _rows(catalog, benchmark)
    if len(rows) < 2:
        return benchmark
    return _current(rows, datetime.now(timezone.utc)).name


def submission_row(catalog: BenchmarkCatalog, benchmark: str, submission_id: str) -> str:
    """The row of the phase a submission of the benchmark ``benchmark`` is in (else its current phase's:
    whoever asks, the route's own refusal follows for a submission that is not theirs or not there)."""
    record = catalog.benchmark_store.get_submission(submission_id)
    if record is not None and record.benchmark.split(PHASE_SEPARATOR, 1)[0] == benchmark:
        return record.benchmark
    return current_row(catalog, benchmark)


def current_phase_of(catalog: BenchmarkCatalog, first: Benchmark) -> Benchmark:
    """The current phase of the benchmark whose first row is ``first`` (``first`` itself for one phase)."""
    if not first.config.get("phases"):
        return first
    rows = _rows(catalog, first.name)
    return _current(rows, datetime.now(timezone.utc)) if rows else first


def last_phase(catalog: BenchmarkCatalog, first: Benchmark) -> Benchmark:
    """The last phase of the benchmark whose first row is ``first`` (``first`` itself for one phase): once it
    has closed, the benchmark has (:meth:`.teams.Teams` change no more)."""
    rows = _rows(catalog, first.shown_name)
    return rows[-1] if rows else first


def row_of(catalog: BenchmarkCatalog, benchmark: str, phase: str, caller: Caller) -> str:
    """The row of the benchmark's phase ``phase``, for a caller who sees the benchmark (404 otherwise, as for a
    benchmark that does not exist)."""
    if PHASE_SEPARATOR in benchmark:
        raise NotFound(f"no benchmark named {echo(benchmark)}")
    catalog.get(benchmark, caller)
    for bench in _rows(catalog, benchmark):
        if bench.phase_name == phase:
            catalog.get(bench.name, caller)
            return bench.name
    raise NotFound(f"the benchmark {benchmark!r} has no phase named {echo(phase)}")


def addressed_row(catalog: BenchmarkCatalog, benchmark: str, phase: str | None, caller: Caller) -> str | None:
    """The row a route of the benchmark ``benchmark`` addresses, for whoever asks before a request's body: the
    phase ``phase``'s (:func:`row_of`; None where it refuses: the route refuses them), else the current phase's
    (:func:`current_row`)."""
    if phase is None:
        return current_row(catalog, benchmark)
    try:
        return row_of(catalog, benchmark, phase, caller)
    except ApiError:
        return None


def phase_views(catalog: BenchmarkCatalog, bench: Benchmark, caller: Caller) -> list[dict[str, Any]]:
    """The phases of ``bench``'s benchmark the caller sees, in order, the current one marked."""
    rows = _rows(catalog, bench.shown_name) or [bench]
    now = datetime.now(timezone.utc)
    current = _current(rows, now).name
    return [
        phase_view(
            b,
            current=b.name == current,
            names_test_set=catalog.policy.names_test_set(caller, project=b.project),
            now=now,
        )
        for b in rows
        if catalog.sees(caller, b)
    ]
