"""The benchmarks themselves: who sees which, their test sets, and the admins' creating, closing, reopening and
revealing."""

from __future__ import annotations

import secrets
from dataclasses import replace
from datetime import datetime, timezone
from typing import Any

from kitti_eval.core.frames import Annotations

from ..access.accounts import Accounts
from ..access.audit import Audit
from ..access.policy import Caller, Policy
from ..errors import BadRequest, Conflict, NotFound, echo
from ..ground_truths.cache import GroundTruths
from ..jobs.queue import JobQueue
from ..store import BenchmarkRecord, BenchmarkStore, GroundTruthRecord
from .benchmark import Benchmark
from .lifecycle import check_change
from .phase_settings import PhaseSettings
from .phases import PhaseOf, current_phase_of, phase_views
from .views import benchmark_view

__all__ = ["BenchmarkCatalog"]


class BenchmarkCatalog:
    """Benchmarks on the service's store and ground truths: seeing them (as the policy says), and the admins'
    actions on them (audited)."""

    def __init__(
        self, benchmark_store: BenchmarkStore, ground_truths: GroundTruths, policy: Policy, audit: Audit, jobs: JobQueue
    ) -> None:
        """``ground_truths``: where a benchmark's test set is kept; ``jobs``: the queue its rescorings go through
        (a benchmark described to an admin says how many are left)."""
        self.benchmark_store = benchmark_store
        self.ground_truths = ground_truths
        self.policy = policy
        self.audit = audit
        self.jobs = jobs

    # -- seeing -------------------------------------------------------------------------------------------
    def named(self, row: str) -> Benchmark:
        record = self.benchmark_store.get_benchmark(row)
        if record is None:
            raise NotFound(f"no benchmark named {echo(row)}")
        return Benchmark.from_record(record)

    def sees(self, caller: Caller, bench: Benchmark) -> bool:
        return self.policy.sees_benchmark(
            caller, benchmark=bench.shown_name, public=bench.public, project=bench.project
        )

    def get(self, row: str, caller: Caller) -> Benchmark:
        bench = self.named(row)
        if not self.sees(caller, bench):
            raise NotFound(f"no benchmark named {echo(row)}")
        return bench

    def taking_part(self, row: str) -> tuple[str | None, bool]:
        """Who takes part in the benchmark, for :meth:`Policy.may_take_part
        <kitti_eval_server.access.policy.Policy.may_take_part>`: its test set's project (None: shared, or no such
        benchmark) and whether it is open to all."""
        record = self.benchmark_store.get_benchmark(row)
        if record is None:
            return None, False
        bench = Benchmark.from_record(record)
        return bench.project, bench.open_to_all

    def describe(self, bench: Benchmark, caller: Caller, *, rescoring: bool = False) -> dict[str, Any]:
        """The benchmark as the caller reads it (:func:`.views.benchmark_view`): its test set's name only for
        those the policy lets read it; ``rescoring``: for an admin, the rescoring jobs by state too."""
        out = benchmark_view(
            bench,
            names_test_set=self.policy.names_test_set(caller, project=bench.project),
            phases=phase_views(self, bench, caller),
        )
        if rescoring and self.policy.administers(caller):
            out["rescoring"] = self.jobs.counts(group=bench.name, kind="rescore")
        return out

    def visible(self, caller: Caller) -> list[Benchmark]:
        """The benchmarks the caller sees, by name, each in its current phase."""
        found = [Benchmark.from_record(r) for r in self.benchmark_store.list_benchmarks()]
        firsts = [b for b in found if self.sees(caller, b) and not b.is_later_phase]  # a benchmark, not each phase
        current = [current_phase_of(self, b) for b in firsts]  # each in its current phase
        return [c if self.sees(caller, c) else b for b, c in zip(firsts, current)]

    def frame_ids(self, row: str, caller: Caller) -> list[str]:
        """The test frame ids (public, as KITTI's: the labels are what is sealed)."""
        bench = self.get(row, caller)
        return list(self.ground_truth_of(bench)[1].frame_ids)

    def using_ground_truth(self, name: str) -> list[Benchmark]:
        """The benchmarks whose test set is the ground truth ``name`` (whoever may see them), by name."""
        return [Benchmark.from_record(r) for r in self.benchmark_store.benchmarks_using(name)]

    def ground_truth_of(self, bench: Benchmark) -> tuple[GroundTruthRecord, Annotations]:
        """The benchmark's test set as registered now, loaded (see :meth:`ground_truth_record_of`)."""
        record = self.ground_truth_record_of(bench)
        return record, self.ground_truths.load(record)

    def ground_truth_record_of(self, bench: Benchmark) -> GroundTruthRecord:
        """The record of the benchmark's test set as registered now: refused unless it is sealed (registering a
        benchmark's ground truth unsealed is refused too, so this holds unless the database was changed by hand)."""
        record = self.ground_truths.record(bench.gt_name)
        if not record.sealed and not bench.open_labels:
            raise Conflict(
                f"the test set {bench.gt_name!r} of benchmark {bench.name!r} is not sealed; an admin deletes it "
                "and registers it again with sealed=true"
            )
        return record

    # -- admin ----------------------------------------------------------------------------------------------
    def create(
        self,
        benchmark: str,
        settings: PhaseSettings,
        *,
        caller: Caller,
        share_test_set: bool = False,
        phase: PhaseOf | None = None,
    ) -> Benchmark:
        """Make the benchmark ``benchmark``'s row with ``settings`` (checked as they were made: the route, the
        admin command and a benchmark file make them alike, :class:`.phase_settings.PhaseSettings`), stored by
        their rule. ``share_test_set``: the test set may already be another benchmark's (refused otherwise: each
        benchmark gives a participant a quota and a public part of its own on the same labels). ``phase``: the
        row is a phase of a benchmark defined by a file (:mod:`.phases`): stored under its row's name, the first
        row with the list of phases; a phase without a split may be on open labels (a ground truth not
        sealed)."""
        self.policy.require_admin(caller)
        Accounts.check_name(benchmark, "benchmark")
        row = phase.row if phase is not None else benchmark
        record = self.ground_truths.record(settings.ground_truth)
        open_labels = phase is not None and settings.split_percent is None and not record.sealed
        if not record.sealed and not open_labels:
            raise BadRequest(
                f"the ground truth {settings.ground_truth!r} is not sealed; a benchmark's test set is registered "
                "with sealed=true"
            )
        others = [b.name for b in self.using_ground_truth(record.name)]
        if others and not share_test_set:
            named = ", ".join(repr(b) for b in others)
            raise Conflict(
                f"the ground truth {record.name!r} is already the test set of benchmark {named}: a second "
                "benchmark on it gives every participant a second quota and a second public part of the same "
                "labels; register another test set, or say share_test_set=true (--share-test-set) to take it "
                "anyway"
            )
        now = datetime.now(timezone.utc)
        if settings.opens_at is None:  # a phase opens when it is made unless it says when
            settings = replace(settings, opens_at=now)
        columns, config = settings.stored()
        if open_labels:
            config["open_labels"] = True
        if phase is not None and phase.phases:
            config["phases"] = [list(p) for p in phase.phases]
        bench = BenchmarkRecord(
            name=row,
            project=record.project,
            config=config,
            split_seed=secrets.token_hex(16) if settings.split_percent is not None else None,
            closed=False,
            revealed=False,
            created_at=now,
            **columns,
        )
        if not self.benchmark_store.add_benchmark(bench):
            raise Conflict(f"a benchmark named {row!r} exists")
        detail = record.name + (f", shared with {', '.join(others)}" if others else "")
        self.audit.record(caller, "benchmark.add", row, detail=detail)
        return self.named(row)

    def set_state(self, row: str, *, caller: Caller, **values: bool) -> Benchmark:
        """close (closed=True), reopen (closed=False), reveal (revealed=True), as :func:`.lifecycle.check_change`
        allows: a phase is revealed once it has opened and is closed (by hand or by its ``closes_at``), and is
        never reopened after."""
        self.policy.require_admin(caller)
        bench = self.named(row)
        check_change(row, bench, values)  # the phase's life allows it (:mod:`.lifecycle`)
        self.benchmark_store.update_benchmark(row, **values)
        action = ",".join(f"{k}={v}" for k, v in sorted(values.items()))
        self.audit.record(caller, "benchmark.state", row, detail=action)
        return self.named(row)
