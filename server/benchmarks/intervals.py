"""How sure the board is: each entry's ranking key under the paired bootstrap over frames, kept per submission.

Each scoring (of a submission, or a rescoring) also computes the submission's ranking key under
:data:`RESAMPLES` resamples of the frames of each part a board may rank on (the whole test set without a
split; the public and the private part with one), every submission of a benchmark under the same draws:
:func:`kitti_eval.analysis.bootstrap.frame_weights` over the part's frames, in the test set's order, with the
benchmark's seed (:func:`board_seed`, from its name). It reuses the scoring's own plan of each evaluation
(:func:`kitti_eval.analysis.ranking.evaluate_resampled`): only the key's matching is swept again, 1000 times.
A resampled key is the mean of the key's columns under the resample, each the AP
:func:`kitti_eval.analysis.bootstrap.resampled_ap` gives (the one ``kitti-eval compare --bootstrap`` gives).
The values are kept in the database with the scores, in the same transaction (``submission_resamples``: one
float64 a resample, per submission and part), so the board ranks from them as it answers
(:func:`kitti_eval.analysis.ranking.standings`): each entry's 95% interval, its rank range and whether it
differs from the next, all recomputed from the kept values when an entry comes or goes, which is cheap. A
participant's submission is compared with their previous best and with the leader the same way, on the part
the board shows (the public part until the reveal).

A submission scored before the values were kept has none: the board (or its participant's view) that finds
one missing queues a job (kind ``intervals``) that computes them; its id is a function of the submission's
scoring, so it is queued once, and the entry is ``null`` (``pending``) until it is done.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from kitti_eval.analysis.bootstrap import frame_weights, interval95
from kitti_eval.analysis.ranking import LEVEL, METHOD, resampled_key
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.frames import Annotations
from kitti_eval.core.result import ValueKey
from kitti_eval.io.reading import LoadOptions
from kitti_eval.io.upload import UploadLimits, read_upload

from ..errors import Conflict
from ..jobs.queue import JobQueue, JobRecord
from ..scoring.uploads import stored_upload
from ..store import BenchmarkStore, GroundTruthStore, JobInputStore, ResampledKey, SubmissionRecord
from .benchmark import Benchmark
from .catalog import BenchmarkCatalog
from .rules import key_value, part_frames

__all__ = [
    "Intervals",
    "RESAMPLES",
    "METHOD",
    "board_seed",
    "intervals_job_id",
    "ranked_submissions",
    "part_name",
    "rounded",
]

#: resamples of every board
RESAMPLES = 1000
#: a board's part as the JSON names it
_PART_NAMES = {"all": "whole", "public": "public", "private": "private"}


def part_name(phase: str) -> str:
    """``whole``, ``public`` or ``private``: the part of the test set a board of this phase ranks on."""
    return _PART_NAMES[phase]


def board_seed(name: str) -> int:
    """The seed of a benchmark's resamples: the first 4 bytes of sha256("kitti-eval board " + its name), as an
    unsigned integer (the same for the benchmark's life, and reproducible by anyone who knows its name)."""
    return int.from_bytes(hashlib.sha256(f"kitti-eval board {name}".encode()).digest()[:4], "big")


@lru_cache(maxsize=4)
def _weights(n_frames: int, resamples: int, seed: int) -> npt.NDArray[np.int64]:
    """The draws of a part (kept: every submission of the benchmark uses them; never changed in place)."""
    return frame_weights(n_frames, resamples, seed)


def intervals_job_id(submission_id: str, scored_at: datetime, seed: int, resamples: int) -> str:
    """The id of the job computing a scoring's resampled keys: one job a scoring, whoever queues it."""
    moment = scored_at.astimezone(timezone.utc).isoformat()
    return hashlib.sha256(f"intervals:{submission_id}:{moment}:{seed}:{resamples}".encode()).hexdigest()[:32]


def ranked_submissions(
    bench: Benchmark, submissions: Sequence[SubmissionRecord]
) -> list[tuple[SubmissionRecord, float | None]]:
    """The scored ones of ``submissions`` (oldest first) with their key on the board's part, best first: by the key,
    ties by submission time, those without a key last."""
    keyed = [
        (r, key_value((r.scores or {}).get(bench.board_part) or {}, bench.key))
        for r in submissions
        if r.status == "scored"
    ]
    return sorted(keyed, key=lambda rk: (rk[1] is None, -(rk[1] or 0.0)))


def rounded(pair: tuple[float, float] | None) -> list[float] | None:
    """An interval as the JSON shows it: to 4 places, as the keys are."""
    return None if pair is None else [round(pair[0], 4), round(pair[1], 4)]


class Intervals:
    """The resampled keys of a benchmark's submissions: computed with each scoring (or by a job for one scored
    before), kept, and read by the board and by the participants' comparisons."""

    def __init__(
        self,
        catalog: BenchmarkCatalog,
        benchmark_store: BenchmarkStore,
        ground_truth_store: GroundTruthStore,
        job_input_store: JobInputStore,
        jobs: JobQueue,
        limits: UploadLimits,
        scratch: Callable[[], AbstractContextManager[Path]],
        *,
        wake: Callable[[int], None] = lambda n: None,
    ) -> None:
        """``catalog``: the benchmarks and their test sets; ``jobs``: where an ``intervals`` job is queued for a
        submission scored before the keys were kept; ``wake(n)``: n jobs were queued."""
        self.catalog = catalog
        self.benchmark_store = benchmark_store
        self.ground_truth_store = ground_truth_store
        self.job_input_store = job_input_store
        self.jobs = jobs
        self.limits = limits
        self.scratch = scratch
        self.wake = wake

    def bootstrap_of(self, bench: Benchmark) -> dict[str, Any]:
        """What the board says of its intervals (without ``pending``)."""
        return {
            "method": METHOD,
            "resamples": RESAMPLES,
            "seed": board_seed(bench.name),
            "part": part_name(bench.board_part),
            "level": LEVEL,
        }

    # -- computing ------------------------------------------------------------------------------------------
    def board_weights(self, bench: Benchmark, n_frames: int) -> npt.NDArray[np.int64]:
        """The benchmark's draws of a part of ``n_frames`` frames (every submission's, kept in this process)."""
        return _weights(n_frames, RESAMPLES, board_seed(bench.name))

    def resampled_key_record(
        self, bench: Benchmark, part: str, values: npt.NDArray[np.float64], n_frames: int
    ) -> ResampledKey:
        """The row kept of a submission's key under the resamples of a part of ``n_frames`` frames."""
        return ResampledKey(part, board_seed(bench.name), RESAMPLES, n_frames, values.astype("<f8").tobytes())

    def resampled_keys_of(self, bench: Benchmark, gt: Annotations, dt: Annotations) -> list[ResampledKey]:
        """The key of the predictions ``dt`` under the benchmark's resamples of each part of its test set (a
        scoring computes the same beside its documents, from the same plans)."""
        config = bench.options().config()
        key_columns = [ValueKey.parse(k) for k in bench.key]  # the ranking key's columns
        out = []
        for part, frames in part_frames(bench.split_seed, gt.frame_ids, bench.split_percent).items():
            if not frames:
                continue
            g, d = (gt, dt) if part == "all" else (gt.subset(frames), dt.subset(frames))
            values = resampled_key(plan_evaluation(g, d, config), key_columns, self.board_weights(bench, len(frames)))
            out.append(self.resampled_key_record(bench, part, values, len(frames)))
        return out

    def intervals_job(self, job: JobRecord) -> tuple[str, Callable[[Any], None]]:
        """Run an ``intervals`` job (queued for a scored submission without resampled keys: one scored before
        they were kept): the submission's id and the write of its resampled keys (for the transaction that ends
        the job; nothing is written when the submission was scored again meanwhile, which kept its own)."""
        sid = str(job.payload["submission_id"])
        scored_at = datetime.fromisoformat(str(job.payload["scored_at"]))
        submission = self.benchmark_store.get_submission(sid)
        if submission is None or submission.status != "scored" or submission.scored_at != scored_at:
            return sid, lambda conn: None  # gone, or scored again: that scoring kept its own
        bench = self.catalog.named(submission.benchmark)
        record, gt = self.catalog.ground_truth_of(bench)
        if record.sha256 != submission.gt_sha256:
            return sid, lambda conn: None  # the test set changed: a rescoring follows
        resampled = self.resampled_keys_of(bench, gt, self.predictions_of(job, submission, gt))

        def write(conn: Any) -> None:
            self.benchmark_store.replace_resampled_keys_in(conn, sid, scored_at, resampled)

        return sid, write

    def predictions_of(self, job: JobRecord, submission: SubmissionRecord, gt: Annotations) -> Annotations:
        """The submission's predictions: its job's input (a submission's scoring), else the kept file."""
        stored = self.job_input_store.job_input(job.id, "predictions") if job.kind == "submission" else None
        if stored is not None:
            content: bytes | None = stored.content
        else:
            content = self.ground_truth_store.prediction_content(submission.pred_sha256)
        if content is None:
            raise Conflict(f"the predictions of submission {submission.id} are not kept")
        with self.scratch() as scratch:
            upload = stored_upload(content, submission.pred_filename, submission.pred_sha256)
            options = LoadOptions(known_frames=gt.frame_index())
            return read_upload(
                upload.file, "detections", source=upload.filename, scratch=scratch, limits=self.limits, options=options
            ).annotations

    # -- reading ----------------------------------------------------------------------------------------------
    def resampled(
        self, bench: Benchmark, submissions: Sequence[SubmissionRecord]
    ) -> dict[str, npt.NDArray[np.float64]]:
        """Submission id -> its resampled key on the board's part, for those of ``submissions`` that have one; the
        job of each scored one that has none is queued unless it was (see :func:`intervals_job_id`)."""
        seed = board_seed(bench.name)
        kept = self.benchmark_store.resampled_keys(
            bench.name, part=bench.board_part, seed=seed, resamples=RESAMPLES, ids=[r.id for r in submissions]
        )
        found = {sid: np.frombuffer(blob, dtype="<f8") for sid, blob in kept.items()}
        found = {sid: v for sid, v in found.items() if v.shape == (RESAMPLES,)}
        missing = [r for r in submissions if r.id not in found and r.status == "scored" and r.scored_at is not None]
        if missing:
            self._queue_missing(missing, seed)
        return found

    def _queue_missing(self, submissions: Sequence[SubmissionRecord], seed: int) -> None:
        queued = 0
        for submission in submissions:
            assert submission.scored_at is not None
            job_id = intervals_job_id(submission.id, submission.scored_at, seed, RESAMPLES)
            if self.jobs.get(job_id) is not None:
                continue
            self.jobs.enqueue(
                "intervals",
                {
                    "submission_id": submission.id,
                    "benchmark": submission.benchmark,
                    "scored_at": submission.scored_at.isoformat(),
                },
                owner=submission.participant,
                group=submission.benchmark,
                job_id=job_id,
            )
            queued += 1
        if queued:
            self.wake(queued)

    def comparison(self, bench: Benchmark, record: SubmissionRecord) -> dict[str, Any] | None:
        """A scored submission against its participant's best earlier one and against the board's leader, on
        the part the board shows: the differences of the keys (this one's minus the other's) with the paired
        95% intervals from the kept resamples (None while one of them is being computed)."""
        if record.status != "scored":
            return None
        own = self.benchmark_store.list_submissions(bench.name, participant=record.participant)
        before = [r for r in own if r.created_at < record.created_at]
        earlier = [(r, k) for r, k in ranked_submissions(bench, before) if k is not None]
        published = self.benchmark_store.list_submissions(bench.name, published_only=True)
        board = ranked_submissions(bench, [r for r in published if not r.baseline])  # baselines lead no one
        leader = board[0] if board and board[0][1] is not None else None
        mine = key_value((record.scores or {}).get(bench.board_part) or {}, bench.key)
        others = [x for x in (earlier[0] if earlier else None, leader) if x is not None]
        values = self.resampled(bench, [record, *(r for r, _ in others)]) if mine is not None else {}

        def against(other: tuple[SubmissionRecord, float | None] | None, **shown: Any) -> dict[str, Any] | None:
            if other is None or mine is None:
                return None
            theirs, key = other
            if key is None:
                return None
            a, b = values.get(record.id), values.get(theirs.id)
            interval = None if a is None or b is None else interval95(a - b)
            return {
                "id": theirs.id,
                **shown,
                "key": key,
                "difference": round(mine - key, 4),
                "interval": rounded(interval),
                "significant": None if interval is None else bool(interval[0] > 0 or interval[1] < 0),
            }

        return {
            **self.bootstrap_of(bench),
            "key": mine,
            "pending": mine is not None and record.id not in values,
            "previous_best": against(earlier[0] if earlier else None, created_at=earlier[0][0].created_at.isoformat())
            if earlier
            else None,
            "leader": against(leader, method=leader[0].method) if leader else None,
        }
