"""Evaluations: upload predictions against a ground truth and keep the result; list, read, and look at the
frames of the evaluations a caller may see (the policy decides which). No HTTP in here.

An evaluation is committed to the database before :meth:`Evaluations.evaluate` returns. Blocking work runs on
the runner's threads (:class:`~kitti_eval_server.jobs.runner.Runner`); the routes hand it over.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from kitti_eval.analysis.diagnostics import frames_document
from kitti_eval.analysis.frame_question import ASKED, FrameQuestion
from kitti_eval.analysis.inspection import inspect_frame, model_name, unique_names
from kitti_eval.core.evaluation import Facts
from kitti_eval.core.frames import Annotations, normalize_frame_id
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.io.reading import LoadOptions
from kitti_eval.io.upload import UploadLimits, read_upload

from ..access.audit import Audit
from ..access.policy import Caller, Policy, default_project
from ..errors import MAX_ECHO_CHARS, BadRequest, Conflict, NotFound, clip, echo
from ..ground_truths.cache import GroundTruthCache
from ..ground_truths.catalog import GroundTruthCatalog
from ..idempotency import EVALUATIONS, GATE_EVALUATIONS, Idempotency, RequestKey, fingerprint
from ..jobs.queue import JobQueue
from ..scoring.evaluator import (
    EvalOptions,
    check_worst,
    evaluated_plan,
    frame_listing,
    sealed_document,
    summarize,
)
from ..scoring.uploads import FileIn, receive_content, stored_upload
from ..store import (
    AccountStore,
    EvaluationRecord,
    EvaluationStore,
    GroundTruthRecord,
    GroundTruthStore,
    IdempotencyRecord,
    JobInput,
    JobInputStore,
    JobRecord,
    KeyTaken,
    new_id,
)
from .frame_rows import facts_of, frame_detections, frame_rows, readable, stats_from_rows

__all__ = ["Evaluations", "EvaluationFrames", "FileIn", "MAX_INSPECTED"]

log = logging.getLogger("kitti_eval.server")

#: most evaluations one frame view compares
MAX_INSPECTED = 8


def _input(name: str, upload: FileIn, *, kept: bool = False) -> JobInput:
    """An uploaded file as a job's input, as it is (read once, hashed); ``kept``: kept for good from the start."""
    received = receive_content(upload.file, upload.filename, name)
    return JobInput(name, received.filename, received.sha256, received.content, kept=kept)


class Evaluations:
    """Evaluations, as callers see them."""

    def __init__(
        self,
        evaluation_store: EvaluationStore,
        ground_truth_store: GroundTruthStore,
        job_input_store: JobInputStore,
        account_store: AccountStore,
        gt_catalog: GroundTruthCatalog,
        predictions: GroundTruthCache,
        policy: Policy,
        audit: Audit,
        limits: UploadLimits,
        scratch: Callable[[], AbstractContextManager[Path]],
        jobs: JobQueue,
        *,
        keep_predictions: bool,
        idempotency: Idempotency | None = None,
    ) -> None:
        self.evaluation_store = evaluation_store
        self.ground_truth_store = ground_truth_store
        self.job_input_store = job_input_store
        self.account_store = account_store  # whether a project exists
        self.gt_catalog = gt_catalog
        self.predictions = predictions
        self.policy = policy
        self.audit = audit
        self.limits = limits
        self.scratch = scratch
        self.jobs = jobs
        self.keep_predictions = keep_predictions
        self.idempotency = idempotency or Idempotency(jobs.idempotency_store, jobs)

    def accept(
        self,
        predictions: FileIn,
        gt_name: str | None,
        gt_file: FileIn | None,
        options: EvalOptions,
        labels: Mapping[str, str],
        caller: Caller,
        project: str | None = None,
        *,
        enqueue: Callable[[str, dict[str, Any], list[JobInput], IdempotencyRecord | None], JobRecord],
        idempotency_key: str | None = None,
        kept: bool = True,
    ) -> JobRecord:
        """Check what can be checked before the evaluation (the options, the ground truth and the caller's right
        to it, the project), and enqueue the job with the uploaded files as its inputs (``enqueue(job_id,
        payload, inputs)``, one transaction; a worker runs it with :meth:`execute`). In accounts mode the
        evaluation belongs to ``project`` (default: the ground truth's, else the caller's only one), which must
        be the caller's. A benchmark's test set is refused to all but admins (whose evaluations against it are
        audited). ``idempotency_key``: the request's (:mod:`kitti_eval_server.idempotency`): the job an earlier
        request with the same key made is answered instead of a new one. ``kept``: False for an evaluation a gate
        asks for without keeping it (:mod:`.gate_evaluations`): in no project, its predictions not kept, its
        result not stored as an evaluation (``payload["kept"]``)."""
        if (gt_name is None) == (gt_file is None):
            raise BadRequest(
                "give the ground truth either by name (form field 'gt', e.g. 'demo'; GET "
                "/v1/ground-truths lists them) or as a file (form field 'gt_file'), not both"
            )
        options.config()  # bad options fail before any upload is read
        gt_record = self.gt_catalog.get(gt_name, caller) if gt_name is not None else None
        if gt_record is not None:
            self.policy.may_evaluate_against(caller, gt_record)
        if kept:
            project = self._project_for(caller, project, gt_record)
        else:  # seen by its owner alone, while they see its ground truth
            project = gt_record.project if gt_record is not None else None
        job_id = new_id()
        # predictions evaluated against a registered ground truth are kept (frames are looked at later): written
        # once, as the job's input; those against an uploaded one go with the job
        keep_file = kept and self.keep_predictions and gt_record is not None
        inputs = [_input("predictions", predictions, kept=keep_file)]
        if gt_file is not None:
            inputs.append(_input("gt_file", gt_file))
        payload: dict[str, Any] = {
            "evaluation_id": job_id,
            "gt_name": gt_name,
            "gt_sha256": gt_record.sha256 if gt_record is not None else None,
            "options": options.to_dict(),
            "labels": dict(labels),
            "project": project,
        }
        if not kept:
            payload["kept"] = False
        request_key = None
        if idempotency_key is not None:
            request_key = RequestKey(
                caller.name,
                EVALUATIONS if kept else GATE_EVALUATIONS,
                idempotency_key,
                fingerprint(
                    files=[(i.name, i.sha256) for i in inputs],
                    gt=gt_name,
                    options=payload["options"],
                    labels=payload["labels"],
                    project=project,
                ),
            )
            if (earlier := self.idempotency.earlier(request_key)) is not None:
                return earlier
        self.jobs.admit(self.policy.job_owner(caller), sum(len(i.content) for i in inputs))
        try:  # the job, its inputs and its idempotency key: one transaction
            job = enqueue(
                job_id, payload, inputs, None if request_key is None else self.idempotency.record(request_key, job_id)
            )
        except KeyTaken as e:  # a copy of this request was recorded first (nothing of this one is kept)
            assert request_key is not None
            return self.idempotency.taken(request_key, e)
        if gt_record is not None and self.policy.is_test_set(gt_record):
            self.audit.record(caller, "evaluation.test_set", f"{job_id} on {gt_record.name}")
        return job

    def execute(self, job_id: str, payload: Mapping[str, Any]) -> tuple[EvaluationRecord, Callable[[Any], None]]:
        """Run an accepted evaluation: load its inputs, evaluate. Returns the record and the writes that store
        it (the record, the predictions when they are kept, the inputs' removal), for the transaction that
        ends the job. Raises the library's or the service's errors for an input that cannot be evaluated. An
        evaluation accepted not to be kept (``payload["kept"]`` False) keeps nothing: its writes only remove
        the inputs (its result is the gate's to store, :mod:`.gate_evaluations`)."""
        started = time.perf_counter()
        options = EvalOptions.from_dict(payload["options"])
        config = options.config()
        gt_name: str | None = payload["gt_name"]
        pred_input = self.job_input_store.job_input(job_id, "predictions")
        if pred_input is None:
            raise Conflict(f"the inputs of evaluation {job_id} are gone (it has run already)")
        with self.scratch() as scratch:
            gt_record = None
            if gt_name is not None:
                gt_record = self.ground_truth_store.get_ground_truth(gt_name)
                if gt_record is None or gt_record.sha256 != payload["gt_sha256"]:
                    raise Conflict(
                        f"the ground truth {gt_name!r} was deleted or replaced after the evaluation was accepted; "
                        "upload the predictions again"
                    )
                gt = self.gt_catalog.files.load(gt_record)
                gt_sha256 = gt_record.sha256
            else:
                gt_input = self.job_input_store.job_input(job_id, "gt_file")
                assert gt_input is not None
                gt_upload = stored_upload(gt_input.content, gt_input.filename, gt_input.sha256)
                gt = read_upload(
                    gt_upload.file,
                    "ground_truth",
                    source=gt_upload.filename,
                    scratch=scratch / "gt",
                    limits=self.limits,
                ).annotations
                gt_sha256 = gt_upload.sha256
            pred = stored_upload(pred_input.content, pred_input.filename, pred_input.sha256)
            kept = bool(payload.get("kept", True))
            keep = kept and self.keep_predictions and gt_record is not None
            loaded = read_upload(
                pred.file,
                "detections",
                source=pred.filename,
                scratch=scratch / "pred",
                limits=self.limits,
                options=LoadOptions(keep_lidar=keep, known_frames=gt.frame_index()),
            )
            doc, plan = evaluated_plan(
                gt,
                loaded.annotations,
                config,
                curves=options.curves,
                errors=options.errors,
                gt_frames_shown=gt_record is None or not gt_record.sealed,
            )
            if gt_record is not None and gt_record.sealed:
                doc = sealed_document(doc)
            # what the frame listings and views read, for an evaluation whose frames can be looked at
            rows = list(frame_rows(plan)) if keep and gt_record is not None and not gt_record.sealed else []
            del plan
        if keep:
            if not pred_input.kept:  # accepted before files were kept at acceptance, or while they were not kept
                self.ground_truth_store.add_prediction_file(pred.sha256, pred_input.content)
            self.predictions.put(pred.sha256, loaded.annotations)
        record = EvaluationRecord(
            id=payload["evaluation_id"],
            created_at=datetime.now(timezone.utc),
            gt_name=gt_name,
            gt_sha256=gt_sha256,
            pred_filename=pred.filename,
            pred_sha256=pred.sha256,
            pred_format=loaded.kind,
            pred_size=pred.size,
            protocol=doc["protocol"],
            duration_ms=round((time.perf_counter() - started) * 1000, 3),
            summary=summarize(doc),
            result=doc,
            labels=dict(payload["labels"]),
            options=options.to_dict(),
            project=payload["project"],
        )
        log.info(
            "evaluation %s: %s frames against %s in %.0f ms",
            record.id,
            doc["frames"],
            gt_name or "an uploaded ground truth",
            record.duration_ms,
        )

        def write(conn: Any) -> None:
            if not kept:
                self.job_input_store.delete_job_inputs_in(conn, job_id)
                return
            self.evaluation_store.add_evaluation_in(conn, record)
            self.evaluation_store.add_frames_in(conn, record.id, rows)
            self.job_input_store.delete_job_inputs_in(conn, job_id)

        return record, write

    def why_not_again(self, job: JobRecord) -> str | None:
        """Why an ended evaluation job cannot run again (None: it can): once done, its evaluation is stored (a
        second run would store it twice); and its inputs must still be kept (they go when it is done)."""
        if job.state == "done":
            return f"job {job.id} is done and its evaluation is stored: upload the predictions again for a new one"
        if self.job_input_store.job_input(job.id, "predictions") is None:
            return f"the inputs of job {job.id} are gone: upload the predictions again"
        return None

    def _project_for(self, caller: Caller, wanted: str | None, gt_record: GroundTruthRecord | None) -> str | None:
        """The project a new evaluation belongs to (None in open mode): its ground truth's, else the one the
        policy gives the caller (:func:`~kitti_eval_server.access.policy.default_project`)."""
        if gt_record is not None and gt_record.project is not None and self.policy.has_accounts():
            if wanted and wanted != gt_record.project:
                raise BadRequest(
                    f"the ground truth {gt_record.name!r} belongs to project {gt_record.project!r}, "
                    f"not {echo(wanted)}; evaluations against it belong to its project"
                )
            return gt_record.project
        return default_project(self.policy, caller, self.account_store.project_exists, wanted)

    def job_of(self, evaluation_id: str, caller: Caller) -> tuple[JobRecord, int | None] | None:
        """The job of an accepted evaluation not stored yet (queued, running, failed or cancelled) and its place
        in the queue, if the caller may see it (its owner's, and the admins')."""
        job = self.jobs.get(evaluation_id)
        if job is None or job.kind != "evaluation":
            return None
        project = job.payload.get("project")
        if not self.policy.sees_job(caller, job.owner, project=str(project) if project else None):
            return None
        return job, self.jobs.position(job.id)

    def get(self, evaluation_id: str, caller: Caller) -> EvaluationRecord:
        """The evaluation, if the caller may see it; another project's is as absent as a missing one, and takes
        as long to refuse (one small read of its project, before anything else is loaded)."""
        if self.policy.project_filter(caller) is not None:
            exists, project = self.evaluation_store.evaluation_project(evaluation_id)
            if not exists or not self.policy.sees_project(caller, project):
                raise NotFound(f"no evaluation with id {echo(evaluation_id)}")
        record = self.evaluation_store.get_evaluation(evaluation_id)
        self.policy.require_evaluation(caller, record, evaluation_id)
        assert record is not None
        return record

    def listed(
        self,
        caller: Caller,
        *,
        gt_name: str | None = None,
        labels: Mapping[str, str] | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> list[EvaluationRecord]:
        if not self.policy.is_signed_in(caller):
            return []
        return self.evaluation_store.list_evaluations(
            gt_name=gt_name,
            labels=labels,
            limit=limit,
            offset=offset,
            projects=self.policy.project_filter(caller),
            hidden_gt_names=self.policy.hidden_ground_truths(caller),
        )


class EvaluationFrames:
    """The frames of stored evaluations, as callers see them: each frame's counts and labelled boxes, from the
    kept ground truth and predictions."""

    def __init__(
        self,
        evaluations: Evaluations,
        ground_truth_store: GroundTruthStore,
        gt_catalog: GroundTruthCatalog,
        predictions: GroundTruthCache,
        policy: Policy,
        limits: UploadLimits,
        scratch: Callable[[], AbstractContextManager[Path]],
    ) -> None:
        """``evaluations``: the stored evaluations as callers see them; ``predictions``: the bounded cache of the
        kept predictions loaded."""
        self.evaluations = evaluations
        self.ground_truth_store = ground_truth_store
        self.gt_catalog = gt_catalog
        self.predictions = predictions
        self.policy = policy
        self.limits = limits
        self.scratch = scratch

    def _checked(self, record: EvaluationRecord) -> tuple[GroundTruthRecord, EvalConfig]:
        """The ground truth and options of a stored evaluation whose frames may be looked at."""
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
        gt_record = self.ground_truth_store.get_ground_truth(record.gt_name)
        if gt_record is not None:
            self.policy.require_frames(gt_record, record.id)
        if gt_record is None or gt_record.sha256 != record.gt_sha256:
            raise Conflict(
                f"the ground truth {record.gt_name!r} of evaluation {record.id} has been deleted or "
                "replaced since; its frames cannot be looked at"
            )
        # a frame view reads no distance bins: an evaluation stored with more than the service now allows is
        # still looked at
        return gt_record, EvalOptions.from_dict({**record.options, "ranges": None}).config()

    def _kept_inputs(self, record: EvaluationRecord) -> tuple[Annotations, Annotations, EvalConfig]:
        """The ground truth, predictions and options of a stored evaluation, for looking at its frames: the
        predictions read whole (bounded by ``KITTI_EVAL_FRAMES_MAX_BOXES``), for an evaluation stored without
        its frames (:mod:`.frame_rows`) or a question they cannot answer."""
        gt_record, config = self._checked(record)
        gt = self.gt_catalog.files.load(gt_record)

        def load_kept() -> Annotations:
            content = self.ground_truth_store.prediction_content(record.pred_sha256)
            if content is None:
                raise Conflict(
                    f"the predictions of evaluation {record.id} were not kept "
                    "(KITTI_EVAL_KEEP_PREDICTIONS was off); upload them again to look at frames"
                )
            with self.scratch() as scratch:
                upload = stored_upload(content, record.pred_filename, record.pred_sha256)
                options = LoadOptions(keep_lidar=True)
                return read_upload(
                    upload.file,
                    "detections",
                    source=upload.filename,
                    scratch=scratch,
                    limits=self.limits,
                    options=options,
                ).annotations

        return gt, self.predictions.get_or_load(record.pred_sha256, load_kept), config

    def frames(
        self,
        evaluation_id: str,
        question: FrameQuestion = ASKED,
        *,
        worst: int | None = 20,
        caller: Caller,
    ) -> dict[str, Any]:
        """TP/FP/FN per frame of a stored evaluation (the ``worst`` n first, or all), as
        :func:`~kitti_eval_server.scoring.evaluator.frame_listing` answers it: from the frames its job stored, else
        from its kept inputs."""
        record = self.evaluations.get(evaluation_id, caller)
        _, config = self._checked(record)
        check_worst(worst)
        stats = None
        if self.evaluations.evaluation_store.has_frames(record.id):
            stats = stats_from_rows(self.evaluations.evaluation_store.frame_events(record.id), config, question)
        if stats is not None:
            doc = frames_document(stats, worst=worst)
        else:
            gt, dt, config = self._kept_inputs(record)
            doc = frame_listing(gt, dt, config, question, worst=worst)
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
        caller: Caller,
    ) -> dict[str, Any]:
        """One frame's boxes for several stored evaluations against the same ground truth, labelled by the
        matching (:func:`kitti_eval.analysis.inspection.inspect_frame`, under the first evaluation's options)."""
        ids = list(dict.fromkeys(evaluation_ids))
        if not ids:
            raise BadRequest("name at least one evaluation")
        if len(ids) > MAX_INSPECTED:
            raise BadRequest(f"at most {MAX_INSPECTED} evaluations in one frame view")
        records = [self.evaluations.get(i, caller) for i in ids]
        if len({r.gt_sha256 for r in records}) > 1:
            raise Conflict(
                "these evaluations used different ground truths; a frame view compares evaluations against the same one"
            )
        try:
            fid = normalize_frame_id(frame_id)
        except (TypeError, ValueError) as e:
            raise BadRequest(f"bad frame id {echo(frame_id)}: {e}") from None
        names = unique_names([r.labels.get("model") or model_name(r.pred_filename) for r in records])
        notes: list[str] = []
        stored = self._stored_frame(records, fid, cls)
        if stored is not None:
            gt, config, models, facts = stored
        else:
            inputs = [self._kept_inputs(r) for r in records]
            gt, _, config = inputs[0]
            if fid not in gt.frame_index():
                raise NotFound(f"no frame {clip(fid, MAX_ECHO_CHARS)} in the ground truth {records[0].gt_name!r}")
            models, facts = [dt for _, dt, _ in inputs], None
            if any(c.protocol.name != config.protocol.name for _, _, c in inputs[1:]):
                notes = [f"all are matched under the first evaluation's protocol ({config.protocol.name})"]
        report = inspect_frame(
            gt,
            list(zip(names, models)),
            fid,
            config,
            cls=cls,
            metric=metric,
            difficulty=difficulty,
            oset=oset,
            score_threshold=score_threshold,
            facts=facts,
        )
        for name, record in zip(names, records):
            report["models"][name]["evaluation"] = record.id
            report["models"][name]["source"] = record.pred_filename
        if notes:
            report["notes"] = notes
        return report

    def _stored_frame(
        self, records: Sequence[EvaluationRecord], fid: str, cls: str
    ) -> tuple[Annotations, EvalConfig, list[Annotations], list[Facts]] | None:
        """The ground truth, the first evaluation's options, and each evaluation's detections of frame ``fid``
        with what its whole set decided for the matching, from the rows the evaluations stored (one frame each,
        never the predictions whole). None when they cannot answer: an evaluation stored without its frames,
        one that did not evaluate ``cls`` or the first one's classes, or evaluations under different
        protocols (the first one's is used, with facts of its own)."""
        checked = [self._checked(r) for r in records]
        config = checked[0][1]
        for _, c in checked:
            if (
                c.protocol.name != config.protocol.name
                or cls not in c.classes
                or not set(config.classes) <= set(c.classes)
            ):
                return None
        rows = []
        for record, (_, c) in zip(records, checked):
            row = self.evaluations.evaluation_store.frame(record.id, fid)
            if row is None or not readable(c, row[1]):
                if self.evaluations.evaluation_store.has_frames(record.id):
                    break  # stored, but not this frame: the ground truth has none such (refused below)
                return None
            rows.append((record, c, row))
        gt = self.gt_catalog.files.load(checked[0][0])
        if fid not in gt.frame_index():
            raise NotFound(f"no frame {clip(fid, MAX_ECHO_CHARS)} in the ground truth {records[0].gt_name!r}")
        if len(rows) < len(records):
            return None
        models = [frame_detections(row[0], fid, source=record.pred_filename) for record, _, row in rows]
        return gt, config, models, [facts_of(c, row[1]) for _, c, row in rows]
