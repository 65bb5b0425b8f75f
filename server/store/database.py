"""The shared part of the database: the SQLAlchemy 2 Core tables, the engine, the schema (its versions are
Alembic's revisions, :mod:`.schema`), and
the retry of a call that found SQLite locked. Each area of the store (:mod:`.ground_truth_store`,
:mod:`.evaluation_store`, :mod:`.account_store`, :mod:`.benchmark_store`) reads and writes its tables
through one :class:`Database`; :mod:`.job_store` is the queue of work (evaluations, submissions, rescoring)
the service's workers take from.

SQLite (the default, one file in the data folder) runs in WAL mode with ``synchronous=FULL``; PostgreSQL is
reached through psycopg 3. Every write is one transaction committed before the method returns, so a
caller that answers 2xx after it has a durable row.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterator
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
    Text,
    create_engine,
    event,
    insert,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Connection, Engine, RowMapping
from sqlalchemy.exc import IntegrityError, OperationalError

log = logging.getLogger("kitti_eval.server")

__all__ = [
    "Database",
    "Area",
    "retry_when_locked",
    "new_id",
    "utc",
    "dated",
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
    "job_inputs",
    "job_workers",
    "idempotency_keys",
    "gate_results",
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

#: what an evaluation's job stores of each frame of its ground truth, for its frame listings and frame views (see
#: kitti_eval_server.evaluations.frame_rows): the frame's detections, and its share of every matching
evaluation_frames = Table(
    "evaluation_frames",
    metadata,
    Column("evaluation_id", String(32), ForeignKey("evaluations.id", ondelete="CASCADE"), primary_key=True),
    Column("frame_index", Integer, primary_key=True),  # the frame's place in the ground truth
    Column("frame_id", Text, nullable=False),
    Column("detections", LargeBinary, nullable=False),
    Column("events", LargeBinary, nullable=False),
    Index("ix_evaluation_frames_id", "evaluation_id", "frame_id"),
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
    Column("max_published", Integer, nullable=True),  # published entries per participant (None: no cap)
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
    Column("public_result", _JSON, nullable=True),  # a split benchmark's: the (sealed) document on the public part
    Column("published", Boolean, nullable=False),
    Column("method", String(100), nullable=True),
    Column("anonymous", Boolean, nullable=False),
    Column("affiliation", String(200), nullable=True),
    Column("link", String(500), nullable=True),
    Column("published_at", DateTime(timezone=True), nullable=True),
    Column("disqualified", Boolean, nullable=False),
    #: an admin's submission: shown on the board as a reference, not ranked, counted against no quota
    Column("baseline", Boolean, nullable=False, default=False),
    #: why a failed submission failed (its file refused, its scoring cancelled or given up on)
    Column("failure", String(500), nullable=True),
    #: the team it counted for, recorded when it was accepted (None: its participant was in no team then); the
    #: board names it and the team's quota counts it, whoever has left the team since
    Column("team", String(64), nullable=True),
    Index("ix_submissions_quota", "benchmark", "participant", "created_at"),
)

#: a scored submission's ranking key under each of its benchmark's bootstrap resamples over the frames of a part
#: of the test set (see kitti_eval_server.benchmarks.intervals): written by a job after each scoring, read by
#: the leaderboard; one row per (submission, part, seed, resamples)
submission_resamples = Table(
    "submission_resamples",
    metadata,
    Column("submission_id", String(32), ForeignKey("submissions.id", ondelete="CASCADE"), primary_key=True),
    Column("part", String(16), primary_key=True),  # all | public | private
    Column("seed", BigInteger, primary_key=True),
    Column("resamples", Integer, primary_key=True),
    Column("benchmark", String(64), nullable=False),
    Column("scored_at", DateTime(timezone=True), nullable=False),  # the scoring the values are of
    Column("frames", Integer, nullable=False),  # the part's frames the resamples draw from
    Column("key_values", LargeBinary, nullable=False),  # float64, little-endian: the key under each resample
    Index("ix_submission_resamples_board", "benchmark", "part", "seed", "resamples"),
)

#: one row per (benchmark, participant), locked while a submission is counted against the quota
quota_locks = Table(
    "quota_locks",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
)

#: the queue of work: every evaluation, submission and rescoring, recorded when its input is stored and taken by
#: a worker (of this process or another) with a lease; see kitti_eval_server.jobs.queue for the rules
jobs = Table(
    "jobs",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("kind", String(16), nullable=False),  # evaluation | gate | submission | rescore | intervals
    Column("state", String(16), nullable=False),  # queued | running | done | failed | cancelled
    Column("attempts", Integer, nullable=False),  # 0 when queued, +1 at each claim
    Column("max_attempts", Integer, nullable=False),
    Column("worker", String(128), nullable=True),  # who holds it (running) or held it last
    Column("lease_until", DateTime(timezone=True), nullable=True),  # running: another worker may take it after
    Column("accepted_at", DateTime(timezone=True), nullable=False),
    Column("started_at", DateTime(timezone=True), nullable=True),  # the first claim
    Column("finished_at", DateTime(timezone=True), nullable=True),
    Column("owner", String(64), nullable=False),  # the caller's name (per-participant limits)
    Column("grp", String(128), nullable=True),  # e.g. the benchmark a rescoring belongs to
    Column("payload", _JSON, nullable=False),  # the executor's input
    Column("result_id", String(32), nullable=True),
    Column("error", Text, nullable=True),
    Index("ix_jobs_claim", "state", "accepted_at", "id"),
    Index("ix_jobs_owner", "owner", "accepted_at"),
    Index("ix_jobs_group", "grp", "accepted_at"),
)


#: the files a job was accepted with (the predictions; a ground truth uploaded with the request), kept in the
#: database so that a worker on any machine reads them; the rows are deleted when the job ends. Predictions
#: the service keeps for good are written once, to ``prediction_files``, when the job is accepted: their row
#: here is ``kept`` and holds no content (it is read from there by its sha256)
job_inputs = Table(
    "job_inputs",
    metadata,
    Column("job_id", String(32), primary_key=True),
    Column("name", String(32), primary_key=True),  # predictions | gt_file
    Column("filename", String(255), nullable=False),
    Column("sha256", String(64), nullable=False),
    Column("content", LargeBinary, nullable=False),  # empty when kept
    Column("kept", Boolean, nullable=False, default=False),
)


#: the processes that run jobs, each beating its row while it runs (what the readiness and the metrics say of the
#: workers outside the service's own process); a row no process has beaten for an hour is dropped
job_workers = Table(
    "job_workers",
    metadata,
    Column("name", String(128), primary_key=True),  # host:pid
    Column("host", String(255), nullable=False),
    Column("pid", Integer, nullable=False),
    Column("threads", Integer, nullable=False),
    Column("started_at", DateTime(timezone=True), nullable=False),
    Column("seen_at", DateTime(timezone=True), nullable=False),
    Index("ix_job_workers_seen", "seen_at"),
)


#: the Idempotency-Key of a request that made a job (an evaluation, a submission): the same caller sending the
#: same key to the same place again gets that job back instead of a second one, while the key has not expired.
#: ``fingerprint`` is the sha256 of what the request sent (its files and fields), so that a key sent again with
#: another request is refused; written in the transaction that records the job
idempotency_keys = Table(
    "idempotency_keys",
    metadata,
    Column("owner", String(64), primary_key=True),  # the caller's name
    Column("scope", String(128), primary_key=True),  # where it was sent: "POST /v1/evaluations", ...
    Column("key", String(255), primary_key=True),
    Column("fingerprint", String(64), nullable=False),
    Column("job_id", String(32), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("expires_at", DateTime(timezone=True), nullable=False),
    Index("ix_idempotency_keys_expires", "expires_at"),
)


#: the result of an evaluation a gate asked for without keeping it (a ``gate`` job: a read-only token's gate): the
#: document its owner reads once (then the row is deleted), or that is deleted a few minutes after it was made
#: unread; never listed, ranked or looked at by frame as an evaluation is, and no predictions are kept with it
gate_results = Table(
    "gate_results",
    metadata,
    Column("id", String(32), primary_key=True),  # the job's id
    Column("owner", String(64), nullable=False),  # the caller's name: only they read it
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("document", _JSON, nullable=False),  # the answer an evaluation's would be, without being stored
    Index("ix_gate_results_created", "created_at"),
)


#: the PostgreSQL advisory lock held while the schema is created or upgraded (any fixed 64-bit number)
_SCHEMA_LOCK = 0x6B69747469657661  # "kittieva"

#: a host's invitations to a benchmark: looked up by the sha256 of their code, named by their public id
invitations = Table(
    "invitations",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("code_sha256", String(64), nullable=False, unique=True),
    Column("benchmark", String(64), nullable=False),  # the benchmark's name (its first phase's row)
    Column("project", String(64), nullable=True),  # the accounts it makes are members of it (None: of none)
    Column("max_uses", Integer, nullable=True),  # None: as many as join before it expires
    Column("uses", Integer, nullable=False),
    Column("created_by", String(128), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
    Column("expires_at", DateTime(timezone=True), nullable=True),
    Column("revoked_at", DateTime(timezone=True), nullable=True),
)

#: the accounts an invitation made
invitation_accounts = Table(
    "invitation_accounts",
    metadata,
    Column("user_name", String(64), ForeignKey("users.name", ondelete="CASCADE"), primary_key=True),
    Column("invitation", String(32), ForeignKey("invitations.id", ondelete="CASCADE"), nullable=False),
    Column("joined_at", DateTime(timezone=True), nullable=False),
    Index("ix_invitation_accounts_invitation", "invitation", "joined_at"),
)


def utc(value: datetime) -> datetime:
    return value if value.tzinfo else value.replace(tzinfo=timezone.utc)  # SQLite keeps no zone


def dated(row: RowMapping, *keys: str) -> dict[str, Any]:
    """The row as a dict, its times at ``keys`` given their zone."""
    values = dict(row)
    for key in keys:
        if values.get(key) is not None:
            values[key] = utc(values[key])
    return values


def new_id() -> str:
    return uuid.uuid4().hex


#: SQLite's page size for a new database: the uploaded files it keeps (a val-sized result.pkl is 6-22 MB) are
#: chains of overflow pages, and at 64 KB a 22 MB file is written with half the CPU of the 4 KB default (~40 ms
#: instead of ~85 ms). A database made with other pages keeps them (SQLite changes them only on a VACUUM)
SQLITE_PAGE_SIZE = 65536


def _sqlite_pragmas(busy_ms: int) -> Callable[[Any, Any], None]:
    def on_connect(dbapi_connection: Any, _record: Any) -> None:
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA page_size={SQLITE_PAGE_SIZE}")  # before WAL: only an empty database takes it
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


def retry_when_locked(method: F) -> F:
    """Run a method of the :class:`Database` or of an :class:`Area` again, after a short pause growing from
    20 ms to 0.5 s, while SQLite says the database is locked (another process writing: a CLI command, a
    second worker, a backup holding a lock), until :attr:`Database.busy_s` has passed; then the last error is
    raised. Each attempt is one transaction, rolled back when it fails, so running it again is safe. Calls
    from inside a retried method are not retried on their own (one budget a call)."""

    @functools.wraps(method)
    def wrapper(self: Database | Area, *args: Any, **kwargs: Any) -> Any:
        db = self if isinstance(self, Database) else self.db
        if db.busy_s is None or getattr(_retrying, "active", False):
            return method(self, *args, **kwargs)
        deadline = time.monotonic() + db.busy_s
        pause = _FIRST_PAUSE_S
        _retrying.active = True
        try:
            while True:
                try:
                    return method(self, *args, **kwargs)
                except OperationalError as e:
                    if not _locked(e) or time.monotonic() + pause >= deadline:
                        raise
                    db.lock_retries += 1
                time.sleep(pause)
                pause = min(2 * pause, _LONGEST_PAUSE_S)
        finally:
            _retrying.active = False

    return wrapper  # type: ignore[return-value]


class UnusableDatabase(Exception):
    """The database cannot hold the service's data as it is (a PostgreSQL database not encoded in UTF8); the
    message says why and what to do, in one sentence."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


def check_encoding(engine: Engine) -> None:
    """A PostgreSQL database must be encoded in UTF8: with SQL_ASCII (``initdb`` under the C locale, or
    ``CREATE DATABASE ... ENCODING 'SQL_ASCII'``) psycopg hands back bytes instead of text, SQLAlchemy's first
    connection fails on them (``TypeError: cannot use a string pattern on a bytes-like object``), and any other
    encoding cannot hold every name and label a caller may send. Asked over a plain driver connection, before
    SQLAlchemy's own first one; raises :class:`UnusableDatabase` naming the encoding and the fix."""
    if engine.dialect.name != "postgresql":
        return
    dialect = engine.dialect
    cargs, cparams = dialect.create_connect_args(engine.url)
    try:
        conn = dialect.connect(*cargs, **cparams)
    except dialect.loaded_dbapi.Error as e:  # not reached, or refused: as SQLAlchemy's connection would say it
        raise OperationalError(None, None, e) from e
    try:
        cursor = conn.cursor()
        cursor.execute(
            "SELECT pg_encoding_to_char(encoding), current_database() FROM pg_database "
            "WHERE datname = current_database()"
        )
        row = cursor.fetchone() or ("", "")
        encoding, name = (v.decode("ascii", "replace") if isinstance(v, bytes) else str(v) for v in row)
    finally:
        conn.close()
    if encoding.upper() != "UTF8":
        raise UnusableDatabase(
            f"the PostgreSQL database {name} is encoded in {encoding}, not UTF8, which the service needs for "
            f"every name and label it keeps: create it again with CREATE DATABASE {name} ENCODING 'UTF8' "
            "TEMPLATE template0 (or createdb -E UTF8 -T template0)"
        )


class Database:
    """The engine on SQLite or PostgreSQL, the schema, and what the areas of the store share."""

    def __init__(self, url: str, *, busy_s: float = 10.0) -> None:
        """``busy_s``: how long a SQLite call keeps trying while another connection holds the write lock
        (:func:`retry_when_locked`). PostgreSQL connections are checked before each use
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

    @retry_when_locked
    def create_schema(self, *, upgrade: bool = True, where: str = "") -> str | None:
        """Bring the schema to this release's (:mod:`.schema`): an empty database is created at the newest
        revision; an older one is upgraded when ``upgrade``, else refused (:class:`UnusableDatabase` naming
        ``kitti-eval admin db upgrade``); one a newer release upgraded is refused. Returns the revision it was
        at before (None: none recorded). ``where`` names the database in the refusals.

        It runs in one transaction under a lock (PostgreSQL's advisory lock, SQLite's write lock): servers
        started together on one database (replicas rolled out at once) would otherwise all create or upgrade
        it, and all but one fail at start-up; the others wait for the lock, then find it done."""
        from . import schema

        check_encoding(self.engine)
        where = where or self.engine.url.render_as_string(hide_password=True)
        with self.writing() as conn:
            if self.dialect == "postgresql":
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _SCHEMA_LOCK})
            state = schema.state_of(conn)
            if state.current:
                return state.revision
            if state.newer:
                raise UnusableDatabase(
                    f"the database {where} is {state.describe()}: this release's newest is {schema.head()}; run "
                    "the release that upgraded it, or a newer one"
                )
            if not state.empty and not upgrade:
                raise UnusableDatabase(
                    f"the database {where} is {state.describe()}, older than this release's {schema.head()}: run "
                    "kitti-eval admin db upgrade (after kitti-eval admin backup), or start the service with "
                    "KITTI_EVAL_DB_UPGRADE=true to upgrade it at start"
                )
            schema.upgrade(conn)
            if not state.empty:
                log.info("database %s upgraded from %s to %s", where, state.revision or "no revision", schema.head())
            return state.revision

    def schema_state(self) -> Any:
        """Where the database's schema is (:class:`.schema.SchemaState`)."""
        from . import schema

        check_encoding(self.engine)
        with self.engine.connect() as conn:
            return schema.state_of(conn)

    @retry_when_locked
    def ping(self) -> None:
        with self.engine.connect() as conn:
            conn.execute(text("SELECT 1"))

    def dispose(self) -> None:
        self.engine.dispose()

    @contextlib.contextmanager
    def writing(self) -> Iterator[Connection]:
        """One transaction, committed when the block ends and rolled back when it raises; on SQLite it holds the
        write lock from its start (``BEGIN IMMEDIATE``: no other writer between its reads and its writes, and no
        failed upgrade of a read transaction to a write one). Every area writes through it, and a write that spans
        areas hands its connection to each area's ``..._in`` method: one commit."""
        if self.dialect != "sqlite":
            with self.engine.begin() as conn:
                yield conn
            return
        with self.engine.connect() as conn:
            conn.exec_driver_sql("BEGIN IMMEDIATE")
            try:
                yield conn
                conn.commit()
            except BaseException:
                conn.rollback()
                raise


class Area:
    """One area of the store (its records' reads and writes) on a shared :class:`Database`."""

    def __init__(self, db: Database) -> None:
        self.db = db

    @property
    def engine(self) -> Engine:
        return self.db.engine

    @property
    def dialect(self) -> str:
        return self.db.dialect

    def _writing(self) -> contextlib.AbstractContextManager[Connection]:
        return self.db.writing()

    @retry_when_locked
    def _insert(self, table: Table, **values: Any) -> bool:
        """Insert one row; False if its key is taken."""
        try:
            with self.engine.begin() as conn:
                conn.execute(insert(table).values(**values))
        except IntegrityError:
            return False
        return True
