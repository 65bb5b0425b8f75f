"""The base revision: the schema of the first versioned release, as the release before it made it.

Its tables are a frozen copy of that release's (never edited: a later change is a migration of its own, see
docs/development/index.md). Its upgrade is what that release's start did, so that it brings either database to
this schema: an empty one (every table created), or one an earlier, unversioned release made (the tables it
lacks created, the columns added since the first release added, ``_ADDED_COLUMNS``), which are then stamped
with this revision. On PostgreSQL it also sets how the uploaded files are stored (``_file_storage``).

Revision ID: 0001
Revises:
"""

from __future__ import annotations

import logging

from alembic import op
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
    inspect,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Connection
from sqlalchemy.exc import DBAPIError

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

log = logging.getLogger("kitti_eval.server")

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
    Column("kind", String(16), nullable=False),  # evaluation | submission | rescore
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


# the teams of a hosted benchmark (team_store.py's tables, on the same metadata)
#: a benchmark's teams (the benchmark's name: the one its participants address, not a phase's)
teams = Table(
    "teams",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("name", String(64), primary_key=True),
    Column("created_by", String(64), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
)

#: who is in which team: one row per (benchmark, participant), so a participant is in one team of a benchmark
team_members = Table(
    "team_members",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
    Column("team", String(64), nullable=False),
    Column("joined_at", DateTime(timezone=True), nullable=False),
    Index("ix_team_members_team", "benchmark", "team"),
)

#: whom a team's maker invited: they join when they accept (an invitation binds nobody until then)
team_invites = Table(
    "team_invites",
    metadata,
    Column("benchmark", String(64), primary_key=True),
    Column("team", String(64), primary_key=True),
    Column("participant", String(64), primary_key=True),
    Column("invited_at", DateTime(timezone=True), nullable=False),
    Index("ix_team_invites_participant", "benchmark", "participant"),
)

#: columns added since the first release, by table, with their SQL kinds ("{json}": the dialect's JSON): a
#: database made by an earlier version gets them when the schema is created
_ADDED_COLUMNS = {
    "evaluations": {"options": "{json}", "project": "VARCHAR(64)"},
    "ground_truths": {"project": "VARCHAR(64)", "sealed": "BOOLEAN NOT NULL DEFAULT FALSE"},
    "benchmarks": {"max_published": "INTEGER"},
    "submissions": {
        "public_result": "{json}",
        "baseline": "BOOLEAN NOT NULL DEFAULT FALSE",
        "failure": "VARCHAR(500)",
    },
    "job_inputs": {"kept": "BOOLEAN NOT NULL DEFAULT FALSE"},
}


def _file_storage(conn: Connection) -> None:
    """How PostgreSQL keeps the uploaded files. By default it compresses a large value with pglz before storing
    it, which cost ~95 ms of the database's CPU for every val-sized result.pkl accepted. A job's inputs live until
    the job ends: they are stored as they are (``EXTERNAL``). The files kept for good (predictions, ground truths)
    are compressed with lz4 where the server has it (PostgreSQL 14 and later, built with it), several times
    faster than pglz (predictions kept for good are written once, when their job is accepted). Only new rows are
    written the new way; the changes are made once, by the first server."""
    columns = {"job_inputs": "e", "prediction_files": "l", "ground_truth_files": "l"}
    lz4 = int(conn.execute(text("SHOW server_version_num")).scalar_one()) >= 140000
    for table, want in columns.items():
        if want == "l" and not lz4:
            continue
        field = "attstorage" if want == "e" else "attcompression"
        now = conn.execute(
            text(
                f"SELECT a.{field} FROM pg_attribute a JOIN pg_class c ON a.attrelid = c.oid "
                "WHERE c.relname = :table AND a.attname = 'content' AND pg_table_is_visible(c.oid)"
            ),
            {"table": table},
        ).scalar_one_or_none()
        if now is None or now == want:
            continue
        if want == "e":
            conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN content SET STORAGE EXTERNAL"))
            continue
        try:
            with conn.begin_nested():  # a server built without lz4 refuses it: pglz stays
                conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN content SET COMPRESSION lz4"))
        except DBAPIError:
            log.info("PostgreSQL has no lz4: %s keeps pglz", table)


def upgrade() -> None:
    conn = op.get_bind()
    metadata.create_all(conn)  # the tables missing (all of them in an empty database)
    json_kind = "JSONB" if conn.dialect.name == "postgresql" else "JSON"
    for table, columns in _ADDED_COLUMNS.items():
        present = {c["name"] for c in inspect(conn).get_columns(table)}
        for column, kind in columns.items():
            if column not in present:
                conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {column} {kind.format(json=json_kind)}"))
    if conn.dialect.name == "postgresql":
        _file_storage(conn)


def downgrade() -> None:
    raise NotImplementedError("the base revision is not undone: restore a backup (kitti-eval admin restore)")
