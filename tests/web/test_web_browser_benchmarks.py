"""A public benchmark's page in a real headless Chromium with JavaScript switched off, against a real uvicorn in
accounts mode, without signing in: the published entry is on the board, the unpublished one is not, and the
column links sort it. Skipped as ``test_web_browser`` is; only run with the slow tests."""

from __future__ import annotations

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import LiveServer, golden_bytes
from test_web_browser import By, chromium

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def no_script_browser(tmp_path_factory):
    with chromium(tmp_path_factory.mktemp("chromium-no-script"), scripts=False) as driver:
        yield driver


def test_the_leaderboard_page_shows_the_published_entry_without_scripts(tmp_path, no_script_browser) -> None:
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = host(c, benchmark={"title": "Demo 3D", "description": "Read the **rules**. <b>not bold</b>"})
            published = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
            ok(submit(c, hosted.headers("bob"), golden_bytes("result.pkl")), 201)
            body = {"method": "Shown-Method", "affiliation": "Lab A", "link": "https://example.org/m"}
            ok(
                c.post(
                    f"/v1/benchmarks/bench/submissions/{published['id']}/publish",
                    headers=hosted.headers("alice"),
                    json=body,
                )
            )
        browser = no_script_browser
        browser.delete_all_cookies()
        browser.get(server.url + "/benchmarks/bench")
        assert browser.find_element(By.ID, "benchmark-title").text == "Demo 3D"
        assert browser.find_element(By.TAG_NAME, "strong").text == "rules"
        assert "<b>not bold</b>" in browser.find_element(By.CLASS_NAME, "description").text  # shown, not obeyed
        rows = browser.find_elements(By.CSS_SELECTOR, "#leaderboard tbody tr")
        assert len(rows) == 1  # bob's submission is not published
        cells = [td.text for td in rows[0].find_elements(By.TAG_NAME, "td")]
        key = round(published["scores"]["Car/3d/moderate/R40/strict"], 4)
        # the method with its participant below it, then the key (two decimals on the board: the intervals, once
        # computed, are shown under it and say what further decimals would be worth)
        assert [cells[0].split("\n")[0], cells[1]] == ["1", "Shown-Method\nalice (Lab A)"] and cells[2].split("\n")[
            0
        ] == f"{key:.2f}"
        assert rows[0].find_element(By.CSS_SELECTOR, "td.method a").get_attribute("href") == "https://example.org/m"
        browser.find_element(By.LINK_TEXT, "Method").click()  # a plain link: sorting needs no script
        assert "sort=method" in browser.current_url
        assert len(browser.find_elements(By.CSS_SELECTOR, "#leaderboard tbody tr")) == 1
