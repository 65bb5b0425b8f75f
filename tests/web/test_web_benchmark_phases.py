"""The page of a benchmark defined by a file, in process (accounts mode): its phases (the current one first, each
with its board), the participant's team (made through the page's form, then named with its members), the
submission form of the phase shown, and the board entries naming the team."""

from __future__ import annotations

import re

import pytest
from server_benchmarks import bearer, ok
from server_helpers import app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world
from test_web_benchmarks import until_scored

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = phased_world(c)
        apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST)
        yield c, hosted


def _session(c, token: str) -> str:
    c.cookies.clear()
    form = c.get("/signin")
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text).group(1)
    assert c.post("/signin", data={"token": token, "csrf": csrf}, follow_redirects=False).status_code == 303
    return re.search(r'name="csrf" value="([^"]+)"', c.get("/benchmarks/kitti-phases").text).group(1)


def _phases(html: str) -> list[tuple[str, bool, bool]]:
    """(phase, current, shown) of the page's list of phases, in its order."""
    items = re.findall(r'<li class="phase( current)?( shown)?" id="phase-([a-z0-9_-]+)">', html)
    return [(name, bool(current), bool(shown)) for current, shown, name in items]


def test_the_page_shows_the_phases_the_current_first_and_each_board(world) -> None:
    c, _ = world
    page = c.get("/benchmarks/kitti-phases")
    assert page.status_code == 200
    assert _phases(page.text) == [("dev", True, True), ("test", False, False)]
    assert "Leaderboard: dev phase" in page.text and 'id="team"' not in page.text  # a visitor has no team
    test = c.get("/benchmarks/kitti-phases", params={"phase": "test"})
    assert _phases(test.text) == [("dev", True, False), ("test", False, True)]
    assert "Leaderboard: test phase" in test.text and "/v1/benchmarks/kitti-phases/phases/test/leaderboard" in test.text
    assert c.get("/benchmarks/kitti-phases", params={"phase": "nope"}).status_code == 404
    listed = c.get("/benchmarks").text
    assert '<dd class="phase-now">dev (of dev, test); teams of up to 3</dd>' in listed


def test_a_participant_makes_a_team_and_submits_to_the_test_phase_through_the_page(world) -> None:
    c, hosted = world
    csrf = _session(c, hosted.tokens["alice"])
    page = c.get("/benchmarks/kitti-phases").text
    assert 'id="make-team"' in page and "a team of up to 3" in page
    refused = c.post("/benchmarks/kitti-phases/teams", data={"csrf": csrf, "name": "Two", "members": "nobody"})
    assert refused.status_code == 422 and "may not join a team" in refused.text and 'id="team-error"' in refused.text
    made = c.post(
        "/benchmarks/kitti-phases/teams", data={"csrf": csrf, "name": "Two", "members": "bob"}, follow_redirects=False
    )
    assert made.status_code == 303 and made.headers["location"] == "/benchmarks/kitti-phases#team"
    page = c.get("/benchmarks/kitti-phases").text
    assert re.search(r'id="team-name">You are in <strong>Two</strong>: alice\.', page)
    assert re.search(r'id="team-invited">Invited, not joined yet: bob\.', page)
    # bob, signed in, finds the invitation and joins through the page
    bob_csrf = _session(c, hosted.tokens["bob"])
    assert 'data-team="Two">Join Two</button>' in c.get("/benchmarks/kitti-phases").text
    joined = c.post("/benchmarks/kitti-phases/teams/Two/join", data={"csrf": bob_csrf}, follow_redirects=False)
    assert joined.status_code == 303 and joined.headers["location"] == "/benchmarks/kitti-phases#team"
    assert c.post("/benchmarks/kitti-phases/teams/Two/join", data={"csrf": bob_csrf}).status_code == 404
    csrf = _session(c, hosted.tokens["alice"])
    page = c.get("/benchmarks/kitti-phases").text
    assert re.search(r'id="team-name">You are in <strong>Two</strong>: alice, bob\.', page)
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    sent = c.post(
        "/benchmarks/kitti-phases/submissions?phase=test", data={"csrf": csrf}, files=files, follow_redirects=False
    )
    assert sent.status_code == 303
    url = sent.headers["location"]
    assert url.startswith("/benchmarks/kitti-phases/submissions/")
    until_scored(c, url)
    sid = url.rsplit("/", 1)[1]
    published = c.post(f"{url}/publish", data={"csrf": csrf, "method": "Team-Net"}, follow_redirects=False)
    assert published.status_code == 303
    assert published.headers["location"] == f"/benchmarks/kitti-phases?phase=test#entry-{sid}"
    board = ok(c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard"))
    assert [(e["method"], e["participant"], e["team"]) for e in board["entries"]] == [("Team-Net", "alice", "Two")]
    table = c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard", params={"format": "csv"}).text.splitlines()
    assert table[0].startswith("rank,method,participant,team,affiliation,") and table[1].startswith(
        "1,Team-Net,alice,Two,"
    )
    shown = c.get("/benchmarks/kitti-phases", params={"phase": "test"}).text
    assert '<span class="team-of">Two</span>: alice' in shown
    assert "sort=rank&amp;order=asc&amp;phase=test" in shown  # sorting keeps the phase
    assert "sort=Car/3d/moderate/R40/strict&amp;order=desc&amp;phase=test" in shown  # by a column too
    # bob's page: the team's quota, one of two used
    c.cookies.clear()
    mine = ok(c.get("/v1/benchmarks/kitti-phases/phases/test/submissions", headers=bearer(hosted.tokens["bob"])))
    assert mine["quota"]["used"] == 1 and mine["quota"]["left"] == 1
