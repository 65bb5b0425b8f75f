"""A pool of worker processes on this machine: each is ``python -m kitti_eval_server.commands.process``, a fresh
interpreter with its own global lock (N processes use N cores), running the service's jobs on the database.

:class:`WorkerPool` starts them, starts one again when it dies (after a pause that grows from 1 s to 60 s while
they keep dying within a minute of their start), and stops them: SIGTERM to each, which drains it (it takes no
new job, its running ones finish or, past the grace, go back to the queue), then waits for them to exit.
``kitti-eval worker`` is a pool in a process of its own; ``kitti-eval serve`` starts one with the service when
``KITTI_EVAL_WORKER_PROCESSES`` is set.

The database URL goes to the processes in their environment (``KITTI_EVAL_DATABASE_URL``), never on their
command line, where ``ps`` would show its password.
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from .queue import JobQueue
from .spawn import CHILD_MODULE, child_command, child_env, take_early

__all__ = ["WorkerPool", "CHILD_MODULE"]  # CHILD_MODULE: from .spawn, where it is kept

log = logging.getLogger("kitti_eval.server")

#: a process that died sooner than this after its start counts as failing (its next start waits longer)
_QUICK_DEATH_S = 60.0
_LONGEST_PAUSE_S = 60.0
_TICK_S = 0.2
#: beyond the grace, what a draining process may take to close its database connections and exit
_EXIT_MARGIN_S = 15.0


@dataclass
class _Slot:
    proc: subprocess.Popen[bytes] | None = None
    started: float = 0.0
    quick_deaths: int = 0
    restart_at: float | None = None
    exits: list[int] = field(default_factory=list)


class WorkerPool:
    """``processes`` worker processes of ``threads`` workers each, on ``database_url``, each with ``work_dir``
    as its folder (scratch space, unpacked ground truths: processes may share one)."""

    def __init__(
        self,
        processes: int,
        *,
        threads: int,
        grace_s: float,
        work_dir: Path,
        database_url: str,
        env: Mapping[str, str] | None = None,
    ) -> None:
        if processes < 1 or threads < 1:
            raise ValueError("a pool needs at least one process of at least one thread")
        self.processes = processes
        self.threads = threads
        self.grace_s = grace_s
        self.work_dir = work_dir
        self.env = child_env(processes, threads, database_url, env)
        self._slots = [_Slot() for _ in range(processes)]
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._watch: threading.Thread | None = None

    def _command(self) -> list[str]:
        return child_command(self.work_dir, self.threads, self.grace_s)

    def _spawn(self, slot: _Slot) -> None:
        slot.proc = subprocess.Popen(self._command(), env=self.env, stdin=subprocess.DEVNULL)
        slot.started = time.monotonic()
        slot.restart_at = None

    def start(self) -> None:
        """Start the processes; those the command started early (:func:`~.spawn.start_early`) for a pool like
        this one are taken over instead (watched, started again and stopped as the pool's own)."""
        self.work_dir.mkdir(parents=True, exist_ok=True)
        self._stopping.clear()
        early, ago = take_early(self.processes, self.threads, self.grace_s, self.work_dir, self.env)
        adopted = len(early)
        with self._lock:
            for slot in self._slots:
                if early:
                    slot.proc, slot.started, slot.restart_at = early.pop(0), time.monotonic() - ago, None
                else:
                    self._spawn(slot)
        self._watch = threading.Thread(target=self._watch_loop, name="kitti-eval-worker-pool", daemon=True)
        self._watch.start()
        how = f" ({adopted} started with the command, {ago:.1f} s ago)" if adopted else ""
        log.info("started %d worker processes of %d thread(s): %s%s", self.processes, self.threads, self.pids, how)

    def _watch_loop(self) -> None:
        while not self._stopping.wait(_TICK_S):
            with self._lock:
                if self._stopping.is_set():
                    return
                now = time.monotonic()
                for slot in self._slots:
                    if slot.proc is not None and slot.proc.poll() is not None:
                        code = slot.proc.returncode
                        slot.exits.append(code)
                        lived = now - slot.started
                        slot.quick_deaths = slot.quick_deaths + 1 if lived < _QUICK_DEATH_S else 0
                        pause = min(_LONGEST_PAUSE_S, 2.0 ** max(0, slot.quick_deaths - 1))
                        log.warning(
                            "worker process %d exited with %s after %.0f s; another starts in %.0f s",
                            slot.proc.pid,
                            code,
                            lived,
                            pause,
                        )
                        slot.proc, slot.restart_at = None, now + pause
                    if slot.proc is None and slot.restart_at is not None and now >= slot.restart_at:
                        try:
                            self._spawn(slot)
                        except OSError:
                            log.exception("could not start a worker process")
                            slot.restart_at = now + _LONGEST_PAUSE_S

    def stop(self, grace_s: float | None = None) -> bool:
        """Drain every process (SIGTERM) and wait for it to exit: ``grace_s`` (default the pool's) for its
        running jobs, and a little more for its exit; one still there after that is killed. True when every
        process exited 0, or was ended by that SIGTERM before it had a handler for it (it was still starting)."""
        grace = self.grace_s if grace_s is None else grace_s
        self._stopping.set()
        if self._watch is not None:
            self._watch.join()
            self._watch = None
        with self._lock:
            procs = [slot.proc for slot in self._slots if slot.proc is not None]
            for slot in self._slots:
                slot.proc, slot.restart_at = None, None
        for proc in procs:
            if proc.poll() is None:
                try:
                    proc.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + grace + _EXIT_MARGIN_S
        clean = True
        for proc in procs:
            try:
                code = proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("worker process %d did not exit within %.0f s of SIGTERM: killed", proc.pid, grace)
                proc.kill()
                code = proc.wait()
            # ended by this SIGTERM before it caught it (still importing): it held no job, it stopped as asked
            clean = clean and code in (0, -signal.SIGTERM)
        return clean

    @property
    def pids(self) -> list[int]:
        with self._lock:
            return [slot.proc.pid for slot in self._slots if slot.proc is not None]

    @property
    def alive(self) -> int:
        """Worker processes running now."""
        with self._lock:
            return sum(slot.proc is not None and slot.proc.poll() is None for slot in self._slots)

    @property
    def exits(self) -> list[int]:
        """The exit codes of the processes that ended while the pool ran (those it started again after)."""
        with self._lock:
            return [code for slot in self._slots for code in slot.exits]


#: a worker process not seen on the database for this long does not count for the readiness
WORKERS_SEEN_S = 60.0


def why_no_worker(
    threads: int, jobs: JobQueue, pool: WorkerPool | None, within_s: float = WORKERS_SEEN_S
) -> str | None:
    """Why no accepted evaluation would run (None: a worker can run it): no worker thread in this process
    (``threads``), and no worker process seen on the database within ``within_s``. A worker process records
    itself there once its kernels are warm and it takes jobs: while the service's own (``pool``) are still
    starting, it is not ready."""
    if threads > 0:
        return None
    try:
        seen = jobs.workers_seen(within_s)
    except Exception as e:  # noqa: BLE001 - the ping answered: a failure here is a passing one
        log.warning("could not read the worker processes: %s", e)
        return "the database is unavailable"
    if pool is not None:
        host, own = socket.gethostname(), set(pool.pids)
        if any(w.host == host and w.pid in own for w in seen):
            return None
        if pool.alive > 0:
            return "the worker processes are starting (warming the evaluation kernels)"
    if seen:
        return None
    return (
        "no worker runs evaluations: KITTI_EVAL_JOB_THREADS is 0, KITTI_EVAL_WORKER_PROCESSES is 0, and no "
        f"'kitti-eval worker' was seen on the database in the last {within_s:g} s"
    )
