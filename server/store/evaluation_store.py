"""The store's evaluations and their labels."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import exists, insert, or_, select
from sqlalchemy.engine import Connection, RowMapping

from .database import Area, evaluation_labels, evaluations, retry_when_locked, utc

__all__ = ["EvaluationRecord", "EvaluationStore"]


@dataclass(frozen=True)
class EvaluationRecord:
    id: str
    created_at: datetime
    gt_name: str | None
    gt_sha256: str
    pred_filename: str
    pred_sha256: str
    pred_format: str
    pred_size: int
    protocol: str
    duration_ms: float
    summary: Mapping[str, Any]
    result: Mapping[str, Any] | None  # None when listed without results
    labels: Mapping[str, str] = field(default_factory=dict)
    #: the request's options (:class:`kitti_eval_server.scoring.evaluator.EvalOptions` as a dict); None for
    #: older rows
    options: Mapping[str, Any] | None = None
    project: str | None = None


class EvaluationStore(Area):
    """Stored evaluations: their results, summaries and labels."""

    @staticmethod
    def add_evaluation_in(conn: Connection, record: EvaluationRecord) -> None:
        """Within a transaction of the caller's (a job's, committed with the job's end)."""
        values = {k: v for k, v in record.__dict__.items() if k != "labels"}
        conn.execute(insert(evaluations).values(**values))
        if record.labels:
            conn.execute(
                insert(evaluation_labels),
                [{"evaluation_id": record.id, "key": k, "value": v} for k, v in record.labels.items()],
            )

    @retry_when_locked
    def get_evaluation(self, evaluation_id: str) -> EvaluationRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(evaluations).where(evaluations.c.id == evaluation_id)).mappings().first()
            if row is None:
                return None
            labels = self._labels(conn, [evaluation_id])
        return self._evaluation(row, labels.get(evaluation_id, {}))

    @retry_when_locked
    def evaluation_project(self, evaluation_id: str) -> tuple[bool, str | None]:
        """(whether the evaluation exists, its project): one small read, before any result is loaded."""
        with self.engine.connect() as conn:
            row = conn.execute(select(evaluations.c.project).where(evaluations.c.id == evaluation_id)).first()
        return (False, None) if row is None else (True, row[0])

    def list_evaluations(
        self,
        *,
        gt_name: str | None = None,
        labels: Mapping[str, str] | None = None,
        limit: int = 50,
        offset: int = 0,
        projects: frozenset[str] | None = None,
        hidden_gt_names: Sequence[str] = (),
    ) -> list[EvaluationRecord]:
        """Newest first, without the full results (the summary is there); ``projects``: only those of these
        projects (None: all); none against the ground truths ``hidden_gt_names``."""
        columns = [c for c in evaluations.c if c.name != "result"]
        query = select(*columns)
        if projects is not None:
            query = query.where(evaluations.c.project.in_(sorted(projects)))
        if hidden_gt_names:
            query = query.where(
                or_(evaluations.c.gt_name.is_(None), evaluations.c.gt_name.not_in(sorted(hidden_gt_names)))
            )
        if gt_name is not None:
            query = query.where(evaluations.c.gt_name == gt_name)
        for key, value in (labels or {}).items():
            query = query.where(
                exists().where(
                    evaluation_labels.c.evaluation_id == evaluations.c.id,
                    evaluation_labels.c.key == key,
                    evaluation_labels.c.value == value,
                )
            )
        query = query.order_by(evaluations.c.created_at.desc(), evaluations.c.id.desc()).limit(limit).offset(offset)
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
            found = self._labels(conn, [r["id"] for r in rows])
        return [self._evaluation(r, found.get(r["id"], {})) for r in rows]

    @staticmethod
    def _labels(conn: Any, ids: list[str]) -> dict[str, dict[str, str]]:
        out: dict[str, dict[str, str]] = {}
        if not ids:
            return out
        rows = conn.execute(
            select(evaluation_labels)
            .where(evaluation_labels.c.evaluation_id.in_(ids))
            .order_by(evaluation_labels.c.key)
        )
        for eid, key, value in rows:
            out.setdefault(eid, {})[key] = value
        return out

    @staticmethod
    def _evaluation(row: RowMapping, labels: dict[str, str]) -> EvaluationRecord:
        values = dict(row)
        values["created_at"] = utc(values["created_at"])
        values.setdefault("result", None)
        return EvaluationRecord(**values, labels=labels)
