"""The store's job inputs: the files a job was accepted with, until the job ends."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import delete, func, insert, select
from sqlalchemy.engine import Connection

from .database import Area, job_inputs, jobs, retry_when_locked

__all__ = ["JobInput", "JobInputStore"]


@dataclass(frozen=True)
class JobInput:
    name: str
    filename: str
    sha256: str
    content: bytes


class JobInputStore(Area):
    @retry_when_locked
    def add_job_inputs(self, job_id: str, inputs: list[JobInput]) -> None:
        with self.engine.begin() as conn:
            self.add_job_inputs_in(conn, job_id, inputs)

    @staticmethod
    def add_job_inputs_in(conn: Connection, job_id: str, inputs: list[JobInput]) -> None:
        """Within a transaction of the caller's (the one that records the job)."""
        conn.execute(
            insert(job_inputs),
            [
                {"job_id": job_id, "name": i.name, "filename": i.filename, "sha256": i.sha256, "content": i.content}
                for i in inputs
            ],
        )

    @retry_when_locked
    def job_input(self, job_id: str, name: str) -> JobInput | None:
        with self.engine.connect() as conn:
            row = (
                conn.execute(select(job_inputs).where(job_inputs.c.job_id == job_id, job_inputs.c.name == name))
                .mappings()
                .first()
            )
        if row is None:
            return None
        return JobInput(row["name"], row["filename"], row["sha256"], bytes(row["content"]))

    @retry_when_locked
    def job_input_bytes(self) -> int:
        """Bytes of the inputs kept for the jobs queued or running."""
        active = select(jobs.c.id).where(jobs.c.state.in_(("queued", "running")))
        query = select(func.coalesce(func.sum(func.length(job_inputs.c.content)), 0)).where(
            job_inputs.c.job_id.in_(active)
        )
        with self.engine.connect() as conn:
            return int(conn.execute(query).scalar_one())

    @staticmethod
    def delete_job_inputs_in(conn: Connection, job_id: str) -> None:
        """Within a transaction of the caller's (the one that ends the job)."""
        conn.execute(delete(job_inputs).where(job_inputs.c.job_id == job_id))

    @retry_when_locked
    def delete_job_inputs(self, job_id: str) -> None:
        with self.engine.begin() as conn:
            self.delete_job_inputs_in(conn, job_id)
