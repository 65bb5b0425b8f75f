"""The database, by area: :mod:`.database` holds what they share (the tables, the engine, the schema, the
retry of a call that found SQLite locked); :mod:`.ground_truth_store`, :mod:`.evaluation_store`,
:mod:`.account_store`, :mod:`.benchmark_store`, :mod:`.job_store`, :mod:`.job_input_store`, :mod:`.worker_store`
and :mod:`.idempotency_store` each define an area's records (frozen dataclasses) and a class of its reads and
writes. :class:`Store` is all of them over one :class:`Database`, as the service and the command line use it.
(The modules are named after their classes, not their tables: a submodule named ``ground_truths`` would replace
the table of that name among the package's attributes when imported.)
"""

from __future__ import annotations

from .account_store import AccountStore, AuditRecord, TokenRecord, UserRecord
from .benchmark_store import (
    BenchmarkRecord,
    BenchmarkStore,
    PublishRefused,
    QuotaRefused,
    ResampledKey,
    SubmissionRecord,
)
from .database import (
    Area,
    Database,
    audit,
    benchmarks,
    evaluation_labels,
    evaluations,
    ground_truth_files,
    ground_truths,
    jobs,
    memberships,
    metadata,
    new_id,
    prediction_files,
    projects,
    quota_locks,
    retry_when_locked,
    submission_resamples,
    submissions,
    tokens,
    users,
)
from .evaluation_store import EvaluationRecord, EvaluationStore
from .ground_truth_store import GroundTruthRecord, GroundTruthStore
from .idempotency_store import IdempotencyRecord, IdempotencyStore, KeyTaken
from .job_input_store import JobInput, JobInputStore
from .job_store import JobRecord, JobStore
from .team_store import TeamRecord, TeamStore
from .worker_store import WorkerRecord, WorkerStore

__all__ = [
    "Store",
    "Database",
    "Area",
    "GroundTruthStore",
    "EvaluationStore",
    "AccountStore",
    "BenchmarkStore",
    "JobStore",
    "WorkerStore",
    "TeamStore",
    "TeamRecord",
    "IdempotencyStore",
    "IdempotencyRecord",
    "KeyTaken",
    "GroundTruthRecord",
    "EvaluationRecord",
    "UserRecord",
    "TokenRecord",
    "AuditRecord",
    "BenchmarkRecord",
    "SubmissionRecord",
    "ResampledKey",
    "JobRecord",
    "WorkerRecord",
    "QuotaRefused",
    "PublishRefused",
    "JobInput",
    "new_id",
    "metadata",
    "ground_truths",
    "ground_truth_files",
    "evaluations",
    "evaluation_labels",
    "prediction_files",
    "users",
    "projects",
    "memberships",
    "tokens",
    "audit",
    "benchmarks",
    "submissions",
    "submission_resamples",
    "quota_locks",
    "jobs",
]


class Store(
    GroundTruthStore,
    EvaluationStore,
    AccountStore,
    BenchmarkStore,
    JobStore,
    JobInputStore,
    WorkerStore,
    IdempotencyStore,
):
    """Every area of the database on one :class:`Database` (SQLite or PostgreSQL)."""

    def __init__(self, url: str, *, busy_s: float = 10.0) -> None:
        """``busy_s``: how long a SQLite call keeps trying while another connection holds the write lock."""
        super().__init__(Database(url, busy_s=busy_s))

    @property
    def busy_s(self) -> float | None:
        return self.db.busy_s

    @retry_when_locked
    def add_job_with_inputs(
        self, record: JobRecord, inputs: list[JobInput], key: IdempotencyRecord | None = None
    ) -> bool:
        """The job and its uploaded files in one transaction (one commit: a job is never without its input);
        False, and nothing added, when the job's id is taken. ``key``: the request's idempotency key, recorded in
        the same transaction (:class:`KeyTaken` when another request recorded it first: nothing is added)."""
        with self._writing() as conn:
            if key is not None:
                self.add_idempotency_key_in(conn, key)
            if not self.add_job_in(conn, record):
                return False
            self.add_job_inputs_in(conn, record.id, inputs)
            return True

    @property
    def lock_retries(self) -> int:
        """Attempts run again because the database was locked (for the tests and the curious)."""
        return self.db.lock_retries

    def create_schema(self) -> None:
        """Create missing tables, and add the columns a database made by an earlier version lacks."""
        self.db.create_schema()

    def ping(self) -> None:
        self.db.ping()

    def dispose(self) -> None:
        self.db.dispose()
