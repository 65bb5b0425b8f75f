"""Replicas of the service on one PostgreSQL behave as one service.

Skipped, with the reason, when no PostgreSQL binaries are installed (Debian: ``apt-get install postgresql``).
"""

from __future__ import annotations

import threading
import uuid

import psycopg
import pytest
from server_postgres import PostgresCluster, why_no_postgres

from server.store import Store

pytestmark = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")


@pytest.fixture(scope="module")
def postgres():
    with PostgresCluster() as cluster:
        yield cluster


def fresh_database(cluster: PostgresCluster) -> str:
    """A new, empty database on the cluster; its SQLAlchemy URL (psycopg 3)."""
    name = f"db_{uuid.uuid4().hex}"
    with psycopg.connect(
        host="127.0.0.1", port=cluster.port, user="postgres", dbname="postgres", autocommit=True
    ) as conn:
        conn.execute(f"CREATE DATABASE {name}")
    return f"postgresql+psycopg://postgres@127.0.0.1:{cluster.port}/{name}"


def test_servers_creating_the_schema_at_once_all_succeed(postgres) -> None:
    """PostgreSQL's CREATE TABLE races with itself (a unique violation in its catalog): without a lock, servers
    started together on an empty database crashed at start-up, all but one."""

    def create(store: Store, start: threading.Barrier, failures: list[BaseException]) -> None:
        start.wait()
        try:
            store.create_schema()
        except Exception as e:  # noqa: BLE001 - collected and reported
            failures.append(e)

    for _ in range(3):
        url = fresh_database(postgres)
        stores = [Store(url) for _ in range(4)]
        start = threading.Barrier(len(stores))
        failures: list[BaseException] = []
        threads = [threading.Thread(target=create, args=(s, start, failures)) for s in stores]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        try:
            assert not failures, failures[0]
            assert stores[0].list_ground_truths() == []
        finally:
            for store in stores:
                store.dispose()
