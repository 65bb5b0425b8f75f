"""The web pages in accounts mode: sign in once with a token, a session cookie (HttpOnly, SameSite=Strict, not
the token), CSRF tokens on the forms that change state, sign out."""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

import pytest
from server_accounts import add_token, make_teams
from server_helpers import ADMIN, ADMIN_TOKEN, app_client, golden_bytes
from sqlalchemy import update

from kitti_eval_server.access.accounts import csrf_token, split_token
from kitti_eval_server.access.auth import CSRF_COOKIE, SESSION_COOKIE
from kitti_eval_server.store import tokens


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    data = tmp_path_factory.mktemp("web-accounts") / "data"
    with app_client(data, auth="accounts", auth_max_failures=1000) as c:
        yield c, make_teams(c)


def _hidden(html: str, name: str = "csrf") -> str:
    found = re.search(rf'name="{name}" value="([^"]+)"', html)
    assert found, html[:2000]
    return found.group(1)


def sign_in(c, token: str):
    c.cookies.clear()
    form = c.get("/signin")
    assert form.status_code == 200
    return c.post("/signin", data={"token": token, "csrf": _hidden(form.text)}, follow_redirects=False)


def test_sign_in_opens_a_session_of_its_own(service) -> None:
    c, teams = service
    r = sign_in(c, teams.tokens["bob"])
    assert r.status_code == 303 and r.headers["location"] == "/"
    set_cookie = [h for h in r.headers.get_list("set-cookie") if h.startswith(SESSION_COOKIE + "=")]
    assert len(set_cookie) == 1
    attributes = set_cookie[0].lower()
    assert "httponly" in attributes and "samesite=strict" in attributes and "path=/" in attributes
    session = c.cookies[SESSION_COOKIE]
    assert session != teams.tokens["bob"] and teams.tokens["bob"] not in r.text  # not the token itself
    assert split_token(session) not in (None, teams.token_ids["bob"])
    home = c.get("/")
    assert home.status_code == 200
    assert "model-of-bob-on-gt-b" in home.text and "model-of-alice" not in home.text
    assert 'id="sign-out"' in home.text and ">bob<" in home.text
    assert _hidden(home.text) == csrf_token(session)
    c.cookies.clear()


def test_a_wrong_token_or_a_forged_form_does_not_sign_in(service) -> None:
    c, teams = service
    r = sign_in(c, teams.tokens["bob"][:-1] + "!")
    assert r.status_code == 401 and SESSION_COOKIE not in c.cookies and "not valid" in r.text
    c.cookies.clear()
    r = c.post("/signin", data={"token": teams.tokens["bob"], "csrf": "made-up"}, follow_redirects=False)
    assert r.status_code == 403 and SESSION_COOKIE not in c.cookies  # no CSRF cookie from our form
    c.cookies.set(CSRF_COOKIE, "a", path="/signin")
    r = c.post("/signin", data={"token": teams.tokens["bob"], "csrf": "b"}, follow_redirects=False)
    assert r.status_code == 403 and SESSION_COOKIE not in c.cookies
    c.cookies.clear()


def test_forms_that_change_state_need_the_sessions_csrf_token(service) -> None:
    c, teams = service
    assert sign_in(c, teams.tokens["alice"]).status_code == 303
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
    before = len(c.get("/v1/evaluations").json()["items"])  # the session also works for the API
    forged = c.post("/ui/evaluations", data={"gt": "gt-a"}, files=files, follow_redirects=False)
    assert forged.status_code == 403 and "CSRF" in forged.text
    wrong = c.post("/ui/evaluations", data={"gt": "gt-a", "csrf": "0" * 64}, files=files, follow_redirects=False)
    assert wrong.status_code == 403
    assert len(c.get("/v1/evaluations").json()["items"]) == before
    csrf = _hidden(c.get("/").text)
    r = c.post("/ui/evaluations", data={"gt": "gt-a", "csrf": csrf}, files=files, follow_redirects=False)
    assert r.status_code == 303, r.text
    assert len(c.get("/v1/evaluations").json()["items"]) == before + 1
    assert c.post("/signout", data={}, follow_redirects=False).status_code == 403  # sign-out needs it too
    c.cookies.clear()


def test_sign_out_ends_the_session_everywhere(service) -> None:
    c, teams = service
    assert sign_in(c, teams.tokens["bob"]).status_code == 303
    session = c.cookies[SESSION_COOKIE]
    r = c.post("/signout", data={"csrf": _hidden(c.get("/").text)}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/signin"
    assert SESSION_COOKIE not in c.cookies
    c.cookies.set(SESSION_COOKIE, session)  # the old cookie, kept by someone: refused
    page = c.get("/")
    assert page.status_code == 401 and 'action="/signin"' in page.text
    c.cookies.clear()


def test_revoking_the_token_ends_its_sessions(service) -> None:
    c, teams = service
    token_id, token = add_token(c, "bob")
    assert sign_in(c, token).status_code == 303
    assert c.get("/").status_code == 200
    assert c.delete(f"/v1/admin/tokens/{token_id}", headers=ADMIN).status_code == 204
    assert c.get("/").status_code == 401
    c.cookies.clear()


def test_a_session_cookie_is_not_a_bearer_token_and_the_admin_token_cannot_sign_in(service) -> None:
    c, teams = service
    assert sign_in(c, teams.tokens["bob"]).status_code == 303
    session = c.cookies[SESSION_COOKIE]
    c.cookies.clear()
    assert c.get("/v1/evaluations", headers={"Authorization": f"Bearer {session}"}).status_code == 401
    r = sign_in(c, ADMIN_TOKEN)
    assert r.status_code == 422 and SESSION_COOKIE not in c.cookies
    c.cookies.clear()


def test_sign_in_sign_out_and_refused_forms_are_in_the_audit_log(service) -> None:
    c, teams = service
    assert sign_in(c, teams.tokens["alice-ro"]).status_code == 303
    session_id = split_token(c.cookies[SESSION_COOKIE])
    csrf = _hidden(c.get("/").text)
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
    r = c.post("/ui/evaluations", data={"gt": "gt-a", "csrf": csrf}, files=files, follow_redirects=False)
    assert r.status_code == 403 and "read-only" in r.text
    assert c.post("/signout", data={"csrf": csrf}, follow_redirects=False).status_code == 303
    c.cookies.clear()
    audit = c.get("/v1/admin/audit", params={"limit": 50}, headers=ADMIN).json()["items"]
    actor = f"alice ({teams.token_ids['alice-ro']})"
    rows = [(r["actor"], r["action"], r["target"], r["outcome"]) for r in audit]
    assert (actor, "session.open", f"session {session_id}", "ok") in rows
    session_actor = f"alice ({session_id})"
    assert (session_actor, "token.forbidden", "POST /ui/evaluations", "refused") in rows
    assert (session_actor, "session.close", f"session {session_id}", "ok") in rows


def test_the_upload_form_offers_a_choice_of_project_only_where_there_is_one(service) -> None:
    c, teams = service
    assert sign_in(c, teams.tokens["root"]).status_code == 303  # an admin: every project
    home = c.get("/").text
    assert re.findall(r'<select name="project">(.*?)</select>', home, re.S)
    assert re.findall(r'<option value="([^"]+)"', home.split('name="project"')[1].split("</select>")[0]) == [
        "team-a",
        "team-b",
    ]
    assert sign_in(c, teams.tokens["bob"]).status_code == 303  # one project: nothing to choose
    assert 'name="project"' not in c.get("/").text
    c.cookies.clear()


def test_ended_sessions_do_not_pile_up(service) -> None:
    c, teams = service
    store = c.app.state.service.store
    assert sign_in(c, teams.tokens["bob"]).status_code == 303
    old = split_token(c.cookies[SESSION_COOKIE])
    two_days_ago = datetime.now(timezone.utc) - timedelta(days=2)
    with store.engine.begin() as conn:  # it ended two days ago
        conn.execute(update(tokens).where(tokens.c.id == old).values(expires_at=two_days_ago))
    assert c.get("/").status_code == 401
    assert store.account_store.get_token(old) is not None
    assert sign_in(c, teams.tokens["bob"]).status_code == 303  # the next sign-in clears it away
    assert store.account_store.get_token(old) is None
    assert store.account_store.get_token(teams.token_ids["bob"]) is not None  # tokens are never purged
    c.cookies.clear()
