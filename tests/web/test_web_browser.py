"""The web pages in a real headless Chromium (Selenium 4) against a real uvicorn.

Needs Debian's ``chromium`` and ``chromedriver`` at /usr/bin; without them the module is skipped, unless
``KITTI_EVAL_BROWSER_TESTS=require``. ``KITTI_EVAL_SCREENSHOTS=1`` saves screenshots to /tmp/kitti-eval-shots.
The tests run in order and share the server and the browser: upload, curves, drag and drop, compare, frames,
the API docs. The browser's only way out is a proxy that refuses every connection, so nothing but the local
server (loopback goes direct) is reachable: a page that needs the internet fails here as it would offline.
"""

from __future__ import annotations

import base64
import gzip
import os
import pickle
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from server_helpers import LiveServer, free_port

from kitti_eval.demo import demo_paths
from kitti_eval.io.safe_pickle import load_pickle

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
SHOTS = Path("/tmp/kitti-eval-shots")
WAIT_S = 30

if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
    missing = ", ".join(str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists())
    if os.environ.get("KITTI_EVAL_BROWSER_TESTS") == "require":
        pytest.fail(
            f"KITTI_EVAL_BROWSER_TESTS=require but {missing} is missing (apt-get install chromium chromium-driver)",
            pytrace=False,
        )
    pytest.skip(f"no browser: {missing} is missing", allow_module_level=True)

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.chrome.service import Service as DriverService  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support import expected_conditions as ec  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

# dispatches a drop event carrying a File built from base64 bytes, as a drag from the desktop would
_DROP_JS = """
const [selector, name, b64] = arguments;
const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
const transfer = new DataTransfer();
transfer.items.add(new File([bytes], name, {type: "application/octet-stream"}));
const zone = document.querySelector(selector);
for (const type of ["dragenter", "dragover", "drop"]) {
  zone.dispatchEvent(new DragEvent(type, {dataTransfer: transfer, bubbles: true, cancelable: true}));
}
const files = document.getElementById("predictions").files;
return files.length ? [files.length, files[0].name, files[0].size] : [0, null, 0];
"""


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("web-live") / "data") as server:
        yield server


@contextmanager
def chromium(profile: Path, *, scripts: bool = True) -> Iterator[Any]:
    """Headless Chromium at a laptop's width, with a profile of its own in ``profile``, kept off the internet (a
    proxy where nothing listens); ``scripts`` False: JavaScript switched off."""
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--disable-quic",
        "--window-size=1280,1600",
        f"--proxy-server=http://127.0.0.1:{free_port()}",  # nothing listens there: the internet is out of reach
        f"--user-data-dir={profile}",
    ):
        options.add_argument(arg)
    if not scripts:
        options.add_experimental_option("prefs", {"profile.managed_default_content_settings.javascript": 2})
    driver = webdriver.Chrome(options=options, service=DriverService(executable_path=str(CHROMEDRIVER)))
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    with chromium(tmp_path_factory.mktemp("chromium-profile")) as driver:
        yield driver


@pytest.fixture(scope="module")
def state() -> dict[str, Any]:
    """What one test leaves for the next (evaluation ids, in upload order)."""
    return {"ids": []}


@pytest.fixture(scope="module")
def perturbed(tmp_path_factory) -> Path:
    """The demo predictions with every third detection dropped and the rest's scores shuffled a little."""
    results = load_pickle(demo_paths()[1], source="demo result.pkl.gz")
    rng = np.random.default_rng(3)
    out = []
    for frame in results:
        n = len(frame["score"])
        keep = np.arange(n) % 3 != 2
        changed = {k: v[keep] if isinstance(v, np.ndarray) and v.ndim and len(v) == n else v for k, v in frame.items()}
        changed["score"] = np.clip(changed["score"] * rng.uniform(0.8, 1.0, keep.sum()), 0, 1).astype(np.float32)
        out.append(changed)
    path = tmp_path_factory.mktemp("perturbed") / "perturbed.pkl.gz"
    path.write_bytes(gzip.compress(pickle.dumps(out, protocol=4)))
    return path


def printed(value: float | None, metric: str, sign: bool = False) -> str:
    """An AP as the CLI's table prints it: AOS with 2 decimals, the others with 4."""
    if value is None:
        return "-"
    return f"{value:{'+' if sign else ''}.{2 if metric == 'aos' else 4}f}"


def wait(driver: Any) -> WebDriverWait:
    return WebDriverWait(driver, WAIT_S)


def shoot(driver: Any, name: str) -> None:
    if os.environ.get("KITTI_EVAL_SCREENSHOTS"):
        SHOTS.mkdir(parents=True, exist_ok=True)
        height = driver.execute_script("return document.documentElement.scrollHeight")
        driver.set_window_size(1280, max(800, min(int(height), 6000)))
        driver.save_screenshot(str(SHOTS / f"{name}.png"))
        driver.set_window_size(1280, 1600)


def submit_upload(driver: Any, gt: str = "demo", protocol: str = "official", model: str | None = None) -> str:
    Select(driver.find_element(By.NAME, "gt")).select_by_value(gt)
    Select(driver.find_element(By.NAME, "protocol")).select_by_value(protocol)
    if model:
        driver.find_element(By.NAME, "model").send_keys(model)
    driver.find_element(By.CSS_SELECTOR, "form.upload button[type=submit]").click()
    wait(driver).until(ec.url_contains("/evaluations/"))
    return driver.current_url.rsplit("/", 1)[-1].split("?")[0]


def check_scores(driver: Any, live: LiveServer, evaluation_id: str) -> None:
    with live.client() as c:
        doc = c.get(f"/v1/evaluations/{evaluation_id}").json()
    cells = driver.find_elements(By.CSS_SELECTOR, "td[data-key]")
    assert len(cells) == 144
    for cell in cells:
        oset, recall, cls, metric, difficulty = cell.get_attribute("data-key").split("/")
        value = doc["ap"][oset][recall][cls][metric][difficulty]
        # textContent: cells inside closed <details> have no rendered text
        assert cell.get_attribute("textContent").strip() == printed(value, metric)


def test_upload_lands_on_the_evaluation_page_with_the_json_values(live, browser, state) -> None:
    browser.get(live.url + "/")
    file_input = browser.find_element(By.ID, "predictions")
    file_input.send_keys(str(demo_paths()[1]))
    assert "result.pkl.gz" in browser.find_element(By.ID, "drop-name").text
    evaluation_id = submit_upload(browser, model="pointpillars")
    state["ids"].append(evaluation_id)
    assert browser.find_element(By.TAG_NAME, "h1").text == "pointpillars"
    check_scores(browser, live, evaluation_id)
    visible = [c for c in browser.find_elements(By.CSS_SELECTOR, "td[data-key]") if c.is_displayed()]
    assert {c.get_attribute("data-key").split("/")[:2] == ["strict", "R40"] for c in visible} == {True}
    assert len(visible) == 36
    shoot(browser, "evaluation")


def test_the_curves_are_drawn(live, browser, state) -> None:
    svgs = [s for s in browser.find_elements(By.CSS_SELECTOR, "svg.pr") if s.is_displayed()]
    assert len(svgs) == 12  # the strict set: 3 classes × 4 metrics; the loose one is folded
    for svg in svgs:
        assert svg.size["width"] > 100 and svg.size["height"] > 100
        lines = svg.find_elements(By.CSS_SELECTOR, "polyline.curve")
        assert sorted(p.get_attribute("data-difficulty") for p in lines) == ["easy", "hard", "moderate"]
        for line in lines:
            points = browser.execute_script("return arguments[0].points.numberOfItems", line)
            assert points == 41
            box = browser.execute_script("const b = arguments[0].getBBox(); return [b.width, b.height]", line)
            assert box[0] > 0  # the line spans some recall


def test_drag_and_drop_fills_the_file_input(live, browser, state, perturbed) -> None:
    browser.get(live.url + "/")
    data = base64.b64encode(perturbed.read_bytes()).decode()
    count, name, size = browser.execute_script(_DROP_JS, "#drop", perturbed.name, data)
    assert (count, name, size) == (1, "perturbed.pkl.gz", perturbed.stat().st_size)
    assert "perturbed.pkl.gz" in browser.find_element(By.ID, "drop-name").text
    evaluation_id = submit_upload(browser, model="perturbed")
    state["ids"].append(evaluation_id)
    check_scores(browser, live, evaluation_id)
    with live.client() as c:
        assert (
            c.get(f"/v1/evaluations/{evaluation_id}").json()["evaluation"]["predictions"]["filename"]
            == "perturbed.pkl.gz"
        )


def test_compare_two_from_the_history(live, browser, state) -> None:
    older, newer = state["ids"]
    browser.get(live.url + "/")
    compare = browser.find_element(By.ID, "compare")
    assert not compare.is_enabled()
    for evaluation_id in (newer, older):  # ticked newest first: the page still makes the older one the base
        browser.find_element(By.CSS_SELECTOR, f"input[type=checkbox][value='{evaluation_id}']").click()
    assert compare.is_enabled()
    compare.click()
    wait(browser).until(ec.url_contains("/compare"))
    assert browser.current_url.endswith(f"/compare?a={older}&b={newer}")
    assert browser.find_elements(By.CSS_SELECTOR, ".delta.pos, .delta.neg")
    with live.client() as c:
        a, b = (c.get(f"/v1/evaluations/{i}").json()["ap"] for i in (older, newer))
    cells = browser.find_elements(By.CSS_SELECTOR, "td.delta[data-key]")
    assert len(cells) == 144
    for cell in cells:
        oset, recall, cls, metric, difficulty = cell.get_attribute("data-key").split("/")
        va, vb = a[oset][recall][cls][metric][difficulty], b[oset][recall][cls][metric][difficulty]
        if va is None or vb is None:
            assert cell.get_attribute("textContent").strip() == "-"
            continue
        assert float(cell.get_attribute("data-value")) == vb - va
        assert cell.get_attribute("textContent").strip() == printed(vb - va, metric, sign=True)
    shoot(browser, "compare")


def test_worst_frames_open_the_frame_view(live, browser, state) -> None:
    older, newer = state["ids"]
    browser.get(f"{live.url}/evaluations/{older}")
    links = browser.find_elements(By.CSS_SELECTOR, "table.frames a")
    assert 0 < len(links) <= 20
    frame = links[0].text
    links[0].click()
    wait(browser).until(ec.url_contains(f"/frames/{frame}"))
    assert browser.find_element(By.TAG_NAME, "h1").text == f"Frame {frame}"
    assert len(browser.find_elements(By.CSS_SELECTOR, "svg.bev")) == 1
    labels = {b.text for b in browser.find_elements(By.CSS_SELECTOR, "table.detections .badge")}
    assert labels and labels <= {"tp", "fp", "ignored", "dontcare", "below threshold", "other class"}
    assert browser.find_elements(By.CSS_SELECTOR, "svg.bev .box.gt, svg.bev .box.gt.missed")

    def colours(selector: str, prop: str) -> set[str]:
        script = "return getComputedStyle(arguments[0])[arguments[1]]"
        return {browser.execute_script(script, e, prop) for e in browser.find_elements(By.CSS_SELECTOR, selector)}

    missed, fp = colours("svg.bev .box.gt.missed polygon", "stroke"), colours("svg.bev .box.fp polygon", "stroke")
    assert len(missed) == len(fp) == 1  # the worst frame has both, each in one colour
    assert missed != fp and missed != colours("svg.bev .box.gt:not(.missed) polygon", "stroke")
    assert missed == colours(".key.missed", "borderTopColor") and fp == colours(".key.fp", "borderTopColor")

    Select(browser.find_element(By.ID, "add-evaluation")).select_by_value(newer)
    browser.find_element(By.CSS_SELECTOR, "form.inline button[type=submit]").click()
    wait(browser).until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "svg.bev")) == 2)
    sections = browser.find_elements(By.CSS_SELECTOR, "section.model")
    assert [s.get_attribute("data-evaluation") for s in sections] == [older, newer]
    for svg in browser.find_elements(By.CSS_SELECTOR, "svg.bev"):
        assert svg.is_displayed() and svg.size["width"] > 100
    shoot(browser, "frame")


def test_frame_input_on_the_history_opens_the_frame_view(live, browser, state) -> None:
    older, newer = state["ids"]
    browser.get(live.url + "/")
    button = browser.find_element(By.ID, "open-frame")
    browser.find_element(By.CSS_SELECTOR, f"input[type=checkbox][value='{older}']").click()
    assert not button.is_enabled()  # no frame yet
    browser.find_element(By.ID, "frame-id").send_keys("000015")
    assert button.is_enabled()
    button.click()
    wait(browser).until(ec.url_contains("/frames/000015"))
    assert browser.current_url.endswith(f"/frames/000015?e={older}")
    assert len(browser.find_elements(By.CSS_SELECTOR, "svg.bev")) == 1


# fetches a URL the way a page's script or stylesheet would (no-cors), saying whether anything answered
_REACH_JS = """
const [url, done] = arguments;
fetch(url, {mode: "no-cors", cache: "no-store"}).then(() => done("reached"), () => done("unreachable"));
"""


def test_the_api_docs_render_without_the_internet(live, browser) -> None:
    browser.get(live.url + "/docs")
    operation = ".opblock .opblock-summary-path[data-path]"
    wait(browser).until(lambda d: d.find_elements(By.CSS_SELECTOR, operation), "Swagger UI shows no operation")
    with live.client() as c:
        documented = set(c.get("/openapi.json").json()["paths"])
    assert {e.get_attribute("data-path") for e in browser.find_elements(By.CSS_SELECTOR, operation)} == documented
    fetched = browser.execute_script("return performance.getEntriesByType('resource').map((e) => e.name)")
    assert fetched and all(url.startswith(live.url + "/") for url in fetched), fetched
    # and the CDN the docs used to load from really is out of reach
    assert browser.execute_async_script(_REACH_JS, "https://cdn.jsdelivr.net/npm/swagger-ui-dist@5/") == "unreachable"
    shoot(browser, "docs")


def test_history_dates_stay_on_one_line_in_a_narrow_window(live, browser, state) -> None:
    browser.get(live.url + "/")
    browser.set_window_size(720, 1200)
    try:
        dates = browser.find_elements(By.CSS_SELECTOR, "table.history td.created a")
        assert len(dates) >= len(state["ids"])
        lines = [browser.execute_script("return arguments[0].getClientRects().length", a) for a in dates]
        assert lines == [1] * len(dates), [a.text for a in dates]
        assert "Moderate 3D AP (R40, strict IoU)" in browser.find_element(By.CSS_SELECTOR, "table.history thead").text
    finally:
        browser.set_window_size(1280, 1600)
    shoot(browser, "history")


def test_the_error_decomposition_is_drawn(live, browser) -> None:
    """Ticking "error decomposition" on the upload form gives a bar chart per class, drawn with the JSON's values."""
    browser.get(live.url + "/")
    browser.find_element(By.ID, "predictions").send_keys(str(demo_paths()[1]))
    browser.find_element(By.CSS_SELECTOR, "input[type=checkbox][name=errors]").click()
    evaluation_id = submit_upload(browser, model="with errors")
    with live.client() as c:
        doc = c.get(f"/v1/evaluations/{evaluation_id}").json()
    svgs = browser.find_elements(By.CSS_SELECTOR, "svg.errors")
    assert len(svgs) == 3
    script = "const b = arguments[0].getBBox(); return [b.x, b.y, b.width, b.height]"
    fills: dict[str, set[str]] = {}
    for svg in svgs:
        assert svg.is_displayed() and svg.size["width"] > 200 and svg.size["height"] > 200
        width = float(svg.get_attribute("width"))
        bars = svg.find_elements(By.CSS_SELECTOR, "g.bar")
        assert len(bars) == 3 * 6 + 7
        for bar in bars:
            cls, metric, kind = bar.get_attribute("data-error").split("/")
            value = doc["errors"][cls][metric]["moderate"][kind]
            text = bar.find_element(By.CSS_SELECTOR, "text.value")
            assert text.text == f"{value:.2f}"
            x, _, w, h = browser.execute_script(script, text)
            assert w > 0 and h > 0 and x + w <= width  # the value is drawn, inside the chart
            rect = bar.find_element(By.CSS_SELECTOR, "rect")
            if value > 0:
                assert browser.execute_script(script, rect)[2] > 0
            fill = browser.execute_script("return getComputedStyle(arguments[0]).fill", rect)
            fills.setdefault(kind, set()).add(fill)
        for label in svg.find_elements(By.CSS_SELECTOR, "text.label"):
            x, _, w, _ = browser.execute_script(script, label)
            assert x >= 0 and x + w <= float(bars[0].find_element(By.CSS_SELECTOR, "rect").get_attribute("x"))
    assert all(len(f) == 1 for f in fills.values())  # one colour a type, a different one for each
    assert len({next(iter(f)) for f in fills.values()}) == len(fills) == 7
    tp = browser.find_elements(By.CSS_SELECTOR, "table.tp-errors td[data-tp]")
    assert len(tp) == 3 * 3 * 3
    for cell in tp:
        cls, difficulty, name = cell.get_attribute("data-tp").split("/")
        assert cell.text == f"{doc['tp_errors'][cls][difficulty][name]:.3f}"
    fetched = browser.execute_script("return performance.getEntriesByType('resource').map((e) => e.name)")
    assert all(url.startswith(live.url + "/") for url in fetched), fetched
    shoot(browser, "errors")
