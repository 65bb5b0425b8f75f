"""The service's parts, assembled once, and its life: start, stop, readiness. No HTTP in here.

:class:`Service` builds each part with only what it uses: the store, the audit log, the policy, the accounts,
the ground truths (their files, ``ground_truths``, and what callers see of them, ``gt_catalog``), the evaluations,
and the runner that runs blocking work on worker threads. The routes call the parts; no part reaches into another
through here.
"""

from __future__ import annotations

import dataclasses
import logging
import os
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
from kitti_eval.errors import ConfigError
from kitti_eval.io.limits import BoxLimits, box_limits, input_limits, overlap_budget
from kitti_eval.io.upload import UploadLimits

from .access.accounts import Accounts, admin_token
from .access.audit import Audit
from .access.auth import FailureLimiter
from .access.invitations import Invitations
from .access.policy import Policy
from .benchmarks import Benchmarks
from .benchmarks.phases import last_phase
from .data_folder import check_writable
from .errors import NotFound, StartupRefused, echo
from .evaluations.evaluations import EvaluationFrames, Evaluations
from .evaluations.gate_evaluations import GateEvaluations
from .ground_truths.cache import GroundTruthCache, GroundTruths
from .ground_truths.catalog import GroundTruthCatalog
from .idempotency import Idempotency
from .jobs.admin import JobAdmin
from .jobs.pool import WorkerPool, why_no_worker
from .jobs.queue import JobQueue, JobRecord, QueueLimits
from .jobs.runner import Runner, release_memory
from .jobs.scratch import ScratchSpace
from .jobs.workers import Workers, await_outcome
from .observability import AdmissionState
from .scoring.evaluator import sealed_document
from .scoring.uploads import FileIn
from .settings import AuthMode, Settings
from .store import IdempotencyRecord, JobInput, Store, UnusableDatabase

__all__ = ["Service", "FileIn", "DEMO_NAME", "sealed_document", "release_memory"]

log = logging.getLogger("kitti_eval.server")
T = TypeVar("T")

DEMO_NAME = "demo"


def _frames_view_limits(most: int) -> BoxLimits:
    """The box limits of kept predictions read to look at their frames: the limits on work, and at most ``most``
    boxes in all (``KITTI_EVAL_FRAMES_MAX_BOXES``), since they are read whole by the process that answers. The
    limits on input and work the loaders read from the environment are checked here: a bad one refuses the start."""
    try:
        input_limits()
        overlap_budget()
        bounds = box_limits()
    except ConfigError as e:
        raise StartupRefused(f"{e} (a limit on input or work)") from None
    if bounds.per_input is not None and bounds.per_input <= most:
        return bounds
    return dataclasses.replace(bounds, per_input=most, per_input_setting="KITTI_EVAL_FRAMES_MAX_BOXES")


def _check_open_mode(policy: Policy, accounts: Accounts, settings: Settings) -> None:
    """Open mode serves every project's work to anyone: not on a database whose accounts say otherwise,
    unless ``allow_open_with_accounts``."""
    if policy.has_accounts() or settings.allow_open_with_accounts:
        return
    users, tokens = accounts.holders()
    if users or tokens:
        raise StartupRefused(
            f"the database holds accounts ({users} user{'s' * (users != 1)}, {tokens} token"
            f"{'s' * (tokens != 1)} not revoked) but KITTI_EVAL_AUTH is open, which would serve every project's "
            "evaluations and ground truths to anyone who reaches the service: start with KITTI_EVAL_AUTH=accounts, "
            "or set KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS=true to serve it open anyway"
        )


def _log_start(settings: Settings) -> None:
    log.info(
        "auth %s, database %s, %d worker process%s, %d job thread%s",
        AuthMode(settings.auth).value,
        settings.database_name,
        settings.worker_processes,
        "es" * (settings.worker_processes != 1),
        settings.job_threads,
        "s" * (settings.job_threads != 1),
    )


def _invited_to(benchmarks: Benchmarks) -> Callable[[str], tuple[str, str | None, bool]]:
    """What an invitation reads of the benchmark it admits to: its name, its test set's project, whether it is
    open to all (404 for none, and for a phase's row: an invitation is to a benchmark)."""

    def benchmark(name: str) -> tuple[str, str | None, bool]:
        bench = benchmarks.catalog.named(name)
        if bench.is_later_phase:
            raise NotFound(f"no benchmark named {echo(name)}")
        return bench.shown_name, bench.project, bench.open_to_all

    return benchmark


def _test_sets(store: Store) -> dict[str, list[str]]:
    """Ground truth name -> the benchmarks whose test set it is (for the policy)."""
    found: dict[str, list[str]] = {}
    for bench in store.benchmark_store.list_benchmarks():
        found.setdefault(bench.gt_name, []).append(bench.name)
    return found


def _has_closed(benchmarks: Benchmarks) -> Callable[[str], bool]:
    """Whether a benchmark's last phase has closed (closed or revealed, as the phases' lifecycle says): its
    invitations admit no one any more (404 for no such benchmark)."""

    def closed(name: str) -> bool:
        return last_phase(benchmarks.catalog, benchmarks.catalog.named(name)).is_closed()

    return closed


class Service:
    """The parts of one service process (``create_app`` and ``kitti-eval admin`` make one)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.data_dir = settings.data_dir.resolve()
        self.store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
        self.audit = Audit(self.store.account_store)
        self.admin_token = ""
        self.policy = Policy(
            AuthMode(settings.auth),
            admin_token=lambda: self.admin_token,
            metrics_token=lambda: settings.metrics_token.get_secret_value() if settings.metrics_token else None,
            test_sets=lambda: _test_sets(self.store),
        )
        self.accounts = Accounts(self.store.account_store, self.audit, lambda: self.admin_token)
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
            self.store.ground_truth_store,
            self.store.benchmark_store,
            self.data_dir / "ground-truths",
            GroundTruthCache(settings.gt_cache_entries, settings.gt_cache_bytes),
            self.limits,
            self.runner.scratch,
        )
        #: the ground truths as callers see them (the policy's rules and the audit over ``ground_truths``)
        self.gt_catalog = GroundTruthCatalog(
            self.ground_truths,
            self.store.ground_truth_store,
            self.policy,
            self.audit,
            self.runner.scratch,
            check_project=self.accounts.check_project,
        )
        self.predictions = GroundTruthCache(
            settings.pred_cache_entries, settings.gt_cache_bytes, what="predictions", setting="KITTI_EVAL_GT_CACHE_MB"
        )
        #: every accepted evaluation is a job; workers of this process run them (and any ``kitti-eval worker``)
        self.jobs = JobQueue.of(
            self.store,
            lease_s=settings.job_lease_s,
            max_attempts=settings.job_max_attempts,
            time_limit_s=settings.job_timeout_s,
            limits=QueueLimits(
                jobs=settings.max_queued_jobs,
                per_owner=settings.max_queued_per_caller,
                input_bytes=int(settings.max_queued_input_mb * (1 << 20)),
                retry_after_s=settings.retry_after_s,
            ),
        )
        #: the requests' idempotency keys (evaluations and submissions)
        self.idempotency = Idempotency(self.store.idempotency_store, self.jobs, settings.idempotency_key_hours)
        self.evaluations = Evaluations(
            self.store.evaluation_store,
            self.store.ground_truth_store,
            self.store.job_input_store,
            self.store.account_store,
            self.gt_catalog,
            self.predictions,
            self.policy,
            self.audit,
            self.limits,
            self.runner.scratch,
            self.jobs,
            keep_predictions=settings.keep_predictions,
            idempotency=self.idempotency,
        )
        #: the evaluations gates ask for without keeping them (a read-only token's gate)
        self.gate_evaluations = GateEvaluations(self.evaluations, self.store.gate_result_store)
        #: the frames of stored evaluations (counts, labelled boxes)
        self.evaluation_frames = EvaluationFrames(
            self.evaluations,
            self.store.ground_truth_store,
            self.gt_catalog,
            self.predictions,
            self.policy,
            self.limits,  # with the frame views' box limits once they are read from the environment (start)
            self.runner.scratch,
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
                "gate": self.gate_evaluations.execute,
                "submission": lambda job: self.benchmarks.scoring.score_job(job),
                "rescore": lambda job: self.benchmarks.scoring.score_job(job),
                "intervals": lambda job: self.benchmarks.intervals.intervals_job(job),
            },
            threads=settings.job_threads,
            admission=self.admission,
            timeout_s=settings.job_timeout_s,
        )
        #: the jobs as admins see them (list, cancel, run again)
        self.job_admin = JobAdmin(
            self.jobs,
            self.policy,
            self.audit,
            run_again={"evaluation": self.evaluations.why_not_again, "gate": self.gate_evaluations.why_not_again},
            wake=self.workers.wake,
        )
        #: worker processes of the service's own (KITTI_EVAL_WORKER_PROCESSES), started and stopped with it
        self.pool: WorkerPool | None = None
        self.benchmarks = Benchmarks.assemble(
            self.store,
            self.ground_truths,
            self.policy,
            self.audit,
            self.runner.scratch,
            self.limits,
            jobs=self.jobs,
            idempotency=self.idempotency,
            draining=self.draining.is_set,
            wake=lambda n: self.workers.wake(n),
        )
        self.invitations = Invitations(
            self.store.invitation_store,
            self.accounts,
            self.policy,
            self.audit,
            _invited_to(self.benchmarks),
            _has_closed(self.benchmarks),
        )
        self.join_limiter = FailureLimiter(settings.join_max_attempts, settings.join_window_s, what="attempts to join")

    # -- lifecycle ---------------------------------------------------------------------------------------
    def start(self) -> None:
        """Create folders and tables, register the demo, start the warm-up and the workers (called from the
        lifespan)."""
        check_writable(self.data_dir)  # one sentence naming the folder and the fix, not a PermissionError
        view = _frames_view_limits(self.settings.frames_max_boxes)  # a bad limit on input or work refuses the start
        self.evaluation_frames.limits = dataclasses.replace(self.limits, boxes=view)
        self.runner.open()
        self.scratch_space.open()  # and removes what processes killed meanwhile left
        log.info("data folder %s", self.data_dir)
        self._open_database(upgrade=self.settings.db_upgrade)
        _check_open_mode(self.policy, self.accounts, self.settings)
        if self.settings.worker_processes:  # first: they import and warm up while this process goes on
            self.pool = WorkerPool(
                self.settings.worker_processes,
                threads=1,
                grace_s=self.settings.shutdown_grace_s,
                work_dir=self.data_dir,
                database_url=self.settings.resolved_database_url,
            )
            self.pool.start()
        if self.settings.warmup:
            threading.Thread(target=self._warm_up, name="kitti-eval-warmup", daemon=True).start()
        else:
            self.warm.set()
        self.admin_token = admin_token(self.settings, self.data_dir)
        if self.settings.register_demo:
            with self.scratch() as scratch:
                self.ground_truths.register_bundled(DEMO_NAME, demo_paths()[0], scratch)
        self.workers.start()
        _log_start(self.settings)

    def _open_database(self, upgrade: bool = False) -> None:
        """The tables: created in an empty database, upgraded in an older one when ``upgrade``; a database the
        service cannot use (not reached, refused, not UTF8, older and not to be upgraded, newer) is
        :class:`StartupRefused` with one sentence, not a traceback."""
        try:
            self.store.create_schema(upgrade=upgrade, where=self.settings.database_name)
        except UnusableDatabase as e:
            raise StartupRefused(e.message) from None
        except sqlalchemy.exc.OperationalError as e:  # not reached, or refused: said in one line, not a traceback
            reason = (str(e.orig or e).strip() or type(e).__name__).splitlines()[0]
            hint = ""
            if self.settings.resolved_database_url.partition("://")[2].count("@") > 1:
                hint = (
                    " (a password holding @, /, # or : must be percent-encoded in KITTI_EVAL_DATABASE_URL, or left "
                    "out of it and given as PGPASSWORD)"
                )
            raise StartupRefused(f"cannot use the database {self.settings.database_name}: {reason}{hint}") from None

    def run_jobs(self, nice: int = 0) -> None:
        """Start as a worker process (``kitti-eval worker``): the scratch space, the tables, the kernels, then the
        workers; no HTTP, no admin token, no demo. :meth:`stop` ends it. ``nice``: how much the process lowers its
        scheduling priority once its kernels are warm, before it takes a job (so that accepting comes before
        evaluating on a machine shared with a web process, but a start, which accepts nothing yet, is not
        slowed: warming at the lower priority took a loaded machine's workers 14 s instead of 3)."""
        check_writable(self.data_dir, "--work-dir")
        self.scratch_space.open()
        self._open_database()
        warm_up(everything=False)
        if nice:
            os.nice(nice)
        self.warm.set()
        self.workers.start()

    def _run_evaluation(self, job: JobRecord) -> tuple[str, Callable[[Any], None]]:
        record, write = self.evaluations.execute(job.id, job.payload)
        return record.id, write

    def enqueue_evaluation(
        self, caller: Any, kind: str = "evaluation"
    ) -> Callable[[str, dict[str, Any], list[JobInput], IdempotencyRecord | None], JobRecord]:
        """How an accepted evaluation of ``caller``'s is queued (and the idle workers of this process woken);
        ``kind``: ``gate`` for one a gate asks for without keeping it."""

        def enqueue(
            job_id: str, payload: dict[str, Any], inputs: list[JobInput], idempotency_key: IdempotencyRecord | None
        ) -> JobRecord:
            job = self.jobs.enqueue(
                kind, payload, owner=caller.name, job_id=job_id, inputs=inputs, idempotency_key=idempotency_key
            )
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

    def _no_worker(self) -> str | None:
        """Why no accepted evaluation would run (None: a worker can run it): :func:`why_no_worker`."""
        return why_no_worker(self.workers.threads, self.jobs, self.pool)

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
        """Blocking work on the runner's threads (:meth:`Runner.run <kitti_eval_server.jobs.runner.Runner.run>`)."""
        return await self.runner.run(func, *args)

    async def accept(self, func: Callable[[], T]) -> T:
        """Accepting an upload as a job (an evaluation or a submission) on the runner's threads: the file is
        stored, not read, so nothing is left for :func:`release_memory` to hand back."""
        return await self.runner.run(func, release=False)

    def scratch(self) -> AbstractContextManager[Path]:
        return self.runner.scratch()
