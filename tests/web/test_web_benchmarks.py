"""The benchmark pages in process (accounts mode): a participant's path through forms only (the list, the
benchmark with their quota, the submission form, the submission's page while it is scored, publishing and
withdrawing), a refused file's sentences, the CSRF token on every new form, the admins' baselines (on the
board without a rank, under no quota), the board's grouped header and the intervals it renders when the board
has them, and the calm first visit to ``/``."""

from __future__ import annotations

import re
import time
from datetime import datetime
from typing import Any

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, GOLDEN, app_client, golden_bytes, golden_txt, zip_of

from kitti_eval.io.loaders import load_ground_truth
from kitti_eval.io.submission import SubmissionRules, validate_submission
from kitti_eval_server.web.boards import board_entries, board_header, bootstrap_line, comparison_rows

KEY = "Car/3d/moderate/R40/strict"


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        yield c, host(c)


def _hidden(html: str, name: str = "csrf") -> str:
    found = re.search(rf'name="{name}" value="([^"]+)"', html)
    assert found, html[:2000]
    return found.group(1)


def sign_in(c, token: str) -> str:
    """A web session for ``token``; returns its CSRF token (as the pages' forms hold it)."""
    c.cookies.clear()
    form = c.get("/signin")
    r = c.post("/signin", data={"token": token, "csrf": _hidden(form.text)}, follow_redirects=False)
    assert r.status_code == 303, r.text
    return _hidden(c.get("/benchmarks/bench").text)


def form_submit(c, data: bytes, filename: str = "result.pkl", csrf: str | None = None) -> Any:
    fields = {} if csrf is None else {"csrf": csrf}
    files = {"predictions": (filename, data, "application/octet-stream")}
    return c.post("/benchmarks/bench/submissions", data=fields, files=files, follow_redirects=False)


def until_scored(c, url: str, timeout_s: float = 120.0) -> str:
    """The submission's page once it says scored (while it does not, it reloads itself)."""
    deadline = time.monotonic() + timeout_s
    while True:
        page = c.get(url)
        assert page.status_code == 200, page.text[:1000]
        if 'data-state="scored"' in page.text:
            assert 'http-equiv="refresh"' not in page.text
            return page.text
        assert 'http-equiv="refresh"' in page.text and re.search(r'data-state="(queued|running)"', page.text)
        assert time.monotonic() < deadline, page.text[:2000]
        time.sleep(0.1)


def test_a_participant_goes_from_the_list_to_a_published_entry_through_forms(world) -> None:
    c, hosted = world
    csrf = sign_in(c, hosted.tokens["alice"])
    listed = c.get("/benchmarks")
    assert listed.status_code == 200
    row = re.search(r'<article class="bench-card" data-name="bench">(.*?)</article>', listed.text, re.S)
    assert row and "3 submissions per 1 day" in row.group(1)
    assert "Car 3D moderate (R40, strict IoU)" in row.group(
        1
    ) and "<strong>3 of 3</strong> submissions left" in row.group(1)
    page = c.get("/benchmarks/bench").text
    assert 'id="quota-left"' in page and "<strong>3</strong> of 3 submissions left" in page
    assert 'action="/benchmarks/bench/submissions"' in page

    r = form_submit(c, golden_bytes("result.pkl"), csrf=csrf)
    assert r.status_code == 303, r.text[:2000]
    url = r.headers["location"]
    sid = url.rsplit("/", 1)[1]
    assert url == f"/benchmarks/bench/submissions/{sid}"
    scored = until_scored(c, url)
    api = ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=hosted.headers("alice")))
    key = re.search(r'id="key-value">([^<]+)<', scored)
    assert key and key.group(1) == f"{api['scores'][KEY]:.2f}"
    assert f'data-column="{KEY}" data-value="{api["scores"][KEY]!r}"' in scored
    assert 'id="publish-form"' in scored
    assert ("comparison" in api) == ('id="comparison"' in scored)
    assert "<strong>2</strong> of 3 submissions left" in c.get("/benchmarks/bench").text

    form = {"method": "Form-Method", "affiliation": "Lab F", "link": "https://example.org/f"}
    r = c.post(f"{url}/publish", data={**form, "csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/benchmarks/bench#entry-{sid}"
    board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
    assert [(e["id"], e["method"], e["rank"], e["baseline"]) for e in board["entries"]] == [
        (sid, "Form-Method", 1, False)
    ]
    page = c.get("/benchmarks/bench").text
    entry = re.search(rf'<tr class="entry[^"]*" id="entry-{sid}">(.*?)</tr>', page, re.S)
    assert entry and "Form-Method" in entry.group(1) and "alice (Lab F)" in entry.group(1)

    r = c.post(f"{url}/withdraw", data={"csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == url
    assert ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"] == []
    assert 'id="publish-form"' in c.get(url).text
    c.cookies.clear()


def test_with_no_submission_left_the_form_is_disabled_and_says_when_the_next_is_accepted(tmp_path) -> None:
    """The Submit button stayed active at 0 left and the post got 429: now the form is disabled and names the
    time the next submission is accepted (the time a 429 would give)."""
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"quota": "1/1"})
        csrf = sign_in(c, hosted.tokens["alice"])
        page = c.get("/benchmarks/bench").text
        assert 'id="next-slot"' not in page and re.search(r'<button type="submit" id="submit">', page)
        assert form_submit(c, golden_bytes("result.pkl"), csrf=csrf).status_code == 303
        page = c.get("/benchmarks/bench").text
        assert "<strong>0</strong> of 1 submissions left" in page
        assert re.search(r'<button type="submit" id="submit" disabled>', page)
        assert re.search(r'<input type="file" name="predictions" id="predictions" required disabled>', page)
        refused = submit(c, hosted.headers("alice"), golden_bytes("result.pkl"))
        assert refused.status_code == 429
        retry_at = datetime.fromisoformat(refused.json()["error"]["retry_at"])
        slot = re.search(
            r'id="next-slot">No submission left: the next one is accepted from\s+<strong>([^<]+)</strong>', page
        )
        assert slot and slot.group(1) == f"{retry_at:%Y-%m-%d %H:%M:%S} UTC"
        c.cookies.clear()


def test_a_refused_file_shows_the_validators_sentences_and_costs_nothing(world, tmp_path) -> None:
    c, hosted = world
    csrf = sign_in(c, hosted.tokens["alice"])
    txt = golden_txt("pred.tar.gz")
    broken = dict(list(txt.items())[2:])  # two test frames missing
    first = next(iter(broken))
    broken[first] = b"Car 0 0 0 1 2 3\n"  # too few fields
    data = zip_of(broken)
    r = form_submit(c, data, "broken.zip", csrf=csrf)
    assert r.status_code == 422, r.text[:2000]
    path = tmp_path / "broken.zip"
    path.write_bytes(data)
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    expected = validate_submission(path, SubmissionRules(frames=tuple(gt.frame_ids))).lines()
    problems = re.search(r'<div class="error" role="alert" id="problems">(.*?)</div>', r.text, re.S)
    assert problems, r.text[:3000]
    shown = [
        re.sub(r"&#3[49];", lambda m: {"&#34;": '"', "&#39;": "'"}[m.group(0)], li)
        for li in re.findall(r"<li>(.*?)</li>", problems.group(1))
    ]
    assert shown == expected and len(expected) == 2 and "2 test frames are missing: 000000, 000001" in shown
    assert "does not count against your quota" in problems.group(1)
    assert "<strong>3</strong> of 3 submissions left" in r.text  # the page said it and the quota agrees
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))
    assert mine["items"] == [] and mine["quota"]["used"] == 0
    # a file that is not a submission at all (unreadable): the message, and nothing counted either
    r = form_submit(c, b"not a pickle or an archive", "x.pkl", csrf=csrf)
    assert 400 <= r.status_code < 500 and 'id="submit-error"' in r.text
    assert ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))["quota"]["used"] == 0
    c.cookies.clear()


def test_the_new_forms_need_the_sessions_csrf_token(world) -> None:
    c, hosted = world
    sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    csrf = sign_in(c, hosted.tokens["alice"])
    for sent in (None, "0" * 43):
        r = form_submit(c, golden_bytes("result.pkl"), csrf=sent)
        assert r.status_code == 403 and "CSRF" in r.text
        for action in ("publish", "withdraw"):
            data = {"method": "Forged"} if sent is None else {"method": "Forged", "csrf": sent}
            r = c.post(f"/benchmarks/bench/submissions/{sid}/{action}", data=data, follow_redirects=False)
            assert r.status_code == 403 and "CSRF" in r.text, (action, sent)
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))
    assert [i["id"] for i in mine["items"]] == [sid] and mine["quota"]["used"] == 1  # nothing more was counted
    assert ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"] == []  # nor published
    r = c.post(f"/benchmarks/bench/submissions/{sid}/publish", data={"method": "M", "csrf": csrf})
    assert r.status_code == 200 and [e["method"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]] == [
        "M"
    ]
    c.cookies.clear()
    # another participant's submission is as absent as a missing one, on the page and to the forms
    bob = sign_in(c, hosted.tokens["bob"])
    assert c.get(f"/benchmarks/bench/submissions/{sid}").status_code == 404
    r = c.post(f"/benchmarks/bench/submissions/{sid}/withdraw", data={"csrf": bob}, follow_redirects=False)
    assert r.status_code == 404
    assert len(ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]) == 1
    c.cookies.clear()


def test_an_admins_baseline_is_on_the_board_without_a_rank_and_under_no_quota(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        hosted = host(c, benchmark={"quota": "1/1", "max_published": 1})
        root = hosted.headers("root")
        baselines = [ok(submit(c, root, golden_bytes("result.pkl")), 201) for _ in range(3)]  # over a quota of 1
        assert all(b["baseline"] is True for b in baselines)
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=root))
        assert mine["baselines"] is True and mine["quota"]["used"] == 0
        alice = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)  # her quota is whole
        assert alice["baseline"] is False
        assert submit(c, hosted.headers("alice"), golden_bytes("result.pkl")).status_code == 429
        txt = golden_txt("pred.tar.gz")
        worse = dict(txt)
        for name in list(worse)[: len(worse) // 2]:
            worse[name] = b""  # half the frames without detections: a lower key
        bob = ok(submit(c, hosted.headers("bob"), zip_of(worse), "worse.zip"), 201)
        for who, sid, method in (
            ("alice", alice["id"], "A"),
            ("bob", bob["id"], "B"),
            ("root", baselines[0]["id"], "R"),
        ):
            ok(
                c.post(
                    f"/v1/benchmarks/bench/submissions/{sid}/publish",
                    json={"method": method},
                    headers=hosted.headers(who),
                )
            )
        board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
        entries = {e["method"]: e for e in board["entries"]}
        assert entries["R"]["baseline"] is True and entries["R"]["rank"] is None
        assert (entries["A"]["rank"], entries["B"]["rank"]) == (1, 2)  # ranked among participants only
        assert entries["R"]["key"] == entries["A"]["key"] > entries["B"]["key"]
        # in its place by the key (ties by submission time: the baseline came first), yet A is still 1
        assert [e["method"] for e in board["entries"]] == ["R", "A", "B"]
        by_rank = ok(c.get("/v1/benchmarks/bench/leaderboard", params={"sort": "rank", "order": "asc"}))
        assert [e["method"] for e in by_rank["entries"]] == ["R", "A", "B"]
        csv_rows = c.get("/v1/benchmarks/bench/leaderboard", params={"format": "csv"}).text.splitlines()
        assert [r.split(",")[:2] for r in csv_rows[1:]] == [["baseline", "R"], ["1", "A"], ["2", "B"]]
        page = c.get("/benchmarks/bench").text
        row = re.search(rf'<tr class="entry baseline[^"]*" id="entry-{baselines[0]["id"]}">(.*?)</tr>', page, re.S)
        assert row and 'class="tag baseline-tag">baseline<' in row.group(1)
        actions = [
            (a["action"], a["actor"].split(" ")[0]) for a in ok(c.get("/v1/admin/audit", headers=ADMIN))["items"]
        ]
        assert ("baseline.add", "root") in actions and ("baseline.publish", "root") in actions
        assert ("submission.add", "alice") in actions and ("baseline.add", "alice") not in actions
        # no cap on published baselines (max_published is 1 here)
        second = f"/v1/benchmarks/bench/submissions/{baselines[1]['id']}/publish"
        ok(c.post(second, json={"method": "R2"}, headers=root))
        assert sum(e["baseline"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]) == 2
        # a closed benchmark takes no baseline either; one that has not opened yet takes baselines only
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        assert submit(c, root, golden_bytes("result.pkl")).status_code == 409
        body = {
            "name": "later",
            "ground_truth": "test-set",
            "opens_at": "2099-01-01T00:00:00+00:00",
            "share_test_set": True,
        }
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        assert ok(submit(c, root, golden_bytes("result.pkl"), name="later"), 201)["baseline"] is True
        assert submit(c, hosted.headers("alice"), golden_bytes("result.pkl"), name="later").status_code == 409
        # the admin token is no account: it submits nothing
        assert submit(c, ADMIN, golden_bytes("result.pkl"), name="later").status_code == 403


def test_the_board_renders_intervals_rank_ranges_and_ties_when_the_board_has_them(world, monkeypatch) -> None:
    c, hosted = world
    for who in ("alice", "bob"):
        sid = ok(submit(c, hosted.headers(who), golden_bytes("result.pkl")), 201)["id"]
        ok(
            c.post(
                f"/v1/benchmarks/bench/submissions/{sid}/publish",
                json={"method": f"m-{who}"},
                headers=hosted.headers(who),
            )
        )
    benchmarks = c.app.state.benchmarks.board
    plain = benchmarks.leaderboard

    page = c.get("/benchmarks/bench").text  # the board's own intervals, rank ranges and bootstrap line
    assert page.count('<span class="interval">[') == 2 and 'id="bootstrap"' in page

    def without_intervals(name, caller, **kw):  # a board without the keys (an older service): nothing of them
        board = plain(name, caller, **kw)
        board.pop("bootstrap")
        for entry in board["entries"]:
            for k in ("interval", "rank_range", "differs_from_next"):
                entry.pop(k)
        return board

    monkeypatch.setattr(benchmarks, "leaderboard", without_intervals)
    page = c.get("/benchmarks/bench").text
    assert "computing" not in page and 'class="interval"' not in page and 'class="range"' not in page
    assert 'id="bootstrap"' not in page and "≈" not in page

    def with_intervals(name, caller, **kw):
        board = plain(name, caller, **kw)
        board["entries"][0].update(interval=[77.9, 78.7], rank_range=[1, 2], differs_from_next=False)
        board["entries"][1].update(interval=None, rank_range=None, differs_from_next=None)
        board["bootstrap"] = {
            "method": "percentile",
            "resamples": 1000,
            "seed": 7,
            "part": "all",
            "level": 0.95,
            "pending": 1,
        }
        return board

    monkeypatch.setattr(benchmarks, "leaderboard", with_intervals)
    page = c.get("/benchmarks/bench").text
    rows = re.findall(r'<tr class="entry[^"]*" id="entry-[0-9a-f]+">(.*?)</tr>', page, re.S)
    assert len(rows) == 2
    assert '<span class="interval">[77.90, 78.70]</span>' in rows[0] and ">1–2</span>" in rows[0]
    assert 'class="tie"' in rows[0] and 'class="tie"' not in rows[1]
    assert '<span class="interval">computing</span>' in rows[1] and ">computing</span>" in rows[1]
    line = re.search(r'<span id="bootstrap">(.*?)</span>', page, re.S)
    assert (
        line and "1000 resamples, seed 7" in line.group(1) and "95 %" in line.group(1) and "percentile" in line.group(1)
    )
    sorted_by_method = c.get("/benchmarks/bench", params={"sort": "method", "order": "asc"}).text
    assert 'class="tie"' not in sorted_by_method  # "the one below" means something in the key's order only


def test_the_board_header_groups_class_metric_and_difficulty() -> None:
    columns = [
        f"{c}/{m}/{d}/R40/strict"
        for c in ("Car", "Pedestrian")
        for m in ("3d", "bev")
        for d in ("easy", "moderate", "hard")
    ]
    header = board_header(columns)
    assert header["classes"] == [{"name": "Car", "span": 6}, {"name": "Pedestrian", "span": 6}]
    assert [(m["name"], m["span"]) for m in header["metrics"]] == [("3D", 3), ("BEV", 3)] * 2
    assert [c["label"] for c in header["cells"]] == ["easy", "moderate", "hard"] * 4
    assert header["common"] == "R40, strict IoU"
    mixed = board_header(["Car/3d/moderate/R40/strict", "Car/3d/moderate/R11/loose"])
    assert mixed["common"] is None and [c["label"] for c in mixed["cells"]] == [
        "moderate (R40, strict IoU)",
        "moderate (R11, loose IoU)",
    ]
    assert [(m["name"], m["span"]) for m in mixed["metrics"]] == [("3D", 2)]


def test_intervals_show_computing_when_null_and_nothing_when_absent() -> None:
    entry = {"id": "a", "date": "2026-05-01T14:03:22.5+00:00", "key": 78.3123, "rank": 1, "columns": {}}
    absent = board_entries({"sort": "key", "order": "desc", "entries": [entry]})[0]
    assert (absent["interval"], absent["rank_range"], absent["tie"]) == (None, None, False)
    assert (absent["key"], absent["date"], absent["time"]) == ("78.31", "2026-05-01", "2026-05-01 14:03:22 UTC")
    null = board_entries({"entries": [{**entry, "interval": None, "rank_range": None, "differs_from_next": None}]})[0]
    assert (null["interval"], null["rank_range"], null["tie"]) == ("computing", "computing", False)
    baseline = board_entries({"entries": [{**entry, "rank": None, "baseline": True, "rank_range": [1, 2]}]})[0]
    assert baseline["rank"] == "" and baseline["rank_range"] is None  # a baseline has no rank
    # a range that is the entry's own rank alone is not shown (a lone "1" under rank 1 read as a typo)
    certain = board_entries({"entries": [{**entry, "interval": [78.0, 78.6], "rank_range": [1, 1]}]})[0]
    assert certain["rank"] == "1" and certain["rank_range"] is None
    assert board_entries({"entries": [{**entry, "rank": 2, "rank_range": [1, 1]}]})[0]["rank_range"] == "1"
    assert board_entries({"entries": [{**entry, "rank_range": [1, 2]}]})[0]["rank_range"] == "1–2"
    assert bootstrap_line({"entries": []}) is None
    assert comparison_rows(None) is None
    rows = comparison_rows(
        {"previous_best": None, "leader": {"id": "x", "difference": -1.25, "interval": [-2.0, -0.5]}}
    )
    assert rows is not None and rows[0]["none"] and rows[1]["difference"] == "−1.25"
    assert rows[1]["interval"] == "[−2.00, −0.50]" and rows[1]["verdict"].startswith("a real difference")
    pending = comparison_rows({"previous_best": {"id": "y", "difference": 0.4, "interval": None}, "leader": None})
    assert pending is not None and pending[0]["interval"] == "computing" and pending[0]["verdict"] == "computing"


def test_the_api_link_of_a_public_page_reaches_the_api_docs_without_signing_in(world) -> None:
    """The nav's "API" link led a visitor of a public board to the sign-in form (401)."""
    c, _ = world
    page = c.get("/benchmarks/bench")
    assert page.status_code == 200
    link = re.search(r'<a href="([^"]+)">API</a>', page.text)
    assert link and link.group(1) == "/docs"
    docs = c.get(link.group(1))
    assert docs.status_code == 200 and 'action="/signin"' not in docs.text and "swagger" in docs.text.lower()


def test_a_submission_that_leads_the_board_says_so_instead_of_comparing_with_itself(world) -> None:
    """Its page said "leader: +0.00 [0.00, 0.00]": the leader was the submission itself."""
    c, hosted = world
    sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    publish = {"method": "Leader"}
    ok(c.post(f"/v1/benchmarks/bench/submissions/{sid}/publish", json=publish, headers=hosted.headers("alice")))
    api = ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=hosted.headers("alice")))
    assert api["comparison"]["leader"]["id"] == sid  # the API's comparison: itself, difference 0
    sign_in(c, hosted.tokens["alice"])
    page = c.get(f"/benchmarks/bench/submissions/{sid}").text
    row = re.search(r'<tr data-against="leader">(.*?)</tr>', page, re.S)
    assert row and 'id="you-lead"><strong>you lead the board</strong>' in row.group(1)
    assert "+0.00" not in row.group(1) and "0.00, 0.00" not in row.group(1)
    rows = comparison_rows(
        {"previous_best": None, "leader": {"id": "x", "difference": 0.0, "interval": [0.0, 0.0]}}, "x"
    )
    assert rows is not None and rows[1]["lead"] == "you lead the board" and "difference" not in rows[1]
    c.cookies.clear()


def test_the_submission_page_shows_the_comparison_when_the_submission_has_one(world, monkeypatch) -> None:
    c, hosted = world
    sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    sign_in(c, hosted.tokens["alice"])
    assert 'id="comparison"' in c.get(f"/benchmarks/bench/submissions/{sid}").text  # the service's own
    benchmarks = c.app.state.benchmarks.submissions
    plain = benchmarks.submission

    def without(name, submission_id, caller):  # a submission without the key (an older service): no table
        out = plain(name, submission_id, caller)
        out.pop("comparison")
        return out

    monkeypatch.setattr(benchmarks, "submission", without)
    assert 'id="comparison"' not in c.get(f"/benchmarks/bench/submissions/{sid}").text

    def compared(name, submission_id, caller):
        out = plain(name, submission_id, caller)
        out["comparison"] = {
            "previous_best": {"id": "p", "difference": 0.52, "interval": [-0.1, 1.2]},
            "leader": {"id": "l", "difference": -1.5, "interval": None},
        }
        return out

    monkeypatch.setattr(benchmarks, "submission", compared)
    page = c.get(f"/benchmarks/bench/submissions/{sid}").text
    table = re.search(r'<table class="comparison" id="comparison">(.*?)</table>', page, re.S)
    assert table, page[:3000]
    best = re.search(r'data-against="previous_best">(.*?)</tr>', table.group(1), re.S).group(1)
    leader = re.search(r'data-against="leader">(.*?)</tr>', table.group(1), re.S).group(1)
    assert "+0.52" in best and "[−0.10, 1.20]" in best and "within the noise" in best
    assert "−1.50" in leader and "computing" in leader
    c.cookies.clear()


def test_the_first_visit_in_accounts_mode_is_a_calm_sign_in_form(world) -> None:
    c, _ = world
    c.cookies.clear()
    page = c.get("/")
    assert page.status_code == 401 and 'action="/signin"' in page.text
    assert 'class="error"' not in page.text and "Authorization" not in page.text and "Bearer" not in page.text
    assert 'id="sign-in-intro"' in page.text
    # a session that was ended is still told so
    c.cookies.set("kitti_eval_session", "kte_0000000000000000_gone")
    page = c.get("/")
    assert page.status_code == 401 and 'class="error"' in page.text
    c.cookies.clear()
    # the benchmarks are open to anyone: the public one is listed without signing in, with no form
    listed = c.get("/benchmarks")
    assert listed.status_code == 200 and 'data-name="bench"' in listed.text and 'class="left"' not in listed.text
    assert 'id="yours"' not in c.get("/benchmarks/bench").text


def test_a_queued_submission_says_its_place_and_reloads_itself(tmp_path) -> None:
    """Without a worker the submission waits in the queue: its page says so, with its place, and reloads."""
    with app_client(tmp_path / "data", auth="accounts", job_threads=0, ready=False) as c:
        hosted = host(c)
        files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
        first = c.post(
            "/v1/benchmarks/bench/submissions", params={"wait": 0}, files=files, headers=hosted.headers("bob")
        )
        assert first.status_code == 202, first.text
        sign_in(c, hosted.tokens["alice"])
        csrf = _hidden(c.get("/benchmarks/bench").text)
        r = form_submit(c, golden_bytes("result.pkl"), csrf=csrf)
        assert r.status_code == 303
        page = c.get(r.headers["location"]).text
        assert 'data-state="queued"' in page and "queued (2nd in line)" in page  # bob's is first
        assert '<meta http-equiv="refresh" content="2">' in page and 'id="publish-form"' not in page
        listed = c.get("/benchmarks/bench").text
        assert 'class="state queued">queued (2nd in line)<' in listed and "<strong>2</strong> of 3" in listed
        c.cookies.clear()


def test_a_failed_scoring_says_why_and_stops_reloading(world, monkeypatch) -> None:
    from kitti_eval.errors import InputError

    c, hosted = world
    benchmarks = c.app.state.benchmarks.scoring

    def refuse(*args, **kwargs):
        raise InputError("predictions for frame 000007: boxes with a negative size", frame="000007", field="dimensions")

    monkeypatch.setattr(benchmarks, "_scores", refuse)
    csrf = sign_in(c, hosted.tokens["alice"])
    r = form_submit(c, golden_bytes("result.pkl"), csrf=csrf)
    assert r.status_code == 303
    url = r.headers["location"]
    deadline = time.monotonic() + 60
    while 'data-state="failed"' not in (page := c.get(url).text):
        assert time.monotonic() < deadline, page[:2000]
        time.sleep(0.1)
    failure = re.search(r'<p class="error" role="alert" id="failure">(.*?)</p>', page, re.S)
    assert failure and "frame 000007: boxes with a negative size" in failure.group(1)
    assert 'http-equiv="refresh"' not in page and 'id="publish-form"' not in page
    assert "<strong>3</strong> of 3" in c.get("/benchmarks/bench").text  # a failed one does not count
    c.cookies.clear()


def test_a_file_refused_after_the_form_answered_shows_its_sentences_on_the_submissions_page(world) -> None:
    """A submission whose scoring job ran after the form stopped waiting: its page (where the form sent the
    participant) shows the validator's sentences once the job refused it, and the quota is untouched."""
    c, hosted = world
    alice = hosted.headers("alice")
    service = c.app.state.service
    txt = golden_txt("pred.tar.gz")
    broken = dict(list(txt.items())[1:])  # one test frame missing
    service.workers.stop(5)  # the job waits: the API answers 202
    try:
        files = {"predictions": ("broken.zip", zip_of(broken), "application/octet-stream")}
        job = ok(c.post("/v1/benchmarks/bench/submissions", params={"wait": 0}, files=files, headers=alice), 202)
    finally:
        service.workers.start()
    ended = service.jobs.wait(job["id"], 120)
    assert ended is not None and ended.state == "failed"
    sign_in(c, hosted.tokens["alice"])
    page = c.get(f"/benchmarks/bench/submissions/{job['id']}")
    assert page.status_code == 422
    assert "1 test frames are missing: 000000" in page.text and "does not count against your quota" in page.text
    c.cookies.clear()
    assert c.get(f"/benchmarks/bench/submissions/{job['id']}", headers=hosted.headers("bob")).status_code == 404
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
    assert mine["items"] == [] and mine["quota"]["used"] == 0
