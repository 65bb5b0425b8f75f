"""The store's hosted benchmarks and their submissions (the rules are :mod:`kitti_eval_server.benchmarks`'s)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Select, delete, func, insert, or_, select, update
from sqlalchemy.engine import Connection, RowMapping

from .database import (
    Area,
    benchmarks,
    dated,
    quota_locks,
    retry_when_locked,
    submission_resamples,
    submissions,
    utc,
)
from .idempotency_store import IdempotencyRecord, IdempotencyStore

__all__ = [
    "BenchmarkRecord",
    "SubmissionRecord",
    "SUBMISSION_STATUSES",
    "ResampledKey",
    "QuotaRefused",
    "QuotaTeam",
    "PublishRefused",
    "BenchmarkStore",
]

#: a submission's status, in the order of its life: accepted (its scoring job queued or running), then scored
#: or failed (with the reason); docs/service/benchmarks.md names these (a test compares)
SUBMISSION_STATUSES = ("accepted", "scored", "failed")


class QuotaRefused(Exception):
    """No room in the quota: ``retry_at`` is when the oldest accepted submission of the window leaves it."""

    def __init__(self, retry_at: datetime, used: int) -> None:
        super().__init__(f"quota used ({used})")
        self.retry_at = retry_at
        self.used = used


class PublishRefused(Exception):
    """The participant already has ``used`` published entries, the benchmark's cap."""

    def __init__(self, used: int) -> None:
        super().__init__(f"published entries: {used}")
        self.used = used


@dataclass(frozen=True)
class BenchmarkRecord:
    """A benchmark's row: its ground truth, its options (``config``), its period and its state."""

    name: str
    title: str
    description: str
    gt_name: str
    project: str | None  # the ground truth's project when the benchmark was created (None: shared)
    config: Mapping[str, Any]  # protocol, classes, sets, key, columns, quota, split_percent
    public: bool
    opens_at: datetime
    closes_at: datetime | None
    closed: bool  # closed by hand (whatever closes_at says)
    revealed: bool  # the private ranking is shown
    created_at: datetime
    split_seed: str | None = None  # secret: draws the public part of the test frames
    max_published: int | None = None  # published entries per participant (None: no cap)


@dataclass(frozen=True)
class SubmissionRecord:
    """A participant's submission: the predictions file, its scores and, once published, its board entry."""

    id: str
    benchmark: str
    participant: str
    created_at: datetime
    status: str  # one of SUBMISSION_STATUSES
    pred_filename: str
    pred_sha256: str
    pred_size: int
    gt_sha256: str | None = None  # the ground truth it was last scored against
    scored_at: datetime | None = None
    result: Mapping[str, Any] | None = None  # the (sealed) evaluation document on every test frame
    scores: Mapping[str, Mapping[str, float | None]] | None = None  # {"all"|"public"|"private": {column: AP}}
    public_result: Mapping[str, Any] | None = None  # a split benchmark's: the (sealed) document on the public part
    published: bool = False
    method: str | None = None
    anonymous: bool = False
    affiliation: str | None = None
    link: str | None = None
    published_at: datetime | None = None
    disqualified: bool = False
    baseline: bool = False  # an admin's: on the board as a reference, not ranked, under no quota
    failure: str | None = None  # why a failed submission failed
    team: str | None = None  # the team it counted for when it was accepted (None: its participant was in none)


@dataclass(frozen=True)
class ResampledKey:
    """A submission's ranking key under each bootstrap resample of one part of the test set."""

    part: str  # all | public | private
    seed: int
    resamples: int
    frames: int  # the part's frames the resamples draw from
    key_values: bytes  # float64, little-endian, one a resample


@dataclass(frozen=True)
class QuotaTeam:
    """A participant's team, whose submissions count together against a phase's quota: those its members made
    (alone before joining too) and those made for it by members who have left it since."""

    name: str
    members: tuple[str, ...]

    @property
    def lock(self) -> str:
        """The name its members' submissions are accepted under, one after another (a participant's is their
        own name, which holds no ``~``)."""
        return f"team~{self.name}"


def _quota_count(
    benchmark: str, participant: str, window_start: datetime, team: QuotaTeam | None = None
) -> Select[int, Any]:
    """The submissions that count against the participant's quota since ``window_start`` (not failed, not
    baselines), and the oldest one's acceptance time: their own (those they made for a team they have left too),
    or in a team the team's (:class:`QuotaTeam`)."""
    who = submissions.c.participant == participant
    if team is not None:
        who = or_(submissions.c.participant.in_(list(team.members)), submissions.c.team == team.name)
    return select(func.count(), func.min(submissions.c.created_at)).where(
        submissions.c.benchmark == benchmark,
        who,
        submissions.c.created_at > window_start,
        submissions.c.status != "failed",
        submissions.c.baseline.is_(False),
    )


class BenchmarkStore(Area):
    """Benchmarks and their submissions, with the quota counted and applied in one transaction."""

    @retry_when_locked
    def add_benchmark(self, record: BenchmarkRecord) -> bool:
        """False if the name is taken."""
        return self._insert(benchmarks, **record.__dict__)

    @retry_when_locked
    def get_benchmark(self, name: str) -> BenchmarkRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(benchmarks).where(benchmarks.c.name == name)).mappings().first()
        return None if row is None else self._benchmark(row)

    @retry_when_locked
    def list_benchmarks(self) -> list[BenchmarkRecord]:
        with self.engine.connect() as conn:
            rows = conn.execute(select(benchmarks).order_by(benchmarks.c.name)).mappings().all()
        return [self._benchmark(r) for r in rows]

    @retry_when_locked
    def benchmarks_using(self, gt_name: str) -> list[BenchmarkRecord]:
        """The benchmarks whose test set is the ground truth named ``gt_name``, by name."""
        query = select(benchmarks).where(benchmarks.c.gt_name == gt_name).order_by(benchmarks.c.name)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._benchmark(r) for r in rows]

    @retry_when_locked
    def update_benchmark(self, name: str, **values: Any) -> bool:
        with self.engine.begin() as conn:
            done = conn.execute(update(benchmarks).where(benchmarks.c.name == name).values(**values))
        return bool(done.rowcount)

    @contextlib.contextmanager
    def _holding(self, benchmark: str, participant: str) -> Iterator[Connection]:
        """One transaction that holds a write lock for the (benchmark, participant) pair: on PostgreSQL the
        pair's row in ``quota_locks`` (``SELECT ... FOR UPDATE``), on SQLite the database's write lock
        (``BEGIN IMMEDIATE``). What is counted in it, from any number of servers on the database, is counted
        one transaction after another. Committed when the block ends, rolled back when it raises."""
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
                yield conn
            return
        with self._writing() as conn:
            yield conn

    @retry_when_locked
    def accept_submission(
        self,
        record: SubmissionRecord,
        *,
        limit: int | None,
        window_start: datetime,
        window: timedelta,
        then: Callable[[Connection], object] | None = None,
        idempotency_key: IdempotencyRecord | None = None,
        team: QuotaTeam | None = None,
    ) -> None:
        """Insert the submission if its participant has fewer than ``limit`` submissions in this benchmark
        since ``window_start``; else raise :class:`QuotaRefused` (``limit`` None: an admin's baseline, inserted
        uncounted). Counting and inserting are one transaction
        holding the (benchmark, participant) pair's lock, so concurrent submissions, from any number of
        servers on the database, are counted one after another and none is admitted over the limit. ``then``
        writes what goes with the submission in the same transaction. ``idempotency_key``: the request's
        idempotency key, recorded first (:class:`KeyTaken`, nothing written, when a copy of the request recorded
        it: the copy is not counted again). ``team``: the participant's team, whose submissions count together
        (the lock is the team's, so its members' parallel submissions are counted one after another); the
        submission is recorded as the team's (``record.team``)."""
        lock_as = team.lock if team is not None else record.participant
        count_query = _quota_count(record.benchmark, record.participant, window_start, team)
        values = {**record.__dict__, "team": team.name if team is not None else None}
        if limit is None:  # on SQLite the write lock from the start, as the idempotency key's record needs
            with self._writing() as conn:
                if idempotency_key is not None:
                    IdempotencyStore.add_idempotency_key_in(conn, idempotency_key)
                conn.execute(insert(submissions).values(**values))
                if then is not None:
                    then(conn)
            return
        with self._holding(record.benchmark, lock_as) as conn:
            if idempotency_key is not None:
                IdempotencyStore.add_idempotency_key_in(conn, idempotency_key)
            used, oldest = conn.execute(count_query).one()
            if used >= limit:
                raise QuotaRefused(utc(oldest) + window, used)
            conn.execute(insert(submissions).values(**values))
            if then is not None:  # what is recorded with it (its job and input), in the same commit
                then(conn)

    @retry_when_locked
    def quota_used(
        self, benchmark: str, participant: str, window_start: datetime, team: QuotaTeam | None = None
    ) -> tuple[int, datetime | None]:
        """The participant's submissions that count against the benchmark's quota since ``window_start``, and
        when the oldest of them was accepted: as :meth:`accept_submission` counts them, read without its lock
        (a look before a submission's file is received; the count only grows until the window moves on).
        ``team``: the participant's team, when they are in one."""
        with self.engine.connect() as conn:
            query = _quota_count(benchmark, participant, window_start, team)
            used, oldest = conn.execute(query).one()
        return int(used), utc(oldest) if oldest is not None else None

    @retry_when_locked
    def publish_submission(self, record: SubmissionRecord, *, cap: int | None, **values: Any) -> None:
        """Publish the submission with ``values`` (method, anonymous, ...) unless its participant already has
        ``cap`` other entries published (and not disqualified) in the benchmark: then raise
        :class:`PublishRefused`. Counted and written in one transaction under the (benchmark, participant)
        lock, so parallel publishes never pass the cap."""
        publish = update(submissions).where(submissions.c.id == record.id).values(published=True, **values)
        if cap is None:
            with self.engine.begin() as conn:
                conn.execute(publish)
            return
        count_query = select(func.count()).where(
            submissions.c.benchmark == record.benchmark,
            submissions.c.participant == record.participant,
            submissions.c.published.is_(True),
            submissions.c.disqualified.is_(False),
            submissions.c.id != record.id,
        )
        with self._holding(record.benchmark, record.participant) as conn:
            used = conn.execute(count_query).scalar_one()
            if used >= cap:
                raise PublishRefused(used)
            conn.execute(publish)

    @retry_when_locked
    def update_submission(self, submission_id: str, **values: Any) -> bool:
        with self.engine.begin() as conn:
            return self.update_submission_in(conn, submission_id, **values)

    @retry_when_locked
    def delete_submission(self, submission_id: str) -> bool:
        """Remove a submission that never counted (its first scoring found it breaks the rules)."""
        with self.engine.begin() as conn:
            return bool(conn.execute(delete(submissions).where(submissions.c.id == submission_id)).rowcount)

    @staticmethod
    def update_submission_in(conn: Connection, submission_id: str, **values: Any) -> bool:
        """Within a transaction of the caller's (the one that ends the scoring's job)."""
        done = conn.execute(update(submissions).where(submissions.c.id == submission_id).values(**values))
        return bool(done.rowcount)

    @retry_when_locked
    def get_submission(self, submission_id: str) -> SubmissionRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(submissions).where(submissions.c.id == submission_id)).mappings().first()
        return None if row is None else self._submission(row)

    @retry_when_locked
    def list_submissions(
        self, benchmark: str, *, participant: str | None = None, published_only: bool = False
    ) -> list[SubmissionRecord]:
        """Oldest first."""
        query = select(submissions).where(submissions.c.benchmark == benchmark)
        if participant is not None:
            query = query.where(submissions.c.participant == participant)
        if published_only:
            query = query.where(submissions.c.published.is_(True), submissions.c.disqualified.is_(False))
        query = query.order_by(submissions.c.created_at, submissions.c.id)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._submission(r) for r in rows]

    @staticmethod
    def replace_resampled_keys_in(
        conn: Connection, submission_id: str, scored_at: datetime, keys: Sequence[ResampledKey]
    ) -> bool:
        """Within a job's ending transaction: the submission's resampled keys become ``keys``, if it is still
        scored as it was at ``scored_at`` (else nothing is written: a later scoring has its own). Whether they
        were written."""
        row = conn.execute(
            select(submissions.c.benchmark, submissions.c.scored_at, submissions.c.status).where(
                submissions.c.id == submission_id
            )
        ).first()
        if row is None or row.status != "scored" or row.scored_at is None or utc(row.scored_at) != scored_at:
            return False
        conn.execute(delete(submission_resamples).where(submission_resamples.c.submission_id == submission_id))
        if keys:
            conn.execute(
                insert(submission_resamples),
                [
                    {
                        "submission_id": submission_id,
                        "benchmark": row.benchmark,
                        "scored_at": scored_at,
                        **{k: getattr(key, k) for k in ("part", "seed", "resamples", "frames", "key_values")},
                    }
                    for key in keys
                ],
            )
        return True

    @retry_when_locked
    def resampled_keys(
        self, benchmark: str, *, part: str, seed: int, resamples: int, ids: Collection[str] | None = None
    ) -> dict[str, bytes]:
        """Submission id -> its resampled key on ``part`` under the (``seed``, ``resamples``) draws, of the
        submissions of ``benchmark`` (those of ``ids`` only, when given) that have one."""
        c = submission_resamples.c
        query = select(c.submission_id, c.key_values).where(
            c.benchmark == benchmark, c.part == part, c.seed == seed, c.resamples == resamples
        )
        if ids is not None:
            if not ids:
                return {}
            query = query.where(c.submission_id.in_(list(ids)))
        with self.engine.connect() as conn:
            return {r.submission_id: bytes(r.key_values) for r in conn.execute(query)}

    @staticmethod
    def _benchmark(row: RowMapping) -> BenchmarkRecord:
        return BenchmarkRecord(**dated(row, "opens_at", "closes_at", "created_at"))

    @staticmethod
    def _submission(row: RowMapping) -> SubmissionRecord:
        return SubmissionRecord(**dated(row, "created_at", "scored_at", "published_at"))
