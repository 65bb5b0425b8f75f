"""Joining a benchmark through its invitation's page in a real headless Chromium against a real uvicorn: the host
makes the link with ``kitti-eval admin invite add``, the invited person chooses a name, lands signed in, copies the
token shown once, and goes on to the benchmark. Skipped as ``test_web_browser`` is (its browser fixture is
reused), and only run with the slow tests."""

from __future__ import annotations

import pytest
from server_accounts import bearer, make_teams
from server_helpers import ADMIN, LiveServer
from test_web_browser import By, browser, ec, shoot, wait  # noqa: F401 - the browser fixture

from kitti_eval.cli import main
from kitti_eval_server.access.auth import SESSION_COOKIE

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data = tmp_path_factory.mktemp("web-join-live") / "data"
    with LiveServer(data, auth="accounts") as server:
        with server.client() as c:
            make_teams(c)
            body = {"name": "bench", "ground_truth": "sealed-a", "title": "The class benchmark"}
            assert c.post("/v1/benchmarks", json=body, headers=ADMIN).status_code == 201
        yield server


def _invite(server, capsys, *argv: str) -> str:
    code = main(["admin", "--data-dir", str(server.data_dir), "invite", "add", "--benchmark", "bench", *argv])
    out = capsys.readouterr().out
    assert code == 0, out
    return out.splitlines()[-1]


def test_join_through_the_page_and_land_signed_in_on_the_benchmark(live, browser, capsys) -> None:  # noqa: F811
    link = _invite(live, capsys, "--uses", "1")
    assert link.startswith("/join/")
    browser.delete_all_cookies()
    browser.get(live.url + link)
    assert browser.find_element(By.TAG_NAME, "h1").text == "Join bench"
    shoot(browser, "join")
    browser.find_element(By.ID, "name").send_keys("alice")  # taken: the form again, with why
    browser.find_element(By.ID, "join").click()
    wait(browser).until(ec.presence_of_element_located((By.CSS_SELECTOR, "p.error")))
    assert "taken" in browser.find_element(By.CSS_SELECTOR, "p.error").text
    field = browser.find_element(By.ID, "name")
    field.clear()
    field.send_keys("maya")
    browser.find_element(By.ID, "join").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "token")))
    shoot(browser, "joined")
    assert browser.find_element(By.ID, "who").text == "maya"  # signed in
    token = browser.find_element(By.ID, "token").text
    assert token.startswith("kte_")
    assert browser.find_element(By.ID, "login-command").text == f"kitti-eval login --service {live.url}"
    browser.find_element(By.ID, "copy-token").click()
    wait(browser).until(lambda d: d.find_element(By.ID, "copy-note").text)
    assert browser.find_element(By.ID, "copy-note").text in ("Copied.", "Selected: copy it with Ctrl+C.")
    session = {c["name"]: c for c in browser.get_cookies()}[SESSION_COOKIE]
    assert session["httpOnly"] is True and session["value"] != token
    browser.find_element(By.ID, "to-benchmark").click()
    wait(browser).until(ec.url_contains("/benchmarks/bench"))
    assert "The class benchmark" in browser.find_element(By.TAG_NAME, "h1").text
    assert browser.find_element(By.ID, "who").text == "maya"
    assert browser.find_elements(By.CSS_SELECTOR, "form.submission")  # may take part: the form to submit
    with live.client() as c:
        assert c.get("/v1/me", headers=bearer(token)).json()["user"] == "maya"
    # the link was for one account: used up now
    browser.delete_all_cookies()
    browser.get(live.url + link)
    assert "used up, expired or revoked" in browser.page_source
