"""The benchmark's pages say each phase's state in its own words: "opens DATE" before it opens, "open; closes
DATE", "closed on DATE" and which phase takes submissions now, the final ranking once revealed; a phase on open
labels speaks of its validation set, a sealed one of its test set."""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone
from html import unescape

import pytest
from server_helpers import ADMIN, app_client, golden_bytes, golden_txt, zip_of
from server_phases import HOST, TWO_PHASES, phased_world
from test_web_benchmarks import until_scored

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file
from kitti_eval_server.web.boards import full_time

DAY = timedelta(days=1)
TEST_ROW = "kitti-phases~test"


def _when(delta: timedelta) -> datetime:
    return (datetime.now(timezone.utc) + delta).replace(microsecond=0)


def _file(dev: tuple[datetime, datetime], test: tuple[datetime, datetime]) -> str:
    text = TWO_PHASES.replace(
        'quota = "5/1"', f'quota = "5/1"\nopens_at = {dev[0].isoformat()}\ncloses_at = {dev[1].isoformat()}'
    )
    return text.replace(
        'quota = "2/1"', f'quota = "2/1"\nopens_at = {test[0].isoformat()}\ncloses_at = {test[1].isoformat()}'
    )


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        yield c, phased_world(c)


def _sign_in(c, token: str) -> None:
    c.cookies.clear()
    form = c.get("/signin")
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text).group(1)
    assert c.post("/signin", data={"token": token, "csrf": csrf}, follow_redirects=False).status_code == 303


def _text(html: str, element_id: str) -> str:
    found = re.search(rf'id="{element_id}"[^>]*>(.*?)</(dd|p|span)>', html, re.S)
    assert found is not None, element_id
    return " ".join(unescape(re.sub(r"<[^>]+>", "", found.group(1))).split())


def _phase_state(html: str, phase: str) -> str:
    found = re.search(rf'id="phase-{phase}">.*?<span class="state">(.*?)</span>', html, re.S)
    assert found is not None
    return unescape(found.group(1))


def _page(c, phase: str) -> str:
    page = c.get("/benchmarks/kitti-phases", params={"phase": phase})
    assert page.status_code == 200
    return page.text


def test_the_benchmark_page_says_each_state_in_its_words(world) -> None:
    c, hosted = world
    catalog = c.app.state.benchmarks.catalog
    _sign_in(c, hosted.tokens["alice"])
    # the test phase is scheduled, the dev phase open
    dev, test = (_when(-DAY), _when(10 * DAY)), (_when(20 * DAY), _when(40 * DAY))
    apply_benchmark_file(catalog, _file(dev, test), caller=HOST)
    page = _page(c, "test")
    opens, closes = full_time(test[0].isoformat()), full_time(test[1].isoformat())
    assert _text(page, "period") == f"opens {opens}; closes {closes}; the dev phase takes submissions now"
    assert _phase_state(page, "test") == f"opens {opens}; closes {closes}"
    assert "closed" not in _text(page, "period")  # a phase that has not opened is not called closed
    assert (
        _text(page, "no-submissions")
        == f"The test phase takes submissions once it opens (opens {opens}; closes {closes})."
    )
    assert "Test set" in page and "Validation set" not in page
    dev_page = _page(c, "dev")
    assert _text(dev_page, "period") == f"open; closes {full_time(dev[1].isoformat())}"
    assert "Validation set" in dev_page and "open labels, your whole result is shown" in dev_page
    assert 'id="no-submissions"' not in dev_page
    # the dev phase closed by its date, the test phase open
    dev, test = (_when(-3 * DAY), _when(-2 * DAY)), (_when(-DAY), _when(30 * DAY))
    apply_benchmark_file(catalog, _file(dev, test), caller=HOST)
    dev_page = _page(c, "dev")
    ended = full_time(dev[1].isoformat())
    assert _text(dev_page, "period") == f"closed on {ended}; the test phase takes submissions now"
    assert _text(dev_page, "no-submissions") == (
        f"The dev phase takes no submissions now (closed on {ended}): the test phase does."
    )
    assert _phase_state(dev_page, "test") == f"open; closes {full_time(test[1].isoformat())}"
    # the test phase closed by its date, then revealed
    test = (_when(-DAY), _when(-DAY / 2))
    apply_benchmark_file(catalog, _file(dev, test), caller=HOST)
    page = _page(c, "test")
    assert _text(page, "period") == f"closed on {full_time(test[1].isoformat())}"
    assert _text(page, "no-submissions").startswith("The test phase takes no submissions now (closed on")
    assert c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN).status_code == 200
    page = _page(c, "test")
    assert _text(page, "period") == f"closed on {full_time(test[1].isoformat())}; final ranking"
    assert _phase_state(page, "test").endswith("; final ranking")


def test_a_signed_out_reader_reads_no_dangling_parenthesis(world) -> None:
    c, _ = world
    apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST)
    dev, test = _page(c, "dev"), _page(c, "test")
    assert _text(dev, "labels") == "open labels, your whole result is shown; protocol official"
    assert _text(test, "labels") == "sealed; protocol official"
    assert "(open labels" not in dev and "(sealed)" not in test
    listed = c.get("/benchmarks").text
    assert "the board shows the whole validation set" in listed  # the current phase, dev, is on open labels


def test_a_submissions_page_names_its_phase_and_links_a_validation_sets_frames(world) -> None:
    c, hosted = world
    apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST)
    alice = {"Authorization": f"Bearer {hosted.tokens['alice']}"}
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    ids = {}
    for phase in ("dev", "test"):
        sent = c.post(f"/v1/benchmarks/kitti-phases/phases/{phase}/submissions", files=files, headers=alice)
        assert sent.status_code == 201, sent.text[:500]
        ids[phase] = sent.json()["id"]
    _sign_in(c, hosted.tokens["alice"])
    dev = until_scored(c, f"/benchmarks/kitti-phases/submissions/{ids['dev']}")
    assert _text(dev, "phase") == "dev on its validation set"
    link = re.search(r'<p id="frames-link">.*?<a href="([^"]+)"', dev, re.S)
    assert link is not None and link.group(1) == f"/v1/benchmarks/kitti-phases/submissions/{ids['dev']}/frames"
    assert c.get(link.group(1), headers=alice).status_code == 200
    test = until_scored(c, f"/benchmarks/kitti-phases/submissions/{ids['test']}")
    assert _text(test, "phase") == "test" and 'id="frames-link"' not in test  # a sealed phase's frames stay hidden


def test_a_phase_on_open_labels_calls_its_frames_a_validation_set(world) -> None:
    c, hosted = world
    apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST)
    alice = {"Authorization": f"Bearer {hosted.tokens['alice']}"}
    txt = golden_txt("pred.tar.gz")
    broken = zip_of(dict(list(txt.items())[1:]))  # one frame missing
    said = {}
    for phase in ("dev", "test"):
        files = {"predictions": ("broken.zip", broken, "application/zip")}
        sent = c.post(f"/v1/benchmarks/kitti-phases/phases/{phase}/submissions", files=files, headers=alice)
        assert sent.status_code == 422
        said[phase] = sent.json()["error"]["problems"][0]
        frames = c.get(f"/v1/benchmarks/kitti-phases/phases/{phase}/frames").json()
        assert frames["labels"] == ("validation" if phase == "dev" else "test")
    assert said == {"dev": "1 validation frames are missing: 000000", "test": "1 test frames are missing: 000000"}
