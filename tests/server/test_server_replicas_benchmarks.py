"""The benchmark quota on three replicas of one PostgreSQL: 20 submissions at once from one participant, spread
over the replicas, against a quota of 3: exactly three accepted and seventeen refused with 429.

Skipped, with the reason, when no PostgreSQL binaries are installed.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from datetime import datetime

import httpx
import pytest
from server_benchmarks import bearer, host
from server_helpers import golden_bytes
from server_postgres import PostgresCluster, why_no_postgres
from server_replicas import Replicas

pytestmark = [pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or ""), pytest.mark.slow]


@pytest.fixture(scope="module")
def replicas(tmp_path_factory):
    with PostgresCluster() as cluster:
        root = tmp_path_factory.mktemp("replicas-benchmarks")
        with Replicas(root, cluster.url, 3, auth="accounts", auth_max_failures=1_000_000) as started:
            yield started


def test_twenty_submissions_through_three_replicas_against_a_quota_of_three(replicas) -> None:
    urls = [s.url for s in replicas.servers]
    with httpx.Client(base_url=urls[0], timeout=120) as c0:
        hosted = host(c0)
    data = golden_bytes("result.pkl")

    def send(i: int) -> httpx.Response:
        with httpx.Client(timeout=300) as c:
            return c.post(
                f"{urls[i % 3]}/v1/benchmarks/bench/submissions",
                files={"predictions": ("result.pkl", data, "application/octet-stream")},
                headers=bearer(hosted.tokens["alice"]),
            )

    with ThreadPoolExecutor(20) as pool:
        answers = list(pool.map(send, range(20)))
    statuses = sorted(r.status_code for r in answers)
    assert statuses == [201] * 3 + [429] * 17, ([r.text[:200] for r in answers], replicas.logs()[-3000:])
    accepted = [r.json() for r in answers if r.status_code == 201]
    assert all(a["status"] == "scored" and a["participant"] == "alice" for a in accepted)
    refused = [r for r in answers if r.status_code == 429]
    oldest = min(datetime.fromisoformat(a["created_at"]) for a in accepted)
    for r in refused:
        assert 86400 - 300 <= int(r.headers["Retry-After"]) <= 86401
        assert abs((datetime.fromisoformat(r.json()["error"]["retry_at"]) - oldest).total_seconds() - 86400) < 1
    with httpx.Client(base_url=urls[2], timeout=60) as c2:
        mine = c2.get("/v1/benchmarks/bench/submissions", headers=bearer(hosted.tokens["alice"])).json()
    assert len(mine["items"]) == 3 and mine["quota"]["left"] == 0
