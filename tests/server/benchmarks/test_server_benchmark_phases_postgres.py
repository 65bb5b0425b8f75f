"""A team's quota on PostgreSQL: the members' parallel submissions are counted one after another under the team's
row of ``quota_locks`` (``SELECT ... FOR UPDATE``), so a team of two with a test-phase quota of 2 gets exactly two
accepted whoever sends them; the tables of teams are made on a database made before them."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import pytest
from server_benchmarks import bearer, ok
from server_helpers import app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world
from server_postgres import PostgresCluster, why_no_postgres
from unversioned import as_unversioned

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file

pytestmark = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")


@pytest.fixture(scope="module")
def postgres():
    with PostgresCluster() as cluster:
        yield cluster


def _submit(c, token: str):
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post(
        "/v1/benchmarks/kitti-phases/phases/test/submissions", params={"wait": 0}, files=files, headers=bearer(token)
    )


def test_parallel_submissions_of_a_team_on_postgres_admit_exactly_its_quota(postgres, tmp_path) -> None:
    from sqlalchemy import create_engine, text

    url = postgres.url.rsplit("/", 1)[0] + "/teams"
    admin_engine = create_engine(postgres.url, isolation_level="AUTOCOMMIT")
    with admin_engine.connect() as conn:
        conn.execute(text("CREATE DATABASE teams"))
    admin_engine.dispose()
    with app_client(tmp_path / "data", database_url=url, auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = phased_world(c)
    engine = create_engine(url)
    with engine.begin() as conn:  # as a database made before teams
        conn.execute(text("DROP TABLE team_members"))
        conn.execute(text("DROP TABLE teams"))
        as_unversioned(lambda sql: conn.execute(text(sql)))  # an unversioned release's: upgraded at start, as told
    engine.dispose()
    with app_client(
        tmp_path / "data", database_url=url, auth="accounts", auth_max_failures=1_000_000, db_upgrade=True
    ) as c:
        apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST)
        alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
        team = {"name": "Two", "members": ["bob"]}
        ok(c.post("/v1/benchmarks/kitti-phases/teams", json=team, headers=bearer(alice)), 201)
        ok(c.post("/v1/benchmarks/kitti-phases/teams/Two/join", headers=bearer(bob)))
        with ThreadPoolExecutor(12) as pool:
            answers = list(pool.map(lambda i: _submit(c, alice if i % 2 else bob), range(12)))
        # accepted: 202 (or 201 when its scoring ended before the answer); refused: 429
        statuses = sorted(201 if r.status_code == 202 else r.status_code for r in answers)
        assert statuses == [201] * 2 + [429] * 10, [r.text[:200] for r in answers]
        assert _submit(c, carol).status_code in (201, 202)  # another participant's quota is their own
