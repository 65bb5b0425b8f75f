"""A participant's path through a benchmark of two phases in a real headless Chromium against a real uvicorn
(accounts mode), the benchmark applied from its file by ``kitti-eval admin benchmark apply``: sign in, find the
phases on the benchmark's page (the current one first), make a team with another participant through the form,
submit to the development phase, go to the test phase, submit and publish there, and find the entry with its team
on the test phase's board. Skipped as ``test_web_browser`` is; only run with the slow tests. With
``KITTI_EVAL_SCREENSHOTS`` set, every page is shot at 1280 and 390 px wide into ``/tmp/kitti-eval-shots``."""

from __future__ import annotations

import pytest
from server_benchmarks import ok
from server_helpers import GOLDEN, LiveServer
from server_phases import TWO_PHASES, phased_world
from test_web_browser import By, browser, ec, wait  # noqa: F401 - the browser fixture
from test_web_browser_participant import _state, shoot_widths

from kitti_eval.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    folder = tmp_path_factory.mktemp("web-phases")
    with LiveServer(folder / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = phased_world(c)
        path = folder / "kitti-phases.toml"
        path.write_text(
            TWO_PHASES.replace(
                'title = "KITTI 3D, two phases"',
                'title = "KITTI 3D, two phases"\ndescription = "A **dev** phase on open labels, then the sealed test."',
            )
        )
        assert main(["admin", "--data-dir", str(server.data_dir), "benchmark", "apply", str(path)]) == 0
        yield server, hosted


def _sign_in(driver, server, token: str) -> None:
    driver.delete_all_cookies()
    driver.get(server.url + "/signin")
    driver.find_element(By.ID, "token").send_keys(token)
    driver.find_element(By.ID, "sign-in").click()
    wait(driver).until(ec.presence_of_element_located((By.ID, "sign-out")))


def _phase_items(driver) -> list[str]:
    return [li.get_attribute("id") for li in driver.find_elements(By.CSS_SELECTOR, "#phases li")]


def _submit_file(driver) -> str:
    driver.find_element(By.ID, "predictions").send_keys(str(GOLDEN / "result.pkl"))
    driver.find_element(By.ID, "submit").click()
    wait(driver).until(ec.url_contains("/benchmarks/kitti-phases/submissions/"))
    wait(driver).until(lambda d: _state(d) == "scored")
    return driver.current_url.rsplit("/", 1)[1]


def test_a_participant_goes_through_a_team_and_both_phases_in_the_browser(live, browser) -> None:  # noqa: F811
    server, hosted = live
    _sign_in(browser, server, hosted.tokens["alice"])
    browser.find_element(By.LINK_TEXT, "Benchmarks").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "benchmarks")))
    shoot_widths(browser, "phases-list")
    browser.find_element(By.LINK_TEXT, "KITTI 3D, two phases").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "phases")))
    assert _phase_items(browser) == ["phase-dev", "phase-test"]
    assert browser.find_element(By.ID, "phase-shown").text == "dev phase"
    assert "current" in browser.find_element(By.ID, "phase-dev").text
    shoot_widths(browser, "phases-benchmark")

    browser.find_element(By.ID, "team-name-input").send_keys("Two")
    browser.find_element(By.ID, "team-members").send_keys("bob")
    browser.find_element(By.ID, "make-team").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "team-name")))
    assert browser.find_element(By.ID, "team-name").text.startswith("You are in Two: alice.")
    assert browser.find_element(By.ID, "team-invited").text == "Invited, not joined yet: bob."
    shoot_widths(browser, "phases-team")
    _sign_in(browser, server, hosted.tokens["bob"])  # bob finds the invitation and accepts it
    browser.get(server.url + "/benchmarks/kitti-phases")
    shoot_widths(browser, "phases-invitation")
    browser.find_element(By.CSS_SELECTOR, 'button.join-team[data-team="Two"]').click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "team-name")))
    assert browser.find_element(By.ID, "team-name").text.startswith("You are in Two: alice, bob.")
    _sign_in(browser, server, hosted.tokens["alice"])
    browser.get(server.url + "/benchmarks/kitti-phases")
    assert browser.find_element(By.ID, "team-name").text.startswith("You are in Two: alice, bob.")

    dev = _submit_file(browser)
    shoot_widths(browser, "phases-dev-submission")
    with server.client() as c:
        mine = ok(c.get("/v1/benchmarks/kitti-phases/phases/dev/submissions", headers=hosted.headers("alice")))
    assert [s["id"] for s in mine["items"]] == [dev]

    browser.get(server.url + "/benchmarks/kitti-phases")
    browser.find_element(By.CSS_SELECTOR, "#phase-test a").click()
    wait(browser).until(ec.text_to_be_present_in_element((By.ID, "phase-shown"), "test phase"))
    assert browser.find_element(By.ID, "quota-left").text.startswith("2 of 2 submissions left")
    test = _submit_file(browser)
    browser.find_element(By.ID, "method").send_keys("Team-Net")
    browser.find_element(By.ID, "publish").click()
    wait(browser).until(ec.url_contains(f"#entry-{test}"))
    assert browser.find_element(By.ID, "phase-shown").text == "test phase"
    entry = browser.find_element(By.ID, f"entry-{test}")
    assert entry.find_element(By.CSS_SELECTOR, "td.method").text == "Team-Net\nTwo: alice"
    assert browser.find_element(By.ID, "quota-left").text.startswith("1 of 2 submissions left")
    shoot_widths(browser, "phases-test-board")
    # bob, in the team, has what is left of the team's quota
    with server.client() as c:
        bobs = ok(c.get("/v1/benchmarks/kitti-phases/phases/test/submissions", headers=hosted.headers("bob")))
    assert bobs["quota"]["left"] == 1
