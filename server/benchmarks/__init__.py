"""Hosted benchmarks: a sealed ground truth, participants' submissions under a quota, and a leaderboard.

Who takes part: a benchmark is seen by everyone who sees its ground truth (the members of the ground truth's
project, every signed-in account when the ground truth is shared) and, when it is public, by anyone, without a
token (but its test set's name, :mod:`.views`). Those who see its ground truth may submit to it with a token
that may write, and every signed-in account when it is open to all (accounts mode only: a participant is an
account). A test set is one benchmark's unless the admin says it is shared. Admins create, close, reopen,
reveal and rescore benchmarks, list every submission and disqualify entries; what an admin submits is a
baseline (counted against no quota, accepted until the close, on the board in its place by the key without a
rank of its own).

A submission is first counted against the quota and accepted in one transaction with its scoring job
(``BenchmarkStore.accept_submission``; the acceptance time is the submission's; the file is received and hashed,
not read), then scored on the sealed set by that job (:mod:`kitti_eval_server.jobs.queue`: a worker of this or another
process; rescoring queues one job per submission), which checks the file first as
:func:`kitti_eval.io.submission.validate_submission` does against the test frame ids (the sentences ``kitti-eval
validate`` prints): a refused submission is deleted and costs nothing. Its participant sees its aggregate result (on the
public part only while a benchmark with a split is not revealed); nobody else sees it until it is
published. What is published is frozen when the benchmark closes, and a benchmark may cap the entries a
participant has published (``max_published``).

The public/private split: with ``split_percent`` p, a test frame is in the public part when the first 8 bytes
of sha256(seed + ":" + frame id), read as an integer, are below p % of 2**64. The seed is 32 random hex digits
drawn when the benchmark is created, stored in its row and never shown; the parts are therefore fixed for the
benchmark's life and unknown to participants. While the benchmark runs (or until an admin reveals the
ranking after the close) the board shows the scores on the public part; after the reveal, those on the
private part. A benchmark is revealed only once it has opened and is closed, and is never reopened after.
Its test set stays sealed: a ground truth is registered under a benchmark's test set name sealed only.

How sure the board is: after each scoring a job computes the submission's ranking key under the benchmark's
1000 bootstrap resamples of the frames of each part (the same draws for every submission), kept in the
database; the board gives each entry's 95% interval, rank range and whether it differs from the next from
them, and a participant's submission is compared with their previous best and the leader (:mod:`.intervals`).

The modules: :mod:`.rules` (a benchmark's definition and rules), :mod:`.catalog` (seeing benchmarks, the
admins' actions on them), :mod:`.intervals` (the resampled keys: computed, kept, compared),
:mod:`.submissions` (accepting, scoring, publishing), :mod:`.leaderboard` (ranking, CSV), :mod:`.views` (what
a caller is shown, from allow-lists), :mod:`.markdown` (the description as HTML), :mod:`.phases` (a benchmark's
phases, each a benchmark row of its own, and which one a route addresses), :mod:`.teams` (teams, and the team's
quota), :mod:`.phase_settings` (a phase's settings: one frozen type, checked once, stored by one rule) and
:mod:`.benchmark_file` (a benchmark defined by a TOML file: applied, exported).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

from kitti_eval.io.upload import UploadLimits

from ..access.audit import Audit
from ..access.policy import Policy
from ..ground_truths.cache import GroundTruths
from ..idempotency import Idempotency
from ..jobs.queue import JobQueue
from ..store import Store
from .benchmark import Benchmark
from .catalog import BenchmarkCatalog
from .intervals import Intervals
from .leaderboard import Leaderboard
from .markdown import render_markdown
from .rules import DEFAULT_KEY, in_public_part, key_value, parse_column, parse_quota
from .submissions import InvalidSubmission, QuotaExceeded, Scoring, Submissions
from .teams import Teams

__all__ = [
    "Benchmarks",
    "Benchmark",
    "BenchmarkCatalog",
    "Intervals",
    "Leaderboard",
    "Scoring",
    "Submissions",
    "QuotaExceeded",
    "InvalidSubmission",
    "DEFAULT_KEY",
    "render_markdown",
    "parse_quota",
    "parse_column",
    "in_public_part",
    "key_value",
]


class Benchmarks:
    """The hosted benchmarks, as collaborators the routes reach by name: the ``catalog`` (seeing benchmarks, the
    admins' actions on them), the ``submissions`` (accepting, publishing, the admins' lists), their ``scoring``
    (by jobs), the ``board`` (ranking, CSV), the ``intervals`` (the resampled keys) and the ``teams``, over one
    service."""

    def __init__(
        self,
        catalog: BenchmarkCatalog,
        intervals: Intervals,
        submissions: Submissions,
        scoring: Scoring,
        board: Leaderboard,
        teams: Teams,
    ) -> None:
        self.catalog = catalog
        self.intervals = intervals
        self.submissions = submissions
        self.scoring = scoring
        self.board = board
        self.teams = teams

    @classmethod
    def assemble(
        cls,
        store: Store,
        ground_truths: GroundTruths,
        policy: Policy,
        audit: Audit,
        scratch: Callable[[], AbstractContextManager[Path]],
        limits: UploadLimits,
        *,
        jobs: JobQueue,
        idempotency: Idempotency,
        draining: Callable[[], bool] = lambda: False,
        wake: Callable[[int], None] = lambda n: None,
    ) -> Benchmarks:
        """The collaborators, each given the areas of ``store`` and the parts it uses. ``jobs``: the queue the
        scorings, rescorings and intervals go through; ``wake(n)``: n jobs were queued (idle workers of this
        process look at once); ``draining()``: whether the process is stopping (no submission is accepted)."""
        catalog = BenchmarkCatalog(store.benchmark_store, ground_truths, policy, audit, jobs)
        stores = (store.benchmark_store, store.ground_truth_store, store.job_input_store)
        intervals = Intervals(catalog, *stores, jobs, limits, scratch, wake=wake)
        submissions = Submissions(
            catalog,
            intervals,
            store.benchmark_store,
            store.job_input_store,
            policy,
            audit,
            jobs,
            idempotency,
            draining=draining,
            wake=wake,
        )
        scoring = Scoring(catalog, intervals, *stores, policy, jobs, limits, scratch)
        board = Leaderboard(catalog, intervals, store.benchmark_store)
        teams = Teams(catalog, store.team_store, store.account_store)
        return cls(catalog, intervals, submissions, scoring, board, teams)
