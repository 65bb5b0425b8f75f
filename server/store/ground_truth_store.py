"""The store's ground truths (registrations and their files, kept by content) and kept prediction files."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, func, insert, select
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.engine import Connection, RowMapping
from sqlalchemy.exc import IntegrityError

from .contents import insert_with_content, read_content
from .database import Area, ground_truth_files, ground_truths, prediction_files, retry_when_locked, utc

__all__ = ["GroundTruthRecord", "GroundTruthStore", "keep_prediction_file"]


@dataclass(frozen=True)
class GroundTruthRecord:
    name: str
    sha256: str
    format: str
    filename: str
    storage: str
    size_bytes: int
    frames: int
    boxes: int
    created_at: datetime
    project: str | None = None
    sealed: bool = False


class GroundTruthStore(Area):
    """Named ground truths with their files, and the prediction files kept for later looks at frames."""

    @retry_when_locked
    def add_ground_truth(self, record: GroundTruthRecord, content: bytes) -> bool:
        """Insert the record and (once per sha256) its file; False if the name is taken (nothing changed)."""
        for _ in range(2):  # a concurrent registration of the same file may insert its content first
            try:
                with self.engine.begin() as conn:
                    known = conn.execute(
                        select(ground_truth_files.c.sha256).where(ground_truth_files.c.sha256 == record.sha256)
                    ).first()
                    if known is None:
                        insert_with_content(conn, insert(ground_truth_files).values(sha256=record.sha256), content)
                    conn.execute(insert(ground_truths).values(**record.__dict__))
                return True
            except IntegrityError:
                if self.get_ground_truth(record.name) is not None:
                    return False
        return False

    @retry_when_locked
    def ground_truth_content(self, sha256: str) -> bytes | None:
        with self.engine.connect() as conn:
            return read_content(conn, ground_truth_files, ground_truth_files.c.sha256 == sha256)

    @retry_when_locked
    def get_ground_truth(self, name: str) -> GroundTruthRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(select(ground_truths).where(ground_truths.c.name == name)).mappings().first()
        return None if row is None else self._gt(row)

    @retry_when_locked
    def list_ground_truths(self, *, projects: frozenset[str] | None = None) -> list[GroundTruthRecord]:
        """By name; ``projects``: only those of these projects and the shared ones (None: all)."""
        query = select(ground_truths).order_by(ground_truths.c.name)
        if projects is not None:
            query = query.where(ground_truths.c.project.is_(None) | ground_truths.c.project.in_(sorted(projects)))
        with self.engine.connect() as conn:
            rows = conn.execute(query).mappings().all()
        return [self._gt(r) for r in rows]

    @retry_when_locked
    def delete_ground_truth(self, name: str) -> tuple[GroundTruthRecord | None, bool]:
        """Delete by name: (the deleted record or None, whether another name still uses the same file)."""
        with self.engine.begin() as conn:
            row = conn.execute(select(ground_truths).where(ground_truths.c.name == name)).mappings().first()
            if row is None:
                return None, False
            conn.execute(delete(ground_truths).where(ground_truths.c.name == name))
            shared = conn.execute(
                select(func.count()).select_from(ground_truths).where(ground_truths.c.sha256 == row["sha256"])
            ).scalar_one()
            if not shared:
                conn.execute(delete(ground_truth_files).where(ground_truth_files.c.sha256 == row["sha256"]))
        return self._gt(row), bool(shared)

    @staticmethod
    def _gt(row: RowMapping) -> GroundTruthRecord:
        values = dict(row)
        values["created_at"] = utc(values["created_at"])
        values["sealed"] = bool(values.get("sealed"))
        return GroundTruthRecord(**values)

    # -- predictions -----------------------------------------------------------------------------------
    @retry_when_locked
    def add_prediction_file(self, sha256: str, content: bytes) -> None:
        """Keep an uploaded predictions file (once per content)."""
        with self.engine.begin() as conn:
            keep_prediction_file(conn, sha256, content)

    @retry_when_locked
    def prediction_content(self, sha256: str) -> bytes | None:
        with self.engine.connect() as conn:
            return read_content(conn, prediction_files, prediction_files.c.sha256 == sha256)


def keep_prediction_file(conn: Connection, sha256: str, content: bytes) -> None:
    """Keep a predictions file by its content within the caller's transaction: written unless it is there; a copy
    kept at the same moment by another transaction is left as it is (the contents are the same)."""
    if conn.execute(select(prediction_files.c.sha256).where(prediction_files.c.sha256 == sha256)).first() is not None:
        return
    dialect = pg_insert if conn.dialect.name == "postgresql" else sqlite_insert
    insert_with_content(conn, dialect(prediction_files).values(sha256=sha256).on_conflict_do_nothing(), content)
