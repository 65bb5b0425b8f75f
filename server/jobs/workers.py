"""Workers: threads that take jobs from the queue and run them, in the service's process or in a process of
their own (``kitti-eval worker``), on any machine that reaches the database.

A worker holds its job with a lease it extends while the job runs (a heartbeat every third of the lease); a
worker that stops (killed, frozen, cut off) loses the job to another once the lease has run out, and its own
result, if it comes later, is not committed (the queue's ``finish`` answers False). A job whose input cannot
be evaluated (the library's or the service's refusal) fails at once with the error a client would have been
answered, kept as JSON with the job; anything else is tried again, up to the queue's ``max_attempts``.

A job still running past the time limit (``timeout_s``, ``KITTI_EVAL_JOB_TIMEOUT_S``) is failed then, once, with
its reason (``job_timeout``), and not tried again; a thread cannot be stopped from outside, so the worker's place
is taken at once by a new thread, and the late one ends when its job returns, its result not stored.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import anyio
import anyio.to_thread

from kitti_eval.errors import KittiEvalError

from ..errors import ApiError, fault_of, library_error_status
from ..observability import AdmissionState
from ..store.job_store import timeout_error
from .queue import ENDED_STATES, JobQueue, JobRecord, now_utc
from .runner import release_memory

__all__ = [
    "Workers",
    "Handler",
    "JobEnded",
    "OUTCOMES",
    "JobFailed",
    "JobCancelled",
    "admin_job_view",
    "error_of",
    "worker_name",
    "await_job",
    "await_outcome",
    "job_view",
]

log = logging.getLogger("kitti_eval.server")

#: what runs a job of a kind: the id of what it made, and the writes that store it (committed with the job's end)
Handler = Callable[[JobRecord], tuple[str, Callable[[Any], None]]]


def worker_name(index: int) -> str:
    """Unique among the workers on one database: host, process and thread."""
    return f"{socket.gethostname()}:{os.getpid()}:{index}"


def error_of(exc: BaseException) -> tuple[dict[str, Any], bool]:
    """(the error as the API answers it, whether to try again): a refusal of the input is final; a fault of
    the database or the disk, or a bug, is tried again."""
    if isinstance(exc, ApiError):
        details = {k: v for k, v in getattr(exc, "details", {}).items() if k not in ("status", "code", "message")}
        body = {"status": exc.status_code, "code": exc.code, "message": exc.message, **details}
        return body, exc.status_code >= 500
    if isinstance(exc, KittiEvalError):
        status, code = library_error_status(exc)
        lib: dict[str, Any] = {"status": status, "code": code, "message": str(exc)}
        for detail in ("frame", "field"):
            value = getattr(exc, detail, None)
            if value is not None:
                lib[detail] = value
        return lib, False
    fault = fault_of(exc, 2) if isinstance(exc, Exception) else None
    if fault is not None:
        return {"status": fault.status_code, "code": fault.code, "message": fault.message}, True
    return {"status": 500, "code": "internal_error", "message": "the evaluation failed on the server"}, True


#: told of every run of a job in this process: (kind, outcome, seconds, the attempt it was)
JobEnded = Callable[[str, str, float, int], None]

#: what a run of a job ended with (the log line's and the metrics' ``outcome``)
OUTCOMES = ("done", "refused", "retried", "failed", "lost", "released", "timed_out")


class Workers:
    """``threads`` workers of this process on ``queue``, running each kind of job with its handler.

    While its threads run, the process beats its row in the database every ``beat_s`` (the readiness and the
    metrics of any process on the database count the workers seen lately). Each run of a job writes one log
    line (the job, its kind, the outcome, the seconds) and is told to ``on_ended`` (the metrics)."""

    #: how often a worker process beats its row in the database (the default of ``beat_s``)
    BEAT_S = 15.0

    def __init__(
        self,
        queue: JobQueue,
        handlers: Mapping[str, Handler],
        *,
        threads: int,
        admission: AdmissionState | None = None,
        idle_s: float = 0.5,
        names: Callable[[int], str] = worker_name,
        beat_s: float = BEAT_S,
        timeout_s: float | None = None,
    ) -> None:
        self.queue = queue
        self.handlers = dict(handlers)
        self.threads = threads
        self.admission = admission or AdmissionState()
        self.idle_s = idle_s
        self.names = names
        self.beat_s = beat_s
        #: a job running longer than this is failed (``job_timeout``), not tried again; None: no limit
        self.timeout_s = timeout_s
        self.on_ended: JobEnded | None = None
        self.process_name = f"{socket.gethostname()}:{os.getpid()}"
        self._wake = threading.Condition()
        self._pending = 0
        self._stopping = threading.Event()
        self._running: list[threading.Thread] = []
        self._beating: threading.Thread | None = None
        self._count_lock = threading.Lock()
        #: worker name -> the job it runs now
        self._current: dict[str, JobRecord] = {}
        self._released: set[str] = set()
        #: the jobs failed past their time limit while their thread still runs them
        self._timed_out: set[str] = set()
        #: threads started so far (a thread that replaces one held by a job past its time limit takes the next name)
        self._started = 0

    # -- life ----------------------------------------------------------------------------------------------
    def start(self) -> None:
        self._stopping.clear()
        for _ in range(self.threads):
            self._start_thread()
        if self.threads:
            self._beating = threading.Thread(target=self._beat_process, name="kitti-eval-worker-beat", daemon=True)
            self._beating.start()

    def _start_thread(self) -> None:
        with self._count_lock:
            i = self._started
            self._started += 1
        thread = threading.Thread(target=self._loop, args=(self.names(i),), name=f"kitti-eval-worker-{i}", daemon=True)
        thread.start()
        self._running.append(thread)

    def stop(self, grace_s: float = 30.0) -> int:
        """Take no new job; the running ones have ``grace_s`` to finish, then those still running are released
        back to the queue (their attempt not counted; another worker runs them, and this one's late result, if
        it comes, is not stored). How many were released."""
        self._stopping.set()
        self.wake(len(self._running))
        deadline = time.monotonic() + grace_s
        for thread in self._running:
            thread.join(max(0.0, deadline - time.monotonic()))
        with self._count_lock:
            held = list(self._current.items())
        released = 0
        for name, job in held:
            try:
                if self.queue.release(job.id, name):
                    released += 1
                    with self._count_lock:
                        self._released.add(job.id)
                    log.warning("job %s %s released: still running after %g s of grace", job.id, job.kind, grace_s)
            except Exception:  # noqa: BLE001 - its lease runs out and another worker takes it over
                log.warning("job %s could not be released", job.id, exc_info=True)
        self._running = [t for t in self._running if t.is_alive()]
        if self._beating is not None:
            self._beating.join(max(1.0, deadline - time.monotonic()))
            self._beating = None
        return released

    def wake(self, n: int = 1) -> None:
        """Jobs were enqueued in this process: idle workers look at once."""
        with self._wake:
            self._pending += n
            self._wake.notify(n)

    @property
    def alive(self) -> int:
        """Worker threads alive in this process."""
        return sum(t.is_alive() for t in self._running)

    @property
    def busy(self) -> int:
        """Jobs running in this process now."""
        with self._count_lock:
            return len(self._current)

    def _beat_process(self) -> None:
        started_at = now_utc()
        host, pid = socket.gethostname(), os.getpid()
        while True:
            try:
                self.queue.worker_beat(
                    self.process_name, host=host, pid=pid, threads=self.threads, started_at=started_at
                )
            except Exception:  # noqa: BLE001 - the next beat may reach the database
                log.warning("could not record worker process %s in the database", self.process_name, exc_info=True)
            if self._stopping.wait(self.beat_s):
                break
        try:
            self.queue.worker_gone(self.process_name)
        except Exception:  # noqa: BLE001 - forgotten an hour later anyway
            log.debug("could not remove worker process %s from the database", self.process_name, exc_info=True)

    # -- the loop ------------------------------------------------------------------------------------------
    def _loop(self, name: str) -> None:
        ran = False  # a job ran since the memory was last handed back
        while not self._stopping.is_set():
            try:
                job = self.queue.claim(name, kinds=list(self.handlers))
            except Exception:  # noqa: BLE001 - the database is away: wait and try again
                log.warning("worker %s could not claim a job", name, exc_info=True)
                job = None
            if job is None:
                if ran:  # no next job: what the last ones freed goes back to the system while this one waits
                    release_memory()
                    ran = False
                with self._wake:
                    if self._pending == 0 and not self._stopping.is_set():
                        self._wake.wait(self.idle_s)
                    self._pending = max(0, self._pending - 1)
                continue
            ran = True
            try:
                self.run_one(job, name)
            except Exception:  # noqa: BLE001 - the database went away for good: the job's lease will lapse
                log.warning("worker %s could not record the end of job %s", name, job.id, exc_info=True)
            with self._count_lock:
                replaced = job.id in self._timed_out
                self._timed_out.discard(job.id)
            if replaced:  # a new thread took this one's place when its job passed the time limit
                return

    def _until_recorded(self, record: Callable[[], bool]) -> bool:
        """Record a job's end, trying again while the database is away (its lease is still being extended, so
        the job stays this worker's meanwhile; once the lease lapses, ``record`` answers False)."""
        delay = 0.1
        while True:
            try:
                return record()
            except Exception:
                if self._stopping.is_set():
                    raise
                log.warning("recording a job's end failed; trying again in %.1f s", delay, exc_info=True)
                time.sleep(delay)
                delay = min(5.0, delay * 2)

    def run_one(self, job: JobRecord, name: str) -> bool:
        """Run a claimed job, extending its lease meanwhile; True when its result was committed."""
        beat = threading.Event()

        def heartbeat() -> None:
            period = max(0.05, self.queue.lease_s / 3)
            if self.timeout_s is not None:
                period = min(period, max(0.05, self.timeout_s / 10))
            while not beat.wait(period):
                if self.timeout_s is not None and time.perf_counter() - started > self.timeout_s:
                    self._time_out(job, name)
                    return
                try:
                    if not self.queue.heartbeat(job.id, name):
                        log.warning("job %s is no longer %s's (taken over or cancelled)", job.id, name)
                        return
                except Exception:  # noqa: BLE001 - the next beat may reach the database
                    log.warning("heartbeat of job %s failed", job.id, exc_info=True)

        beating = threading.Thread(target=heartbeat, name=f"heartbeat-{job.id}", daemon=True)
        beating.start()
        started = time.perf_counter()
        with self._count_lock:
            self.admission.running += 1
            self._current[name] = job
        outcome, detail = "lost", ""
        try:
            result_id, write = self.handlers[job.kind](job)
            if job.id in self._timed_out:
                return False  # failed past its time limit meanwhile: nothing of it is stored
        except BaseException as e:  # noqa: BLE001 - every failure is the job's, recorded with it
            body, retry = error_of(e)
            detail = f": {body['code']}: {body['message']}"
            if body["code"] == "internal_error":  # a bug: its traceback for the log (the job keeps the message)
                log.error("job %s raised an unexpected error (attempt %s)", job.id, job.attempts, exc_info=True)
            if self._until_recorded(lambda: self.queue.fail(job.id, name, json.dumps(body), retry=retry)):
                outcome = "refused" if not retry else "retried" if job.attempts < job.max_attempts else "failed"
            return False
        else:
            committed = self._until_recorded(lambda: self.queue.finish(job.id, name, result_id, within=write))
            outcome = "done" if committed else "lost"
            return committed
        finally:
            beat.set()
            with self._count_lock:
                self.admission.running -= 1
                self._current.pop(name, None)
                if job.id in self._released:
                    self._released.discard(job.id)
                    outcome = "released" if outcome == "lost" else outcome
                if job.id in self._timed_out:
                    outcome, detail = "timed_out", f": job_timeout: past {self.timeout_s:g} s"
            seconds = time.perf_counter() - started
            log.info(
                "job %s %s %s in %.2f s (attempt %d of %d)%s",
                job.id,
                job.kind,
                outcome,
                seconds,
                job.attempts,
                job.max_attempts,
                detail,
            )
            if self.on_ended is not None:
                try:
                    self.on_ended(job.kind, outcome, seconds, job.attempts)
                except Exception:  # noqa: BLE001 - a metric never fails a job
                    log.debug("on_ended failed", exc_info=True)

    def _time_out(self, job: JobRecord, name: str) -> None:
        """Fail ``job``, still running on ``name`` past the time limit, with its reason (not tried again), and
        put a new thread in the place of the one it holds."""
        assert self.timeout_s is not None
        error = timeout_error(job.kind, self.timeout_s)
        try:
            failed = self._until_recorded(lambda: self.queue.fail(job.id, name, error, retry=False))
        except Exception:  # noqa: BLE001 - stopping: the job's lease lapses and it is taken over
            log.warning("job %s could not be failed past its time limit", job.id, exc_info=True)
            return
        if not failed:
            return  # no longer this worker's (cancelled, taken over)
        log.warning("job %s %s failed: still running after its time limit of %g s", job.id, job.kind, self.timeout_s)
        with self._count_lock:
            self._timed_out.add(job.id)
        if not self._stopping.is_set():
            self._start_thread()


class JobFailed(ApiError):
    """A job's failure, answered as the error its input would have been answered with at once."""

    def __init__(self, error: str | None) -> None:
        try:
            body = json.loads(error or "")
        except ValueError:
            body = {}
        if not isinstance(body, dict):
            body = {}
        super().__init__(str(body.get("message") or error or "the job failed"))
        self.status_code = int(body.get("status") or 500)
        self.code = str(body.get("code") or "job_failed")
        self.details = {k: v for k, v in body.items() if k not in ("status", "code", "message")}


class JobCancelled(ApiError):
    """A job an admin cancelled before it ended."""

    status_code = 409
    code = "cancelled"


async def await_outcome(queue: JobQueue, job_id: str, timeout_s: float) -> JobRecord:
    """:func:`await_job`, with a failed job raised as the error its input is answered with and a cancelled one
    as :class:`JobCancelled`: the job returned is done, or still queued or running."""
    ended = await await_job(queue, job_id, timeout_s)
    if ended.state == "failed":
        raise JobFailed(ended.error)
    if ended.state == "cancelled":
        raise JobCancelled(f"the {ended.kind} job {job_id} was cancelled by an admin before it ended")
    return ended


async def await_job(queue: JobQueue, job_id: str, timeout_s: float) -> JobRecord:
    """The job once it has ended, or as it is when ``timeout_s`` has passed. Polls without holding a thread:
    at once, then at growing intervals (20 ms to 250 ms)."""
    deadline = time.monotonic() + timeout_s
    delay = 0.02
    while True:
        record = await anyio.to_thread.run_sync(queue.get, job_id)
        if record is None:
            raise KeyError(job_id)
        remaining = deadline - time.monotonic()
        if record.state in ENDED_STATES or remaining <= 0:
            return record
        await anyio.sleep(min(delay, remaining))
        delay = min(0.25, delay * 1.5)


#: a job, as its owner (or an admin) reads it
JOB_FIELDS = (
    "id",
    "kind",
    "state",
    "position",
    "attempts",
    "accepted_at",
    "started_at",
    "finished_at",
    "location",
    "evaluation",
    "submission",
    "result_location",
    "error",
)


def job_view(record: JobRecord, position: int | None) -> dict[str, Any]:
    """A job as its owner (or an admin) sees it (:data:`JOB_FIELDS`)."""
    out: dict[str, Any] = {
        "id": record.id,
        "kind": record.kind,
        "state": record.state,
        "position": position,
        "attempts": record.attempts,
        "accepted_at": record.accepted_at.isoformat(),
        "started_at": record.started_at.isoformat() if record.started_at else None,
        "finished_at": record.finished_at.isoformat() if record.finished_at else None,
        "location": f"/v1/jobs/{record.id}",
    }
    if record.kind == "evaluation" and record.result_id:
        out["evaluation"] = record.result_id
        out["result_location"] = f"/v1/evaluations/{record.result_id}"
    if record.kind == "gate" and record.result_id:  # read once by its owner, not an evaluation
        out["result_location"] = f"/v1/gates/evaluations/{record.result_id}"
    if record.kind in ("submission", "rescore", "intervals") and record.group:
        sid = record.result_id or record.payload.get("submission_id")
        out["submission"] = sid
        out["result_location"] = f"/v1/benchmarks/{record.group}/submissions/{sid}"
    if record.state == "failed":
        failure = JobFailed(record.error)
        out["error"] = {"status": failure.status_code, "code": failure.code, "message": failure.message}
    return {k: out[k] for k in JOB_FIELDS if k in out}


def admin_job_view(record: JobRecord) -> dict[str, Any]:
    """A job as the admins' list shows it: its owner, its worker and lease, and the last error of one queued
    again after a failure."""
    out = job_view(record, None)
    out.update(
        owner=record.owner,
        group=record.group,
        max_attempts=record.max_attempts,
        worker=record.worker,
        lease_until=record.lease_until.isoformat() if record.lease_until else None,
    )
    if record.error and record.state != "failed":
        last = JobFailed(record.error)
        out["last_error"] = {"status": last.status_code, "code": last.code, "message": last.message}
    return out
