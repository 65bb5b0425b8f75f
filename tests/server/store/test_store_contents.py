"""Files kept in the database (server/store/contents.py): written and read back whole, once per key, from the row
their key names; on SQLite (blob I/O) and PostgreSQL (plain columns; skipped without its binaries)."""

from __future__ import annotations

import os

import pytest
from server_postgres import PostgresCluster, why_no_postgres
from sqlalchemy import delete, insert, select
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert

from kitti_eval_server.store.contents import insert_with_content, read_content, snapshot
from kitti_eval_server.store.database import Database, prediction_files

PAGE = 65536


@pytest.fixture(scope="module")
def postgres_url():
    if why_no_postgres() is not None:
        pytest.skip(why_no_postgres() or "")
    with PostgresCluster() as cluster:
        yield cluster.url


@pytest.fixture(params=["sqlite", "postgresql"])
def db(request, tmp_path):
    url = (
        f"sqlite:///{tmp_path / 'kitti-eval.db'}"
        if request.param == "sqlite"
        else request.getfixturevalue("postgres_url")
    )
    database = Database(url)
    database.create_schema()
    yield database
    with database.engine.begin() as conn:
        conn.execute(delete(prediction_files))
    database.engine.dispose()


def _keep(db: Database, sha256: str, content: bytes) -> None:
    dialect = pg_insert if db.dialect == "postgresql" else sqlite_insert
    statement = dialect(prediction_files).values(sha256=sha256).on_conflict_do_nothing()
    with db.engine.begin() as conn:
        insert_with_content(conn, statement, content)


def _read(db: Database, sha256: str) -> bytes | None:
    with db.engine.connect() as conn:
        return read_content(conn, prediction_files, prediction_files.c.sha256 == sha256)


@pytest.mark.parametrize("size", [0, 1, PAGE - 1, 3 * PAGE + 1, 2_000_003])
def test_a_file_is_read_back_whole_as_it_was_written(db, size) -> None:
    content = os.urandom(size)
    _keep(db, "a" * 64, content)
    got = _read(db, "a" * 64)
    assert type(got) is bytes and len(got) == size and got == content


def test_a_second_file_under_the_same_key_inserts_nothing_and_the_first_stays(db) -> None:
    first, second = os.urandom(3 * PAGE), os.urandom(3 * PAGE)
    _keep(db, "b" * 64, first)
    _keep(db, "b" * 64, second)
    assert _read(db, "b" * 64) == first
    with db.engine.connect() as conn:
        assert conn.execute(select(prediction_files.c.sha256)).scalars().all() == ["b" * 64]


def test_a_key_with_no_row_reads_as_none(db) -> None:
    _keep(db, "c" * 64, b"kept")
    assert _read(db, "d" * 64) is None


def test_each_file_is_read_from_the_row_its_key_names(db) -> None:
    files = {ch * 64: os.urandom(PAGE + i) for i, ch in enumerate("efgh")}
    for key, content in files.items():
        _keep(db, key, content)
    assert {key: _read(db, key) for key in files} == files


def test_within_a_snapshot_a_file_replaced_by_another_connection_reads_as_it_was(db) -> None:
    if db.dialect != "sqlite":
        pytest.skip("SQLite's: a file is found by its rowid there; PostgreSQL reads it by its key in one statement")
    # SQLite gives a row inserted after the newest one was deleted that one's rowid: a read that found the row
    # by its key and then opened the blob by its rowid, in two transactions, would read the other file
    old, new = os.urandom(2 * PAGE), os.urandom(2 * PAGE)
    _keep(db, "i" * 64, old)
    with db.engine.connect() as conn, snapshot(conn):
        assert conn.execute(select(prediction_files.c.sha256)).scalars().all() == ["i" * 64]  # the snapshot's
        with db.engine.begin() as other:
            other.execute(delete(prediction_files))
            other.execute(insert(prediction_files).values(sha256="i" * 64, content=new))
        assert read_content(conn, prediction_files, prediction_files.c.sha256 == "i" * 64) == old
    assert _read(db, "i" * 64) == new
