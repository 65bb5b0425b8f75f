"""The database, by area: :mod:`.database` holds what they share (the tables, the engine, the schema, the
retry of a call that found SQLite locked); :mod:`.ground_truth_store`, :mod:`.evaluation_store`,
:mod:`.account_store`, :mod:`.benchmark_store`, :mod:`.job_store`, :mod:`.job_input_store`, :mod:`.worker_store`,
:mod:`.idempotency_store`, :mod:`.gate_result_store`, :mod:`.team_store` and :mod:`.invitation_store` (these two
define their tables themselves) each define an area's records (frozen dataclasses) and a class of its reads and
writes, an object of its own over the shared :class:`Database`; a write that spans areas takes one connection of
:meth:`Database.writing` to each area's ``..._in`` method. :class:`Store` holds one of each area over one
:class:`Database`; the service hands each of its parts the areas that part uses.
(The modules are named after their classes, not their tables: a submodule named ``ground_truths`` would replace
the table of that name among the package's attributes when imported.)
"""

from __future__ import annotations

from typing import Any

from sqlalchemy.engine import Engine

from .account_store import AccountStore, AuditRecord, TokenRecord, UserRecord
from .benchmark_store import (
    BenchmarkRecord,
    BenchmarkStore,
    PublishRefused,
    QuotaRefused,
    QuotaTeam,
    ResampledKey,
    SubmissionRecord,
)
from .database import (
    Area,
    Database,
    UnusableDatabase,
    audit,
    benchmarks,
    evaluation_frames,
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
from .gate_result_store import GateResult, GateResultStore
from .ground_truth_store import GroundTruthRecord, GroundTruthStore
from .idempotency_store import IdempotencyRecord, IdempotencyStore, KeyTaken
from .invitation_store import InvitationRecord, InvitationStore, JoinRefused, NewAccount
from .job_input_store import JobInput, JobInputStore
from .job_store import JobRecord, JobStore
from .team_store import TeamRecord, TeamStore
from .worker_store import WorkerRecord, WorkerStore

__all__ = [
    "Store",
    "Database",
    "UnusableDatabase",
    "Area",
    "GroundTruthStore",
    "EvaluationStore",
    "AccountStore",
    "BenchmarkStore",
    "JobStore",
    "JobInputStore",
    "WorkerStore",
    "TeamStore",
    "InvitationStore",
    "InvitationRecord",
    "JoinRefused",
    "NewAccount",
    "TeamRecord",
    "IdempotencyStore",
    "GateResultStore",
    "GateResult",
    "IdempotencyRecord",
    "KeyTaken",
    "GroundTruthRecord",
    "EvaluationRecord",
    "UserRecord",
    "TokenRecord",
    "AuditRecord",
    "BenchmarkRecord",
    "SubmissionRecord",
    "QuotaTeam",
    "ResampledKey",
    "JobRecord",
    "WorkerRecord",
    "QuotaRefused",
    "PublishRefused",
    "JobInput",
    "new_id",
    "retry_when_locked",
    "metadata",
    "ground_truths",
    "ground_truth_files",
    "evaluations",
    "evaluation_labels",
    "evaluation_frames",
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


class Store:
    """Every area of the database, each its own object over one :class:`Database` (SQLite or PostgreSQL). A part
    of the service is given the areas it uses, not this; the service and the command line hold it to create the
    schema, ping and close the database."""

    def __init__(self, url: str, *, busy_s: float = 10.0) -> None:
        """``busy_s``: how long a SQLite call keeps trying while another connection holds the write lock."""
        self.db = Database(url, busy_s=busy_s)
        self.ground_truth_store = GroundTruthStore(self.db)
        self.evaluation_store = EvaluationStore(self.db)
        self.account_store = AccountStore(self.db)
        self.benchmark_store = BenchmarkStore(self.db)
        self.job_store = JobStore(self.db)
        self.job_input_store = JobInputStore(self.db)
        self.worker_store = WorkerStore(self.db)
        self.idempotency_store = IdempotencyStore(self.db)
        self.gate_result_store = GateResultStore(self.db)
        self.team_store = TeamStore(self.db)
        self.invitation_store = InvitationStore(self.db)

    @property
    def engine(self) -> Engine:
        return self.db.engine

    @property
    def dialect(self) -> str:
        return self.db.dialect

    @property
    def busy_s(self) -> float | None:
        return self.db.busy_s

    @property
    def lock_retries(self) -> int:
        """Attempts run again because the database was locked (for the tests and the curious)."""
        return self.db.lock_retries

    def create_schema(self, *, upgrade: bool = True, where: str = "") -> str | None:
        """Bring the schema to this release's: created when the database is empty, upgraded when it is older and
        ``upgrade``, else refused (:meth:`Database.create_schema`); the revision it was at before."""
        return self.db.create_schema(upgrade=upgrade, where=where)

    def schema_state(self) -> Any:
        """Where the database's schema is (:class:`.schema.SchemaState`)."""
        return self.db.schema_state()

    def ping(self) -> None:
        self.db.ping()

    def dispose(self) -> None:
        self.db.dispose()
