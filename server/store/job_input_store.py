"""The store's job inputs: the files a job was accepted with, until the job ends."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import and_, case, delete, func, insert, select
from sqlalchemy.engine import Connection

from .contents import insert_with_content, read_content, snapshot
from .database import Area, job_inputs, jobs, prediction_files, retry_when_locked
from .ground_truth_store import keep_prediction_file

__all__ = ["JobInput", "JobInputStore"]

#: the job inputs beside the kept predictions a ``kept`` one refers to
_WITH_KEPT = job_inputs.outerjoin(
    prediction_files, and_(job_inputs.c.kept, prediction_files.c.sha256 == job_inputs.c.sha256)
)


@dataclass(frozen=True)
class JobInput:
    name: str
    filename: str
    sha256: str
    content: bytes
    #: predictions the service keeps for good: written once, to the kept files, when the job is accepted (the
    #: job's row refers to them by ``sha256``; nothing is copied or deleted when the job ends)
    kept: bool = False


class JobInputStore(Area):
    @staticmethod
    def add_job_inputs_in(conn: Connection, job_id: str, inputs: list[JobInput]) -> None:
        """Within a transaction of the caller's (the one that records the job). A ``kept`` input is written to
        the kept predictions unless a file of its content is there already (then nothing is written again)."""
        for i in inputs:
            if i.kept:
                keep_prediction_file(conn, i.sha256, i.content)
        for i in inputs:
            row = {"job_id": job_id, "name": i.name, "filename": i.filename, "sha256": i.sha256, "kept": i.kept}
            insert_with_content(conn, insert(job_inputs).values(row), b"" if i.kept else i.content)

    @retry_when_locked
    def job_input(self, job_id: str, name: str) -> JobInput | None:
        """A job's input with its content (a kept one's read from the kept predictions)."""
        fields = [job_inputs.c.name, job_inputs.c.filename, job_inputs.c.sha256, job_inputs.c.kept]
        key = (job_inputs.c.job_id == job_id, job_inputs.c.name == name)
        with self.engine.connect() as conn, snapshot(conn):
            row = conn.execute(select(*fields).where(*key)).mappings().first()
            if row is None:
                return None
            if row["kept"]:
                content = read_content(conn, prediction_files, prediction_files.c.sha256 == row["sha256"])
            else:
                content = read_content(conn, job_inputs, *key)
        if content is None:
            return None
        return JobInput(row["name"], row["filename"], row["sha256"], content, kept=bool(row["kept"]))

    @retry_when_locked
    def job_input_bytes(self) -> int:
        """Bytes of the inputs kept for the jobs queued or running."""
        active = select(jobs.c.id).where(jobs.c.state.in_(("queued", "running")))
        size = case(
            (job_inputs.c.kept, func.coalesce(func.length(prediction_files.c.content), 0)),
            else_=func.length(job_inputs.c.content),
        )
        query = select(func.coalesce(func.sum(size), 0)).select_from(_WITH_KEPT).where(job_inputs.c.job_id.in_(active))
        with self.engine.connect() as conn:
            return int(conn.execute(query).scalar_one())

    @staticmethod
    def delete_job_inputs_in(conn: Connection, job_id: str) -> None:
        """Within a transaction of the caller's (the one that ends the job)."""
        conn.execute(delete(job_inputs).where(job_inputs.c.job_id == job_id))
