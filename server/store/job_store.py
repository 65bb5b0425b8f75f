"""The store's queue of work (the rules, and the times they use, are :mod:`kitti_eval_server.jobs.queue`'s).

A job is taken in one transaction that no other taker can share: on PostgreSQL the oldest takeable row is
locked with ``SELECT ... FOR UPDATE SKIP LOCKED`` (takers on other servers skip it and lock the next one), on
SQLite the transaction holds the database's write lock from its start (``BEGIN IMMEDIATE``). Every change of a
job held by a worker has the worker's name among its conditions (an UPDATE guarded by them, or a read of the row
under the same locks before the change), so a worker that lost its job (taken over, cancelled) changes nothing.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Update, and_, case, func, insert, or_, select, update
from sqlalchemy.engine import Connection, RowMapping

from .database import Area, dated, jobs, retry_when_locked, submissions, utc

__all__ = ["JobRecord", "JobStore", "JOB_STATES", "ENDED_STATES", "WORKER_LOST", "lost_error", "timeout_error"]

#: every state of a job, in the order a job goes through them
JOB_STATES = ("queued", "running", "done", "failed", "cancelled")
#: the states a job stays in until it is run again by hand
ENDED_STATES = frozenset({"done", "failed", "cancelled"})


@dataclass(frozen=True)
class JobRecord:
    """A job's row (``group`` is the ``grp`` column)."""

    id: str
    kind: str  # evaluation | submission | rescore | intervals
    state: str  # queued | running | done | failed | cancelled
    attempts: int  # 0 when queued, +1 at each claim
    max_attempts: int
    worker: str | None  # who holds it (running) or held it last
    lease_until: datetime | None  # running: another worker may take it over after this
    accepted_at: datetime
    started_at: datetime | None  # the first claim
    finished_at: datetime | None
    owner: str  # the caller's name
    group: str | None  # e.g. the benchmark a rescoring belongs to
    payload: Mapping[str, Any]  # the executor's input
    result_id: str | None = None
    error: str | None = None


class _NotHeld(Exception):
    """Rolls back a change of a job its worker no longer holds."""


def lost_message(attempts: int) -> str:
    return f"the worker was lost {attempts} time{'' if attempts == 1 else 's'}"


#: the code of a job's error when its worker was lost (killed, out of memory, its machine gone)
WORKER_LOST = "worker_lost"


def lost_error(lost: int, *, again: bool) -> str:
    """The error of a job whose worker was lost ``lost`` times: kept while it is taken over (``again``), or the
    one it fails with. Its body is that of an error answer (as :class:`kitti_eval_server.jobs.workers.JobFailed`
    reads it)."""
    message = lost_message(lost)
    if not again:
        message += (
            "; a job is taken over once when its worker is lost: an input that makes its worker run out of memory"
            " would take the next one down too"
        )
    return json.dumps({"status": 500, "code": WORKER_LOST, "message": message, "lost": lost})


def _times_lost(job: JobRecord) -> int:
    """How many times the job's worker was lost, as its error says (0: never, or not since its last failure)."""
    try:
        body = json.loads(job.error or "")
    except ValueError:
        return 0
    return int(body.get("lost") or 0) if isinstance(body, dict) and body.get("code") == WORKER_LOST else 0


def timeout_error(kind: str, limit_s: float) -> str:
    """The error of a job failed past its time limit (the body of an error answer)."""
    message = f"the {kind} ran past the time limit of {limit_s:g} s (KITTI_EVAL_JOB_TIMEOUT_S); it is not tried again"
    return json.dumps({"status": 422, "code": "job_timeout", "message": message})


#: why a submission whose scoring an admin cancelled failed
CANCELLED_MESSAGE = "its scoring was cancelled by an admin before it ended"


def _fail_submission_in(conn: Connection, job: JobRecord, reason: str) -> None:
    """A submission's scoring job that ends without a score (cancelled, given up on) fails the submission with
    ``reason`` in the transaction that ends the job: a failed submission does not count against the quota."""
    if job.kind != "submission":
        return
    sid = str(job.payload.get("submission_id") or job.id)
    still = and_(submissions.c.id == sid, submissions.c.status == "accepted")
    conn.execute(update(submissions).where(still).values(status="failed", failure=reason[:500]))


class JobStore(Area):
    """Jobs: added, taken with a lease, kept, finished, failed, released, cancelled, queued again; listed."""

    @retry_when_locked
    def add_job(self, record: JobRecord) -> bool:
        """False if the id is taken."""
        return self._insert(jobs, **self._job_values(record))

    @classmethod
    def add_job_in(cls, conn: Connection, record: JobRecord) -> bool:
        """Within a transaction of the caller's (another job's end): False if the id is taken (nothing added)."""
        if conn.execute(select(jobs.c.id).where(jobs.c.id == record.id)).first() is not None:
            return False
        conn.execute(insert(jobs).values(**cls._job_values(record)))
        return True

    @retry_when_locked
    def add_jobs(self, records: Sequence[JobRecord]) -> None:
        """All of them in one transaction (none when one id is taken: IntegrityError)."""
        if not records:
            return
        with self.engine.begin() as conn:
            conn.execute(insert(jobs), [self._job_values(r) for r in records])

    @retry_when_locked
    def get_job(self, job_id: str) -> JobRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(jobs).where(jobs.c.id == job_id)).mappings().first()
        return None if row is None else self._job(row)

    @retry_when_locked
    def claim_job(
        self,
        worker: str,
        *,
        now: datetime,
        lease_until: datetime,
        kinds: Sequence[str] | None = None,
        time_limit_s: float | None = None,
    ) -> tuple[JobRecord | None, list[str]]:
        """Take a job for ``worker`` until ``lease_until``: the oldest (by ``accepted_at``, then ``id``) of those
        running with a lease run out before ``now`` (their workers were lost; they were at the head of the queue
        when first claimed), else the oldest queued one. Answers (the job, or None when there is none; the ids
        of the jobs failed on the way). A lapsed job is failed instead of taken, and the next one is looked at,
        when its attempts reached its ``max_attempts``, when its worker was lost before (``worker_lost``: a job
        is taken over once), or when it was first started more than ``time_limit_s`` ago (``job_timeout``).

        Each of the two looks is an ordered scan of the (state, accepted_at, id) index that stops at the first
        row, however long the queue and its history."""
        lapsed = select(jobs).where(jobs.c.state == "running", jobs.c.lease_until < now)
        queued = select(jobs).where(jobs.c.state == "queued")
        if kinds is not None:
            lapsed = lapsed.where(jobs.c.kind.in_(list(kinds)))
            queued = queued.where(jobs.c.kind.in_(list(kinds)))
        first = [
            query.order_by(jobs.c.accepted_at, jobs.c.id).limit(1).with_for_update(skip_locked=True)
            for query in (lapsed, queued)
        ]
        lost: list[str] = []
        with self._writing() as conn:
            while True:
                row = conn.execute(first[0]).mappings().first() or conn.execute(first[1]).mappings().first()
                if row is None:
                    return None, lost
                job = self._job(row)
                times_lost = _times_lost(job) + 1 if job.state == "running" else 0
                if job.state == "running":
                    error = None
                    started = job.started_at
                    if time_limit_s is not None and started and now - started > timedelta(seconds=time_limit_s):
                        error = timeout_error(job.kind, time_limit_s)
                    elif job.attempts >= job.max_attempts or times_lost > 1:
                        error = lost_error(times_lost, again=False)
                    if error is not None:
                        ended = dict(state="failed", lease_until=None, finished_at=now, error=error)
                        conn.execute(update(jobs).where(jobs.c.id == job.id).values(**ended))
                        _fail_submission_in(conn, job, json.loads(error)["message"])
                        lost.append(job.id)
                        continue
                taken = dict(
                    state="running",
                    worker=worker,
                    lease_until=lease_until,
                    started_at=job.started_at or now,
                    attempts=job.attempts + 1,
                )
                if times_lost:
                    taken["error"] = lost_error(times_lost, again=True)
                conn.execute(update(jobs).where(jobs.c.id == job.id).values(**taken))
                return JobRecord(**{**job.__dict__, **taken}), lost

    def _job_held(self, conn: Connection, job_id: str, worker: str) -> JobRecord | None:
        """The job, locked for the transaction, if it is running and held by ``worker``."""
        query = select(jobs).where(jobs.c.id == job_id, jobs.c.state == "running", jobs.c.worker == worker)
        row = conn.execute(query.with_for_update()).mappings().first()
        return None if row is None else self._job(row)

    def _job_guarded(self, job_id: str, worker: str) -> Update:
        """An UPDATE of the job that changes it only if it is running and held by ``worker``."""
        return update(jobs).where(jobs.c.id == job_id, jobs.c.state == "running", jobs.c.worker == worker)

    @retry_when_locked
    def extend_lease(self, job_id: str, worker: str, lease_until: datetime) -> bool:
        """Keep the job until ``lease_until``; False when ``worker`` no longer holds it."""
        with self.engine.begin() as conn:
            return bool(conn.execute(self._job_guarded(job_id, worker).values(lease_until=lease_until)).rowcount)

    @retry_when_locked
    def complete_job(
        self,
        job_id: str,
        worker: str,
        result_id: str,
        finished_at: datetime,
        within: Callable[[Connection], None] | None = None,
    ) -> bool:
        """Mark the job done with ``result_id`` if ``worker`` still holds it, after ``within(conn)`` wrote what it
        produced in the same transaction: both are committed, or neither. False (nothing written, ``within`` not
        called) when the job is no longer the worker's; an exception of ``within`` rolls back and propagates."""
        done = dict(state="done", result_id=result_id, finished_at=finished_at, lease_until=None, error=None)
        try:
            with self._writing() as conn:
                if self._job_held(conn, job_id, worker) is None:
                    raise _NotHeld
                if within is not None:
                    within(conn)
                if not conn.execute(self._job_guarded(job_id, worker).values(**done)).rowcount:
                    raise _NotHeld
        except _NotHeld:
            return False
        return True

    @retry_when_locked
    def fail_job(self, job_id: str, worker: str, error: str, finished_at: datetime, *, retry: bool) -> JobRecord | None:
        """Queue the job again (``retry`` and attempts left: the worker and lease cleared, ``error`` kept as the
        last one) or fail it with ``error``; None when ``worker`` no longer holds it, else the job as it is now."""
        with self._writing() as conn:
            job = self._job_held(conn, job_id, worker)
            if job is None:
                return None
            if retry and job.attempts < job.max_attempts:
                values: dict[str, Any] = dict(state="queued", worker=None, lease_until=None, error=error)
            else:
                values = dict(state="failed", lease_until=None, finished_at=finished_at, error=error)
            conn.execute(update(jobs).where(jobs.c.id == job_id).values(**values))
        return JobRecord(**{**job.__dict__, **values})

    @retry_when_locked
    def release_job(self, job_id: str, worker: str) -> bool:
        """Queue the job again without counting the attempt; False when ``worker`` no longer holds it."""
        values = dict(state="queued", worker=None, lease_until=None, attempts=jobs.c.attempts - 1)
        with self.engine.begin() as conn:
            return bool(conn.execute(self._job_guarded(job_id, worker).values(**values)).rowcount)

    @retry_when_locked
    def cancel_job(self, job_id: str, finished_at: datetime) -> JobRecord | None:
        """A queued or running job becomes cancelled; any other is left as it is. The job as it is now (None:
        no such job)."""
        with self._writing() as conn:
            row = conn.execute(select(jobs).where(jobs.c.id == job_id).with_for_update()).mappings().first()
            if row is None:
                return None
            job = self._job(row)
            if job.state not in ("queued", "running"):
                return job
            values = dict(state="cancelled", lease_until=None, finished_at=finished_at)
            conn.execute(update(jobs).where(jobs.c.id == job_id).values(**values))
            _fail_submission_in(conn, job, CANCELLED_MESSAGE)
        return JobRecord(**{**job.__dict__, **values})

    @retry_when_locked
    def requeue_job(self, job_id: str, accepted_at: datetime) -> JobRecord | None:
        """An ended job (done, failed, cancelled) is queued again as new, at the end of the queue (accepted at
        ``accepted_at``, no attempt, no worker, result or error); a queued or running one is left as it is. The
        job as it is now (None: no such job)."""
        with self._writing() as conn:
            row = conn.execute(select(jobs).where(jobs.c.id == job_id).with_for_update()).mappings().first()
            if row is None:
                return None
            job = self._job(row)
            if job.state not in ENDED_STATES:
                return job
            values: dict[str, Any] = dict(
                state="queued",
                attempts=0,
                worker=None,
                lease_until=None,
                accepted_at=accepted_at,
                started_at=None,
                finished_at=None,
                result_id=None,
                error=None,
            )
            conn.execute(update(jobs).where(jobs.c.id == job_id).values(**values))
        return JobRecord(**{**job.__dict__, **values})

    @retry_when_locked
    def list_jobs(
        self,
        *,
        state: str | None = None,
        kind: str | None = None,
        owner: str | None = None,
        group: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[JobRecord]:
        """Newest first (``accepted_at``, then ``id``, descending)."""
        query = select(jobs)
        for column, value in ((jobs.c.state, state), (jobs.c.kind, kind), (jobs.c.owner, owner), (jobs.c.grp, group)):
            if value is not None:
                query = query.where(column == value)
        query = query.order_by(jobs.c.accepted_at.desc(), jobs.c.id.desc()).limit(limit).offset(offset)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._job(r) for r in rows]

    @retry_when_locked
    def count_jobs(
        self, *, owner: str | None = None, group: str | None = None, kind: str | None = None
    ) -> dict[str, int]:
        """Jobs by state, every state present (0 when none)."""
        query = select(jobs.c.state, func.count()).group_by(jobs.c.state)
        if kind is not None:
            query = query.where(jobs.c.kind == kind)
        if owner is not None:
            query = query.where(jobs.c.owner == owner)
        if group is not None:
            query = query.where(jobs.c.grp == group)
        with self.engine.connect() as conn:
            found: dict[str, int] = dict(conn.execute(query).all())
        return {state: int(found.get(state, 0)) for state in JOB_STATES}

    @retry_when_locked
    def active_jobs(self, owner: str) -> tuple[int, int]:
        """Jobs queued or running: all of them, and ``owner``'s."""
        active = jobs.c.state.in_(("queued", "running"))
        query = select(func.count(), func.coalesce(func.sum(case((jobs.c.owner == owner, 1), else_=0)), 0)).where(
            active
        )
        with self.engine.connect() as conn:
            total, mine = conn.execute(query).one()
        return int(total), int(mine)

    @retry_when_locked
    def queued_before(self, job_id: str) -> int | None:
        """How many queued jobs come before this one (None when it is not queued)."""
        with self.engine.connect() as conn:
            row = conn.execute(select(jobs.c.state, jobs.c.accepted_at).where(jobs.c.id == job_id)).first()
            if row is None or row.state != "queued":
                return None
            accepted_at = row.accepted_at
            earlier = or_(jobs.c.accepted_at < accepted_at, and_(jobs.c.accepted_at == accepted_at, jobs.c.id < job_id))
            return int(conn.execute(select(func.count()).where(jobs.c.state == "queued", earlier)).scalar_one())

    @retry_when_locked
    def oldest_queued_at(self) -> datetime | None:
        with self.engine.connect() as conn:
            oldest = conn.execute(select(func.min(jobs.c.accepted_at)).where(jobs.c.state == "queued")).scalar()
        return None if oldest is None else utc(oldest)

    @staticmethod
    def _job_values(record: JobRecord) -> dict[str, Any]:
        values = dict(record.__dict__)
        values["grp"] = values.pop("group")
        values["payload"] = dict(record.payload)
        return values

    @staticmethod
    def _job(row: RowMapping) -> JobRecord:
        values = dated(row, "lease_until", "accepted_at", "started_at", "finished_at")
        values["group"] = values.pop("grp")
        return JobRecord(**values)
