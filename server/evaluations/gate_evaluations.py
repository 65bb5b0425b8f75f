"""Evaluations a gate asks for without keeping them: a CI job with a read-only token gates its predictions against
a floor or the history, and the service evaluates them as it does an evaluation (the same options, the same job
queue and limits) but keeps nothing of them. No HTTP in here.

Such an evaluation is a job of its own kind (``gate``): its predictions are not kept, no evaluation is stored
(so it shows in no list, board, comparison or frame listing), and its result is a row of ``gate_results``
(:class:`~kitti_eval_server.store.GateResultStore`), which its owner reads once (then it is deleted) within
:data:`GATE_RESULT_S` of its making; unread, it is deleted after that, with the inputs of the ``gate`` jobs that
ended without one. Whether a caller may have one made, and read it, is the policy's
(:func:`~kitti_eval_server.access.policy.may_gate_unkept`, :func:`~kitti_eval_server.access.policy.owns_gate_result`).
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime, timedelta, timezone
from typing import Any

from ..access.policy import Caller, may_gate_unkept, owns_gate_result
from ..errors import NotFound, echo
from ..schemas import evaluation_response
from ..scoring.evaluator import EvalOptions
from ..scoring.uploads import FileIn
from ..store import GateResult, GateResultStore, IdempotencyRecord, JobInput, JobRecord
from .evaluations import Evaluations

__all__ = ["GateEvaluations", "GATE_RESULT_S"]

#: how long an unread gate result is kept (its owner's client reads it as soon as its job ends)
GATE_RESULT_S = 600.0


class GateEvaluations:
    """The evaluations gates ask for without keeping them, as callers see them."""

    def __init__(
        self, evaluations: Evaluations, gate_result_store: GateResultStore, *, kept_s: float = GATE_RESULT_S
    ) -> None:
        self.evaluations = evaluations
        self.gate_result_store = gate_result_store
        self.kept_s = kept_s

    def _made_after(self) -> datetime:
        return datetime.now(timezone.utc) - timedelta(seconds=self.kept_s)

    def accept(
        self,
        predictions: FileIn,
        gt_name: str | None,
        gt_file: FileIn | None,
        options: EvalOptions,
        caller: Caller,
        *,
        enqueue: Callable[[str, dict[str, Any], list[JobInput], IdempotencyRecord | None], JobRecord],
        idempotency_key: str | None = None,
    ) -> JobRecord:
        """Check and enqueue the evaluation as :meth:`Evaluations.accept` does (the same ground truths refused,
        the same limits of the queue), as a job that keeps nothing; the results left unread are dropped on the
        way."""
        may_gate_unkept(caller)
        self.gate_result_store.drop_gate_results(made_before=self._made_after())
        return self.evaluations.accept(
            predictions,
            gt_name,
            gt_file,
            options,
            {},
            caller,
            None,
            enqueue=enqueue,
            idempotency_key=idempotency_key,
            kept=False,
        )

    def execute(self, job: JobRecord) -> tuple[str, Callable[[Any], None]]:
        """Run an accepted gate evaluation: the evaluation's own run, its result written as the job's gate result
        (the job's inputs removed in the same transaction), nothing else."""
        record, remove_inputs = self.evaluations.execute(job.id, job.payload)
        document = evaluation_response(record)
        document["evaluation"]["kept"] = False
        result = GateResult(record.id, job.owner, record.created_at, document)

        def write(conn: Any) -> None:
            remove_inputs(conn)
            self.gate_result_store.add_gate_result_in(conn, result)

        return record.id, write

    def take(self, result_id: str, caller: Caller) -> dict[str, Any]:
        """The result of a gate evaluation, once, to its owner (then it is deleted); 404 for another's, one read
        already, or one older than :data:`GATE_RESULT_S`."""
        taken = self.gate_result_store.take_gate_result(
            result_id, lambda owner: owns_gate_result(caller, owner), made_after=self._made_after()
        )
        if taken is None:
            raise NotFound(
                f"no gate result with id {echo(result_id)} of yours (a gate's result is read once, within "
                f"{self.kept_s / 60:g} minutes of its making)"
            )
        return taken.document

    def why_not_again(self, job: JobRecord) -> str | None:
        """Why an ended gate job cannot run again (None: it can): once done, its result was read or dropped (its
        owner runs the gate again); failed or cancelled, its inputs must still be kept (they go ten minutes
        after it ended)."""
        if job.state == "done":
            return f"job {job.id} is a gate's evaluation, done and not kept: run the gate again for a new one"
        return self.evaluations.why_not_again(job)
