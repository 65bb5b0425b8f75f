"""Accounts mode in a real headless Chromium against a real uvicorn: sign in with a token, see only your
project's history, upload through the form (its CSRF token), sign out. Skipped as ``test_web_browser`` is
(its browser fixture is reused), and only run with the slow tests."""

from __future__ import annotations

import pytest
from server_accounts import make_teams
from server_helpers import ADMIN, LiveServer
from test_web_browser import By, browser, ec, submit_upload, wait  # noqa: F401 - the browser fixture

from kitti_eval.demo import demo_paths
from kitti_eval_server.access.auth import SESSION_COOKIE

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("web-accounts-live") / "data", auth="accounts") as server:
        with server.client() as c:
            teams = make_teams(c)
        yield server, teams


def test_sign_in_see_only_your_projects_history_and_sign_out(live, browser) -> None:  # noqa: F811
    server, teams = live
    browser.delete_all_cookies()
    browser.get(server.url + "/")
    assert browser.find_element(By.TAG_NAME, "h1").text == "Sign in"  # answered 401 with the sign-in form
    assert "model-of" not in browser.page_source

    browser.find_element(By.ID, "token").send_keys(teams.tokens["bob"])
    browser.find_element(By.ID, "sign-in").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "sign-out")))
    assert browser.find_element(By.ID, "who").text == "bob"
    history = browser.find_element(By.CSS_SELECTOR, "table.history").text
    assert "model-of-bob-on-gt-b" in history and "model-of-alice" not in history
    cookies = {c["name"]: c for c in browser.get_cookies()}
    session = cookies[SESSION_COOKIE]
    assert session["httpOnly"] is True and session["sameSite"] == "Strict"
    assert session["value"] != teams.tokens["bob"]
    assert SESSION_COOKIE not in browser.execute_script("return document.cookie")  # out of scripts' reach
    options = [o.get_attribute("value") for o in browser.find_elements(By.CSS_SELECTOR, "select[name=gt] option")]
    assert sorted(options) == ["demo", "gt-b"]

    browser.find_element(By.ID, "predictions").send_keys(str(demo_paths()[1]))
    evaluation_id = submit_upload(browser, gt="demo", model="bob-in-the-browser")
    assert browser.find_element(By.TAG_NAME, "h1").text == "bob-in-the-browser"
    with server.client() as c:
        made = c.get(f"/v1/evaluations/{evaluation_id}", headers=ADMIN).json()
        assert made["evaluation"]["project"] == "team-b"
        alice = c.get(f"/v1/evaluations/{evaluation_id}", headers=teams.headers("alice"))
        assert alice.status_code == 404

    browser.find_element(By.ID, "sign-out").click()
    wait(browser).until(ec.url_contains("/signin"))
    assert SESSION_COOKIE not in {c["name"] for c in browser.get_cookies()}
    browser.get(server.url + "/")
    assert browser.find_element(By.TAG_NAME, "h1").text == "Sign in"
    assert "model-of-bob" not in browser.page_source
    with server.client(cookies={SESSION_COOKIE: session["value"]}) as c:  # ended on the server too, not only
        assert c.get("/").status_code == 401  # forgotten by the browser
