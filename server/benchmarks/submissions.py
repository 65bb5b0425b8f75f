"""Submissions to a benchmark: accepted (counted against the quota), checked and scored on the sealed test
set, published and withdrawn by their participants; listed, disqualified and rescored by admins."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from contextlib import AbstractContextManager
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

from kitti_eval.core.frames import Annotations
from kitti_eval.core.result import ValueKey
from kitti_eval.errors import InputError, InvalidSubmissionError
from kitti_eval.io.submission import SubmissionRules
from kitti_eval.io.upload import UploadLimits, read_upload

from ..access.audit import Audit
from ..access.policy import Caller, Policy
from ..errors import ApiError, BadRequest, Conflict, Forbidden, NotFound, NotReady, echo
from ..idempotency import Idempotency, RequestKey, fingerprint, submissions_scope
from ..jobs.queue import JobQueue, JobRecord
from ..jobs.workers import JobFailed, error_of
from ..scoring.evaluator import evaluate_document, evaluate_document_resampled, sealed_document
from ..scoring.uploads import FileIn, Upload, receive_content, stored_upload
from ..store import (
    BenchmarkStore,
    GroundTruthRecord,
    GroundTruthStore,
    JobInput,
    JobInputStore,
    KeyTaken,
    PublishRefused,
    QuotaRefused,
    ResampledKey,
    SubmissionRecord,
    new_id,
)
from .benchmark import Benchmark
from .catalog import BenchmarkCatalog
from .intervals import Intervals
from .rules import part_frames, quota_words, scores_of
from .teams import quota_team
from .views import submission_view

__all__ = ["Submissions", "Scoring", "QuotaExceeded", "InvalidSubmission"]

_LINK = re.compile(r"^https?://[^\s<>\"']{1,490}$")


class QuotaExceeded(ApiError):
    status_code = 429
    code = "quota_exceeded"

    def __init__(self, message: str, retry_after_s: int, retry_at: datetime) -> None:
        super().__init__(message, headers={"Retry-After": str(retry_after_s)})
        self.retry_at = retry_at
        self.details = {"retry_at": retry_at.isoformat()}

    @classmethod
    def of(cls, count: int, days: float, retry_at: datetime) -> QuotaExceeded:
        retry = max(1, math.ceil((retry_at - datetime.now(timezone.utc)).total_seconds()))
        return cls(
            f"the quota of {quota_words(count, days, 'accepted submission')} is used; the next one is "
            f"accepted from {retry_at.isoformat()} (in {retry} s)",
            retry,
            retry_at,
        )


class InvalidSubmission(ApiError):
    """The submission breaks the rules: ``problems`` are the sentences ``kitti-eval validate`` prints."""

    status_code = 422
    code = "invalid_submission"

    def __init__(self, problems: list[str]) -> None:
        counted = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
        super().__init__(f"the submission is not valid ({counted}): " + "; ".join(problems[:5]))
        self.problems = problems
        self.details = {"problems": problems}


class Submissions:
    """A benchmark's submissions: the participants' side and the admins' (their scoring: :class:`Scoring`)."""

    def __init__(
        self,
        catalog: BenchmarkCatalog,
        intervals: Intervals,
        benchmark_store: BenchmarkStore,
        job_input_store: JobInputStore,
        policy: Policy,
        audit: Audit,
        jobs: JobQueue,
        idempotency: Idempotency,
        *,
        draining: Callable[[], bool] = lambda: False,
        wake: Callable[[int], None] = lambda n: None,
    ) -> None:
        """``jobs``: the queue submissions' scorings and rescorings go through; ``idempotency``: the submissions'
        idempotency keys; ``draining()``: whether the process is stopping (no submission is accepted);
        ``wake(n)``: n jobs were queued (idle workers of this process look at once)."""
        self.catalog = catalog
        self.intervals = intervals
        self.benchmark_store = benchmark_store
        self.job_input_store = job_input_store
        self.policy = policy
        self.audit = audit
        self.jobs = jobs
        self.idempotency = idempotency
        self.draining = draining
        self.wake = wake

    # -- admin ----------------------------------------------------------------------------------------------
    def all_submissions(self, row: str, caller: Caller) -> list[dict[str, Any]]:
        self.policy.require_admin(caller)
        bench = self.catalog.named(row)
        return [
            submission_view(r, bench, full=False, everything=True) for r in self.benchmark_store.list_submissions(row)
        ]

    def disqualify(self, row: str, submission_id: str, *, caller: Caller) -> dict[str, Any]:
        self.policy.require_admin(caller)
        bench = self.catalog.named(row)
        record = self.benchmark_store.get_submission(submission_id)
        if record is None or record.benchmark != row:
            raise NotFound(f"no submission {echo(submission_id)} in benchmark {echo(row)}")
        self.benchmark_store.update_submission(submission_id, disqualified=True)
        self.audit.record(caller, "submission.disqualify", submission_id)
        again = self.benchmark_store.get_submission(submission_id)
        assert again is not None
        return submission_view(again, bench, full=False, everything=True)

    def rescore(self, row: str, *, caller: Caller) -> dict[str, Any]:
        """Queue one job per stored submission that evaluates it again against the ground truth as registered
        when the job runs; returns at once (``GET /v1/benchmarks/{name}`` shows an admin the jobs' progress)."""
        self.policy.require_admin(caller)
        bench = self.catalog.named(row)
        record, _ = self.catalog.ground_truth_of(bench)
        records = self.benchmark_store.list_submissions(row)
        queued = self.jobs.enqueue_many(
            "rescore", [{"submission_id": r.id, "benchmark": row} for r in records], owner=caller.name, group=row
        )
        self.wake(len(queued))
        self.audit.record(caller, "benchmark.rescore", row, detail=f"{len(queued)} queued")
        return {
            "benchmark": row,
            "queued": len(queued),
            "jobs": [j.id for j in queued],
            "rescoring": self.rescoring(row),
            "ground_truth_sha256": record.sha256,
        }

    def rescoring(self, row: str) -> dict[str, int]:
        """The rescoring jobs of the benchmark by state (every rescoring so far: queued, running, done, ...)."""
        return self.jobs.counts(group=row, kind="rescore")

    # -- participants -------------------------------------------------------------------------------------
    def submit(self, row: str, predictions: FileIn, caller: Caller, *, idempotency_key: str | None = None) -> JobRecord:
        """Count against the quota and accept (one transaction; the acceptance time is the submission's), keep
        the upload as the job's input and queue its scoring: the job, whose id is the submission's. Never waits
        for an evaluator, and reads nothing of the file: its scoring job checks it as ``kitti-eval validate``
        does on the read it scores (see :meth:`score_job`). ``idempotency_key``: the request's
        (:mod:`kitti_eval_server.idempotency`): the submission an earlier request with the same key and file made
        is answered instead of a new one, counted once."""
        if self.draining():
            raise NotReady("the service is shutting down; submit again in a moment")
        if not self.policy.has_accounts():
            raise Forbidden("benchmarks take submissions in accounts mode (KITTI_EVAL_AUTH=accounts)")
        if not self.policy.is_participant(caller):
            raise Forbidden("a participant submits with their own token (kitti-eval admin token add USER)")
        bench = self.catalog.get(row, caller)
        if not self.policy.may_take_part(
            caller, benchmark=bench.shown_name, project=bench.project, open_to_all=bench.open_to_all
        ):
            raise _not_taking_part(row)
        upload = request_key = None
        if idempotency_key is not None:  # a retry is answered first, whatever has changed since: the file's hash
            upload = receive_content(predictions.file, predictions.filename, "predictions")
            request_key = RequestKey(
                caller.name, submissions_scope(row), idempotency_key, fingerprint(file=upload.sha256)
            )
            if (earlier := self.idempotency.earlier(request_key)) is not None:
                return earlier  # accepted before (and counted then)
        baseline = self.policy.is_baseline(caller)  # under no quota, never ranked
        if baseline and bench.is_closed():
            raise Conflict(f"the benchmark {row!r} is closed: its board is frozen")
        if not baseline and not bench.is_open() and not bench.takes_late():
            raise Conflict(f"the benchmark {row!r} is not open for submissions")
        self.catalog.ground_truth_record_of(bench)  # registered, and sealed if it is to be
        if upload is None:  # read (and hashed) only once the cheap refusals are past
            upload = receive_content(predictions.file, predictions.filename, "predictions")
        self.jobs.admit(caller.name, upload.size)
        count, days = bench.quota
        now = datetime.now(timezone.utc)
        window = timedelta(days=days)
        submission_id = new_id()
        accepted = SubmissionRecord(
            id=submission_id,
            benchmark=row,
            participant=caller.name,
            created_at=now,
            status="accepted",
            pred_filename=upload.filename,
            pred_sha256=upload.sha256,
            pred_size=upload.size,
            baseline=baseline,
        )
        inputs = [JobInput("predictions", upload.filename, upload.sha256, upload.content, kept=True)]
        payload = {"submission_id": submission_id, "benchmark": row}
        action = "baseline.add" if baseline else "submission.add"

        def with_its_job(conn: Any) -> None:  # the submission, its input, its job and its audit row: one commit
            self.job_input_store.add_job_inputs_in(conn, submission_id, inputs)
            self.jobs.enqueue_in(conn, "submission", payload, owner=caller.name, group=row, job_id=submission_id)
            self.audit.record_in(conn, caller, action, f"{row} {submission_id}")

        try:
            limit = None if baseline else count
            self.benchmark_store.accept_submission(
                accepted,
                limit=limit,
                window_start=now - window,
                window=window,
                then=with_its_job,
                idempotency_key=None if request_key is None else self.idempotency.record(request_key, submission_id),
                team=None
                if baseline
                else quota_team(self.benchmark_store, bench, caller.name),  # counted as the team's
            )
        except QuotaRefused as e:
            raise QuotaExceeded.of(count, days, e.retry_at) from None
        except KeyTaken as e:  # a copy of this request was accepted first: its submission, counted once
            assert request_key is not None
            return self.idempotency.taken(request_key, e)
        job = self.jobs.get(submission_id)
        assert job is not None
        self.wake(1)
        return job

    def refused_now(self, row: str, caller: Caller, size: int, idempotency_key: str | None = None) -> ApiError | None:
        """What a participant's submission of ``size`` bytes to the phase ``row`` would be refused with now (the
        row the route addresses, :func:`.phases.addressed_row`), found before
        its file is received: a caller who reads the benchmark but does not take part in it (403), a used quota
        (429 ``quota_exceeded``) or a full queue (:meth:`JobQueue.admit <kitti_eval_server.jobs.queue.JobQueue.admit>`).
        None when it may be accepted, or for any other answer: the route decides those, and the transaction that
        accepts counts the quota again. A request sent again with an idempotency key already recorded is not
        refused here: the route answers it with its first job."""
        if not self.policy.counts_quota(caller):
            return None
        if self.idempotency.known(caller.name, submissions_scope(row), idempotency_key):
            return None
        try:
            bench = self.catalog.get(row, caller)
            if not self.policy.may_take_part(
                caller, benchmark=bench.shown_name, project=bench.project, open_to_all=bench.open_to_all
            ):
                return _not_taking_part(row)
            if not bench.is_open():
                return None
            self.jobs.admit(caller.name, size)
        except ApiError as e:
            return e if e.status_code in (429, 503) else None
        count, days = bench.quota
        window = timedelta(days=days)
        team = quota_team(self.benchmark_store, bench, caller.name)
        since = datetime.now(timezone.utc) - window
        used, oldest = self.benchmark_store.quota_used(row, caller.name, since, team)
        if used >= count and oldest is not None:
            return QuotaExceeded.of(count, days, oldest + window)
        return None

    def _own(self, row: str, submission_id: str, caller: Caller) -> SubmissionRecord:
        """One of the caller's own submissions (another's is as absent as a missing one; admins list every
        submission with ``all_submissions``)."""
        self.catalog.get(row, caller)
        record = self.benchmark_store.get_submission(submission_id)
        if record is None or record.benchmark != row or not self.policy.owns(caller, record.participant):
            raise NotFound(f"no submission of yours with id {echo(submission_id)}")
        return record

    def submission(self, row: str, submission_id: str, caller: Caller) -> dict[str, Any]:
        """One of the caller's submissions with its full result and its ``comparison`` (:meth:`comparison`: with
        their best earlier submission and the leader, on the part the board shows)."""
        record = self._own(row, submission_id, caller)
        bench = self.catalog.named(row)
        out = submission_view(record, bench, full=True)
        out["comparison"] = self.intervals.comparison(bench, record)
        return out

    def mine(self, row: str, caller: Caller) -> dict[str, Any]:
        bench = self.catalog.get(row, caller)
        records = self.benchmark_store.list_submissions(row, participant=caller.name)
        count, days = bench.quota
        since = datetime.now(timezone.utc) - timedelta(days=days)
        team = quota_team(self.benchmark_store, bench, caller.name)  # counted as accept_submission counts them
        pool = (
            [
                r
                for r in self.benchmark_store.list_submissions(row)
                if r.participant in team.members or r.team == team.name
            ]
            if team
            else records
        )
        counted = sorted(r.created_at for r in pool if r.created_at > since and r.status != "failed" and not r.baseline)
        used = len(counted)
        # none left: the next is accepted when enough of the window's oldest have left it (the 429's retry_at)
        next_at = (counted[used - count] + timedelta(days=days)).isoformat() if used >= count else None
        return {
            "items": [submission_view(r, bench, full=False) for r in reversed(records)],
            "quota": {
                "submissions": count,
                "days": days,
                "used": used,
                "left": max(0, count - used),
                "next_at": next_at,
            },
            # an admin submits baselines: counted against no quota ("left" does not apply)
            "baselines": self.policy.is_baseline(caller),
        }

    def publish(
        self,
        row: str,
        submission_id: str,
        caller: Caller,
        *,
        method: str,
        anonymous: bool = False,
        affiliation: str | None = None,
        link: str | None = None,
    ) -> dict[str, Any]:
        record = self._own(row, submission_id, caller)
        bench = _still_selecting(self.catalog, row)
        if record.status != "scored":
            raise Conflict("only a scored submission can be published")
        if record.disqualified:
            raise Conflict("the submission was disqualified")
        method = method.strip()
        if not 1 <= len(method) <= 100 or not method.isprintable():
            raise BadRequest("a method name is 1-100 printable characters")
        if affiliation is not None and (len(affiliation) > 200 or not affiliation.isprintable()):
            raise BadRequest("an affiliation is at most 200 printable characters")
        if link and not _LINK.fullmatch(link):
            raise BadRequest("a link is an http:// or https:// address of at most 500 characters")
        try:
            self.benchmark_store.publish_submission(
                record,
                cap=None if record.baseline else bench.max_published,
                method=method,
                anonymous=anonymous,
                affiliation=affiliation or None,
                link=link or None,
                published_at=datetime.now(timezone.utc),
            )
        except PublishRefused:
            raise Conflict(
                f"at most {bench.max_published} published entries per participant in {row!r}, and "
                f"{record.participant} has them: withdraw one first"
            ) from None
        action = "baseline.publish" if record.baseline else "submission.publish"
        self.audit.record(caller, action, f"{row} {submission_id}", detail=method)
        return self.submission(row, submission_id, caller)

    def withdraw(self, row: str, submission_id: str, caller: Caller) -> dict[str, Any]:
        record = self._own(row, submission_id, caller)
        _still_selecting(self.catalog, row)
        self.benchmark_store.update_submission(submission_id, published=False, published_at=None)
        action = "baseline.withdraw" if record.baseline else "submission.withdraw"
        self.audit.record(caller, action, f"{row} {submission_id}")
        return self.submission(row, submission_id, caller)


def _still_selecting(catalog: BenchmarkCatalog, row: str) -> Benchmark:
    """The benchmark, while its participants may still choose what is published: until it closes. The
    entries published at the close are the ones ranked on the private part after the reveal."""
    bench = catalog.named(row)
    if bench.is_closed():
        raise Conflict(
            f"the benchmark {row!r} is closed: the published entries were frozen at the close (they are "
            "the ones ranked on the private part)"
        )
    return bench


def _not_taking_part(row: str) -> Forbidden:
    """The refusal of a submission from a caller who may read the benchmark but not take part in it."""
    return Forbidden(
        f"the benchmark {row!r} takes part from the members of its test set's project (an account made by an "
        "invitation, in its invitation's benchmark only): reading it is not taking part in it"
    )


class Scoring:
    """A submission scored on the sealed test set by its job (a submission's, or a rescoring's), and why a
    refused one was refused."""

    def __init__(
        self,
        catalog: BenchmarkCatalog,
        intervals: Intervals,
        benchmark_store: BenchmarkStore,
        ground_truth_store: GroundTruthStore,
        job_input_store: JobInputStore,
        policy: Policy,
        jobs: JobQueue,
        limits: UploadLimits,
        scratch: Callable[[], AbstractContextManager[Path]],
    ) -> None:
        self.catalog = catalog
        self.intervals = intervals
        self.benchmark_store = benchmark_store
        self.ground_truth_store = ground_truth_store
        self.job_input_store = job_input_store
        self.policy = policy
        self.jobs = jobs
        self.limits = limits
        self.scratch = scratch

    def score_job(self, job: JobRecord) -> tuple[str, Callable[[Any], None]]:
        """Run a submission's scoring or rescoring job: the submission's id and the writes of its scores (for
        the transaction that ends the job). A submission's first scoring checks it as ``kitti-eval validate``
        does on the same read of the file: one that breaks the rules, or cannot be read, is removed (it never
        counted, as a file refused at once would not) and its job fails with the validator's sentences or the
        reader's refusal. A submission whose scoring fails, or whose last attempt failed, is marked failed (and
        no longer counts against the quota)."""
        sid = str(job.payload["submission_id"])
        submission = self.benchmark_store.get_submission(sid)
        if submission is None:
            raise Conflict(f"the submission {sid} is gone")
        try:
            bench = self.catalog.named(submission.benchmark)
            record, gt = self.catalog.ground_truth_of(bench)
            if job.kind == "submission":
                stored = self.job_input_store.job_input(job.id, "predictions")
                if stored is None:
                    raise Conflict(f"the predictions of submission {submission.id} are not kept")
                try:
                    upload = stored_upload(stored.content, submission.pred_filename, stored.sha256)
                    dt = self._checked(upload, gt, labels="validation" if bench.open_labels else "test")
                except (InputError, InvalidSubmission):  # the file is refused: it never counted
                    self.benchmark_store.delete_submission(sid)
                    raise
                if not stored.kept:  # accepted before files were kept at acceptance
                    self.ground_truth_store.add_prediction_file(submission.pred_sha256, stored.content)
            else:
                dt = self.intervals.predictions_of(job, submission, gt)  # a rescoring: the kept file
            values, resampled = self._scores(bench, record, gt, dt)
        except BaseException as e:
            body, retry = error_of(e)
            if not retry or job.attempts >= job.max_attempts:
                self.benchmark_store.update_submission(sid, status="failed", failure=str(body["message"])[:500])
            raise

        def write(conn: Any) -> None:
            self.benchmark_store.update_submission_in(conn, sid, **values)
            self.benchmark_store.replace_resampled_keys_in(conn, sid, values["scored_at"], resampled)
            if job.kind == "submission":
                self.job_input_store.delete_job_inputs_in(conn, job.id)

        return sid, write

    def refusal(self, submission_id: str, caller: Caller) -> JobFailed | None:
        """Why the caller's submission was refused by its scoring job's check of the file (the validator's
        sentences, or the reader's refusal), if that is what happened to it: the job failed and the submission
        was removed (it never counted)."""
        job = self.jobs.get(submission_id)
        if job is None or job.kind != "submission" or job.state != "failed":
            return None
        if (
            not self.policy.sees_job(caller, job.owner)
            or self.benchmark_store.get_submission(submission_id) is not None
        ):
            return None
        return JobFailed(job.error)

    def _checked(self, upload: Upload, gt: Annotations, *, labels: str = "test") -> Annotations:
        """The submission's predictions, read once and checked as :func:`validate_submission` checks them (its
        sentences, naming the upload): raises :class:`InvalidSubmission` with them when it breaks the rules;
        unreadable or unsafe input raises as every load does."""
        rules = SubmissionRules(frames=tuple(gt.frame_ids), labels=labels)  # a phase on open labels: "validation"
        with self.scratch() as scratch:
            try:
                read = read_upload(
                    upload.file, "detections", source=upload.filename, scratch=scratch, limits=self.limits, rules=rules
                )
            except InvalidSubmissionError as e:
                raise InvalidSubmission(e.lines()) from None
            return read.annotations

    def _scores(
        self, bench: Benchmark, record: GroundTruthRecord, gt: Annotations, dt: Annotations
    ) -> tuple[dict[str, Any], list[ResampledKey]]:
        """A submission's scored values: its (sealed) documents and its scores on the whole set and each part;
        and its key under the benchmark's resamples of each part a board ranks on (from the same plans)."""
        config = bench.options().config()
        columns = list(dict.fromkeys([*bench.columns, *bench.key]))
        key_columns = [ValueKey.parse(k) for k in bench.key]  # the ranking key's columns
        parts = part_frames(bench.split_seed, gt.frame_ids, bench.split_percent)
        resampled: list[ResampledKey] = []

        def scored(part: str, g: Annotations, d: Annotations) -> dict[str, Any]:
            if part not in parts:  # the whole set of a benchmark with a split: no board ranks on it
                return evaluate_document(g, d, config)
            n = len(parts[part])
            doc, values = evaluate_document_resampled(g, d, config, key_columns, self.intervals.board_weights(bench, n))
            resampled.append(self.intervals.resampled_key_record(bench, part, values, n))
            return doc

        doc = scored("all", gt, dt)
        scores: dict[str, dict[str, float | None]] = {"all": scores_of(doc, columns)}
        public_result = None
        if "all" not in parts:
            for part, frames in parts.items():
                if frames:
                    part_doc = scored(part, gt.subset(frames), dt.subset(frames))
                    scores[part] = scores_of(part_doc, columns)
                    if part == "public":
                        public_result = sealed_document(part_doc)
                else:
                    scores[part] = dict.fromkeys(columns)
        values = {
            "status": "scored",
            "result": sealed_document(doc),
            "scores": scores,
            "public_result": public_result,
            "gt_sha256": record.sha256,
            "scored_at": datetime.now(timezone.utc),
        }
        return values, resampled
