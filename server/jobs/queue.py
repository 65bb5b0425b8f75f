"""The queue every evaluation, benchmark submission and rescoring goes through: a job is recorded, queued, in
the database the moment its input is stored, and workers (threads of this process, or of other processes and
machines on the same database) take jobs with a lease.

A job's life::

    queued --claim--> running --finish--> done
      ^                  |  \\--fail (no retry, or no attempt left)--> failed
      |                  |   \\-cancel--> cancelled
      +--fail (retry) ---+
      +--release---------+  (a draining worker: the attempt is not counted)
      +--lease run out, claimed by another worker (an attempt more, once: failed worker_lost when lost again
                                                   or max_attempts were used, job_timeout past the time limit)

    done | failed | cancelled --rerun--> queued (as new)

A worker holds a running job until its lease runs out; :meth:`JobQueue.heartbeat` extends it. A worker that
stopped extending it (killed, frozen, cut off) loses the job to the next :meth:`JobQueue.claim`, and its own
later :meth:`~JobQueue.heartbeat`, :meth:`~JobQueue.finish` or :meth:`~JobQueue.fail` then answer False and
change nothing: a job's result is committed once. Worker names must be unique among the workers on the database
(a host, a process id and a thread, say): a job is the worker's while its row names it.

Times are the queue's clock's (the machines' clocks, which the leases trust to agree within a fraction of
``lease_s``), in UTC.
"""

from __future__ import annotations

import builtins
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Any

from sqlalchemy.engine import Connection
from sqlalchemy.exc import IntegrityError

from ..errors import QueueFull, TooManyQueued
from ..store import (
    IdempotencyRecord,
    IdempotencyStore,
    JobInput,
    JobInputStore,
    JobRecord,
    JobStore,
    Store,
    WorkerRecord,
    WorkerStore,
    new_id,
    retry_when_locked,
)
from ..store.job_store import ENDED_STATES, JOB_STATES

__all__ = ["JobQueue", "QueueLimits", "JobRecord", "WorkerRecord", "JOB_KINDS", "JOB_STATES", "ENDED_STATES", "now_utc"]

#: what a job runs: an evaluation, an evaluation a gate asks for without keeping it, a benchmark submission's
#: scoring, a submission scored again, or a scored submission's ranking key under its benchmark's bootstrap
#: resamples (queued by its scoring)
JOB_KINDS = ("evaluation", "gate", "submission", "rescore", "intervals")


def now_utc() -> datetime:
    return datetime.now(timezone.utc)


class _Endings:
    """Jobs that ended (done, failed, cancelled) in this process, for the waiters of this process: each
    ending counts up its job's number (the last few thousand jobs are remembered)."""

    _KEPT = 4096

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._count = 0
        self._seen: OrderedDict[str, int] = OrderedDict()

    def mark(self, job_id: str) -> int:
        """The job's number now (0: never ended here); a later :meth:`await_change` compares with it."""
        with self._changed:
            return self._seen.get(job_id, 0)

    def ended(self, job_ids: Sequence[str]) -> None:
        if not job_ids:
            return
        with self._changed:
            for job_id in job_ids:
                self._count += 1
                self._seen[job_id] = self._count
                self._seen.move_to_end(job_id)
            while len(self._seen) > self._KEPT:
                self._seen.popitem(last=False)
            self._changed.notify_all()

    def await_change(self, job_id: str, mark: int, timeout_s: float) -> None:
        with self._changed:
            self._changed.wait_for(lambda: self._seen.get(job_id, 0) != mark, timeout_s)


#: shared by every queue of the process, whatever its store object
_ENDINGS = _Endings()


@dataclass(frozen=True)
class QueueLimits:
    """What the queue holds at most; :meth:`JobQueue.admit` refuses a new job past it (with ``retry_after_s``).
    The defaults are the service's settings' (``KITTI_EVAL_MAX_QUEUED_JOBS``, ...)."""

    #: jobs queued or running, everybody's
    jobs: int = 2000
    #: jobs queued or running of one owner
    per_owner: int = 20
    #: bytes of the inputs of the jobs queued or running
    input_bytes: int = 4096 << 20
    retry_after_s: int = 2


class JobQueue:
    """The jobs of one database, as the service and its workers use them."""

    def __init__(
        self,
        job_store: JobStore,
        job_input_store: JobInputStore,
        worker_store: WorkerStore,
        idempotency_store: IdempotencyStore,
        *,
        lease_s: float = 30.0,
        max_attempts: int = 3,
        limits: QueueLimits | None = None,
        clock: Callable[[], datetime] = now_utc,
        time_limit_s: float | None = None,
    ) -> None:
        """``lease_s``: how long a claim or a heartbeat keeps a job its worker's; ``max_attempts``: the claims
        a job enqueued here gets (a failure with retry, or a lost worker, uses one); ``limits``: what
        :meth:`admit` lets in; ``clock``: the current time (timezone-aware); ``time_limit_s``: the jobs' time
        limit (``KITTI_EVAL_JOB_TIMEOUT_S``): a job whose worker was lost after it is failed, not taken over."""
        if lease_s <= 0 or max_attempts < 1:
            raise ValueError("lease_s must be positive and max_attempts at least 1")
        self.job_store = job_store
        self.job_input_store = job_input_store
        self.worker_store = worker_store
        self.idempotency_store = idempotency_store
        self.db = job_store.db  # one database: a job, its inputs and its key are written in one transaction
        self.lease_s = lease_s
        self.max_attempts = max_attempts
        self.limits = limits or QueueLimits()
        self.clock = clock
        self.time_limit_s = time_limit_s

    @classmethod
    def of(cls, store: Store, **options: Any) -> JobQueue:
        """A queue on the areas of ``store`` it uses (``options``: those of the constructor)."""
        return cls(store.job_store, store.job_input_store, store.worker_store, store.idempotency_store, **options)

    def admit(self, owner: str | None, size: int) -> None:
        """Refuse a new job of ``owner``'s (None: nobody's in particular, as in open mode) with ``size`` bytes
        of input when the queue is full: 503 :class:`~kitti_eval_server.errors.QueueFull` past the jobs or the
        bytes it holds, 429 :class:`~kitti_eval_server.errors.TooManyQueued` past the jobs one owner may have
        queued or running. Busy evaluators are no reason: a job waits its turn. Checked before the job's input
        is stored; requests accepted at the same moment may each pass it (the limits are exceeded by at most
        those)."""
        lim = self.limits
        total, mine = self.job_store.active_jobs(owner or "")
        if total >= lim.jobs:
            raise QueueFull(
                f"the queue holds {total} jobs, as many as it keeps (KITTI_EVAL_MAX_QUEUED_JOBS); retry in "
                f"{lim.retry_after_s} s",
                lim.retry_after_s,
            )
        if owner is not None and mine >= lim.per_owner:
            raise TooManyQueued(
                f"you have {mine} jobs queued or running, as many as one user may "
                f"(KITTI_EVAL_MAX_QUEUED_PER_CALLER); retry when one has ended",
                lim.retry_after_s,
            )
        held = self.job_input_store.job_input_bytes()
        if held + size > lim.input_bytes:
            raise QueueFull(
                f"the queue's inputs take {held / (1 << 20):.0f} MB, as much as it keeps "
                f"(KITTI_EVAL_MAX_QUEUED_INPUT_MB); retry in {lim.retry_after_s} s",
                lim.retry_after_s,
            )

    def _now(self) -> datetime:
        now = self.clock()
        return (now if now.tzinfo else now.replace(tzinfo=timezone.utc)).astimezone(timezone.utc)

    def _lease_from(self, now: datetime) -> datetime:
        return now + timedelta(seconds=self.lease_s)

    def _new(
        self, kind: str, payload: Mapping[str, Any], owner: str, group: str | None, job_id: str | None, at: datetime
    ) -> JobRecord:
        if kind not in JOB_KINDS:
            raise ValueError(f"unknown kind of job {kind!r} (one of {', '.join(JOB_KINDS)})")
        return JobRecord(
            id=job_id or new_id(),
            kind=kind,
            state="queued",
            attempts=0,
            max_attempts=self.max_attempts,
            worker=None,
            lease_until=None,
            accepted_at=at,
            started_at=None,
            finished_at=None,
            owner=owner,
            group=group,
            payload=dict(payload),
        )

    def enqueue(
        self,
        kind: str,
        payload: dict,
        *,
        owner: str,
        group: str | None = None,
        job_id: str | None = None,
        inputs: builtins.list[JobInput] | None = None,
        idempotency_key: IdempotencyRecord | None = None,
    ) -> JobRecord:
        """Record a queued job (committed when this returns), with its uploaded ``inputs`` in the same
        transaction. ``job_id``: the id to give it (a new one when None); when a job already has it, that job
        is returned as it is (enqueueing the same job again, as a retried request does, records it once).
        ``idempotency_key``: the request's, recorded in the same transaction (with ``inputs`` only);
        :class:`~kitti_eval_server.store.KeyTaken`, and nothing recorded, when a request recorded it first."""
        record = self._new(kind, payload, owner, group, job_id, self._now())
        if inputs:
            added = self._add_with_inputs(record, inputs, idempotency_key)
        else:
            added = self.job_store.add_job(record)
        if added:
            return record
        existing = self.job_store.get_job(record.id)
        if existing is None:  # deleted in between: only a database changed by hand gets here
            raise RuntimeError(f"job {record.id} could neither be added nor read")
        return existing

    @retry_when_locked
    def _add_with_inputs(
        self, record: JobRecord, inputs: builtins.list[JobInput], idempotency_key: IdempotencyRecord | None
    ) -> bool:
        """The job and its uploaded files in one transaction (one commit: a job is never without its input);
        False, and nothing added, when the job's id is taken. ``idempotency_key``: the request's, recorded in
        the same transaction (:class:`~kitti_eval_server.store.KeyTaken` when another request recorded it first:
        nothing is added)."""
        with self.db.writing() as conn:
            if idempotency_key is not None:
                self.idempotency_store.add_idempotency_key_in(conn, idempotency_key)
            if not self.job_store.add_job_in(conn, record):
                return False
            self.job_input_store.add_job_inputs_in(conn, record.id, inputs)
            return True

    def enqueue_in(
        self, conn: Connection, kind: str, payload: dict, *, owner: str, group: str | None = None, job_id: str
    ) -> bool:
        """Record a queued job within the caller's transaction (committed with it: the end of the job that
        queues it). False when a job already has ``job_id`` (then nothing is added)."""
        return self.job_store.add_job_in(conn, self._new(kind, payload, owner, group, job_id, self._now()))

    def enqueue_many(
        self, kind: str, payloads: builtins.list[dict], *, owner: str, group: str | None = None
    ) -> builtins.list[JobRecord]:
        """Record queued jobs, one a payload, in one transaction; they are claimed in the order given (each is
        accepted a microsecond after the one before)."""
        now = self._now()
        records = [
            self._new(kind, payload, owner, group, None, now + timedelta(microseconds=i))
            for i, payload in enumerate(payloads)
        ]
        try:
            self.job_store.add_jobs(records)
        except IntegrityError as e:  # a new id taken: 128 random bits make this a broken generator, not bad luck
            raise RuntimeError("a new job id was taken") from e
        return records

    def claim(self, worker: str, *, kinds: Sequence[str] | None = None) -> JobRecord | None:
        """Take a job of ``kinds`` (None: any): the oldest (by ``accepted_at``, then ``id``) running one whose
        lease ran out (taken over from a worker that was lost; it was at the head of the queue when first
        claimed), else the oldest queued one. It becomes running, held by ``worker`` for ``lease_s``, with one
        attempt more (``started_at`` is set at its first claim). None when there is none. A lapsed job is
        taken over once: one whose worker was lost before, or that already used its ``max_attempts``, is failed
        instead (``worker_lost``: "the worker was lost N times"), as is one first started longer ago than the
        time limit (``job_timeout``), and the next is looked at.

        Never gives a job to two workers: on PostgreSQL the row is locked with ``SELECT ... FOR UPDATE SKIP
        LOCKED`` (concurrent claims take the next rows), on SQLite the claim holds the write lock from its
        start (``BEGIN IMMEDIATE``: claims run one after another)."""
        now = self._now()
        job, lost = self.job_store.claim_job(
            worker, now=now, lease_until=self._lease_from(now), kinds=kinds, time_limit_s=self.time_limit_s
        )
        _ENDINGS.ended(lost)
        return job

    def heartbeat(self, job_id: str, worker: str) -> bool:
        """Extend the job's lease by ``lease_s`` from now. False when the job is no longer ``worker``'s (taken
        over after its lease ran out, cancelled, ended): the worker should stop working on it."""
        return self.job_store.extend_lease(job_id, worker, self._lease_from(self._now()))

    def finish(
        self, job_id: str, worker: str, result_id: str, *, within: Callable[[Connection], None] | None = None
    ) -> bool:
        """Mark the job done with ``result_id`` if it is still running and held by ``worker``. ``within(conn)``
        runs first, in the same transaction (the executor writes its result there through ``conn``, and only
        through it: another connection of the store would wait for this transaction's lock on SQLite): the
        result and the job's end are committed together or not at all. False when the job is no longer this
        worker's: then nothing is written (``within`` is not called, or its writes are rolled back). An
        exception of ``within`` rolls everything back and propagates (the job stays running, its worker's)."""
        finished = self.job_store.complete_job(job_id, worker, result_id, self._now(), within)
        if finished:
            _ENDINGS.ended([job_id])
        return finished

    def fail(self, job_id: str, worker: str, error: str, *, retry: bool) -> bool:
        """The job failed with ``error``. With ``retry`` and attempts left (``attempts < max_attempts``) it is
        queued again, its worker and lease cleared (``error`` kept as the last one, until it ends); else it is
        failed, with ``error`` and ``finished_at``. False (nothing changed) when the job is no longer
        ``worker``'s."""
        job = self.job_store.fail_job(job_id, worker, error, self._now(), retry=retry)
        if job is not None and job.state == "failed":
            _ENDINGS.ended([job_id])
        return job is not None

    def release(self, job_id: str, worker: str) -> bool:
        """Give the job back, queued, without counting the attempt (a worker that is draining). False when it
        is no longer ``worker``'s."""
        return self.job_store.release_job(job_id, worker)

    def cancel(self, job_id: str) -> JobRecord | None:
        """A queued or running job becomes cancelled (a running one's worker learns it at its next heartbeat,
        finish or fail, which answer False). The job as it is then (an ended job is left as it is: its state
        says whether it was cancelled); None when there is no such job."""
        job = self.job_store.cancel_job(job_id, self._now())
        if job is not None and job.state == "cancelled":
            _ENDINGS.ended([job_id])
        return job

    def rerun(self, job_id: str) -> JobRecord | None:
        """An ended job (failed, cancelled or done) is queued again as new: at the end of the queue (accepted
        now), no attempt used, its worker, result and error cleared. A queued or running job is left as it is.
        The job as it is then; None when there is no such job."""
        return self.job_store.requeue_job(job_id, self._now())

    def get(self, job_id: str) -> JobRecord | None:
        return self.job_store.get_job(job_id)

    def position(self, job_id: str) -> int | None:
        """The job's place among the queued jobs, 1 for the next to be claimed (None when it is not queued).
        Jobs whose worker was lost are not counted, though a claim takes them first when they are older."""
        before = self.job_store.queued_before(job_id)
        return None if before is None else before + 1

    def list(
        self,
        *,
        state: str | None = None,
        kind: str | None = None,
        owner: str | None = None,
        group: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> builtins.list[JobRecord]:
        """Newest first (by ``accepted_at``); each filter given narrows the list."""
        return self.job_store.list_jobs(state=state, kind=kind, owner=owner, group=group, limit=limit, offset=offset)

    def counts(self, *, owner: str | None = None, group: str | None = None, kind: str | None = None) -> dict[str, int]:
        """Jobs by state (every state a key, 0 when none), of ``owner``, ``group`` and ``kind`` when given."""
        return self.job_store.count_jobs(owner=owner, group=group, kind=kind)

    def oldest_queued_age_s(self) -> float | None:
        """Seconds since the oldest queued job was accepted (None when none is queued)."""
        oldest = self.job_store.oldest_queued_at()
        return None if oldest is None else max(0.0, (self._now() - oldest).total_seconds())

    # -- the processes that run jobs ------------------------------------------------------------------------
    #: a process not seen for this long is forgotten (its row dropped by any other's beat)
    FORGET_WORKERS_S = 3600.0

    def worker_beat(self, name: str, *, host: str, pid: int, threads: int, started_at: datetime) -> None:
        """The process ``name`` (``host:pid``), running ``threads`` workers since ``started_at``, is alive now."""
        now = self._now()
        record = WorkerRecord(name, host, pid, threads, started_at, now)
        self.worker_store.beat_worker(record, forget_before=now - timedelta(seconds=self.FORGET_WORKERS_S))

    def worker_gone(self, name: str) -> None:
        """The process ``name`` stopped (its row is removed)."""
        self.worker_store.forget_worker(name)

    def workers_seen(self, within_s: float) -> builtins.list[WorkerRecord]:
        """The processes that beat within the last ``within_s`` seconds."""
        return self.worker_store.workers_seen(self._now() - timedelta(seconds=within_s))

    def wait(self, job_id: str, timeout_s: float, *, poll_s: float = 0.05) -> JobRecord | None:
        """Block until the job is done, failed or cancelled, or ``timeout_s`` has passed; the job as it is then
        (None when there is no such job). Wakes at once when the job ends in this process (any queue of it);
        otherwise the database is read again every ``poll_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            mark = _ENDINGS.mark(job_id)
            job = self.get(job_id)
            remaining = deadline - time.monotonic()
            if job is None or job.state in ENDED_STATES or remaining <= 0:
                return job
            _ENDINGS.await_change(job_id, mark, min(poll_s, remaining))
