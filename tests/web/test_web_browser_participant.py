"""A participant's whole path in a real headless Chromium against a real uvicorn in accounts mode, without
typing a command: sign in, open the benchmark from the list, upload through the form (its progress bar), wait
on the submission's page while it reloads itself until scored, publish, and find the entry on the board next to
another participant's and an admin's baseline. Skipped as ``test_web_browser`` is; only run with the slow
tests. With ``KITTI_EVAL_SCREENSHOTS`` set, every page is shot at 1280 and 390 px wide into
``/tmp/kitti-eval-shots``."""

from __future__ import annotations

import os
from typing import Any

import pytest
from selenium.common.exceptions import StaleElementReferenceException
from server_benchmarks import host, ok, submit
from server_helpers import GOLDEN, LiveServer, golden_bytes, golden_txt, zip_of
from test_web_browser import SHOTS, By, browser, ec, wait  # noqa: F401 - the browser fixture

pytestmark = pytest.mark.slow

WIDTHS = (1280, 390)


def shoot_widths(driver: Any, name: str) -> None:
    """The page at a laptop's and a phone's width (a phone's viewport: its meta viewport is obeyed)."""
    if not os.environ.get("KITTI_EVAL_SCREENSHOTS"):
        return
    SHOTS.mkdir(parents=True, exist_ok=True)
    for width in WIDTHS:
        metrics = {"width": width, "height": 800, "deviceScaleFactor": 1, "mobile": width < 600}
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
        height = driver.execute_script("return document.documentElement.scrollHeight")
        metrics["height"] = max(600, min(int(height), 4000))
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
        driver.save_screenshot(str(SHOTS / f"{name}-{width}.png"))
    driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def _state(driver: Any) -> str | None:
    """The submission page's state; None while the page is being reloaded."""
    try:
        return driver.find_element(By.ID, "state").get_attribute("data-state")
    except (StaleElementReferenceException, Exception):  # noqa: BLE001 - between two loads of the page
        return None


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("web-participant") / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = host(
                c,
                users=("alice", "bob", "carol"),
                benchmark={
                    "title": "KITTI 3D, golden test set",
                    "description": "Ranked by **Car 3D AP**, moderate, R40. Submit a `result.pkl` or a zip of txt.",
                    "closes_at": "2099-12-31T23:59:00+00:00",
                },
            )
            txt = golden_txt("pred.tar.gz")
            for who, method, dropped in (
                ("bob", "PointPillars (ours)", 2),
                ("carol", "VoxelNet-small", 4),
                ("root", "SECOND baseline", None),
            ):
                if dropped is None:
                    data, filename = golden_bytes("result.pkl"), "result.pkl"
                else:  # every n-th frame without detections: a lower score
                    files = {n: b"" if i % dropped == 0 else v for i, (n, v) in enumerate(txt.items())}
                    data, filename = zip_of(files), "results.zip"
                sid = ok(submit(c, hosted.headers(who), data, filename), 201)["id"]
                body = {"method": method, "affiliation": {"bob": "Lab B", "carol": "Lab C"}.get(who)}
                ok(c.post(f"/v1/benchmarks/bench/submissions/{sid}/publish", json=body, headers=hosted.headers(who)))
        yield server, hosted


def test_a_participant_goes_from_sign_in_to_a_published_entry_in_the_browser(live, browser) -> None:  # noqa: F811
    server, hosted = live
    browser.delete_all_cookies()
    browser.get(server.url + "/")
    assert browser.find_element(By.TAG_NAME, "h1").text == "Sign in"
    assert not browser.find_elements(By.CSS_SELECTOR, ".error")  # a first visit is not an error
    shoot_widths(browser, "signin")
    browser.find_element(By.ID, "token").send_keys(hosted.tokens["alice"])
    browser.find_element(By.ID, "sign-in").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "sign-out")))

    browser.find_element(By.LINK_TEXT, "Benchmarks").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "benchmarks")))
    row = browser.find_element(By.CSS_SELECTOR, '#benchmarks article[data-name="bench"]')
    assert row.find_element(By.CSS_SELECTOR, ".left").text == "3 of 3 submissions left"
    shoot_widths(browser, "benchmarks")
    row.find_element(By.LINK_TEXT, "KITTI 3D, golden test set").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "quota-left")))
    assert browser.find_element(By.ID, "quota-left").text.startswith("3 of 3 submissions left")
    shoot_widths(browser, "benchmark-before")

    browser.find_element(By.ID, "predictions").send_keys(str(GOLDEN / "result.pkl"))
    browser.find_element(By.ID, "submit").click()
    wait(browser).until(ec.url_contains("/benchmarks/bench/submissions/"))
    sid = browser.current_url.rsplit("/", 1)[1]
    wait(browser).until(lambda d: _state(d) == "scored")  # the page reloads itself until then
    shoot_widths(browser, "submission-scored")
    with server.client() as c:
        api = ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=hosted.headers("alice")))
    key = api["scores"]["Car/3d/moderate/R40/strict"]
    assert browser.find_element(By.ID, "key-value").text == f"{key:.2f}"

    browser.find_element(By.ID, "method").send_keys("Browser-Net")
    browser.find_element(By.NAME, "affiliation").send_keys("Lab A")
    browser.find_element(By.ID, "publish").click()
    wait(browser).until(ec.url_contains(f"#entry-{sid}"))
    entry = browser.find_element(By.ID, f"entry-{sid}")
    cells = [td.text for td in entry.find_elements(By.TAG_NAME, "td")]
    assert cells[1] == "Browser-Net\nalice (Lab A)" and cells[2].startswith(f"{key:.2f}")
    methods = [
        r.find_element(By.CSS_SELECTOR, "td.method").text.split("\n")[0]
        for r in browser.find_elements(By.CSS_SELECTOR, "#leaderboard tbody tr")
    ]
    assert methods == ["SECOND baseline", "Browser-Net", "VoxelNet-small", "PointPillars (ours)"]  # by the key
    ranks = {
        r.find_element(By.CSS_SELECTOR, "td.method").text.split("\n")[0]: r.find_element(
            By.CSS_SELECTOR, "td.rank"
        ).text.split("\n")[0]  # the rank, above its range over the resamples
        for r in browser.find_elements(By.CSS_SELECTOR, "#leaderboard tbody tr")
    }
    assert ranks == {
        "SECOND baseline": "baseline",
        "Browser-Net": "1",
        "VoxelNet-small": "2",
        "PointPillars (ours)": "3",
    }
    assert browser.find_element(By.ID, "quota-left").text.startswith("2 of 3 submissions left")
    shoot_widths(browser, "benchmark-after")
    if os.environ.get("KITTI_EVAL_SCREENSHOTS"):  # the board alone, as a visitor sees it (docs/images/leaderboard.png)
        browser.delete_all_cookies()
        browser.get(server.url + "/benchmarks/bench")
        metrics = {"width": 1280, "height": 900, "deviceScaleFactor": 1, "mobile": False}
        browser.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
        browser.find_element(By.ID, "board").screenshot(str(SHOTS / "leaderboard.png"))
        browser.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def test_a_refused_file_in_the_browser_shows_the_sentences_in_place(live, browser, tmp_path) -> None:  # noqa: F811
    """Through the progress bar's request: the page the service answers (422) replaces the form's, with the
    validator's sentences; the quota is whole."""
    server, hosted = live
    browser.delete_all_cookies()
    browser.get(server.url + "/signin")
    browser.find_element(By.ID, "token").send_keys(hosted.tokens["bob"])
    browser.find_element(By.ID, "sign-in").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "sign-out")))
    browser.get(server.url + "/benchmarks/bench")
    left = browser.find_element(By.ID, "quota-left").text
    broken = tmp_path / "broken.zip"
    import zipfile

    with zipfile.ZipFile(broken, "w") as z:
        z.writestr("000000.txt", "Car 0 0 0 1 2 3\n")
    browser.find_element(By.ID, "predictions").send_keys(str(broken))
    browser.find_element(By.ID, "submit").click()
    wait(browser).until(ec.presence_of_element_located((By.ID, "problems")))
    items = [li.text for li in browser.find_elements(By.CSS_SELECTOR, "#problems li")]
    assert any("test frames are missing" in i for i in items), items
    assert browser.find_element(By.ID, "quota-left").text == left
    assert browser.find_element(By.ID, "submit").is_enabled()  # the form is there again, ready
    shoot_widths(browser, "benchmark-refused")
