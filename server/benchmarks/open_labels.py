"""A phase on open labels (a labelled validation set, not sealed): its participants see their own submission's
result frame by frame, as ``kitti-eval frames`` shows an evaluation's (TP, FP and FN per frame, worst first). A
sealed phase's frames never leave the service
(:func:`~kitti_eval_server.access.policy.require_open_labels`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..access.policy import Caller, require_open_labels
from ..errors import Conflict
from ..scoring.evaluator import frame_listing
from ..scoring.uploads import stored_upload

if TYPE_CHECKING:
    from . import Benchmarks

__all__ = ["submission_frames"]


def submission_frames(
    benchmarks: Benchmarks,
    row: str,
    submission_id: str,
    caller: Caller,
    **question: Any,
) -> dict[str, Any]:
    """TP/FP/FN per frame of one of the caller's submissions to the phase ``row``, when the phase is on
    open labels: the submission's file read as its scoring read it, matched as the AP is
    (:func:`~kitti_eval_server.scoring.evaluator.frame_listing`, ``question`` its keywords)."""
    record = benchmarks.submissions._own(row, submission_id, caller)
    bench = benchmarks.catalog.named(row)
    require_open_labels(open_labels=bench.open_labels, what=f"phase {bench.phase_name!r}")
    if record.status != "scored":
        raise Conflict(f"the submission {record.id} is {record.status}: its frames are shown once it is scored")
    _, gt = benchmarks.catalog.ground_truth_of(bench)
    scoring = benchmarks.scoring  # the file is read as its scoring read it
    content = scoring.ground_truth_store.prediction_content(record.pred_sha256)
    if content is None:
        raise Conflict(f"the predictions of submission {record.id} are not kept")
    dt = scoring._checked(stored_upload(content, record.pred_filename, record.pred_sha256), gt, labels="validation")
    doc = frame_listing(gt, dt, bench.options().config(), **question)
    doc["submission"] = record.id
    return doc
