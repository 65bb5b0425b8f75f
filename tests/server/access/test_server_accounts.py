"""Accounts mode (KITTI_EVAL_AUTH=accounts): tokens at the door, projects that do not see each other, scopes,
sealed ground truths, the audit log, and the brute-force limit."""

from __future__ import annotations

import logging
import sqlite3
from datetime import datetime, timedelta, timezone

import pytest
from server_accounts import Teams, add_token, bearer, make_teams
from server_helpers import ADMIN, app_client, assert_error, golden_bytes, upload
from sqlalchemy import update
from unversioned import as_unversioned

from kitti_eval_server.access.accounts import digest, split_token
from kitti_eval_server.store import tokens


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    data = tmp_path_factory.mktemp("accounts") / "data"
    with app_client(data, auth="accounts", auth_max_failures=1000) as c:
        yield c, data, make_teams(c)


def test_without_a_token_only_the_probes_static_files_sign_in_and_api_docs_answer(service) -> None:
    c, _, teams = service
    assert c.get("/healthz").status_code == 200
    assert c.get("/readyz").status_code == 200
    assert c.get("/static/app.css").status_code == 200
    assert c.get("/signin").status_code == 200
    # the API's description (the pages link to it as "API"): routes and fields, none of anyone's data
    assert c.get("/docs").status_code == 200 and "/v1/evaluations" in c.get("/openapi.json").json()["paths"]
    for method, path in (
        ("GET", "/v1/evaluations"),
        ("GET", f"/v1/evaluations/{teams.evaluations['gt-a']}"),
        ("GET", "/v1/ground-truths"),
        ("GET", "/v1/ground-truths/gt-a"),
        ("POST", "/v1/gates"),
        ("GET", "/v1/admin/users"),
        ("GET", "/v1/no-such-route"),
    ):
        err = assert_error(c.request(method, path), 401, "token")
        assert err["code"] == "unauthorized"
    page = c.get("/")
    assert page.status_code == 401 and 'action="/signin"' in page.text and "gt-a" not in page.text
    assert upload(c, golden_bytes("result.pkl"), gt="gt-a").status_code == 401


def test_a_wrong_or_malformed_token_is_401(service) -> None:
    c, _, teams = service
    good = teams.tokens["alice"]
    for token in ("nonsense", good[:-1] + ("A" if good[-1] != "A" else "B"), "kte_" + "0" * 16 + "_x", "Bearer"):
        assert_error(c.get("/v1/evaluations", headers=bearer(token)), 401, "not valid")
    assert_error(c.get("/v1/evaluations", headers={"Authorization": f"Basic {good}"}), 401)


def test_members_see_only_their_projects_work(service) -> None:
    c, _, teams = service
    a, b = teams.evaluations["gt-a"], teams.evaluations["gt-b"]
    listed = c.get("/v1/evaluations", headers=teams.headers("alice")).json()["items"]
    assert {i["id"] for i in listed} == {a, teams.evaluations["sealed-a"]}
    assert {i["evaluation"]["project"] for i in listed} == {"team-a"}
    listed = c.get("/v1/evaluations", headers=teams.headers("bob")).json()["items"]
    assert [i["id"] for i in listed] == [b]
    assert c.get("/v1/evaluations", headers=teams.headers("carol")).json()["items"] == []
    assert {i["id"] for i in c.get("/v1/evaluations", headers=ADMIN).json()["items"]} == set(teams.evaluations.values())

    names = {g["name"] for g in c.get("/v1/ground-truths", headers=teams.headers("bob")).json()["items"]}
    assert names == {"gt-b", "demo"}  # the demo is shared
    assert c.get("/v1/ground-truths/gt-b", headers=teams.headers("bob")).json()["project"] == "team-b"


def test_another_projects_things_are_as_absent_as_missing_ones(service) -> None:
    c, _, teams = service
    a = teams.evaluations["gt-a"]
    bob = teams.headers("bob")
    missing = assert_error(c.get("/v1/evaluations/" + "0" * 32, headers=bob), 404)
    theirs = assert_error(c.get(f"/v1/evaluations/{a}", headers=bob), 404)
    assert theirs["message"] == missing["message"].replace("0" * 32, a)
    assert_error(c.get(f"/v1/evaluations/{teams.evaluations['gt-b']}/compare/{a}", headers=bob), 404)
    assert_error(c.get(f"/v1/evaluations/{a}/frames", headers=bob), 404)
    assert_error(c.get("/v1/frames/000001", params={"evaluation": a}, headers=bob), 404)
    assert_error(c.post("/v1/gates", json={"evaluation": a, "min": ["Car/3d/moderate >= 0"]}, headers=bob), 404)
    gate = {"evaluation": teams.evaluations["gt-b"], "baseline": a, "max_drop": ["0"]}
    assert_error(c.post("/v1/gates", json=gate, headers=bob), 404)
    gt_missing = assert_error(c.get("/v1/ground-truths/nope", headers=bob), 404)
    gt_theirs = assert_error(c.get("/v1/ground-truths/gt-a", headers=bob), 404)
    assert gt_theirs["message"] == gt_missing["message"].replace("nope", "gt-a")
    c.headers.update(bob)
    try:
        assert_error(upload(c, golden_bytes("result.pkl"), gt="gt-a"), 404, "no ground truth named 'gt-a'")
        assert_error(upload(c, golden_bytes("result.pkl"), gt="demo", fields={"project": "team-a"}), 404, "project")
    finally:
        del c.headers["Authorization"]
    page = c.get(f"/evaluations/{a}", headers=bob)
    assert page.status_code == 404 and "model-of-alice" not in page.text
    home = c.get("/", headers=bob)
    assert home.status_code == 200 and "model-of-bob-on-gt-b" in home.text and "model-of-alice" not in home.text


def test_a_member_uploads_into_their_project(service) -> None:
    c, _, teams = service
    c.headers.update(teams.headers("bob"))
    try:
        r = upload(c, golden_bytes("result.pkl"), gt="demo", fields={"model": "bob-demo"})
    finally:
        del c.headers["Authorization"]
    assert r.status_code == 201, r.text
    assert r.json()["evaluation"]["project"] == "team-b"
    listed = c.get("/v1/evaluations", params={"model": "bob-demo"}, headers=teams.headers("alice")).json()["items"]
    assert listed == []
    c.headers.update(teams.headers("carol"))  # in no project: nowhere to put it
    try:
        assert_error(upload(c, golden_bytes("result.pkl"), gt="demo"), 422, "project")
    finally:
        del c.headers["Authorization"]


def test_a_read_only_token_reads_and_gates_but_writes_nothing(service) -> None:
    c, _, teams = service
    ro = teams.headers("alice-ro")
    a = teams.evaluations["gt-a"]
    assert c.get(f"/v1/evaluations/{a}", headers=ro).status_code == 200
    gate = c.post("/v1/gates", json={"evaluation": a, "min": ["Car/3d/moderate >= 0"]}, headers=ro)
    assert gate.status_code == 200 and gate.json()["passed"] is True
    before = len(c.get("/v1/evaluations", headers=ADMIN).json()["items"])
    c.headers.update(ro)
    try:
        assert_error(upload(c, golden_bytes("result.pkl"), gt="gt-a"), 403, "read-only")
    finally:
        del c.headers["Authorization"]
    r = c.post("/ui/evaluations", files={"predictions": ("r.pkl", golden_bytes("result.pkl"))}, headers=ro)
    assert r.status_code == 403
    assert_error(c.delete("/v1/ground-truths/gt-a", headers=ro), 403)
    assert len(c.get("/v1/evaluations", headers=ADMIN).json()["items"]) == before


def test_members_are_not_admins(service) -> None:
    c, _, teams = service
    for who in ("alice", "bob"):
        mallory = {"name": "mallory", "admin": True}
        assert_error(c.post("/v1/admin/users", json=mallory, headers=teams.headers(who)), 403)
        assert_error(c.get("/v1/admin/audit", headers=teams.headers(who)), 403)
        assert_error(c.delete("/v1/ground-truths/gt-a", headers=teams.headers(who)), 403)
    assert c.get("/v1/ground-truths/gt-a", headers=ADMIN).status_code == 200
    users = c.get("/v1/admin/users", headers=teams.headers("root")).json()["items"]  # an admin user's token
    assert {"name": "alice", "admin": False, "projects": ["team-a"]} in users
    assert "mallory" not in {u["name"] for u in users}


def test_revoked_and_expired_tokens_are_refused_at_once(service) -> None:
    c, data, teams = service
    token_id, token = add_token(c, "alice")
    assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 200
    assert c.delete(f"/v1/admin/tokens/{token_id}", headers=ADMIN).status_code == 204
    assert_error(c.get("/v1/evaluations", headers=bearer(token)), 401)
    listed = {t["id"]: t for t in c.get("/v1/admin/tokens", params={"user": "alice"}, headers=ADMIN).json()["items"]}
    assert listed[token_id]["revoked"] is True and "token" not in listed[token_id]

    token_id, token = add_token(c, "alice", expires_days=1)
    assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 200
    store = c.app.state.service.store
    with store.engine.begin() as conn:  # a day later
        conn.execute(
            update(tokens).where(tokens.c.id == token_id).values(expires_at=datetime.now(timezone.utc) - timedelta(1))
        )
    assert_error(c.get("/v1/evaluations", headers=bearer(token)), 401)


def test_only_digests_are_stored_and_no_token_reaches_the_log_or_audit(service, caplog) -> None:
    c, data, teams = service
    with caplog.at_level(logging.DEBUG, logger="kitti_eval.server"):
        token_id, token = add_token(c, "bob")
        assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 200
        assert c.delete(f"/v1/admin/tokens/{token_id}", headers=ADMIN).status_code == 204
        assert c.get("/v1/evaluations", headers=bearer(token)).status_code == 401
    assert split_token(token) == token_id
    secret = token.split("_", 2)[2]
    assert len(secret) >= 43
    everything = b"".join(p.read_bytes() for p in data.glob("kitti-eval.db*"))
    assert digest(token).encode() in everything  # the digest is there ...
    for secret_text in (token, secret, secret[:20]):  # ... and nothing of the secret
        assert secret_text.encode() not in everything
        assert secret_text not in caplog.text
    assert token_id in caplog.text  # the log names the token by its id
    with sqlite3.connect(data / "kitti-eval.db") as db:
        rows = db.execute("SELECT secret_sha256 FROM tokens WHERE id = ?", (token_id,)).fetchall()
    assert rows == [(digest(token),)]
    audit = c.get("/v1/admin/audit", params={"limit": 1000}, headers=ADMIN).json()["items"]
    assert secret not in str(audit)


def test_the_audit_log_names_admin_actions_and_refused_tokens(service) -> None:
    c, _, teams = service
    assert c.get("/v1/evaluations", headers=bearer("kte_" + "f" * 16 + "_guess")).status_code == 401
    assert c.get("/v1/admin/users", headers=teams.headers("bob")).status_code == 403
    audit = c.get("/v1/admin/audit", params={"limit": 1000}, headers=ADMIN).json()["items"]
    actions = [(r["actor"], r["action"], r["target"], r["outcome"]) for r in audit]
    assert ("admin-token", "project.add", "team-a", "ok") in actions
    assert ("admin-token", "user.add", "root", "ok") in actions
    assert ("admin-token", "member.add", "alice -> team-a", "ok") in actions
    assert any(a == "admin-token" and act == "token.add" and t.startswith("alice (") for a, act, t, _ in actions)
    assert ("token ffffffffffffffff", "token.refused", "/v1/evaluations", "refused") in actions
    bob = f"bob ({teams.token_ids['bob']})"
    assert (bob, "token.forbidden", "GET /v1/admin/users", "refused") in actions
    assert all(r["at"].endswith("Z") and r["client"] for r in audit)


def test_sealed_ground_truths_give_aggregates_only(service) -> None:
    c, _, teams = service
    sealed, open_ = teams.evaluations["sealed-a"], teams.evaluations["gt-a"]
    for who in ("alice", "root"):  # not even an admin
        h = teams.headers(who)
        a, b = c.get(f"/v1/evaluations/{sealed}", headers=h).json(), c.get(f"/v1/evaluations/{open_}", headers=h).json()
        assert a["ap"] == b["ap"] and a["num_gt"] == b["num_gt"]  # the same file: the same aggregates
        assert a["frames_without_predictions"] == [] and "sealed" in a["warnings"][0]
        err = assert_error(c.get(f"/v1/evaluations/{sealed}/frames", headers=h), 403, "sealed")
        assert err["code"] == "sealed"
        for frame in ("000001", "999999"):  # in the set or not: the same refusal
            assert_error(c.get(f"/v1/frames/{frame}", params={"evaluation": sealed}, headers=h), 403, "sealed")
        assert c.get(f"/v1/evaluations/{open_}/frames", headers=h).status_code == 200
        page = c.get(f"/frames/000001?e={sealed}", headers=h)
        assert page.status_code == 403 and "sealed" in page.text
        page = c.get(f"/evaluations/{sealed}", headers=h)
        assert page.status_code == 200 and "sealed" in page.text


def test_too_many_refused_tokens_from_one_client_get_429(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=5, auth_failure_window_s=60) as c:
        for _ in range(5):
            assert_error(c.get("/v1/evaluations", headers=bearer("kte_" + "1" * 16 + "_guess")), 401)
        err = assert_error(c.get("/v1/evaluations", headers=bearer("kte_" + "1" * 16 + "_guess")), 429)
        assert err["code"] == "too_many_requests"
        r = c.get("/v1/evaluations", headers=ADMIN)  # even a good token waits: the client is not trusted now
        assert r.status_code == 429 and 1 <= int(r.headers["retry-after"]) <= 61
        assert c.get("/healthz").status_code == 200
        audit = c.app.state.service.store.account_store.list_audit(limit=100)
        assert sum(r.action == "token.refused" for r in audit) == 5  # the 429s are not even looked at


def test_teams_fixture_is_what_the_other_tests_assume(service) -> None:
    _, _, teams = service
    assert isinstance(teams, Teams)
    assert set(teams.tokens) == {"alice", "alice-ro", "bob", "carol", "root"}
    assert all(split_token(t) == teams.token_ids[w] for w, t in teams.tokens.items())


def test_every_token_check_compares_digests_in_constant_time(service, monkeypatch) -> None:
    """Unknown id, wrong secret, right token: each check is one hmac.compare_digest of two sha256 digests (a
    miss is compared against a dummy digest, so it takes as long as a wrong secret)."""
    import kitti_eval_server.access.accounts as accounts_module

    c, _, teams = service
    calls: list[tuple[str, str]] = []
    real = accounts_module.hmac.compare_digest

    def spy(a, b):  # type: ignore[no-untyped-def]
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(accounts_module.hmac, "compare_digest", spy)
    good = teams.tokens["bob"]
    wrong = good[:-2] + ("xy" if not good.endswith("xy") else "zz")
    unknown = "kte_" + "a" * 16 + "_" + "b" * 43
    for token, status in ((good, 200), (wrong, 401), (unknown, 401)):
        calls.clear()
        assert c.get("/v1/evaluations", headers=bearer(token)).status_code == status
        # the admin token's check, then the token's: both digests of 64 hex digits, never the token itself
        assert len(calls) == 2, calls
        assert all(len(a) == len(b) == 64 for a, b in calls)
        assert calls[1][0] == digest(token)


def test_a_database_from_before_accounts_is_upgraded(tmp_path) -> None:
    """Its ground truths become shared, its evaluations (of no project) are the admins' only."""
    data = tmp_path / "data"
    with app_client(data) as c:  # open mode
        old = upload(c, golden_bytes("result.pkl"), gt="demo").json()["id"]
    db = sqlite3.connect(data / "kitti-eval.db")
    for statement in (
        "ALTER TABLE evaluations DROP COLUMN project",
        "ALTER TABLE ground_truths DROP COLUMN project",
        "ALTER TABLE ground_truths DROP COLUMN sealed",
        "DROP TABLE audit",
        "DROP TABLE tokens",
        "DROP TABLE memberships",
        "DROP TABLE users",
        "DROP TABLE projects",
    ):
        db.execute(statement)
    as_unversioned(db.execute)  # an unversioned release's: upgraded at start, as told
    db.commit()
    db.close()
    with app_client(data, auth="accounts", db_upgrade=True) as c:
        assert c.post("/v1/admin/projects", json={"name": "p"}, headers=ADMIN).status_code == 201
        assert c.post("/v1/admin/users", json={"name": "u"}, headers=ADMIN).status_code == 201
        assert c.post("/v1/admin/members", json={"user": "u", "project": "p"}, headers=ADMIN).status_code == 201
        _, token = add_token(c, "u")
        assert c.get(f"/v1/evaluations/{old}", headers=ADMIN).status_code == 200
        assert c.get(f"/v1/evaluations/{old}", headers=bearer(token)).status_code == 404
        demo = c.get("/v1/ground-truths/demo", headers=bearer(token)).json()
        assert demo["project"] is None and demo["sealed"] is False
