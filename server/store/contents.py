"""Files kept in the database (a job's inputs, kept predictions, ground truths' files): their bytes read and
written in one place.

Each of those tables keeps a file's bytes in its ``content`` column. On PostgreSQL they are read and written as
any column. On SQLite a val-sized file (a 22 MB result.pkl) is a chain of overflow pages, and the plain ways
cost more than the file: binding it to an ``INSERT`` copies it once more before SQLite pages it, and a
``SELECT`` assembles it in a buffer of SQLite's before Python copies it into its own. SQLite's incremental
blob I/O (``sqlite3.Connection.blobopen``) reads the pages straight into the bytes handed back, and writes
them from the caller's bytes into a row inserted with a ``zeroblob`` of the file's size. Measured on this
project's machine (22 MB, 64 KB pages, WAL): a read 9-37 ms of CPU by ``SELECT``, 3-6 ms by blob; a write
about 45 ms by ``INSERT``, about 30 ms by blob.

A blob is read inside one read transaction (``BEGIN`` ... ``COMMIT``), so the row found by its key and the
blob opened by its rowid are the same row even while another connection deletes it and inserts another
(SQLite may give a new row the rowid of a deleted one).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from sqlalchemy import Table, func, literal_column, select
from sqlalchemy.engine import Connection
from sqlalchemy.sql import ColumnElement
from sqlalchemy.sql.dml import Insert

__all__ = ["read_content", "insert_with_content", "snapshot"]


def _sqlite3(conn: Connection) -> Any:
    """The ``sqlite3.Connection`` under ``conn``."""
    return conn.connection.driver_connection


@contextlib.contextmanager
def snapshot(conn: Connection) -> Iterator[None]:
    """On SQLite, the reads within see one state of the database (a read transaction: Python's ``sqlite3``
    begins none before a ``SELECT``); nothing within a transaction already begun, or on PostgreSQL, where a
    file is read by its key in one statement."""
    raw = _sqlite3(conn)
    if conn.dialect.name != "sqlite" or raw.in_transaction:
        yield
        return
    raw.execute("BEGIN")
    try:
        yield
    finally:
        raw.execute("COMMIT")


def read_content(conn: Connection, table: Table, *where: ColumnElement[bool]) -> bytes | None:
    """The ``content`` of the row of ``table`` that ``where`` selects (None: no such row)."""
    if conn.dialect.name != "sqlite":
        row = conn.execute(select(table.c.content).where(*where)).first()
        return None if row is None else bytes(row[0])
    with snapshot(conn):
        row = conn.execute(select(literal_column("rowid")).select_from(table).where(*where)).first()
        if row is None:
            return None
        with _sqlite3(conn).blobopen(table.name, "content", row[0], readonly=True) as blob:
            return blob.read()


def insert_with_content(conn: Connection, statement: Insert, content: bytes) -> None:
    """Run ``statement`` (an insert of one row into a table with a ``content`` column, without it) with the
    row's ``content``, within the caller's transaction. An ``ON CONFLICT DO NOTHING`` that meets a row of its
    key leaves that row as it is."""
    table = statement.table
    assert isinstance(table, Table)
    if conn.dialect.name != "sqlite" or not content:
        conn.execute(statement.values(content=content))
        return
    result = conn.execute(statement.values(content=func.zeroblob(len(content))))
    if result.rowcount != 1:  # nothing inserted (SQLite counts the rows an INSERT wrote)
        return
    with _sqlite3(conn).blobopen(table.name, "content", result.lastrowid) as blob:
        blob.write(content)
