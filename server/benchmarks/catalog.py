"""The benchmarks themselves: who sees which, their test sets, and the admins' creating, closing, reopening and
revealing."""

from __future__ import annotations

import secrets
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import Any

from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import THRESHOLD_SETS

from ..access.accounts import Accounts
from ..access.audit import Audit
from ..access.policy import Caller, Policy
from ..errors import BadRequest, Conflict, NotFound, echo
from ..ground_truths.cache import GroundTruths
from ..jobs.queue import JobQueue
from ..scoring.evaluator import EvalOptions
from ..store import BenchmarkRecord, BenchmarkStore, GroundTruthRecord
from .lifecycle import check_change
from .phases import PhaseOf, current_phase_of, phase_views
from .rules import (
    DEFAULT_KEY,
    DIFFICULTIES,
    Benchmark,
    check_max_published,
    check_split_percent,
    check_texts,
    parse_column,
    parse_quota,
    parse_time,
)
from .views import benchmark_view

__all__ = ["BenchmarkCatalog", "scoring_options"]

_MAX_COLUMNS = 60


def scoring_options(
    protocol: str, classes: str, threshold_sets: str, key: Sequence[str], columns: Sequence[str]
) -> dict[str, Any]:
    """A benchmark's scoring as its row keeps it (``protocol``, ``classes``, ``sets``, ``key``, ``columns``),
    checked and normalised: the library's checks of the options, each column to its five parts."""
    options = EvalOptions(protocol=protocol, classes=classes, threshold_sets=threshold_sets)
    config = options.config()  # the library's checks of the options
    class_names, sets = list(config.classes), list(config.threshold_sets)
    keys = [parse_column(k, class_names, sets) for k in key if k.strip()] or [DEFAULT_KEY]
    wanted = list(columns) or [f"{c}/3d/{d}" for c in class_names for d in DIFFICULTIES]
    cols = list(dict.fromkeys(parse_column(c, class_names, sets) for c in wanted if c.strip()))
    if len(cols) > _MAX_COLUMNS:
        raise BadRequest(f"at most {_MAX_COLUMNS} columns")
    return {
        "protocol": protocol,
        "classes": ",".join(class_names),
        "sets": ",".join(sets),
        "key": keys,
        "columns": cols,
    }


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
    def named(self, name: str) -> Benchmark:
        record = self.benchmark_store.get_benchmark(name)
        if record is None:
            raise NotFound(f"no benchmark named {echo(name)}")
        return Benchmark.from_record(record)

    def sees(self, caller: Caller, bench: Benchmark) -> bool:
        return self.policy.sees_benchmark(caller, public=bench.public, project=bench.project)

    def get(self, name: str, caller: Caller) -> Benchmark:
        bench = self.named(name)
        if not self.sees(caller, bench):
            raise NotFound(f"no benchmark named {echo(name)}")
        return bench

    def taking_part(self, name: str) -> tuple[str | None, bool]:
        """Who takes part in the benchmark, for :meth:`Policy.may_take_part
        <kitti_eval_server.access.policy.Policy.may_take_part>`: its test set's project (None: shared, or no such
        benchmark) and whether it is open to all."""
        record = self.benchmark_store.get_benchmark(name)
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

    def frame_ids(self, name: str, caller: Caller) -> list[str]:
        """The test frame ids (public, as KITTI's: the labels are what is sealed)."""
        bench = self.get(name, caller)
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
        name: str,
        *,
        ground_truth: str,
        title: str | None = None,
        description: str = "",
        protocol: str = "official",
        classes: str = "Car,Pedestrian,Cyclist",
        threshold_sets: str = ",".join(THRESHOLD_SETS),
        key: Sequence[str] = (DEFAULT_KEY,),
        columns: Sequence[str] = (),
        quota: str = "3/1",
        public: bool = False,
        opens_at: str | datetime | None = None,
        closes_at: str | datetime | None = None,
        split_percent: float | None = None,
        max_published: int | None = None,
        open_to_all: bool = False,
        share_test_set: bool = False,
        caller: Caller,
        phase: PhaseOf | None = None,
    ) -> Benchmark:
        """``open_to_all``: every signed-in account may take part (else the members of the test set's project);
        ``share_test_set``: the test set may already be another benchmark's (refused otherwise: each benchmark
        gives a participant a quota and a public part of its own on the same labels). ``phase``: the row is a
        phase of a benchmark defined by a file (:mod:`.phases`): stored under its row's name, with its phase's
        settings; a phase without a split may be on open labels (a ground truth not sealed)."""
        self.policy.require_admin(caller)
        Accounts.check_name(name, "benchmark")
        name = phase.row if phase is not None else name
        record = self.ground_truths.record(ground_truth)
        open_labels = phase is not None and split_percent is None and not record.sealed
        if not record.sealed and not open_labels:
            raise BadRequest(
                f"the ground truth {ground_truth!r} is not sealed; a benchmark's test set is registered "
                "with sealed=true"
            )
        scoring = scoring_options(protocol, classes, threshold_sets, key, columns)
        count, days = parse_quota(quota)
        split_percent = check_split_percent(split_percent)
        check_max_published(max_published)
        check_texts(title or "", description)
        others = [b.name for b in self.using_ground_truth(record.name)]
        if others and not share_test_set:
            named = ", ".join(repr(b) for b in others)
            raise Conflict(
                f"the ground truth {record.name!r} is already the test set of benchmark {named}: a second "
                "benchmark on it gives every participant a second quota and a second public part of the same "
                "labels; register another test set, or say share_test_set=true (--share-test-set) to take it "
                "anyway"
            )
        opens = parse_time(opens_at, "opens") or datetime.now(timezone.utc)
        closes = parse_time(closes_at, "closes")
        if closes is not None and closes <= opens:
            raise BadRequest("a benchmark closes after it opens")
        bench = BenchmarkRecord(
            name=name,
            title=title or name,
            description=description,
            gt_name=record.name,
            project=record.project,
            config={
                **scoring,
                "quota": [count, days],
                "split_percent": split_percent,
                "open_to_all": bool(open_to_all),
                **(phase.config(open_labels=open_labels) if phase is not None else {}),
            },
            split_seed=secrets.token_hex(16) if split_percent is not None else None,
            public=public,
            opens_at=opens,
            closes_at=closes,
            closed=False,
            revealed=False,
            created_at=datetime.now(timezone.utc),
            max_published=max_published,
        )
        if not self.benchmark_store.add_benchmark(bench):
            raise Conflict(f"a benchmark named {name!r} exists")
        detail = record.name + (f", shared with {', '.join(others)}" if others else "")
        self.audit.record(caller, "benchmark.add", name, detail=detail)
        return self.named(name)

    def set_state(self, name: str, *, caller: Caller, **values: bool) -> Benchmark:
        """close (closed=True), reopen (closed=False), reveal (revealed=True), as :func:`.lifecycle.check_change`
        allows: a phase is revealed once it has opened and is closed (by hand or by its ``closes_at``), and is
        never reopened after."""
        self.policy.require_admin(caller)
        bench = self.named(name)
        check_change(name, bench, values)  # the phase's life allows it (:mod:`.lifecycle`)
        self.benchmark_store.update_benchmark(name, **values)
        action = ",".join(f"{k}={v}" for k, v in sorted(values.items()))
        self.audit.record(caller, "benchmark.state", name, detail=action)
        return self.named(name)
