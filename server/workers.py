"""Workers: threads that take jobs from the queue and run them, in the service's process or in a process of
their own (``kitti-eval worker``), on any machine that reaches the database.

A worker holds its job with a lease it extends while the job runs (a heartbeat every third of the lease); a
worker that stops (killed, frozen, cut off) loses the job to another once the lease has run out, and its own
result, if it comes later, is not committed (the queue's ``finish`` answers False). A job whose input cannot
be evaluated (the library's or the service's refusal) fails at once with the error a client would have been
answered, kept as JSON with the job; anything else is tried again, up to the queue's ``max_attempts``.
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

from .errors import ApiError, fault_of, library_error_status
from .jobs import ENDED_STATES, JobQueue, JobRecord
from .observability import AdmissionState
from .runner import release_memory

__all__ = ["Workers", "Handler", "JobFailed", "error_of", "worker_name", "await_job", "job_view"]

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
        return {"status": exc.status_code, "code": exc.code, "message": exc.message}, exc.status_code >= 500
    if isinstance(exc, KittiEvalError):
        status, code = library_error_status(exc)
        body: dict[str, Any] = {"status": status, "code": code, "message": str(exc)}
        for detail in ("frame", "field"):
            value = getattr(exc, detail, None)
            if value is not None:
                body[detail] = value
        return body, False
    fault = fault_of(exc, 2) if isinstance(exc, Exception) else None
    if fault is not None:
        return {"status": fault.status_code, "code": fault.code, "message": fault.message}, True
    return {"status": 500, "code": "internal_error", "message": "the evaluation failed on the server"}, True


class Workers:
    """``threads`` workers of this process on ``queue``, running each kind of job with its handler."""

    def __init__(
        self,
        queue: JobQueue,
        handlers: Mapping[str, Handler],
        *,
        threads: int,
        admission: AdmissionState | None = None,
        idle_s: float = 0.5,
        names: Callable[[int], str] = worker_name,
    ) -> None:
        self.queue = queue
        self.handlers = dict(handlers)
        self.threads = threads
        self.admission = admission or AdmissionState()
        self.idle_s = idle_s
        self.names = names
        self._wake = threading.Condition()
        self._pending = 0
        self._stopping = threading.Event()
        self._running: list[threading.Thread] = []
        self._count_lock = threading.Lock()

    # -- life ----------------------------------------------------------------------------------------------
    def start(self) -> None:
        self._stopping.clear()
        for i in range(self.threads):
            thread = threading.Thread(
                target=self._loop, args=(self.names(i),), name=f"kitti-eval-worker-{i}", daemon=True
            )
            thread.start()
            self._running.append(thread)

    def stop(self, grace_s: float = 30.0) -> None:
        """Take no new job; the running ones finish within ``grace_s`` (a job still running then goes back to
        the queue when its lease runs out)."""
        self._stopping.set()
        self.wake(len(self._running))
        for thread in self._running:
            thread.join(grace_s)
        self._running = []

    def wake(self, n: int = 1) -> None:
        """Jobs were enqueued in this process: idle workers look at once."""
        with self._wake:
            self._pending += n
            self._wake.notify(n)

    @property
    def alive(self) -> int:
        return sum(t.is_alive() for t in self._running)

    # -- the loop ------------------------------------------------------------------------------------------
    def _loop(self, name: str) -> None:
        while not self._stopping.is_set():
            try:
                job = self.queue.claim(name, kinds=list(self.handlers))
            except Exception:  # noqa: BLE001 - the database is away: wait and try again
                log.warning("worker %s could not claim a job", name, exc_info=True)
                job = None
            if job is None:
                with self._wake:
                    if self._pending == 0 and not self._stopping.is_set():
                        self._wake.wait(self.idle_s)
                    self._pending = max(0, self._pending - 1)
                continue
            self.run_one(job, name)

    def run_one(self, job: JobRecord, name: str) -> bool:
        """Run a claimed job, extending its lease meanwhile; True when its result was committed."""
        beat = threading.Event()

        def heartbeat() -> None:
            period = max(0.05, self.queue.lease_s / 3)
            while not beat.wait(period):
                try:
                    if not self.queue.heartbeat(job.id, name):
                        log.warning("job %s is no longer %s's (taken over or cancelled)", job.id, name)
                        return
                except Exception:  # noqa: BLE001 - the next beat may reach the database
                    log.warning("heartbeat of job %s failed", job.id, exc_info=True)

        beating = threading.Thread(target=heartbeat, name=f"heartbeat-{job.id}", daemon=True)
        beating.start()
        with self._count_lock:
            self.admission.running += 1
        try:
            result_id, write = self.handlers[job.kind](job)
        except BaseException as e:  # noqa: BLE001 - every failure is the job's, recorded with it
            body, retry = error_of(e)
            if retry:
                log.exception("job %s failed (attempt %s)", job.id, job.attempts)
            else:
                log.info("job %s refused: %s", job.id, body["message"])
            self.queue.fail(job.id, name, json.dumps(body), retry=retry)
            return False
        else:
            return self.queue.finish(job.id, name, result_id, within=write)
        finally:
            beat.set()
            with self._count_lock:
                self.admission.running -= 1
            release_memory()


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
        self.details = {k: body[k] for k in ("frame", "field") if k in body}


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


def job_view(record: JobRecord, position: int | None) -> dict[str, Any]:
    """A job as its owner (or an admin) sees it."""
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
    if record.kind in ("submission", "rescore") and record.group:
        sid = record.result_id or record.payload.get("submission_id")
        out["submission"] = sid
        out["result_location"] = f"/v1/benchmarks/{record.group}/submissions/{sid}"
    if record.state == "failed":
        failure = JobFailed(record.error)
        out["error"] = {"status": failure.status_code, "code": failure.code, "message": failure.message}
    return out
