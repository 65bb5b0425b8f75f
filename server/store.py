"""The database: SQLAlchemy 2 Core tables and one small class that reads and writes them.

SQLite (the default, one file in the data folder) runs in WAL mode with ``synchronous=FULL``; PostgreSQL is
reached through psycopg 3. Every write is one transaction committed before the method returns, so a
caller that answers 2xx after it has a durable row.
"""

from __future__ import annotations

import functools
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, TypeVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Table,
    create_engine,
    delete,
    event,
    exists,
    func,
    insert,
    inspect,
    select,
    text,
    update,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Engine, RowMapping
from sqlalchemy.exc import IntegrityError, OperationalError

__all__ = [
    "Store",
    "GroundTruthRecord",
    "EvaluationRecord",
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
    "UserRecord",
    "TokenRecord",
    "AuditRecord",
    "benchmarks",
    "submissions",
    "quota_locks",
    "QuotaRefused",
]

metadata = MetaData()
_JSON = JSON().with_variant(JSONB(), "postgresql")

ground_truths = Table(
    "ground_truths",
    metadata,
    Column("name", String(64), primary_key=True),
    Column("sha256", String(64), nullable=False),
    Column("format", String(16), nullable=False),  # pickle | zip | tar
    Column("filename", String(255), nullable=False),  # the uploader's name for the file
    Column("storage", String(255), nullable=False),  # path under the data folder
    Column("size_bytes", BigInteger, nullable=False),
    Column("frames", Integer, nullable=False),
    Column("boxes", Integer, nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("project", String(64), nullable=True),  # None: shared by every project (and open mode's)
    Column("sealed", Boolean, nullable=False, default=False),  # no per-frame view ever leaves the service
)

#: the registered files themselves, by content, so that any server on the same database can load them
ground_truth_files = Table(
    "ground_truth_files",
    metadata,
    Column("sha256", String(64), primary_key=True),
    Column("content", LargeBinary, nullable=False),
)

evaluations = Table(
    "evaluations",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("gt_name", String(64), nullable=True),  # None: ground truth uploaded with the request
    Column("gt_sha256", String(64), nullable=False),
    Column("pred_filename", String(255), nullable=False),
    Column("pred_sha256", String(64), nullable=False),
    Column("pred_format", String(16), nullable=False),
    Column("pred_size", BigInteger, nullable=False),
    Column("protocol", String(16), nullable=False),
    Column("duration_ms", Float, nullable=False),
    Column("summary", _JSON, nullable=False),  # strict R40 moderate AP per class and metric
    Column("result", _JSON, nullable=False),  # the document `kitti-eval --format json` prints
    Column("options", _JSON, nullable=True),  # the request's options (None: stored before they were)
    Column("project", String(64), nullable=True),  # None: made in open mode (admins only see it in accounts mode)
    Index("ix_evaluations_created", "created_at", "id"),
    Index("ix_evaluations_gt", "gt_name", "created_at"),
)

#: uploaded predictions by content, kept so that frames of an evaluation can be looked at later
prediction_files = Table(
    "prediction_files",
    metadata,
    Column("sha256", String(64), primary_key=True),
    Column("content", LargeBinary, nullable=False),
)

evaluation_labels = Table(
    "evaluation_labels",
    metadata,
    Column("evaluation_id", String(32), ForeignKey("evaluations.id", ondelete="CASCADE"), primary_key=True),
    Column("key", String(64), primary_key=True),
    Column("value", String(256), nullable=False),
    Index("ix_labels_key_value", "key", "value"),
)


users = Table(
    "users",
    metadata,
    Column("name", String(64), primary_key=True),
    Column("is_admin", Boolean, nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
)

projects = Table(
    "projects",
    metadata,
    Column("name", String(64), primary_key=True),
    Column("created_at", DateTime(timezone=True), nullable=False),
)

memberships = Table(
    "memberships",
    metadata,
    Column("user_name", String(64), ForeignKey("users.name", ondelete="CASCADE"), primary_key=True),
    Column("project", String(64), ForeignKey("projects.name", ondelete="CASCADE"), primary_key=True),
)

#: bearer tokens and web sessions: only the sha256 of the secret is kept, looked up by the public id
tokens = Table(
    "tokens",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("user_name", String(64), ForeignKey("users.name", ondelete="CASCADE"), nullable=False),
    Column("kind", String(16), nullable=False),  # token | session
    Column("parent", String(32), nullable=True),  # a session: the token it was opened with
    Column("secret_sha256", String(64), nullable=False),
    Column("scopes", String(64), nullable=False),  # comma-separated: read, write
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("expires_at", DateTime(timezone=True), nullable=True),
    Column("revoked_at", DateTime(timezone=True), nullable=True),
    Index("ix_tokens_parent", "parent"),
)

#: admin actions and refused token uses (never a token itself)
audit = Table(
    "audit",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("at", DateTime(timezone=True), nullable=False),
    Column("actor", String(128), nullable=False),  # user name and token id, "admin-token", "cli:<os user>"
    Column("action", String(64), nullable=False),
    Column("target", String(256), nullable=False),
    Column("outcome", String(32), nullable=False),  # ok | refused | ...
    Column("client", String(64), nullable=False),
    Column("detail", String(512), nullable=False),
    Index("ix_audit_at", "at"),
)


#: hosted benchmarks on a sealed ground truth (see kitti_eval_server.benchmarks)
benchmarks = Table(
    "benchmarks",
    metadata,
    Column("name", String(64), primary_key=True),
    Column("title", String(200), nullable=False),
    Column("description", String(20000), nullable=False),
    Column("gt_name", String(64), nullable=False),
    Column("project", String(64), nullable=True),  # the ground truth's project (None: shared)
    Column("config", _JSON, nullable=False),  # options, key, columns, quota, split percent
    Column("split_seed", String(64), nullable=True),  # secret: draws the public part of the test frames
    Column("public", Boolean, nullable=False),
    Column("opens_at", DateTime(timezone=True), nullable=False),
    Column("closes_at", DateTime(timezone=True), nullable=True),
    Column("closed", Boolean, nullable=False),  # closed by hand (whatever closes_at says)
    Column("revealed", Boolean, nullable=False),  # the private ranking is shown
    Column("created_at", DateTime(timezone=True), nullable=False),
)

submissions = Table(
    "submissions",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("benchmark", String(64), ForeignKey("benchmarks.name", ondelete="CASCADE"), nullable=False),
    Column("participant", String(64), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("status", String(16), nullable=False),  # accepted | scored | failed
    Column("pred_filename", String(255), nullable=False),
    Column("pred_sha256", String(64), nullable=False),
    Column("pred_size", BigInteger, nullable=False),
    Column("gt_sha256", String(64), nullable=True),  # the ground truth it was last scored against
    Column("scored_at", DateTime(timezone=True), nullable=True),
    Column("result", _JSON, nullable=True),  # the (sealed) evaluation document on every test frame
    Column("scores", _JSON, nullable=True),  # {"all"|"public"|"private": {column: AP}}
    Column("published", Boolean, nullable=False),
    Column("method", String(100), nullable=True),
    Column("anonymous", Boolean, nullable=False),
    Column("affiliation", String(200), nullable=True),
    Column("link", String(500), nullable=True),
    Column("published_at", DateTime(timezone=True), nullable=True),
    Column("disqualified", Boolean, nullable=False),
    Index("ix_submissions_quota", "benchmark", "participant", "created_at"),
)

#: one row per (benchmark, participant), locked while a submission is counted against the quota
quota_locks = Table(
    "quota_locks",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
)


class QuotaRefused(Exception):
    """No room in the quota: ``retry_at`` is when the oldest accepted submission of the window leaves it."""

    def __init__(self, retry_at: datetime, used: int) -> None:
        super().__init__(f"quota used ({used})")
        self.retry_at = retry_at
        self.used = used


@dataclass(frozen=True)
class UserRecord:
    name: str
    is_admin: bool
    created_at: datetime
    projects: tuple[str, ...] = ()


@dataclass(frozen=True)
class TokenRecord:
    id: str
    user_name: str
    kind: str
    parent: str | None
    secret_sha256: str
    scopes: str
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None


@dataclass(frozen=True)
class AuditRecord:
    id: int
    at: datetime
    actor: str
    action: str
    target: str
    outcome: str
    client: str
    detail: str


@dataclass(frozen=True)
class GroundTruthRecord:
    name: str
    sha256: str
    format: str
    filename: str
    storage: str
    size_bytes: int
    frames: int
    boxes: int
    created_at: datetime
    project: str | None = None
    sealed: bool = False


@dataclass(frozen=True)
class EvaluationRecord:
    id: str
    created_at: datetime
    gt_name: str | None
    gt_sha256: str
    pred_filename: str
    pred_sha256: str
    pred_format: str
    pred_size: int
    protocol: str
    duration_ms: float
    summary: Mapping[str, Any]
    result: Mapping[str, Any] | None  # None when listed without results
    labels: Mapping[str, str] = field(default_factory=dict)
    #: the request's options (:class:`kitti_eval_server.evaluator.EvalOptions` as a dict); None for older rows
    options: Mapping[str, Any] | None = None
    project: str | None = None


#: the PostgreSQL advisory lock held while the schema is created or upgraded (any fixed 64-bit number)
_SCHEMA_LOCK = 0x6B69747469657661  # "kittieva"


def _utc(value: datetime) -> datetime:
    return value if value.tzinfo else value.replace(tzinfo=timezone.utc)  # SQLite keeps no zone


def _sqlite_pragmas(busy_ms: int) -> Callable[[Any, Any], None]:
    def on_connect(dbapi_connection: Any, _record: Any) -> None:
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=FULL")  # WAL + FULL: a committed row survives a crash and power loss
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={busy_ms}")
        cursor.close()

    return on_connect


#: SQLite's primary result codes for "another connection holds the lock"
_SQLITE_BUSY, _SQLITE_LOCKED = 5, 6
#: the longest one attempt waits for a SQLite lock (SQLite's own busy handler), and the pauses between attempts
_ATTEMPT_S = 1.0
_FIRST_PAUSE_S, _LONGEST_PAUSE_S = 0.02, 0.5

F = TypeVar("F", bound=Callable[..., Any])
_retrying = threading.local()


def _locked(exc: OperationalError) -> bool:
    """SQLite's "database is locked" (or "database table is locked")."""
    orig = exc.orig
    return isinstance(orig, sqlite3.Error) and getattr(orig, "sqlite_errorcode", -1) & 0xFF in (
        _SQLITE_BUSY,
        _SQLITE_LOCKED,
    )


def _retry_when_locked(method: F) -> F:
    """Run a store method again, after a short pause growing from 20 ms to 0.5 s, while SQLite says the
    database is locked (another process writing: a CLI command, a second worker, a backup holding a lock),
    until :attr:`Store.busy_s` has passed; then the last error is raised. Each attempt is one transaction,
    rolled back when it fails, so running it again is safe. Calls from inside a retried method are not
    retried on their own (one budget a call)."""

    @functools.wraps(method)
    def wrapper(self: Store, *args: Any, **kwargs: Any) -> Any:
        if self.busy_s is None or getattr(_retrying, "active", False):
            return method(self, *args, **kwargs)
        deadline = time.monotonic() + self.busy_s
        pause = _FIRST_PAUSE_S
        _retrying.active = True
        try:
            while True:
                try:
                    return method(self, *args, **kwargs)
                except OperationalError as e:
                    if not _locked(e) or time.monotonic() + pause >= deadline:
                        raise
                    self.lock_retries += 1
                time.sleep(pause)
                pause = min(2 * pause, _LONGEST_PAUSE_S)
        finally:
            _retrying.active = False

    return wrapper  # type: ignore[return-value]


def new_id() -> str:
    return uuid.uuid4().hex


class Store:
    """Ground-truth registrations and evaluations, in SQLite or PostgreSQL."""

    def __init__(self, url: str, *, busy_s: float = 10.0) -> None:
        """``busy_s``: how long a SQLite call keeps trying while another connection holds the write lock
        (:func:`_retry_when_locked`). PostgreSQL connections are checked before each use
        (``pool_pre_ping``), so the pool drops the ones a restarted server closed instead of failing a
        request with them."""
        #: SQLite only: the retry budget of a locked database (None: PostgreSQL, whose locks wait themselves)
        self.busy_s: float | None = None
        #: attempts run again because the database was locked (for the tests and the curious)
        self.lock_retries = 0
        if url.startswith("sqlite"):
            self.busy_s = busy_s
            attempt = min(_ATTEMPT_S, busy_s / 4)
            self.engine: Engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": attempt})
            event.listen(self.engine, "connect", _sqlite_pragmas(max(1, round(attempt * 1000))))
        else:
            self.engine = create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=10)
        self.dialect = self.engine.dialect.name

    @_retry_when_locked
    def create_schema(self) -> None:
        """Create missing tables, and add the columns a database made by an earlier version lacks.

        On PostgreSQL this runs in one transaction under an advisory lock: servers started together on one
        empty database (replicas rolled out at once) would otherwise all issue the same CREATE TABLE, and
        all but one fail at start-up (a unique violation in PostgreSQL's catalog). The others wait for the
        lock, then find the tables there."""
        with self.engine.begin() as conn:
            if self.dialect == "postgresql":
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _SCHEMA_LOCK})
            metadata.create_all(conn)
            json_kind = "JSONB" if self.dialect == "postgresql" else "JSON"
            added = {
                "evaluations": {"options": json_kind, "project": "VARCHAR(64)"},
                "ground_truths": {"project": "VARCHAR(64)", "sealed": "BOOLEAN NOT NULL DEFAULT FALSE"},
            }
            for table, columns in added.items():
                present = {c["name"] for c in inspect(conn).get_columns(table)}
                for column, kind in columns.items():
                    if column not in present:
                        conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {column} {kind}"))

    @_retry_when_locked
    def ping(self) -> None:
        with self.engine.connect() as conn:
            conn.execute(text("SELECT 1"))

    def dispose(self) -> None:
        self.engine.dispose()

    # -- ground truths ---------------------------------------------------------------------------------
    @_retry_when_locked
    def add_ground_truth(self, record: GroundTruthRecord, content: bytes) -> bool:
        """Insert the record and (once per sha256) its file; False if the name is taken (nothing changed)."""
        for _ in range(2):  # a concurrent registration of the same file may insert its content first
            try:
                with self.engine.begin() as conn:
                    known = conn.execute(
                        select(ground_truth_files.c.sha256).where(ground_truth_files.c.sha256 == record.sha256)
                    ).first()
                    if known is None:
                        conn.execute(insert(ground_truth_files).values(sha256=record.sha256, content=content))
                    conn.execute(insert(ground_truths).values(**record.__dict__))
                return True
            except IntegrityError:
                if self.get_ground_truth(record.name) is not None:
                    return False
        return False

    @_retry_when_locked
    def ground_truth_content(self, sha256: str) -> bytes | None:
        with self.engine.connect() as conn:
            row = conn.execute(
                select(ground_truth_files.c.content).where(ground_truth_files.c.sha256 == sha256)
            ).first()
        return None if row is None else bytes(row[0])

    @_retry_when_locked
    def get_ground_truth(self, name: str) -> GroundTruthRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(ground_truths).where(ground_truths.c.name == name)).mappings().first()
        return None if row is None else self._gt(row)

    @_retry_when_locked
    def list_ground_truths(self, *, projects: frozenset[str] | None = None) -> list[GroundTruthRecord]:
        """By name; ``projects``: only those of these projects and the shared ones (None: all)."""
        query = select(ground_truths).order_by(ground_truths.c.name)
        if projects is not None:
            query = query.where(ground_truths.c.project.is_(None) | ground_truths.c.project.in_(sorted(projects)))
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._gt(r) for r in rows]

    @_retry_when_locked
    def delete_ground_truth(self, name: str) -> tuple[GroundTruthRecord | None, bool]:
        """Delete by name: (the deleted record or None, whether another name still uses the same file)."""
        with self.engine.begin() as conn:
            row = conn.execute(select(ground_truths).where(ground_truths.c.name == name)).mappings().first()
            if row is None:
                return None, False
            conn.execute(delete(ground_truths).where(ground_truths.c.name == name))
            shared = conn.execute(
                select(func.count()).select_from(ground_truths).where(ground_truths.c.sha256 == row["sha256"])
            ).scalar_one()
            if not shared:
                conn.execute(delete(ground_truth_files).where(ground_truth_files.c.sha256 == row["sha256"]))
        return self._gt(row), bool(shared)

    @staticmethod
    def _gt(row: RowMapping) -> GroundTruthRecord:
        values = dict(row)
        values["created_at"] = _utc(values["created_at"])
        values["sealed"] = bool(values.get("sealed"))
        return GroundTruthRecord(**values)

    # -- predictions -----------------------------------------------------------------------------------
    @_retry_when_locked
    def add_prediction_file(self, sha256: str, content: bytes) -> None:
        """Keep an uploaded predictions file (once per content)."""
        try:
            with self.engine.begin() as conn:
                if (
                    conn.execute(select(prediction_files.c.sha256).where(prediction_files.c.sha256 == sha256)).first()
                    is None
                ):
                    conn.execute(insert(prediction_files).values(sha256=sha256, content=content))
        except IntegrityError:  # the same file, kept concurrently by another request
            pass

    @_retry_when_locked
    def prediction_content(self, sha256: str) -> bytes | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(prediction_files.c.content).where(prediction_files.c.sha256 == sha256)).first()
        return None if row is None else bytes(row[0])

    # -- evaluations -----------------------------------------------------------------------------------
    @_retry_when_locked
    def add_evaluation(self, record: EvaluationRecord) -> None:
        values = {k: v for k, v in record.__dict__.items() if k != "labels"}
        with self.engine.begin() as conn:
            conn.execute(insert(evaluations).values(**values))
            if record.labels:
                conn.execute(
                    insert(evaluation_labels),
                    [{"evaluation_id": record.id, "key": k, "value": v} for k, v in record.labels.items()],
                )

    @_retry_when_locked
    def get_evaluation(self, evaluation_id: str) -> EvaluationRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(evaluations).where(evaluations.c.id == evaluation_id)).mappings().first()
            if row is None:
                return None
            labels = self._labels(conn, [evaluation_id])
        return self._evaluation(row, labels.get(evaluation_id, {}))

    @_retry_when_locked
    def evaluation_project(self, evaluation_id: str) -> tuple[bool, str | None]:
        """(whether the evaluation exists, its project): one small read, before any result is loaded."""
        with self.engine.connect() as conn:
            row = conn.execute(select(evaluations.c.project).where(evaluations.c.id == evaluation_id)).first()
        return (False, None) if row is None else (True, row[0])

    def list_evaluations(
        self,
        *,
        gt_name: str | None = None,
        labels: Mapping[str, str] | None = None,
        limit: int = 50,
        offset: int = 0,
        projects: frozenset[str] | None = None,
    ) -> list[EvaluationRecord]:
        """Newest first, without the full results (the summary is there); ``projects``: only those of these
        projects (None: all)."""
        columns = [c for c in evaluations.c if c.name != "result"]
        query = select(*columns)
        if projects is not None:
            query = query.where(evaluations.c.project.in_(sorted(projects)))
        if gt_name is not None:
            query = query.where(evaluations.c.gt_name == gt_name)
        for key, value in (labels or {}).items():
            query = query.where(
                exists().where(
                    evaluation_labels.c.evaluation_id == evaluations.c.id,
                    evaluation_labels.c.key == key,
                    evaluation_labels.c.value == value,
                )
            )
        query = query.order_by(evaluations.c.created_at.desc(), evaluations.c.id.desc()).limit(limit).offset(offset)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            found = self._labels(conn, [r["id"] for r in rows])
        return [self._evaluation(r, found.get(r["id"], {})) for r in rows]

    @staticmethod
    def _labels(conn: Any, ids: list[str]) -> dict[str, dict[str, str]]:
        out: dict[str, dict[str, str]] = {}
        if not ids:
            return out
        rows = conn.execute(
            select(evaluation_labels)
            .where(evaluation_labels.c.evaluation_id.in_(ids))
            .order_by(evaluation_labels.c.key)
        )
        for eid, key, value in rows:
            out.setdefault(eid, {})[key] = value
        return out

    @staticmethod
    def _evaluation(row: RowMapping, labels: dict[str, str]) -> EvaluationRecord:
        values = dict(row)
        values["created_at"] = _utc(values["created_at"])
        values.setdefault("result", None)
        return EvaluationRecord(**values, labels=labels)

    # -- accounts ----------------------------------------------------------------------------------------
    @_retry_when_locked
    def add_user(self, name: str, is_admin: bool) -> bool:
        """False if the name is taken."""
        return self._insert(users, name=name, is_admin=is_admin, created_at=datetime.now(timezone.utc))

    @_retry_when_locked
    def get_user(self, name: str) -> UserRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(users).where(users.c.name == name)).mappings().first()
            if row is None:
                return None
            member_of = self._projects_of(conn, name)
        return UserRecord(row["name"], bool(row["is_admin"]), _utc(row["created_at"]), member_of)

    @_retry_when_locked
    def list_users(self) -> list[UserRecord]:
        with self.engine.connect() as conn:
            rows = conn.execute(select(users).order_by(users.c.name)).mappings().all()
            pairs = conn.execute(select(memberships).order_by(memberships.c.project)).all()
        member_of: dict[str, list[str]] = {}
        for user_name, project in pairs:
            member_of.setdefault(user_name, []).append(project)
        return [
            UserRecord(r["name"], bool(r["is_admin"]), _utc(r["created_at"]), tuple(member_of.get(r["name"], ())))
            for r in rows
        ]

    @staticmethod
    def _projects_of(conn: Any, user_name: str) -> tuple[str, ...]:
        rows = conn.execute(
            select(memberships.c.project).where(memberships.c.user_name == user_name).order_by(memberships.c.project)
        )
        return tuple(r[0] for r in rows)

    @_retry_when_locked
    def add_project(self, name: str) -> bool:
        return self._insert(projects, name=name, created_at=datetime.now(timezone.utc))

    @_retry_when_locked
    def project_exists(self, name: str) -> bool:
        with self.engine.connect() as conn:
            return conn.execute(select(projects.c.name).where(projects.c.name == name)).first() is not None

    @_retry_when_locked
    def list_projects(self) -> list[str]:
        with self.engine.connect() as conn:
            return [r[0] for r in conn.execute(select(projects.c.name).order_by(projects.c.name))]

    @_retry_when_locked
    def add_membership(self, user_name: str, project: str) -> bool:
        return self._insert(memberships, user_name=user_name, project=project)

    @_retry_when_locked
    def remove_membership(self, user_name: str, project: str) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(
                delete(memberships).where(memberships.c.user_name == user_name, memberships.c.project == project)
            )
        return bool(done.rowcount)

    @_retry_when_locked
    def add_token(self, record: TokenRecord) -> None:
        with self.engine.begin() as conn:
            conn.execute(insert(tokens).values(**record.__dict__))

    @_retry_when_locked
    def get_token(self, token_id: str) -> TokenRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(tokens).where(tokens.c.id == token_id)).mappings().first()
        return None if row is None else self._token(row)

    @_retry_when_locked
    def list_tokens(self, user_name: str | None = None) -> list[TokenRecord]:
        query = select(tokens).where(tokens.c.kind == "token").order_by(tokens.c.created_at)
        if user_name is not None:
            query = query.where(tokens.c.user_name == user_name)
        with self.engine.connect() as conn:
            return [self._token(r) for r in conn.execute(query).mappings().all()]

    @_retry_when_locked
    def revoke_token(self, token_id: str) -> bool:
        """Revoke a token and the sessions opened with it; False if there is no such token."""
        now = datetime.now(timezone.utc)
        with self.engine.begin() as conn:
            found = conn.execute(select(tokens.c.id).where(tokens.c.id == token_id)).first()
            if found is None:
                return False
            conn.execute(
                update(tokens)
                .where((tokens.c.id == token_id) | (tokens.c.parent == token_id), tokens.c.revoked_at.is_(None))
                .values(revoked_at=now)
            )
        return True

    @_retry_when_locked
    def purge_sessions(self, before: datetime) -> int:
        """Delete the web sessions that expired or were revoked before ``before``; how many."""
        with self.engine.begin() as conn:
            done = conn.execute(
                delete(tokens).where(
                    tokens.c.kind == "session", (tokens.c.expires_at < before) | (tokens.c.revoked_at < before)
                )
            )
        return int(done.rowcount or 0)

    @staticmethod
    def _token(row: RowMapping) -> TokenRecord:
        values = dict(row)
        for key in ("created_at", "expires_at", "revoked_at"):
            if values[key] is not None:
                values[key] = _utc(values[key])
        return TokenRecord(**values)

    @_retry_when_locked
    def add_audit(self, *, actor: str, action: str, target: str, outcome: str, client: str, detail: str) -> None:
        with self.engine.begin() as conn:
            conn.execute(
                insert(audit).values(
                    at=datetime.now(timezone.utc),
                    actor=actor[:128],
                    action=action[:64],
                    target=target[:256],
                    outcome=outcome[:32],
                    client=client[:64],
                    detail=detail[:512],
                )
            )

    @_retry_when_locked
    def list_audit(self, *, limit: int = 100, offset: int = 0) -> list[AuditRecord]:
        """Newest first."""
        query = select(audit).order_by(audit.c.id.desc()).limit(limit).offset(offset)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [AuditRecord(**{**dict(r), "at": _utc(r["at"])}) for r in rows]

    # -- benchmarks ----------------------------------------------------------------------------------------
    @_retry_when_locked
    def add_benchmark(self, values: Mapping[str, Any]) -> bool:
        """False if the name is taken."""
        return self._insert(benchmarks, **values)

    @_retry_when_locked
    def get_benchmark(self, name: str) -> dict[str, Any] | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(benchmarks).where(benchmarks.c.name == name)).mappings().first()
        return None if row is None else self._dated(row, "opens_at", "closes_at", "created_at")

    @_retry_when_locked
    def list_benchmarks(self) -> list[dict[str, Any]]:
        with self.engine.connect() as conn:
            rows = conn.execute(select(benchmarks).order_by(benchmarks.c.name)).mappings().all()
        return [self._dated(r, "opens_at", "closes_at", "created_at") for r in rows]

    @_retry_when_locked
    def update_benchmark(self, name: str, **values: Any) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(update(benchmarks).where(benchmarks.c.name == name).values(**values))
        return bool(done.rowcount)

    @_retry_when_locked
    def accept_submission(self, values: Mapping[str, Any], *, limit: int, window_start: datetime, window: Any) -> None:
        """Insert the submission if its participant has fewer than ``limit`` submissions in this benchmark
        since ``window_start``; else raise :class:`QuotaRefused`. Counting and inserting are one transaction
        that holds a write lock for the (benchmark, participant) pair: on PostgreSQL the pair's row in
        ``quota_locks`` (``SELECT ... FOR UPDATE``), on SQLite the database's write lock (``BEGIN
        IMMEDIATE``). Concurrent submissions, from any number of servers on the database, are counted one
        after another, so none is admitted over the limit."""
        benchmark, participant = values["benchmark"], values["participant"]
        count_query = select(func.count(), func.min(submissions.c.created_at)).where(
            submissions.c.benchmark == benchmark,
            submissions.c.participant == participant,
            submissions.c.created_at > window_start,
            submissions.c.status != "failed",
        )
        if self.dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert as pg_insert

            with self.engine.begin() as conn:
                conn.execute(
                    pg_insert(quota_locks).values(benchmark=benchmark, participant=participant).on_conflict_do_nothing()
                )
                conn.execute(
                    select(quota_locks.c.benchmark)
                    .where(quota_locks.c.benchmark == benchmark, quota_locks.c.participant == participant)
                    .with_for_update()
                )
                used, oldest = conn.execute(count_query).one()
                if used >= limit:
                    raise QuotaRefused(_utc(oldest) + window, used)
                conn.execute(insert(submissions).values(**values))
            return
        with self.engine.connect() as conn:
            conn.exec_driver_sql("BEGIN IMMEDIATE")
            try:
                used, oldest = conn.execute(count_query).one()
                if used >= limit:
                    raise QuotaRefused(_utc(oldest) + window, used)
                conn.execute(insert(submissions).values(**values))
                conn.commit()
            except BaseException:
                conn.rollback()
                raise

    @_retry_when_locked
    def update_submission(self, submission_id: str, **values: Any) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(update(submissions).where(submissions.c.id == submission_id).values(**values))
        return bool(done.rowcount)

    @_retry_when_locked
    def get_submission(self, submission_id: str) -> dict[str, Any] | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(submissions).where(submissions.c.id == submission_id)).mappings().first()
        return None if row is None else self._dated(row, "created_at", "scored_at", "published_at")

    @_retry_when_locked
    def list_submissions(
        self, benchmark: str, *, participant: str | None = None, published_only: bool = False
    ) -> list[dict[str, Any]]:
        """Oldest first."""
        query = select(submissions).where(submissions.c.benchmark == benchmark)
        if participant is not None:
            query = query.where(submissions.c.participant == participant)
        if published_only:
            query = query.where(submissions.c.published.is_(True), submissions.c.disqualified.is_(False))
        query = query.order_by(submissions.c.created_at, submissions.c.id)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._dated(r, "created_at", "scored_at", "published_at") for r in rows]

    @staticmethod
    def _dated(row: RowMapping, *keys: str) -> dict[str, Any]:
        values = dict(row)
        for key in keys:
            if values.get(key) is not None:
                values[key] = _utc(values[key])
        return values

    @_retry_when_locked
    def _insert(self, table: Table, **values: Any) -> bool:
        try:
            with self.engine.begin() as conn:
                conn.execute(insert(table).values(**values))
        except IntegrityError:
            return False
        return True
