"""The store's record of the processes that run jobs: each beats its row while it runs, and removes it when it
stops; a row nobody beat for long is dropped by the next beat of any process."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, insert, select, update

from .database import Area, dated, job_workers, retry_when_locked

__all__ = ["WorkerRecord", "WorkerStore"]


@dataclass(frozen=True)
class WorkerRecord:
    name: str  # host:pid, unique among the processes on the database
    host: str
    pid: int
    threads: int
    started_at: datetime
    seen_at: datetime


class WorkerStore(Area):
    @retry_when_locked
    def beat_worker(self, record: WorkerRecord, *, forget_before: datetime) -> None:
        """Record that the worker is alive at ``record.seen_at`` (its row added the first time), and drop the rows
        of the workers not seen since ``forget_before``."""
        with self.engine.begin() as conn:
            seen = dict(seen_at=record.seen_at, threads=record.threads)
            if not conn.execute(update(job_workers).where(job_workers.c.name == record.name).values(**seen)).rowcount:
                conn.execute(insert(job_workers).values(**record.__dict__))
            conn.execute(delete(job_workers).where(job_workers.c.seen_at < forget_before))

    @retry_when_locked
    def forget_worker(self, name: str) -> None:
        with self.engine.begin() as conn:
            conn.execute(delete(job_workers).where(job_workers.c.name == name))

    @retry_when_locked
    def workers_seen(self, since: datetime) -> list[WorkerRecord]:
        """The workers seen at ``since`` or later, most recently started first."""
        query = select(job_workers).where(job_workers.c.seen_at >= since)
        with self.engine.connect() as conn:
            rows = conn.execute(query.order_by(job_workers.c.started_at.desc())).mappings().all()
        return [WorkerRecord(**dated(r, "started_at", "seen_at")) for r in rows]
