"""Joining by an invitation on PostgreSQL: joins at once are counted by one conditional update of the invitation's
row, so an invitation of three uses makes exactly three accounts whoever sends them, and a name two joins want at
once is one account and one 409 (the other's transaction, use included, rolled back)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import pytest
from server_accounts import make_teams
from server_benchmarks import ok
from server_helpers import ADMIN, app_client
from server_postgres import PostgresCluster, why_no_postgres

from kitti_eval_server.access.policy import Policy

pytestmark = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")
HOST = Policy.command_line("host")


@pytest.fixture(scope="module")
def postgres():
    with PostgresCluster() as cluster:
        yield cluster


def test_joins_at_once_on_postgres_never_exceed_the_uses(postgres, tmp_path) -> None:
    with app_client(tmp_path / "data", database_url=postgres.url, auth="accounts", join_max_attempts=1000) as c:
        make_teams(c)
        ok(c.post("/v1/benchmarks", json={"name": "bench", "ground_truth": "sealed-a"}, headers=ADMIN), 201)
        invitations = c.app.state.service.invitations
        record, code = invitations.add("bench", uses=3, expires_days=None, project=None, caller=HOST)
        with ThreadPoolExecutor(8) as pool:
            statuses = list(
                pool.map(lambda i: c.post(f"/v1/join/{code}", json={"name": f"p{i}"}).status_code, range(8))
            )
        assert sorted(statuses) == [201] * 3 + [410] * 5
        _, same = invitations.add("bench", uses=5, expires_days=None, project=None, caller=HOST)
        with ThreadPoolExecutor(4) as pool:
            statuses = list(pool.map(lambda _: c.post(f"/v1/join/{same}", json={"name": "twin"}).status_code, range(4)))
        assert sorted(statuses) == [201] + [409] * 3
        listed = {i.code_sha256: i for i in invitations.listed(HOST)}
        assert [i.uses for i in listed.values()] == [3, 1]
