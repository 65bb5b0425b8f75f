"""Joining by an invitation: a host's link makes accounts that take part in its benchmark and nothing more; a
used-up, expired or revoked invitation answers 410 with one message, a taken name 409; the joins are audited
and limited per client address."""

from __future__ import annotations

import time

import pytest
from server_accounts import bearer, make_teams
from server_benchmarks import ok, submit
from server_helpers import ADMIN, app_client, golden_bytes, upload

from kitti_eval_server.access.invitations import GONE
from kitti_eval_server.access.policy import Policy, invited_projects
from kitti_eval_server.errors import BadRequest

HOST = Policy.command_line("host")


@pytest.fixture(scope="module")
def hosted(tmp_path_factory):
    """Project team-a's sealed set ``sealed-a`` is the benchmark ``bench``'s test set (its members take part);
    team-b has the ground truth ``gt-b``."""
    data = tmp_path_factory.mktemp("invitations") / "data"
    with app_client(data, auth="accounts", join_max_attempts=1000) as c:
        teams = make_teams(c)
        ok(
            c.post("/v1/benchmarks", json={"name": "bench", "ground_truth": "sealed-a", "quota": "5/1"}, headers=ADMIN),
            201,
        )
        yield c, teams


def _invite(c, **options):
    values = {"uses": None, "expires_days": None, "project": None, **options}
    return c.app.state.service.invitations.add("bench", **values, caller=HOST)


def test_an_invitation_of_two_uses_makes_two_participants_of_its_benchmark_and_nothing_more(hosted) -> None:
    c, _ = hosted
    record, code = _invite(c, uses=2)
    assert len(code) >= 43 and record.code_sha256 != code and record.project == "team-a"
    joined = []
    for name in ("dana", "erik"):
        body = ok(c.post(f"/v1/join/{code}", json={"name": name}), 201)
        assert set(body) == {"user", "token", "benchmark"} and body["user"] == name and body["benchmark"] == "bench"
        assert body["token"].startswith("kte_")
        joined.append(body["token"])
    for token in joined:
        me = ok(c.get("/v1/me", headers=bearer(token)))
        assert me["admin"] is False and me["read_only"] is False
        accepted = ok(submit(c, bearer(token), golden_bytes("result.pkl")), 201)
        assert accepted["status"] in ("accepted", "scored")
        # another project's ground truth is not theirs: the same 404 as a missing one
        assert c.get("/v1/ground-truths/gt-b", headers=bearer(token)).status_code == 404
        assert c.get("/v1/admin/users", headers=bearer(token)).status_code == 403
    third = c.post(f"/v1/join/{code}", json={"name": "fay"})
    assert third.status_code == 410 and third.json()["error"]["message"] == GONE
    users = {u["name"]: u for u in ok(c.get("/v1/admin/users", headers=ADMIN))["items"]}
    assert "fay" not in users
    assert [(users[n]["admin"], users[n]["projects"]) for n in ("dana", "erik")] == [(False, ["team-a"])] * 2
    listed = [i for i in c.app.state.service.invitations.listed(HOST) if i.id == record.id]
    assert listed[0].uses == 2 and listed[0].accounts == ("dana", "erik")
    rows = ok(c.get("/v1/admin/audit", headers=ADMIN))["items"]
    joins = [r for r in rows if r["action"] == "invitation.join"]
    assert {r["actor"] for r in joins} >= {"dana", "erik"}
    assert all(f"invitation {record.id}" in r["detail"] for r in joins if r["actor"] in ("dana", "erik"))


def test_an_expired_invitation_answers_410(hosted) -> None:
    c, _ = hosted
    _, code = _invite(c, expires_days=1e-9)  # 86 microseconds
    time.sleep(0.01)
    r = c.post(f"/v1/join/{code}", json={"name": "gus"})
    assert r.status_code == 410 and r.json()["error"]["message"] == GONE


def test_a_revoked_invitation_answers_410(hosted) -> None:
    c, _ = hosted
    record, code = _invite(c)
    c.app.state.service.invitations.revoke(record.id, caller=HOST)
    r = c.post(f"/v1/join/{code}", json={"name": "hal"})
    assert r.status_code == 410 and r.json()["error"]["message"] == GONE


def test_a_taken_name_answers_409_and_uses_nothing(hosted) -> None:
    c, _ = hosted
    record, code = _invite(c, uses=1)
    r = c.post(f"/v1/join/{code}", json={"name": "alice"})
    assert r.status_code == 409 and "taken" in r.json()["error"]["message"]
    for bad in ("admin-token", "no spaces", "", "-x"):
        assert c.post(f"/v1/join/{code}", json={"name": bad}).status_code == 422
    ok(c.post(f"/v1/join/{code}", json={"name": "ines"}), 201)  # its one use is still there


def test_a_name_equal_to_a_users_ignoring_case_is_taken_and_admin_is_reserved(hosted) -> None:
    c, _ = hosted
    _, code = _invite(c, uses=1)
    for name in ("ALICE", "Alice", "aLiCe"):
        r = c.post(f"/v1/join/{code}", json={"name": name})
        assert r.status_code == 409 and "taken" in r.json()["error"]["message"], name
    for name in ("admin", "Admin", "ADMIN"):
        r = c.post(f"/v1/join/{code}", json={"name": name})
        assert r.status_code == 422 and "reserved" in r.json()["error"]["message"], name
    ok(c.post(f"/v1/join/{code}", json={"name": "Nell"}), 201)  # its one use is still there
    names = [u["name"] for u in ok(c.get("/v1/admin/users", headers=ADMIN))["items"]]
    assert sorted(n for n in names if n.lower() in ("alice", "admin", "nell")) == ["Nell", "alice"]


def test_an_unknown_code_answers_404(hosted) -> None:
    c, _ = hosted
    assert c.post("/v1/join/" + "A" * 43, json={"name": "jo"}).status_code == 404
    assert c.post("/v1/join/x", json={"name": "jo"}).status_code == 404


def test_an_invitation_to_a_projects_benchmark_makes_members_of_that_project_only(hosted) -> None:
    c, _ = hosted
    with pytest.raises(BadRequest, match="team-a"):
        _invite(c, project="team-b")


def test_joins_are_limited_per_client_address(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", join_max_attempts=2, register_demo=False) as c:
        make_teams(c)
        ok(c.post("/v1/benchmarks", json={"name": "bench", "ground_truth": "sealed-a"}, headers=ADMIN), 201)
        _, code = _invite(c)
        assert c.post(f"/v1/join/{code}", json={"name": "alice"}).status_code == 409
        ok(c.post(f"/v1/join/{code}", json={"name": "kim"}), 201)
        r = c.post(f"/v1/join/{code}", json={"name": "lou"})
        assert r.status_code == 429 and "join" in r.json()["error"]["message"] and r.headers["retry-after"]


def test_an_invitation_to_a_benchmark_whose_last_phase_has_closed_answers_410(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", register_demo=False) as c:
        make_teams(c)
        ok(c.post("/v1/benchmarks", json={"name": "bench", "ground_truth": "sealed-a"}, headers=ADMIN), 201)
        _, code = _invite(c, uses=5)
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        r = c.post(f"/v1/join/{code}", json={"name": "kim"})
        assert r.status_code == 410 and r.json()["error"]["message"] == GONE
        assert c.get(f"/join/{code}").status_code == 410
        ok(c.post("/v1/benchmarks/bench/reopen", headers=ADMIN))  # the lifecycle's state, not a mark on the link
        ok(c.post(f"/v1/join/{code}", json={"name": "kim"}), 201)


def test_refused_joins_are_audited_by_the_invitations_id_never_its_code(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", join_max_attempts=4, register_demo=False) as c:
        make_teams(c)
        ok(c.post("/v1/benchmarks", json={"name": "bench", "ground_truth": "sealed-a"}, headers=ADMIN), 201)
        record, code = _invite(c, uses=1)
        asked = [("alice", 409), ("bad name", 422), ("kim", 201), ("lou", 410), ("max", 429)]
        for name, status in asked:
            assert c.post(f"/v1/join/{code}", json={"name": name}).status_code == status, name
        assert c.post("/v1/join/" + "A" * 43, json={"name": "ned"}).status_code == 429  # an unknown code: no row
        rows = ok(c.get("/v1/admin/audit", headers=ADMIN))["items"]
        refused = [r for r in reversed(rows) if r["action"] == "invitation.join" and r["outcome"] == "refused"]
        assert [(r["detail"].split(",")[0], r["target"]) for r in refused] == [
            (str(status), f"invitation {record.id}") for name, status in asked if status != 201
        ]
        assert [r["detail"].split("'")[1] for r in refused] == ["alice", "bad name", "lou", "max"]
        assert all(r["client"] == "testclient" and r["actor"] == "anonymous" for r in refused)
        assert not [r for r in rows if code in str(r)]


def test_open_mode_has_no_invitations(tmp_path) -> None:
    with app_client(tmp_path / "data", register_demo=False) as c:
        assert c.post("/v1/join/" + "A" * 43, json={"name": "jo"}).status_code == 404


@pytest.mark.parametrize(
    ("project", "open_to_all", "wanted", "made"),
    [
        ("team-a", False, None, ("team-a",)),  # only its project's members take part: they are made members
        ("team-a", False, "team-a", ("team-a",)),
        ("team-a", True, None, ()),  # open to all: taking part needs no project, none is given
        ("team-a", True, "team-b", ("team-b",)),  # the host's choice
        (None, False, None, ()),  # a shared test set: every account takes part
        (None, False, "team-b", ("team-b",)),
    ],
)
def test_the_projects_an_invited_account_is_a_member_of(project, open_to_all, wanted, made) -> None:
    assert invited_projects(project=project, open_to_all=open_to_all, wanted=wanted) == made


def test_an_invitation_makes_no_member_of_another_project_than_the_one_that_takes_part() -> None:
    with pytest.raises(BadRequest, match="only its members take part"):
        invited_projects(project="team-a", open_to_all=False, wanted="team-b")


def test_joins_at_once_never_exceed_the_uses(hosted) -> None:
    from concurrent.futures import ThreadPoolExecutor

    from kitti_eval_server.errors import Gone

    c, _ = hosted
    service = c.app.state.service
    record, code = _invite(c, uses=3)
    caller = service.policy.anonymous("192.0.2.1")

    def attempt(i: int) -> str:
        try:
            return service.invitations.join(code, f"rush-{i}", caller=caller)[0]
        except Gone:
            return "gone"

    with ThreadPoolExecutor(8) as pool:
        outcomes = list(pool.map(attempt, range(8)))
    made = sorted(o for o in outcomes if o != "gone")
    assert len(made) == 3 and outcomes.count("gone") == 5
    listed = next(i for i in service.invitations.listed(HOST) if i.id == record.id)
    assert listed.uses == 3 and sorted(listed.accounts) == made


def test_an_invited_account_takes_part_in_its_invitations_benchmark_and_no_shared_one(hosted) -> None:
    """A benchmark on a test set shared with every account (no project) takes part from every account, but not
    from one an invitation made: that takes part in its invitation's benchmark (all its phases) and uploads no
    evaluation, even against a shared ground truth."""
    c, teams = hosted
    files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
    form = {"name": "shared-set", "sealed": "true"}
    assert ok(c.post("/v1/ground-truths", data=form, files=files, headers=ADMIN), 201)["project"] is None
    ok(c.post("/v1/benchmarks", json={"name": "sharedbench", "ground_truth": "shared-set"}, headers=ADMIN), 201)
    _, code = _invite(c, uses=1)
    token = ok(c.post(f"/v1/join/{code}", json={"name": "ana"}), 201)["token"]
    assert c.get("/v1/benchmarks/sharedbench", headers=bearer(token)).status_code == 404
    assert "sharedbench" not in [b["name"] for b in ok(c.get("/v1/benchmarks", headers=bearer(token)))["items"]]
    assert submit(c, bearer(token), golden_bytes("result.pkl"), name="sharedbench").status_code == 404
    refused = upload(c, golden_bytes("result.pkl"), gt="demo", headers=bearer(token))
    assert refused.status_code == 403 and "invitation" in refused.json()["error"]["message"]
    ok(submit(c, bearer(token), golden_bytes("result.pkl")), 201)  # its own benchmark still takes it
    # an account an admin made takes part in the shared benchmark as before
    ok(submit(c, teams.headers("carol"), golden_bytes("result.pkl"), name="sharedbench"), 201)
