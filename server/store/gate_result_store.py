"""The store's gate results: the documents of evaluations a gate asked for without keeping them (``gate`` jobs),
each read once by its owner, or deleted unread a few minutes after it was made (the rules are
:mod:`kitti_eval_server.evaluations.gate_evaluations`')."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import and_, delete, insert, select
from sqlalchemy.engine import Connection

from .database import Area, gate_results, job_inputs, jobs, retry_when_locked, utc

__all__ = ["GateResult", "GateResultStore"]


@dataclass(frozen=True)
class GateResult:
    id: str  # the job's id
    owner: str
    created_at: datetime
    document: dict[str, Any]


class GateResultStore(Area):
    @staticmethod
    def add_gate_result_in(conn: Connection, result: GateResult) -> None:
        """Within the transaction that ends the result's job."""
        conn.execute(insert(gate_results).values(**result.__dict__))

    @retry_when_locked
    def take_gate_result(
        self, result_id: str, may_take: Callable[[str], bool], *, made_after: datetime
    ) -> GateResult | None:
        """The result, if ``may_take(its owner)`` and it was made after ``made_after``, deleted as it is read (read
        once: two readers at once get it once); None otherwise (one another may not take is left as it is)."""
        with self._writing() as conn:
            row = conn.execute(select(gate_results).where(gate_results.c.id == result_id)).mappings().first()
            if row is None or not may_take(str(row["owner"])):
                return None
            mine = and_(gate_results.c.id == result_id, gate_results.c.owner == row["owner"])
            if not conn.execute(delete(gate_results).where(mine)).rowcount:
                return None
        made = utc(row["created_at"])
        if made <= made_after:
            return None
        return GateResult(str(row["id"]), str(row["owner"]), made, dict(row["document"]))

    @retry_when_locked
    def drop_gate_results(self, *, made_before: datetime) -> int:
        """Delete the results made before ``made_before`` (unread), and the inputs of the ``gate`` jobs that ended
        before it without a result (failed, cancelled: an ended job's inputs are no longer read). How many
        results were deleted."""
        ended = select(jobs.c.id).where(
            jobs.c.kind == "gate",
            jobs.c.state.in_(("done", "failed", "cancelled")),
            jobs.c.finished_at < made_before,
        )
        with self._writing() as conn:
            dropped = conn.execute(delete(gate_results).where(gate_results.c.created_at < made_before)).rowcount
            conn.execute(delete(job_inputs).where(job_inputs.c.job_id.in_(ended)))
        return int(dropped or 0)
