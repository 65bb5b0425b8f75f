"""What a caller is shown of a benchmark, a submission and its result: one function a view, each building its
document from the fields the view may hold (the ``*_FIELDS`` lists), never by removing fields from a fuller one.

Before the reveal a participant's view of their own submission holds the AP values of the part the board shows
(and, in its ``comparison``, the intervals of its key), the facts about their own file that do not depend on
the split (its size, its frames, its detections per class over the whole file) and nothing else derived from
the sealed set: no count of ground-truth objects, no count over one part, no curve (whose thresholds and
``num_valid_gt`` follow the part's frames). Counting one's own detections over the public part would read back
which frames are public (2**k detections in frame k make the count the binary list of the public frames).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from typing import Any

from ..store import SubmissionRecord
from .benchmark import Benchmark

__all__ = [
    "BENCHMARK_FIELDS",
    "TEST_SET_FIELDS",
    "SUBMISSION_FIELDS",
    "OWN_SUBMISSION_FIELDS",
    "RESULT_FIELDS",
    "BOARD_FIELDS",
    "ENTRY_FIELDS",
    "PHASE_FIELDS",
    "TEAM_FIELDS",
    "OWN_TEAM_FIELDS",
    "pick",
    "benchmark_view",
    "phase_view",
    "submission_view",
    "result_view",
]

#: a benchmark, as everyone who sees it reads it
BENCHMARK_FIELDS = (
    "name",
    "title",
    "description",
    "protocol",
    "classes",
    "threshold_sets",
    "key",
    "columns",
    "quota",
    "public",
    "open_to_all",
    "opens_at",
    "closes_at",
    "state",
    "open",
    "closed",
    "split_percent",
    "revealed",
    "board",
    "max_published",
    "phase",
    "phases",
    "team_size",
)
#: and as those who see its test set read it (admins, the members of the test set's project, every signed-in
#: account when the test set is shared): with the test set's name
TEST_SET_FIELDS = (*BENCHMARK_FIELDS, "ground_truth")

#: a phase of a benchmark (in its ``phases``), as everyone who sees the benchmark reads it; its test set's name
#: only for those who see the ground truth
PHASE_FIELDS = (
    "name",
    "current",
    "ground_truth",
    "opens_at",
    "closes_at",
    "state",
    "open",
    "closed",
    "late_submissions",
    "open_labels",
    "quota",
    "split_percent",
    "revealed",
    "board",
    "max_published",
)
#: a team, as those who see its benchmark's teams read it; and as its members read it, with whom it invited
TEAM_FIELDS = ("benchmark", "name", "members", "created_at")
OWN_TEAM_FIELDS = (*TEAM_FIELDS, "invited")

#: a submission in its participant's list (and the admins')
SUBMISSION_FIELDS = (
    "id",
    "benchmark",
    "phase",
    "participant",
    "created_at",
    "status",
    "reason",
    "filename",
    "sha256",
    "size",
    "published",
    "method",
    "anonymous",
    "affiliation",
    "link",
    "disqualified",
    "baseline",
    "scored_at",
    "scored_on",
    "scores",
    "parts",
)
#: one of the caller's submissions, read alone: with its result (``comparison`` is added by the caller's view)
OWN_SUBMISSION_FIELDS = (*SUBMISSION_FIELDS, "result")

#: a leaderboard, as everyone who sees the benchmark reads it, and each of its entries (a published submission)
BOARD_FIELDS = ("benchmark", "phase", "title", "board", "key", "columns", "sort", "order", "entries", "bootstrap")
ENTRY_FIELDS = (
    "id",
    "method",
    "participant",
    "team",
    "affiliation",
    "link",
    "anonymous",
    "date",
    "key",
    "columns",
    "baseline",
    "rank",
    "interval",
    "rank_range",
    "differs_from_next",
)

#: a participant's result: the evaluation's settings (the benchmark's, not the data's), the AP values of the part
#: the board shows, and the facts of their own file over the whole file
RESULT_FIELDS = (
    "schema_version",
    "protocol",
    "classes",
    "threshold_sets",
    "metrics",
    "difficulties",
    "overlaps",
    "aos_evaluated",
    "ap",
    "frames",
    "num_det",
)


def pick(values: Mapping[str, Any], fields: tuple[str, ...]) -> dict[str, Any]:
    return {f: values[f] for f in fields if f in values}


def benchmark_view(
    bench: Benchmark, *, names_test_set: bool, phases: Sequence[Mapping[str, Any]] = ()
) -> dict[str, Any]:
    """A benchmark as a caller reads it (``names_test_set``: whether the caller may read its test set's name;
    the policy says), in the phase ``bench`` is (its ``phases``: the phases the caller sees, :mod:`.phases`)."""
    n, days = bench.quota
    values = {
        "name": bench.shown_name,
        "phase": bench.phase_name,
        "phases": [dict(p) for p in phases],
        "team_size": bench.team_size,
        "title": bench.title,
        "description": bench.description,
        "ground_truth": bench.gt_name,
        "protocol": bench.settings.protocol,
        "classes": bench.settings.classes.split(","),
        "threshold_sets": bench.settings.threshold_sets.split(","),
        "key": bench.key,
        "columns": bench.columns,
        "quota": {"submissions": n, "days": days},
        "public": bench.public,
        "open_to_all": bench.open_to_all,
        "opens_at": bench.opens_at.isoformat(),
        "closes_at": bench.closes_at.isoformat() if bench.closes_at else None,
        "state": bench.state().value,
        "open": bench.is_open(),
        "closed": bench.closed,
        "split_percent": bench.split_percent,
        "revealed": bench.revealed,
        "board": bench.board_part,
        "max_published": bench.max_published,
    }
    return pick(values, TEST_SET_FIELDS if names_test_set else BENCHMARK_FIELDS)


def phase_view(bench: Benchmark, *, current: bool, names_test_set: bool, now: datetime | None = None) -> dict[str, Any]:
    """A phase as those who see its benchmark read it (:data:`PHASE_FIELDS`; its ground truth's name for
    those the policy lets read it); its ``state`` as :mod:`.lifecycle` says at ``now``."""
    now = now or datetime.now(timezone.utc)
    n, days = bench.quota
    values: Mapping[str, Any] = {
        "name": bench.phase_name,
        "current": current,
        "ground_truth": bench.gt_name,
        "opens_at": bench.opens_at.isoformat(),
        "closes_at": bench.closes_at.isoformat() if bench.closes_at else None,
        "state": bench.state(now).value,
        "open": bench.is_open(now),
        "closed": bench.is_closed(now),
        "late_submissions": bench.late_submissions,
        "open_labels": bench.open_labels,
        "quota": {"submissions": n, "days": days},
        "split_percent": bench.split_percent,
        "revealed": bench.revealed,
        "board": bench.board_part,
        "max_published": bench.max_published,
    }
    fields = PHASE_FIELDS if names_test_set else tuple(f for f in PHASE_FIELDS if f != "ground_truth")
    return pick(values, fields)


def result_view(record: SubmissionRecord, bench: Benchmark, *, everything: bool = False) -> dict[str, Any] | None:
    """A submission's result. ``everything`` (an admin's): the sealed document on the whole test set as kept.
    A participant's (:data:`RESULT_FIELDS`): the AP values of the part the board shows (the public part until
    the reveal: None for a submission scored before that part's document was kept), with the settings and
    their file's frames and detections counted over the whole file."""
    whole = record.result
    if whole is None:
        return None
    if everything or bench.open_labels:  # an admin's; or a phase on open labels: the participant has the labels
        return dict(whole)
    shown = record.public_result if bench.board_part == "public" else whole
    if shown is None:
        return None
    values = {**pick(whole, RESULT_FIELDS), "ap": shown.get("ap")}
    return pick(values, RESULT_FIELDS)


def submission_view(
    record: SubmissionRecord, bench: Benchmark, *, full: bool, everything: bool = False
) -> dict[str, Any]:
    """A submission as its participant sees it (``full``: with its result, :func:`result_view`), or as an
    admin's list does (``everything``). While a benchmark with a public/private split is not revealed, its
    participant sees the scores on the public part only (what the board shows); after the reveal, and always
    in an admin's list, the scores on the whole test set and on each part (``parts``). Without a split the
    whole set is the public part. ``reason``: why a failed submission failed (its file refused, its scoring
    cancelled or given up on)."""
    scores = record.scores or {}
    public_only = bench.board_part == "public" and not everything
    shown = "public" if public_only else "all"
    values = {
        "id": record.id,
        "benchmark": bench.shown_name,
        "phase": bench.phase_name,
        "participant": record.participant,
        "created_at": record.created_at.isoformat(),
        "status": record.status,
        "reason": record.failure if record.status == "failed" else None,
        "filename": record.pred_filename,
        "sha256": record.pred_sha256,
        "size": record.pred_size,
        "published": bool(record.published),
        "method": record.method,
        "anonymous": bool(record.anonymous),
        "affiliation": record.affiliation,
        "link": record.link,
        "disqualified": bool(record.disqualified),
        "baseline": bool(record.baseline),
        "scored_at": record.scored_at.isoformat() if record.scored_at else None,
        "scored_on": shown,
        "scores": scores.get(shown),
        "parts": None
        if public_only or bench.board_part == "all"
        else {p: scores.get(p) for p in ("public", "private")},
    }
    if not full:
        return pick(values, SUBMISSION_FIELDS)
    values["result"] = result_view(record, bench, everything=everything)
    return pick(values, OWN_SUBMISSION_FIELDS)
