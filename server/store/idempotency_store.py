"""The store's idempotency keys: which job a caller's request with an ``Idempotency-Key`` made, until the key
expires (the rules are :mod:`kitti_eval_server.idempotency`'s)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, insert, select, text
from sqlalchemy.engine import Connection

from .database import Area, idempotency_keys, retry_when_locked, utc

__all__ = ["IdempotencyRecord", "IdempotencyStore", "KeyTaken"]


@dataclass(frozen=True)
class IdempotencyRecord:
    owner: str
    scope: str
    key: str
    fingerprint: str  # the sha256 of what the request sent
    job_id: str
    created_at: datetime
    expires_at: datetime


class KeyTaken(Exception):
    """Raised inside the transaction that would record a key another request recorded first: the transaction
    is rolled back (nothing of the second request is kept) and the first request's record is handed on."""

    def __init__(self, record: IdempotencyRecord) -> None:
        super().__init__(f"the key {record.key!r} is taken")
        self.record = record


def _record(row: object) -> IdempotencyRecord:
    values = dict(row._mapping)  # type: ignore[attr-defined]
    values["created_at"] = utc(values["created_at"])
    values["expires_at"] = utc(values["expires_at"])
    return IdempotencyRecord(**values)


def _lock_id(owner: str, scope: str, key: str) -> int:
    """A PostgreSQL advisory lock's number for one (owner, scope, key): a signed 64-bit digest."""
    digest = hashlib.sha256("\0".join((owner, scope, key)).encode()).digest()
    return int.from_bytes(digest[:8], "big", signed=True)


class IdempotencyStore(Area):
    @retry_when_locked
    def idempotency_key(self, owner: str, scope: str, key: str, now: datetime) -> IdempotencyRecord | None:
        """The record of the key, if it has not expired by ``now``."""
        query = select(idempotency_keys).where(
            idempotency_keys.c.owner == owner,
            idempotency_keys.c.scope == scope,
            idempotency_keys.c.key == key,
            idempotency_keys.c.expires_at > now,
        )
        with self.engine.connect() as conn:
            row = conn.execute(query).first()
        return None if row is None else _record(row)

    @staticmethod
    def add_idempotency_key_in(conn: Connection, record: IdempotencyRecord) -> None:
        """Within the transaction that records the key's job: record the key, or raise :class:`KeyTaken` with the
        record of the request that took it first (then the caller's transaction is rolled back). Requests with the
        same key are recorded one after another: on SQLite the transaction holds the write lock from its start,
        on PostgreSQL it takes an advisory lock of the key first (the second waits until the first commits, then
        reads its row). The owner's expired keys are removed on the way."""
        if conn.dialect.name == "postgresql":
            lock = _lock_id(record.owner, record.scope, record.key)
            conn.execute(text("SELECT pg_advisory_xact_lock(:id)"), {"id": lock})
        conn.execute(
            delete(idempotency_keys).where(
                idempotency_keys.c.owner == record.owner, idempotency_keys.c.expires_at <= record.created_at
            )
        )
        row = conn.execute(
            select(idempotency_keys).where(
                idempotency_keys.c.owner == record.owner,
                idempotency_keys.c.scope == record.scope,
                idempotency_keys.c.key == record.key,
            )
        ).first()
        if row is not None:
            raise KeyTaken(_record(row))
        conn.execute(insert(idempotency_keys).values(**record.__dict__))
