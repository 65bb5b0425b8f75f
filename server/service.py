"""The service's parts, assembled once, and its life: start, stop, readiness. No HTTP in here.

:class:`Service` builds each part with only what it uses: the store, the audit log, the policy, the accounts,
the ground truths (their files, and the catalog callers see), the evaluations, and the runner that runs
blocking work on worker threads. The routes call the parts; no part reaches into another through here.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, TypeVar

import sqlalchemy.engine
import sqlalchemy.exc

from kitti_eval._jit import warm_up
from kitti_eval.demo import demo_paths
from kitti_eval.io.upload import UploadLimits

from .accounts import Accounts
from .audit import Audit
from .auth import FailureLimiter
from .benchmarks import Benchmarks
from .catalog import GroundTruthCatalog
from .errors import StartupRefused
from .evaluations import Evaluations, sealed_document
from .ground_truths import GroundTruthCache, GroundTruths
from .idempotency import Idempotency
from .job_admin import JobAdmin
from .jobs import JobQueue, JobRecord, QueueLimits
from .observability import AdmissionState
from .policy import AuthMode, Policy
from .runner import Runner, release_memory
from .scratch import ScratchSpace
from .settings import Settings
from .store import IdempotencyRecord, JobInput, Store
from .uploads import FileIn, receive_upload
from .worker_pool import WorkerPool
from .workers import Workers, await_outcome

__all__ = ["Service", "FileIn", "DEMO_NAME", "sealed_document", "release_memory"]

log = logging.getLogger("kitti_eval.server")
T = TypeVar("T")

DEMO_NAME = "demo"


class Service:
    """The parts of one service process (``create_app`` and ``kitti-eval admin`` make one)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.data_dir = settings.data_dir.resolve()
        self.store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
        self.audit = Audit(self.store)
        self.admin_token = ""
        self.policy = Policy(
            AuthMode(settings.auth),
            admin_token=lambda: self.admin_token,
            metrics_token=lambda: settings.metrics_token.get_secret_value() if settings.metrics_token else None,
            test_sets=self._test_sets,
        )
        self.accounts = Accounts(self.store, self.audit, lambda: self.admin_token)
        self.limiter = FailureLimiter(settings.auth_max_failures, settings.auth_failure_window_s)
        self.limits = UploadLimits(
            max_bytes=settings.max_unpacked_bytes,
            max_members=settings.max_archive_members,
            members_setting="KITTI_EVAL_MAX_ARCHIVE_MEMBERS",
        )
        self.scratch_space = ScratchSpace(self.data_dir)
        #: admission counts, shared with the middlewares (and read by the metrics)
        self.admission = AdmissionState()
        self.runner = Runner(settings.max_concurrent_evals, self.admission, self.scratch_space)
        self.ground_truths = GroundTruths(
            self.store,
            self.data_dir / "ground-truths",
            GroundTruthCache(settings.gt_cache_entries, settings.gt_cache_bytes),
            self.limits,
            self.runner.scratch,
        )
        #: the ground truths as callers see them (the policy's rules and the audit over ``ground_truths``)
        self.catalog = GroundTruthCatalog(
            self.ground_truths,
            self.store,
            self.policy,
            self.audit,
            self.runner.scratch,
            check_project=self.accounts.check_project,
        )
        self.predictions = GroundTruthCache(
            settings.pred_cache_entries, settings.gt_cache_bytes, what="predictions", setting="KITTI_EVAL_GT_CACHE_MB"
        )
        #: every accepted evaluation is a job; workers of this process run them (and any ``kitti-eval worker``)
        self.jobs = JobQueue(
            self.store,
            lease_s=settings.job_lease_s,
            max_attempts=settings.job_max_attempts,
            limits=QueueLimits(
                jobs=settings.max_queued_jobs,
                per_owner=settings.max_queued_per_caller,
                input_bytes=int(settings.max_queued_input_mb * (1 << 20)),
                retry_after_s=settings.retry_after_s,
            ),
        )
        #: the requests' idempotency keys (evaluations and submissions)
        self.idempotency = Idempotency(self.store, self.jobs, settings.idempotency_key_hours)
        self.evaluations = Evaluations(
            self.store,
            self.catalog,
            self.predictions,
            self.policy,
            self.audit,
            self.limits,
            self.runner.scratch,
            self.jobs,
            keep_predictions=settings.keep_predictions,
            idempotency=self.idempotency,
        )
        self.warm = threading.Event()
        self.warmup_error: str | None = None
        #: set on SIGTERM: not ready, no new evaluations, the admitted ones finish (see server.shutdown)
        self.draining = threading.Event()
        #: evaluations, benchmark submissions' scorings and rescorings, and the resampled keys of each scoring
        #: (the board's intervals), each kind a job of its own
        self.workers = Workers(
            self.jobs,
            {
                "evaluation": self._run_evaluation,
                "submission": lambda job: self.benchmarks.score_job(job),
                "rescore": lambda job: self.benchmarks.score_job(job),
                "intervals": lambda job: self.benchmarks.intervals_job(job),
            },
            threads=settings.job_threads,
            admission=self.admission,
        )
        #: the jobs as admins see them (list, cancel, run again)
        self.job_admin = JobAdmin(
            self.jobs,
            self.policy,
            self.audit,
            run_again={"evaluation": self.evaluations.why_not_again},
            wake=self.workers.wake,
        )
        #: worker processes of the service's own (KITTI_EVAL_WORKER_PROCESSES), started and stopped with it
        self.pool: WorkerPool | None = None
        self.benchmarks = Benchmarks(
            self.store,
            self.ground_truths,
            self.policy,
            self.audit,
            self.runner.scratch,
            self.limits,
            draining=self.draining.is_set,
            jobs=self.jobs,
            wake=lambda n: self.workers.wake(n),
            idempotency=self.idempotency,
        )

    # -- lifecycle ---------------------------------------------------------------------------------------
    def start(self) -> None:
        """Create folders and tables, register the demo, start the warm-up and the workers (called from the
        lifespan)."""
        self.runner.open()
        self.scratch_space.open()  # and removes what processes killed meanwhile left
        log.info("data folder %s", self.data_dir)
        try:
            self.store.create_schema()
        except sqlalchemy.exc.OperationalError as e:  # not reached, or refused: said in one line, not a traceback
            url = self.settings.resolved_database_url
            where = self.settings.database_name
            reason = (str(e.orig or e).strip() or type(e).__name__).splitlines()[0]
            hint = ""
            if url.partition("://")[2].count("@") > 1:
                hint = (
                    " (a password holding @, /, # or : must be percent-encoded in KITTI_EVAL_DATABASE_URL, or left "
                    "out of it and given as PGPASSWORD)"
                )
            raise StartupRefused(f"cannot use the database {where}: {reason}{hint}") from None
        self._check_open_mode()
        self.admin_token = self._admin_token()
        if self.settings.register_demo:
            self._register_demo()
        if self.settings.warmup:
            threading.Thread(target=self._warm_up, name="kitti-eval-warmup", daemon=True).start()
        else:
            self.warm.set()
        self.workers.start()
        if self.settings.worker_processes:
            self.pool = WorkerPool(
                self.settings.worker_processes,
                threads=1,
                grace_s=self.settings.shutdown_grace_s,
                work_dir=self.data_dir,
                database_url=self.settings.resolved_database_url,
            )
            self.pool.start()
        log.info(
            "auth %s, database %s, %d worker process%s, %d job thread%s",
            AuthMode(self.settings.auth).value,
            self.settings.database_name,
            self.settings.worker_processes,
            "es" * (self.settings.worker_processes != 1),
            self.settings.job_threads,
            "s" * (self.settings.job_threads != 1),
        )

    def run_jobs(self) -> None:
        """Start as a worker process (``kitti-eval worker``): the scratch space, the tables, the kernels, then the
        workers; no HTTP, no admin token, no demo. :meth:`stop` ends it."""
        self.scratch_space.open()
        self.store.create_schema()
        warm_up(everything=False)
        self.warm.set()
        self.workers.start()

    def _check_open_mode(self) -> None:
        """Open mode serves every project's work to anyone: not on a database whose accounts say otherwise,
        unless ``allow_open_with_accounts``."""
        if self.policy.has_accounts() or self.settings.allow_open_with_accounts:
            return
        users, tokens = self.accounts.holders()
        if users or tokens:
            raise StartupRefused(
                f"the database holds accounts ({users} user{'s' * (users != 1)}, {tokens} token"
                f"{'s' * (tokens != 1)} not revoked) but KITTI_EVAL_AUTH is open, which would serve every project's "
                "evaluations and ground truths to anyone who reaches the service: start with KITTI_EVAL_AUTH=accounts, "
                "or set KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS=true to serve it open anyway"
            )

    def _run_evaluation(self, job: JobRecord) -> tuple[str, Callable[[Any], None]]:
        record, write = self.evaluations.execute(job.id, job.payload)
        return record.id, write

    def enqueue_evaluation(
        self, caller: Any
    ) -> Callable[[str, dict[str, Any], list[JobInput], IdempotencyRecord | None], JobRecord]:
        """How an accepted evaluation of ``caller``'s is queued (and the idle workers of this process woken)."""

        def enqueue(
            job_id: str, payload: dict[str, Any], inputs: list[JobInput], key: IdempotencyRecord | None
        ) -> JobRecord:
            job = self.jobs.enqueue("evaluation", payload, owner=caller.name, job_id=job_id, inputs=inputs, key=key)
            self.workers.wake()
            return job

        return enqueue

    def stop(self, grace_s: float | None = None) -> None:
        """Stop the workers (the running jobs have ``grace_s``, default ``KITTI_EVAL_SHUTDOWN_GRACE_S``, to finish;
        those still running then go back to the queue) and the worker processes, then close the database."""
        grace = self.settings.shutdown_grace_s if grace_s is None else grace_s
        if self.pool is not None:
            self.pool.stop(grace)
            self.pool = None
        self.workers.stop(grace)
        self.store.dispose()
        self.scratch_space.close()

    def _admin_token(self) -> str:
        if self.settings.admin_token is not None:
            return self.settings.admin_token.get_secret_value()
        path = self.data_dir / "admin-token"
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            return path.read_text().strip()
        token = secrets.token_urlsafe(32)
        with os.fdopen(fd, "w") as fh:
            fh.write(token + "\n")
        log.warning("generated an admin token in %s (set KITTI_EVAL_ADMIN_TOKEN to choose one)", path)
        return token

    def _register_demo(self) -> None:
        if self.store.get_ground_truth(DEMO_NAME) is not None:
            return
        gt_path, _ = demo_paths()
        with open(gt_path, "rb") as fh, self.scratch() as scratch:
            upload = receive_upload(fh, gt_path.name, gt_path.name)
            try:
                self.ground_truths.register(DEMO_NAME, upload, scratch)
            except Exception as e:  # noqa: BLE001 - another worker may have registered it meanwhile
                if self.store.get_ground_truth(DEMO_NAME) is None:
                    raise
                log.debug("demo ground truth registered concurrently: %s", e)
        log.info("registered the bundled demo ground truth as %r", DEMO_NAME)

    def _warm_up(self) -> None:
        """Compile (or load) every kernel before requests need them: the same ones the CLI and library use."""
        started = time.perf_counter()
        try:
            warm_up(everything=True)
        except Exception as e:  # noqa: BLE001 - reported through /readyz and the log
            self.warmup_error = f"{type(e).__name__}: {e}"
            log.exception("warm-up failed")
            return
        self.warm.set()
        log.info("kernels warm in %.1f s", time.perf_counter() - started)

    def readiness(self) -> str | None:
        """None when ready, else why not."""
        if self.draining.is_set():
            return "shutting down"
        if self.warmup_error:
            return f"warm-up failed: {self.warmup_error}"
        if not self.warm.is_set():
            return "warming up the evaluation kernels"
        try:
            self.store.ping()
        except Exception as e:  # noqa: BLE001 - any failure means not ready
            log.warning("database ping failed: %s", e)
            return "the database is unavailable"
        return self._no_worker()

    #: a worker process not seen on the database for this long does not count for the readiness
    WORKERS_SEEN_S = 60.0

    def _no_worker(self) -> str | None:
        """Why no accepted evaluation would run (None: a worker can run it): no worker thread in this process,
        and no worker process seen on the database within a minute. A worker process records itself there once
        its kernels are warm and it takes jobs: while this service's own are still starting, it is not ready."""
        if self.workers.threads > 0:
            return None
        try:
            seen = self.jobs.workers_seen(self.WORKERS_SEEN_S)
        except Exception as e:  # noqa: BLE001 - the ping answered: a failure here is a passing one
            log.warning("could not read the worker processes: %s", e)
            return "the database is unavailable"
        if self.pool is not None:
            host, own = socket.gethostname(), set(self.pool.pids)
            if any(w.host == host and w.pid in own for w in seen):
                return None
            if self.pool.alive > 0:
                return "the worker processes are starting (warming the evaluation kernels)"
        if seen:
            return None
        return (
            "no worker runs evaluations: KITTI_EVAL_JOB_THREADS is 0, KITTI_EVAL_WORKER_PROCESSES is 0, and no "
            f"'kitti-eval worker' was seen on the database in the last {self.WORKERS_SEEN_S:g} s"
        )

    # -- the runner ----------------------------------------------------------------------------------------
    async def outcome(self, job_id: str, wait_s: float | None = None) -> JobRecord:
        """A just-accepted job once it has ended, or as it is after ``wait_s`` (default ``KITTI_EVAL_WAIT_S``);
        a failed one raised as the error its input is answered with (:func:`await_outcome`). Past
        ``KITTI_EVAL_MAX_QUEUED_EVALS`` requests waiting at once, it does not wait (the job is answered as it is)."""
        timeout = self.settings.wait_s if wait_s is None else wait_s
        if self.admission.waiting >= self.settings.max_queued_evals:
            timeout = 0.0
        self.admission.waiting += 1
        try:
            return await await_outcome(self.jobs, job_id, timeout)
        finally:
            self.admission.waiting -= 1

    async def run(self, func: Callable[..., T], *args: Any) -> T:
        """Blocking work on the runner's threads (:meth:`Runner.run <kitti_eval_server.runner.Runner.run>`)."""
        return await self.runner.run(func, *args)

    async def accept(self, func: Callable[[], T]) -> T:
        """Accepting an upload as a job (an evaluation or a submission) on the runner's threads: the file is
        stored, not read, so nothing is left for :func:`release_memory` to hand back."""
        return await self.runner.run(func, release=False)

    def scratch(self) -> AbstractContextManager[Path]:
        return self.runner.scratch()

    def _test_sets(self) -> dict[str, list[str]]:
        """Ground truth name -> the benchmarks whose test set it is (for the policy)."""
        found: dict[str, list[str]] = {}
        for bench in self.store.list_benchmarks():
            found.setdefault(bench.gt_name, []).append(bench.name)
        return found
