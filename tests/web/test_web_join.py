"""The join page in process: the form needs its own CSRF token (a page on another site cannot join for someone),
an unknown link is 404 and a used-up one 410 as pages, and a join opens a web session and shows the token once."""

from __future__ import annotations

import re

import pytest
from server_accounts import bearer, make_teams
from server_helpers import ADMIN, app_client

from kitti_eval_server.access.auth import SESSION_COOKIE
from kitti_eval_server.access.invitations import GONE
from kitti_eval_server.access.policy import Policy

HOST = Policy.command_line("host")


@pytest.fixture(scope="module")
def hosted(tmp_path_factory):
    with app_client(tmp_path_factory.mktemp("join-page") / "data", auth="accounts", join_max_attempts=1000) as c:
        make_teams(c)
        body = {"name": "bench", "ground_truth": "sealed-a"}
        assert c.post("/v1/benchmarks", json=body, headers=ADMIN).status_code == 201
        yield c


def _code(c, uses: int | None = None) -> str:
    return _invitation(c, uses)[1]


def _invitation(c, uses: int | None = None):
    invitations = c.app.state.service.invitations
    return invitations.add("bench", uses=uses, expires_days=None, project=None, caller=HOST)


def _csrf(html: str) -> str:
    found = re.search(r'name="csrf" value="([^"]+)"', html)
    assert found, html[:2000]
    return found.group(1)


def test_the_page_joins_signs_in_and_shows_the_token_once(hosted) -> None:
    c = hosted
    code = _code(c, uses=1)
    c.cookies.clear()
    form = c.get(f"/join/{code}")
    assert form.status_code == 200 and "Join bench" in form.text
    r = c.post(f"/join/{code}", data={"name": "nora", "csrf": _csrf(form.text)})
    assert r.status_code == 201 and r.headers["cache-control"] == "no-store"
    token = re.search(r'<code id="token">(kte_[^<]+)</code>', r.text).group(1)
    # the command that asks for it, with the service's address as this page was asked at
    assert f'<code id="login-command">kitti-eval login --service {c.base_url}</code>' in r.text
    assert c.get("/v1/me", headers=bearer(token)).json()["user"] == "nora"
    assert c.cookies.get(SESSION_COOKIE) not in (None, token)
    assert "nora" in c.get("/benchmarks/bench").text  # signed in by the session the join opened
    c.cookies.clear()
    gone = c.get(f"/join/{code}")
    assert gone.status_code == 410 and GONE in gone.text


def test_the_form_without_its_csrf_token_makes_nothing(hosted) -> None:
    c = hosted
    code = _code(c)
    c.cookies.clear()
    c.get(f"/join/{code}")
    r = c.post(f"/join/{code}", data={"name": "otto", "csrf": "made-up"})
    assert r.status_code == 403 and "the join form is stale or came from another site" in r.text
    c.cookies.clear()
    r = c.post(f"/join/{code}", data={"name": "otto"})
    assert r.status_code == 403
    names = {u["name"] for u in c.get("/v1/admin/users", headers=ADMIN).json()["items"]}
    assert "otto" not in names


def test_a_taken_name_shows_the_form_again_and_an_unknown_link_is_404(hosted) -> None:
    c = hosted
    record, code = _invitation(c)
    c.cookies.clear()
    form = c.get(f"/join/{code}")
    r = c.post(f"/join/{code}", data={"name": "bob", "csrf": _csrf(form.text)})
    assert r.status_code == 409 and "taken" in r.text and 'value="bob"' in r.text and _csrf(r.text)
    rows = c.get("/v1/admin/audit", headers=ADMIN).json()["items"]
    refused = [r for r in rows if r["target"] == f"invitation {record.id}" and r["outcome"] == "refused"]
    assert [r["detail"].split(",")[0] for r in refused] == ["409"] and "'bob'" in refused[0]["detail"]
    assert c.get("/join/" + "B" * 43).status_code == 404


def test_the_benchmark_page_shows_admins_how_many_take_part(hosted) -> None:
    c = hosted
    code = _code(c)
    assert c.post(f"/v1/join/{code}", json={"name": "pia"}).status_code == 201
    users = c.get("/v1/admin/users", headers=ADMIN).json()["items"]
    members = [u["name"] for u in users if "team-a" in u["projects"] and not u["admin"]]
    assert "alice" in members and "pia" in members and "bob" not in members
    invitations = c.app.state.service.invitations.listed(HOST)
    joined = sum(len(i.accounts) for i in invitations)
    assert joined >= 1
    c.cookies.clear()
    page = c.get("/benchmarks/bench", headers=ADMIN).text
    found = re.search(r'<dd id="participants">(\d+) accounts? may take part; (\d+) joined by its invitations', page)
    assert found and (int(found.group(1)), int(found.group(2))) == (len(members), joined)
    root = c.app.state.service.accounts.add_token("root", caller=HOST)[1]
    assert 'id="participants"' in c.get("/benchmarks/bench", headers=bearer(root)).text
    alice = c.app.state.service.accounts.add_token("alice", caller=HOST)[1]
    assert 'id="participants"' not in c.get("/benchmarks/bench", headers=bearer(alice)).text
