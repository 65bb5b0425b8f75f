"""``kitti-eval worker``, and each worker process it (or ``kitti-eval serve``) starts.

A worker process needs the database only: a job's inputs, the registered ground truths' files and the results
are all there. It builds the service's parts without HTTP (:class:`~kitti_eval_server.service.Service`, whose
``run_jobs`` starts its workers) on a folder of its own, ``--work-dir`` (its scratch space and its unpacked
copies of the ground truths; processes may share one), and runs ``--threads`` workers that take jobs with a
lease and beat it while they run them.

SIGTERM or SIGINT drains a process: it takes no new job, its running jobs finish (or, still running after
``--grace`` seconds, go back to the queue, their attempt not counted), and it exits 0. It drains too when the
process that started it is gone.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from ..data_folder import check_writable, private_files
from ..errors import StartupRefused
from ..jobs.pool import WorkerPool
from ..observability import Metrics, configure_logging
from ..service import Service
from ..settings import Settings, settings_error

__all__ = ["run_pool", "child_main", "default_processes"]

log = logging.getLogger("kitti_eval.server")

EXIT_OK, EXIT_INPUT, EXIT_USAGE = 0, 1, 2


def default_processes() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class _StoppedWhileStarting(BaseException):
    """SIGTERM or SIGINT while a worker process was still starting: it holds no job, so nothing is drained (a
    BaseException, as KeyboardInterrupt: no `except Exception` on the way swallows it)."""


def _stop_on_signals(starting: threading.Event | None = None) -> threading.Event:
    """An event set by SIGTERM or SIGINT (any number of them: each drains, none stops at once). While
    ``starting`` is set (a worker process opening the database and warming its kernels, which takes a minute
    where every core of a machine compiles them), a signal also raises :class:`_StoppedWhileStarting` in the main
    thread: the process has no job to drain and ends at once, instead of after its warm-up."""
    stop = threading.Event()

    def on_signal(sig: int, frame: FrameType | None) -> None:
        stop.set()
        if starting is not None and starting.is_set():
            starting.clear()  # raised once
            raise _StoppedWhileStarting

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return stop


def _say(msg: str) -> None:
    print(f"kitti-eval worker: {msg}", file=sys.stderr)  # noqa: T201


def _where(url: str) -> str:
    """The database's URL without its password."""
    scheme, _, rest = url.partition("://")
    return f"{scheme}://{rest.rpartition('@')[2]}"


def run_pool(
    *,
    data_dir: Path | None,
    database_url: str | None,
    processes: int | None,
    threads: int,
    grace_s: float | None,
    work_dir: Path | None,
) -> int:
    """``kitti-eval worker``: ``processes`` worker processes (default: the cores) until SIGTERM or SIGINT,
    which drains them; 0 when every one exited 0."""
    overrides: dict[str, Any] = {k: v for k, v in (("data_dir", data_dir), ("database_url", database_url)) if v}
    try:
        settings = Settings(**overrides)
    except ValueError as e:  # pydantic's ValidationError, or no data folder (NoDataFolder)
        _say(settings_error(e))
        return EXIT_USAGE
    if threads < 1 or (processes is not None and processes < 1) or (grace_s is not None and grace_s < 0):
        _say("error: --processes and --threads must be at least 1, --grace at least 0")
        return EXIT_USAGE
    url = settings.resolved_database_url
    if settings.database_url is None and not (settings.data_dir / "kitti-eval.db").is_file():
        _say(
            f"error: no database in {settings.data_dir}: give the service's data folder (--data-dir, "
            "KITTI_EVAL_DATA_DIR) once the service has started on it, or its --database-url"
        )
        return EXIT_INPUT
    if work_dir is not None:
        try:
            check_writable(work_dir, "--work-dir")
        except StartupRefused as e:
            _say(f"error: {e.message}")
            return EXIT_USAGE
    configure_logging(settings.log_format)
    own_dir = work_dir is None
    folder = Path(tempfile.mkdtemp(prefix="kitti-eval-worker-")) if work_dir is None else work_dir
    count = processes or default_processes()
    grace = settings.shutdown_grace_s if grace_s is None else grace_s
    stop = _stop_on_signals()
    pool = WorkerPool(count, threads=threads, grace_s=grace, work_dir=folder, database_url=url)
    try:
        pool.start()
        log.info("kitti-eval worker: %d processes x %d threads on %s, folder %s", count, threads, _where(url), folder)
        stop.wait()
        log.info("kitti-eval worker: draining (at most %g s for the running jobs)", grace)
        clean = pool.stop()
    finally:
        if own_dir:
            shutil.rmtree(folder, ignore_errors=True)
    log.info("kitti-eval worker: stopped%s", "" if clean else " (a process did not exit cleanly)")
    return EXIT_OK if clean else EXIT_INPUT


def child_main(argv: Sequence[str] | None = None) -> int:
    """One worker process (started by :class:`~kitti_eval_server.jobs.pool.WorkerPool`)."""
    p = argparse.ArgumentParser(prog=f"python -m {__name__}", description="One worker process of kitti-eval.")
    p.add_argument("--work-dir", type=Path, required=True)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--grace", type=float, default=30.0)
    p.add_argument("--parent", type=int, help="drain when this process is gone")
    args = p.parse_args(argv)
    settings = Settings(data_dir=args.work_dir, job_threads=args.threads, register_demo=False, warmup=False)
    configure_logging(settings.log_format)
    if settings.database_url is None:
        log.error("a worker process needs KITTI_EVAL_DATABASE_URL")
        return EXIT_USAGE
    starting = threading.Event()
    starting.set()
    service: Service | None = None
    try:
        stop = _stop_on_signals(starting)  # until then, SIGTERM ends the process (the pool counts that as clean)
        service = Service(settings)
        if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):  # counted with the service's, in its scrape
            service.workers.on_ended = Metrics().job_ended
        service.run_jobs(nice=settings.worker_nice)  # accepting before evaluating, once warm
        starting.clear()
        log.info("worker process %d: %d thread(s) on %s", os.getpid(), args.threads, _where(settings.database_url))
        while not stop.wait(0.5):
            if args.parent is not None and os.getppid() != args.parent:
                log.warning("worker process %d: the process that started it is gone", os.getpid())
                break
        released = service.workers.stop(args.grace)
    except StartupRefused as e:  # said in one line of the log, not a traceback
        log.error("worker process %d: %s", os.getpid(), e.message)
        return EXIT_USAGE
    except _StoppedWhileStarting:
        log.info("worker process %d: stopped while starting", os.getpid())
        return EXIT_OK
    finally:
        if service is not None:
            service.stop(grace_s=0)
    log.info("worker process %d: stopped (%d running job(s) released)", os.getpid(), released)
    return EXIT_OK


if __name__ == "__main__":
    with private_files():  # what it unpacks and writes is not readable by other users
        sys.exit(child_main())
