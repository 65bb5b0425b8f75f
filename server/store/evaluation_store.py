"""The store's evaluations and their labels."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import exists, insert, or_, select
from sqlalchemy.engine import Connection, RowMapping

from .database import Area, evaluation_frames, evaluation_labels, evaluations, retry_when_locked, utc

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

    @staticmethod
    def add_frames_in(conn: Connection, evaluation_id: str, rows: Iterable[Any], *, batch: int = 512) -> None:
        """An evaluation's frame rows (:class:`~kitti_eval_server.evaluations.frame_rows.FrameRow`), written in
        batches within the caller's transaction (the one that stores the evaluation)."""
        pending: list[dict[str, Any]] = []
        for row in rows:
            pending.append(
                {
                    "evaluation_id": evaluation_id,
                    "frame_index": row.frame_index,
                    "frame_id": row.frame_id,
                    "detections": row.detections,
                    "events": row.events,
                }
            )
            if len(pending) >= batch:
                conn.execute(insert(evaluation_frames), pending)
                pending = []
        if pending:
            conn.execute(insert(evaluation_frames), pending)

    @retry_when_locked
    def has_frames(self, evaluation_id: str) -> bool:
        """Whether the evaluation's job stored its frames (not those stored before it did)."""
        with self.engine.connect() as conn:
            query = select(evaluation_frames.c.frame_index).where(evaluation_frames.c.evaluation_id == evaluation_id)
            return conn.execute(query.limit(1)).first() is not None

    def frame_events(self, evaluation_id: str, *, batch: int = 256) -> Iterator[tuple[int, str, bytes]]:
        """(frame index, frame id, events) of every frame of the evaluation in order, read ``batch`` rows at a
        time (never the detections, never all at once)."""
        after = -1
        while True:
            with self.engine.connect() as conn:
                rows = conn.execute(
                    select(evaluation_frames.c.frame_index, evaluation_frames.c.frame_id, evaluation_frames.c.events)
                    .where(evaluation_frames.c.evaluation_id == evaluation_id, evaluation_frames.c.frame_index > after)
                    .order_by(evaluation_frames.c.frame_index)
                    .limit(batch)
                ).all()
            for f, frame_id, events in rows:
                yield int(f), str(frame_id), bytes(events)
            if len(rows) < batch:
                return
            after = int(rows[-1][0])

    @retry_when_locked
    def frame(self, evaluation_id: str, frame_id: str) -> tuple[bytes, bytes] | None:
        """(detections, events) of one frame of the evaluation (None: no such row)."""
        with self.engine.connect() as conn:
            row = conn.execute(
                select(evaluation_frames.c.detections, evaluation_frames.c.events).where(
                    evaluation_frames.c.evaluation_id == evaluation_id, evaluation_frames.c.frame_id == frame_id
                )
            ).first()
        return None if row is None else (bytes(row[0]), bytes(row[1]))

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
