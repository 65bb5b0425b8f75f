"""Accounts mode on three replicas of one PostgreSQL: the replicas keep no token cache, so a token made through
one works through every other at once, and one revoked through one is refused by all at once; projects and
sealed sets hold through every replica; the tables are created by replicas started together on an empty
database.

Skipped, with the reason, when no PostgreSQL binaries are installed.
"""

from __future__ import annotations

import pytest
from server_accounts import bearer
from server_helpers import ADMIN, golden_bytes
from server_postgres import PostgresCluster, why_no_postgres
from server_replicas import Replicas

from kitti_eval.cli import main

pytestmark = [pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or ""), pytest.mark.slow]


@pytest.fixture(scope="module")
def cluster():
    with PostgresCluster() as started:
        yield started


@pytest.fixture(scope="module")
def replicas(cluster, tmp_path_factory):
    with Replicas(tmp_path_factory.mktemp("replicas-accounts"), cluster.url, 3, auth="accounts") as started:
        yield started


def _ok(response, status: int = 201):
    assert response.status_code == status, response.text
    return response.json() if response.content else None


def test_tokens_made_or_revoked_through_one_replica_hold_on_all_at_once(replicas) -> None:
    c0, c1, c2 = (s.client() for s in replicas.servers)
    try:
        _ok(c0.post("/v1/admin/projects", json={"name": "team-a"}, headers=ADMIN))
        _ok(c1.post("/v1/admin/projects", json={"name": "team-b"}, headers=ADMIN))
        for user, project, via in (("alice", "team-a", c0), ("bob", "team-b", c2)):
            _ok(via.post("/v1/admin/users", json={"name": user}, headers=ADMIN))
            _ok(via.post("/v1/admin/members", json={"user": user, "project": project}, headers=ADMIN))
        alice = _ok(c0.post("/v1/admin/tokens", json={"user": "alice"}, headers=ADMIN))
        bob = _ok(c1.post("/v1/admin/tokens", json={"user": "bob"}, headers=ADMIN))
        for c in (c0, c1, c2):  # at once: no request in between
            assert c.get("/v1/evaluations", headers=bearer(alice["token"])).status_code == 200
            assert c.get("/v1/evaluations", headers=bearer(bob["token"])).status_code == 200

        form = {"name": "sealed-a", "project": "team-a", "sealed": "true"}
        files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
        _ok(c2.post("/v1/ground-truths", data=form, files=files, headers=ADMIN))
        made = _ok(
            c1.post(
                "/v1/evaluations",
                data={"gt": "sealed-a"},
                files={"predictions": ("result.pkl", golden_bytes("result.pkl"))},
                headers=bearer(alice["token"]),
            )
        )
        assert made["evaluation"]["project"] == "team-a"
        for c in (c0, c1, c2):
            assert c.get(f"/v1/evaluations/{made['id']}", headers=bearer(alice["token"])).status_code == 200
            assert c.get(f"/v1/evaluations/{made['id']}", headers=bearer(bob["token"])).status_code == 404
            frames = c.get(f"/v1/evaluations/{made['id']}/frames", headers=bearer(alice["token"]))
            assert frames.status_code == 403 and frames.json()["error"]["code"] == "sealed"

        assert c2.delete(f"/v1/admin/tokens/{alice['id']}", headers=ADMIN).status_code == 204
        for c in (c0, c1, c2):  # at once
            assert c.get("/v1/evaluations", headers=bearer(alice["token"])).status_code == 401
            assert c.get("/v1/evaluations", headers=bearer(bob["token"])).status_code == 200
        audit = c0.get("/v1/admin/audit", headers=ADMIN).json()["items"]
        refused = [r for r in audit if r["action"] == "token.refused" and r["actor"] == f"token {alice['id']}"]
        assert len(refused) == 3 and all(r["detail"] == "revoked" for r in refused)
    finally:
        for c in (c0, c1, c2):
            c.close()


def test_the_admin_command_on_postgresql_is_seen_by_every_replica(replicas, cluster, capsys) -> None:
    def admin(*argv: str) -> str:
        assert main(["admin", "--database-url", cluster.url, *argv]) == 0
        return capsys.readouterr().out

    admin("project", "add", "team-c")
    admin("user", "add", "carol")
    admin("member", "add", "carol", "team-c")
    token = admin("token", "add", "carol").splitlines()[-1]
    clients = [s.client() for s in replicas.servers]
    try:
        for c in clients:
            assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 200
        admin("token", "revoke", token.split("_")[1])
        for c in clients:
            assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 401
    finally:
        for c in clients:
            c.close()
