"""How a worker process is started (its command line and environment), and the worker processes ``kitti-eval
serve`` starts before it imports the web application.

A worker process takes about 2 s of CPU to import and warm its kernels, and the web process about as long to
import FastAPI, SQLAlchemy and the routes before it can start any: started by the service once it was imported,
the workers were ready 3 s after it, 5-6 s after the command on two idle cores. :func:`start_early` starts them
first, from the command (this module imports nothing heavy), so that both import at once; the service's
:class:`~kitti_eval_server.jobs.pool.WorkerPool` then takes them over (:func:`take_early`) when they are the
processes it would have started itself (same count, threads, grace, folder, database and environment), and
otherwise stops them and starts its own. A worker process started early that finds the tables missing creates
them under the same lock the service takes (``Database.create_schema``), so whichever comes first does it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from kitti_eval.core.cpus import available_cpus

__all__ = ["CHILD_MODULE", "child_command", "child_env", "start_early", "take_early", "discard_early"]

#: what a worker process runs (``python -m``)
CHILD_MODULE = "kitti_eval_server.commands.process"
#: how it is started: as ``python -m CHILD_MODULE`` would, but without the working folder first on the import path
#: (``-m`` puts it there: a service started inside another checkout would run that checkout's code in its
#: workers, not the installed one it runs itself)
_START = (
    "import runpy, sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')]; "
    f"runpy.run_module({CHILD_MODULE!r}, run_name='__main__', alter_sys=True)"
)


def child_command(work_dir: Path, threads: int, grace_s: float) -> list[str]:
    """The command line of a worker process of this process's."""
    return [
        sys.executable,
        "-c",
        _START,
        "--work-dir",
        str(work_dir),
        "--threads",
        str(threads),
        "--grace",
        repr(grace_s),
        "--parent",
        str(os.getpid()),
    ]


def child_env(processes: int, threads: int, database_url: str, env: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a worker process: the database's URL there (never on the command line, where ``ps``
    shows it), and each process matching on its share of the CPUs unless told otherwise (N processes on N cores,
    one evaluation each, with no more matching threads than cores)."""
    out = {**(os.environ if env is None else env), "KITTI_EVAL_DATABASE_URL": database_url}
    out.setdefault("KITTI_EVAL_THREADS", str(max(1, available_cpus() // (processes * threads))))
    return out


@dataclass
class _Early:
    key: tuple[object, ...]
    procs: list[subprocess.Popen[bytes]]
    started: float


_early: _Early | None = None


def _key(processes: int, threads: int, grace_s: float, work_dir: Path, env: Mapping[str, str]) -> tuple[object, ...]:
    return (processes, threads, grace_s, str(work_dir), tuple(child_command(work_dir, threads, grace_s)), dict(env))


def start_early(processes: int, threads: int, grace_s: float, work_dir: Path, database_url: str, now: int = 1) -> None:
    """Start ``now`` of a pool's ``processes`` worker processes at once, for the service this process is about to
    run to take over (it starts the others with itself). One: the readiness needs one, and on two cores a second
    importing beside the first and the web process slowed all three. Best effort: a folder that cannot be made,
    or a process that cannot be started, leaves it to the service (which says why in one sentence)."""
    global _early
    if _early is not None or processes < 1:
        return
    env = child_env(processes, threads, database_url)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        work_dir.mkdir(parents=True, exist_ok=True)
        if not os.access(work_dir, os.W_OK | os.X_OK):
            return
        for _ in range(min(now, processes)):
            procs.append(subprocess.Popen(child_command(work_dir, threads, grace_s), env=env, stdin=subprocess.DEVNULL))
    except OSError:
        _stop(procs)
        return
    _early = _Early(_key(processes, threads, grace_s, work_dir, env), procs, time.monotonic())


def take_early(
    processes: int, threads: int, grace_s: float, work_dir: Path, env: Mapping[str, str]
) -> tuple[list[subprocess.Popen[bytes]], float]:
    """The processes :func:`start_early` started (some of the pool's), and how long ago, when they are those a pool
    of these settings and environment would start (they are then the caller's); else none (any started are
    stopped)."""
    global _early
    early, _early = _early, None
    if early is None:
        return [], 0.0
    if early.key != _key(processes, threads, grace_s, work_dir, env):
        _stop(early.procs)
        return [], 0.0
    return early.procs, time.monotonic() - early.started


def discard_early() -> None:
    """Stop the processes :func:`start_early` started that no service took over (its start failed)."""
    global _early
    early, _early = _early, None
    if early is not None:
        _stop(early.procs)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            try:
                proc.send_signal(signal.SIGTERM)  # drains: nothing runs yet, so it exits at once
            except ProcessLookupError:
                pass
    for proc in procs:
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
