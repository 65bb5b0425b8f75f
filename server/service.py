"""The service behind the routes: evaluations, ground truths, readiness. No HTTP in here.

Blocking work (reading uploads, unpickling, unpacking, evaluating, writing the database) runs on worker
threads through :meth:`Service.run`, at most ``max_concurrent_evals`` at a time; the event loop only
waits. An evaluation is committed to the database before :meth:`Service.evaluate` returns.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import io
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any, TypeVar, cast

import anyio
import anyio.to_thread

from kitti_eval._jit import warm_up
from kitti_eval.analysis.diagnostics import frame_stats, frames_document
from kitti_eval.analysis.inspection import inspect_frame, model_name, unique_names
from kitti_eval.core.frames import Annotations, normalize_frame_id
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.io.synth import demo_paths

from .accounts import OPEN, Accounts, Caller
from .auth import FailureLimiter
from .errors import MAX_ECHO_CHARS, BadRequest, Conflict, NotFound, Sealed, StartupRefused, clip, echo
from .evaluator import EvalOptions, evaluate_document, summarize
from .ground_truths import GroundTruthCache, GroundTruths
from .observability import AdmissionState
from .scratch import ScratchSpace
from .settings import Settings
from .store import EvaluationRecord, GroundTruthRecord, Store, new_id
from .uploads import Limits, load_upload, receive_upload

__all__ = ["Service", "FileIn", "DEMO_NAME", "sealed_document"]

log = logging.getLogger("kitti_eval.server")
T = TypeVar("T")


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return cast(Callable[[int], int], libc.malloc_trim)
    except (OSError, AttributeError):  # not glibc
        return None


def release_memory() -> None:
    """Hand the heap's free pages back to the system. glibc keeps what a request freed (a refused upload of
    a million small objects left the service 100 MB above idle); ``malloc_trim`` returns it. A no-op where
    the C library is not glibc."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


DEMO_NAME = "demo"
#: most evaluations one frame view compares
MAX_INSPECTED = 8


def sealed_document(doc: dict[str, Any]) -> dict[str, Any]:
    """An evaluation document against a sealed ground truth: the aggregates only. The frames without
    predictions (ids of the sealed set) and the warnings (which may name its frames) are withheld."""
    out = dict(doc)
    withheld = len(doc.get("frames_without_predictions") or ())
    out["frames_without_predictions"] = []
    notes = [f"the ground truth is sealed: per-frame details are withheld ({len(doc.get('warnings') or ())} warnings"]
    notes[0] += f", {withheld} frames without predictions)" if withheld else ")"
    out["warnings"] = notes
    return out


@dataclass(frozen=True)
class FileIn:
    """An uploaded file as the routes hand it over: its spooled bytes and the client's name."""

    file: IO[bytes]
    filename: str | None


class Service:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.data_dir = settings.data_dir.resolve()
        self.store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
        self.limits = Limits(max_unpacked_bytes=settings.max_unpacked_bytes, max_members=settings.max_archive_members)
        self.scratch_space = ScratchSpace(self.data_dir)
        self.ground_truths = GroundTruths(
            self.store,
            self.data_dir / "ground-truths",
            GroundTruthCache(settings.gt_cache_entries, settings.gt_cache_bytes),
            self.limits,
            self.scratch,
        )
        self.predictions = GroundTruthCache(
            settings.pred_cache_entries, settings.gt_cache_bytes, what="predictions", setting="KITTI_EVAL_GT_CACHE_MB"
        )
        self.admin_token = ""
        self.accounts = Accounts(self.store, lambda: self.admin_token)
        self.limiter = FailureLimiter(settings.auth_max_failures, settings.auth_failure_window_s)
        self.warm = threading.Event()
        self.warmup_error: str | None = None
        self._limiter: anyio.CapacityLimiter | None = None
        #: admission counts, shared with the middlewares (and read by the metrics)
        self.admission = AdmissionState()
        self._running_lock = threading.Lock()
        #: set on SIGTERM: not ready, no new evaluations, the admitted ones finish (see server.shutdown)
        self.draining = threading.Event()

    # -- lifecycle ---------------------------------------------------------------------------------------
    def start(self) -> None:
        """Create folders and tables, register the demo, start the warm-up (called from the lifespan)."""
        self._limiter = anyio.CapacityLimiter(self.settings.max_concurrent_evals)
        self.scratch_space.open()  # and removes what processes killed meanwhile left
        log.info("data folder %s", self.data_dir)
        self.store.create_schema()
        self._check_open_mode()
        self.admin_token = self._admin_token()
        if self.settings.register_demo:
            self._register_demo()
        if self.settings.warmup:
            threading.Thread(target=self._warm_up, name="kitti-eval-warmup", daemon=True).start()
        else:
            self.warm.set()

    def _check_open_mode(self) -> None:
        """Open mode serves every project's work to anyone: not on a database whose accounts say otherwise,
        unless ``allow_open_with_accounts``."""
        if self.settings.auth != "open" or self.settings.allow_open_with_accounts:
            return
        users, tokens = self.accounts.holders()
        if users or tokens:
            raise StartupRefused(
                f"the database holds accounts ({users} user{'s' * (users != 1)}, {tokens} token"
                f"{'s' * (tokens != 1)} not revoked) but KITTI_EVAL_AUTH is open, which would serve every project's "
                "evaluations and ground truths to anyone who reaches the service: start with KITTI_EVAL_AUTH=accounts, "
                "or set KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS=true to serve it open anyway"
            )

    def stop(self) -> None:
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
        return None

    # -- threads -----------------------------------------------------------------------------------------
    async def run(self, func: Callable[..., T], *args: Any) -> T:
        """Run blocking work on a worker thread, at most ``max_concurrent_evals`` at once; afterwards the
        memory it freed goes back to the system (:func:`release_memory`)."""

        def job() -> T:
            with self._running_lock:
                self.admission.running += 1
            try:
                return func(*args)
            finally:
                with self._running_lock:
                    self.admission.running -= 1
                release_memory()

        return await anyio.to_thread.run_sync(job, limiter=self._limiter)

    def scratch(self) -> AbstractContextManager[Path]:
        """A new scratch folder of this process's (:class:`~kitti_eval_server.scratch.ScratchSpace`), removed on
        the way out."""
        return self.scratch_space.folder()

    # -- evaluations ------------------------------------------------------------------------------------
    def evaluate(
        self,
        predictions: FileIn,
        gt_name: str | None,
        gt_file: FileIn | None,
        options: EvalOptions,
        labels: Mapping[str, str],
        caller: Caller = OPEN,
        project: str | None = None,
    ) -> EvaluationRecord:
        """Load, evaluate, store (committed) and return the record. In accounts mode the evaluation belongs to
        ``project`` (default: the ground truth's, else the caller's only one), which must be the caller's."""
        started = time.perf_counter()
        if (gt_name is None) == (gt_file is None):
            raise BadRequest(
                "give the ground truth either by name (form field 'gt', e.g. 'demo'; GET "
                "/v1/ground-truths lists them) or as a file (form field 'gt_file'), not both"
            )
        config = options.config()  # bad options fail before any upload is read
        gt_record = self.ground_truth(gt_name, caller) if gt_name is not None else None
        project = self._project_for(caller, project, gt_record)
        with self.scratch() as scratch:
            if gt_record is not None:
                gt = self.ground_truths.load(gt_record)
                gt_sha256 = gt_record.sha256
            else:
                assert gt_file is not None
                gt_upload = receive_upload(gt_file.file, gt_file.filename, "gt_file")
                gt = load_upload(gt_upload, "ground_truth", scratch / "gt", self.limits).annotations
                gt_sha256 = gt_upload.sha256
            pred = receive_upload(predictions.file, predictions.filename, "predictions")
            keep = self.settings.keep_predictions and gt_record is not None
            loaded = load_upload(
                pred, "detections", scratch / "pred", self.limits, keep_lidar=keep, known_frames=gt.frame_index()
            )
            doc = evaluate_document(
                gt,
                loaded.annotations,
                config,
                curves=options.curves,
                errors=options.errors,
                gt_frames_shown=gt_record is None or not gt_record.sealed,
            )
            if gt_record is not None and gt_record.sealed:
                doc = sealed_document(doc)
            if keep:
                pred.file.seek(0)
                self.store.add_prediction_file(pred.sha256, pred.file.read())
                self.predictions.put(pred.sha256, loaded.annotations)
        record = EvaluationRecord(
            id=new_id(),
            created_at=datetime.now(timezone.utc),
            gt_name=gt_name,
            gt_sha256=gt_sha256,
            pred_filename=pred.filename,
            pred_sha256=pred.sha256,
            pred_format=str(loaded.format),
            pred_size=pred.size,
            protocol=doc["protocol"],
            duration_ms=round((time.perf_counter() - started) * 1000, 3),
            summary=summarize(doc),
            result=doc,
            labels=dict(labels),
            options=options.to_dict(),
            project=project,
        )
        self.store.add_evaluation(record)
        log.info(
            "evaluation %s: %s frames against %s in %.0f ms",
            record.id,
            doc["frames"],
            gt_name or "an uploaded ground truth",
            record.duration_ms,
        )
        return record

    def _project_for(self, caller: Caller, wanted: str | None, gt_record: GroundTruthRecord | None) -> str | None:
        """The project a new evaluation belongs to (None in open mode)."""
        if self.settings.auth != "accounts":
            return None
        if gt_record is not None and gt_record.project is not None:
            if wanted and wanted != gt_record.project:
                raise BadRequest(
                    f"the ground truth {gt_record.name!r} belongs to project {gt_record.project!r}, "
                    f"not {echo(wanted)}; evaluations against it belong to its project"
                )
            return gt_record.project
        if wanted:
            if not caller.sees_project(wanted) or not self.store.project_exists(wanted):
                raise NotFound(f"no project of yours named {echo(wanted)}")
            return wanted
        if caller.projects is not None and len(caller.projects) == 1:
            return next(iter(caller.projects))
        mine = ", ".join(sorted(caller.projects)) if caller.projects is not None else "any project"
        raise BadRequest(f"name the project of the evaluation (form field 'project'): {mine or 'you have none'}")

    def evaluation(self, evaluation_id: str, caller: Caller = OPEN) -> EvaluationRecord:
        """The evaluation, if the caller may see it; another project's is as absent as a missing one, and takes
        as long to refuse (one small read of its project, before anything else is loaded)."""
        if caller.projects is not None:
            exists, project = self.store.evaluation_project(evaluation_id)
            if not exists or not caller.sees_project(project):
                raise NotFound(f"no evaluation with id {echo(evaluation_id)}")
        record = self.store.get_evaluation(evaluation_id)
        if record is None or not caller.sees_evaluation(record):
            raise NotFound(f"no evaluation with id {echo(evaluation_id)}")
        return record

    def ground_truth(self, name: str, caller: Caller = OPEN) -> GroundTruthRecord:
        """The registered ground truth, if the caller may use it; another project's is as absent as a missing
        one."""
        record = self.ground_truths.record(name)
        if not caller.sees_ground_truth(record):
            raise NotFound(f"no ground truth named {echo(name)}; GET /v1/ground-truths lists them")
        return record

    def list_evaluations(
        self,
        caller: Caller = OPEN,
        *,
        gt_name: str | None = None,
        labels: Mapping[str, str] | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> list[EvaluationRecord]:
        return self.store.list_evaluations(
            gt_name=gt_name, labels=labels, limit=limit, offset=offset, projects=caller.projects
        )

    def list_ground_truths(self, caller: Caller = OPEN) -> list[GroundTruthRecord]:
        return self.store.list_ground_truths(projects=caller.projects)

    # -- frames ------------------------------------------------------------------------------------------
    def _kept_inputs(self, record: EvaluationRecord) -> tuple[Annotations, Annotations, EvalConfig]:
        """The ground truth, predictions and options of a stored evaluation, for looking at its frames."""
        if record.gt_name is None:
            raise Conflict(
                f"evaluation {record.id} used a ground truth uploaded with the request, which is not "
                "kept; frames can be looked at for evaluations against a registered ground truth"
            )
        if record.options is None:
            raise Conflict(
                f"evaluation {record.id} was stored without its options; upload the predictions again "
                "to look at its frames"
            )
        gt_record = self.store.get_ground_truth(record.gt_name)
        if gt_record is not None and gt_record.sealed:
            raise Sealed(
                f"the ground truth {record.gt_name!r} of evaluation {record.id} is sealed: only aggregate "
                "results (AP, curves, error totals) are available, no per-frame view"
            )
        if gt_record is None or gt_record.sha256 != record.gt_sha256:
            raise Conflict(
                f"the ground truth {record.gt_name!r} of evaluation {record.id} has been deleted or "
                "replaced since; its frames cannot be looked at"
            )
        # a frame view reads no distance bins: an evaluation stored with more than the service now allows is
        # still looked at
        config = EvalOptions.from_dict({**record.options, "ranges": None}).config()
        gt = self.ground_truths.load(gt_record)

        def load_kept() -> Annotations:
            content = self.store.prediction_content(record.pred_sha256)
            if content is None:
                raise Conflict(
                    f"the predictions of evaluation {record.id} were not kept "
                    "(KITTI_EVAL_KEEP_PREDICTIONS was off); upload them again to look at frames"
                )
            with self.scratch() as scratch:
                upload = receive_upload(io.BytesIO(content), record.pred_filename, record.pred_filename)
                return load_upload(upload, "detections", scratch, self.limits, keep_lidar=True).annotations

        return gt, self.predictions.get_or_load(record.pred_sha256, load_kept), config

    def frames(
        self,
        evaluation_id: str,
        *,
        cls: str = "Car",
        metric: str = "3d",
        difficulty: str = "moderate",
        oset: str = "strict",
        worst: int | None = 20,
        score_threshold: float = 0.0,
        caller: Caller = OPEN,
    ) -> dict[str, Any]:
        """TP/FP/FN per frame of a stored evaluation (the ``worst`` n first, or all), as
        :func:`kitti_eval.analysis.diagnostics.frames_document`."""
        if worst is not None and worst < 1:
            raise BadRequest("worst must be at least 1")
        record = self.evaluation(evaluation_id, caller)
        gt, dt, config = self._kept_inputs(record)
        stats = frame_stats(
            gt, dt, config, cls=cls, metric=metric, difficulty=difficulty, oset=oset, score_threshold=score_threshold
        )
        doc = frames_document(stats, worst=worst)
        doc["evaluation"] = record.id
        return doc

    def inspect(
        self,
        evaluation_ids: Sequence[str],
        frame_id: str,
        *,
        cls: str = "Car",
        metric: str = "3d",
        difficulty: str = "moderate",
        oset: str = "strict",
        score_threshold: float | None = None,
        caller: Caller = OPEN,
    ) -> dict[str, Any]:
        """One frame's boxes for several stored evaluations against the same ground truth, labelled by the
        matching (:func:`kitti_eval.analysis.inspection.inspect_frame`, under the first evaluation's options)."""
        ids = list(dict.fromkeys(evaluation_ids))
        if not ids:
            raise BadRequest("name at least one evaluation")
        if len(ids) > MAX_INSPECTED:
            raise BadRequest(f"at most {MAX_INSPECTED} evaluations in one frame view")
        records = [self.evaluation(i, caller) for i in ids]
        if len({r.gt_sha256 for r in records}) > 1:
            raise Conflict(
                "these evaluations used different ground truths; a frame view compares evaluations against the same one"
            )
        try:
            fid = normalize_frame_id(frame_id)
        except (TypeError, ValueError) as e:
            raise BadRequest(f"bad frame id {echo(frame_id)}: {e}") from None
        inputs = [self._kept_inputs(r) for r in records]
        gt, _, config = inputs[0]
        if fid not in gt.frame_index():
            raise NotFound(f"no frame {clip(fid, MAX_ECHO_CHARS)} in the ground truth {records[0].gt_name!r}")
        names = unique_names([r.labels.get("model") or model_name(r.pred_filename) for r in records])
        report = inspect_frame(
            gt,
            [(n, dt) for n, (_, dt, _) in zip(names, inputs)],
            fid,
            config,
            cls=cls,
            metric=metric,
            difficulty=difficulty,
            oset=oset,
            score_threshold=score_threshold,
        )
        for name, record in zip(names, records):
            report["models"][name]["evaluation"] = record.id
            report["models"][name]["source"] = record.pred_filename
        if any(c.protocol.name != config.protocol.name for _, _, c in inputs[1:]):
            report["notes"] = [f"all are matched under the first evaluation's protocol ({config.protocol.name})"]
        return report

    # -- ground truths ----------------------------------------------------------------------------------
    def register_ground_truth(
        self, name: str, file: FileIn, *, project: str | None = None, sealed: bool = False
    ) -> GroundTruthRecord:
        """Register a named ground truth; ``project``: only its members see and use it (None: everyone);
        ``sealed``: no per-frame view of it ever leaves the service."""
        if project is not None:
            self.accounts.check_project(project)
        with self.scratch() as scratch:
            upload = receive_upload(file.file, file.filename, "file")
            return self.ground_truths.register(name, upload, scratch, project=project, sealed=sealed)
