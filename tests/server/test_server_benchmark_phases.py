"""A benchmark defined by a file (phases, teams), in process (SQLite): applying the same file twice leaves one
benchmark and changes nothing, a change of quota or dates is applied, a file that contradicts itself or the
service is refused at its line; each phase has its submissions and board, the routes without a phase address the
current one; a team's members share each phase's quota, exactly under parallel submissions."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta, timezone

import pytest
import tomllib
from server_benchmarks import bearer, host, ok
from server_helpers import app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file, export_benchmark_file
from kitti_eval_server.errors import BadRequest


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = phased_world(c)
        apply_benchmark_file(c.app.state.benchmarks, TWO_PHASES, caller=HOST, source="kitti-phases.toml")
        yield c, hosted


def _submit(c, token: str, path: str = "/v1/benchmarks/kitti-phases/phases/test/submissions"):
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post(path, params={"wait": 0}, files=files, headers=bearer(token))


def _team(c, token: str, name: str, *members: str):
    answer = c.post(
        "/v1/benchmarks/kitti-phases/teams", json={"name": name, "members": list(members)}, headers=bearer(token)
    )
    return ok(answer, 201)


def _refusal(text: str, c) -> str:
    with pytest.raises(BadRequest) as e:
        apply_benchmark_file(c.app.state.benchmarks, text, caller=HOST, source="b.toml")
    return e.value.message


def test_applying_the_file_twice_leaves_one_benchmark_and_changes_nothing(world) -> None:
    c, _ = world
    again = apply_benchmark_file(c.app.state.benchmarks, TWO_PHASES, caller=HOST, source="kitti-phases.toml")
    assert again.lines == ("phase dev: unchanged", "phase test: unchanged") and not again.changed
    listed = ok(c.get("/v1/benchmarks"))["items"]
    assert [b["name"] for b in listed] == ["kitti-phases"]
    bench = ok(c.get("/v1/benchmarks/kitti-phases"))
    assert bench["phase"] == "dev" and bench["team_size"] == 3 and bench["title"] == "KITTI 3D, two phases"
    phases = bench["phases"]
    assert [(p["name"], p["current"]) for p in phases] == [("dev", True), ("test", False)]
    assert phases[0]["open_labels"] is True and phases[0]["quota"] == {"submissions": 5, "days": 1.0}
    assert phases[1]["split_percent"] == 50 and phases[1]["board"] == "public" and not phases[1]["open_labels"]
    assert "ground_truth" not in phases[1]  # an anonymous reader never learns the test set's name
    # what export writes is the file applied, and applying it changes nothing
    exported = export_benchmark_file(c.app.state.benchmarks, "kitti-phases", caller=HOST)
    doc = tomllib.loads(exported)
    assert doc["name"] == "kitti-phases" and doc["team_size"] == 3 and doc["key"] == ["Car/3d/moderate/R40/strict"]
    assert [(p["name"], p["ground_truth"], p["quota"]) for p in doc["phases"]] == [
        ("dev", "dev_gt", "5/1"),
        ("test", "test_gt", "2/1"),
    ]
    assert doc["phases"][1]["split_percent"] == 50 and "split_percent" not in doc["phases"][0]
    assert not apply_benchmark_file(c.app.state.benchmarks, exported, caller=HOST).changed


def test_a_change_of_quota_and_dates_is_applied(world) -> None:
    c, _ = world
    closes = datetime.now(timezone.utc) + timedelta(days=30)
    changed = TWO_PHASES.replace('quota = "2/1"', f'quota = "4/2"\ncloses_at = {closes.isoformat()}')
    applied = apply_benchmark_file(c.app.state.benchmarks, changed, caller=HOST)
    assert applied.lines == ("phase dev: unchanged", "phase test: changed closes_at, config")
    test = ok(c.get("/v1/benchmarks/kitti-phases/phases/test"))
    assert test["quota"] == {"submissions": 4, "days": 2.0}
    assert datetime.fromisoformat(test["closes_at"]) == closes
    assert [b["name"] for b in ok(c.get("/v1/benchmarks"))["items"]] == ["kitti-phases"]


@pytest.mark.parametrize(
    ("edit", "line", "says"),
    [
        (lambda t: t.replace("split_percent = 50", "split_percent = 50\nsplit = 3"), 17, "'split' is not a key"),
        (lambda t: t.replace('"test_gt"', '"dev_gt"'), 14, "on one ground truth"),
        (lambda t: t.replace('"test_gt"', '"nope"'), 14, "no ground truth named 'nope'"),
        (lambda t: t.replace('"2/1"', '"two a day"'), 15, "a quota is N/DAYS"),
        (lambda t: t.replace("team_size = 3", 'team_size = "3"'), 5, "team_size is a whole number"),
        (lambda t: t.replace('quota = "5/1"', 'quota = "5/1"\nsplit_percent = 10'), 11, "which is not sealed"),
        (
            lambda t: t.replace('quota = "5/1"', 'quota = "5/1"\ncloses_at = 2030-02-01T00:00:00Z').replace(
                'quota = "2/1"', 'quota = "2/1"\nopens_at = 2030-01-15T00:00:00Z'
            ),
            17,
            "before the phase 'dev' closes",
        ),
        (lambda t: t.replace('name = "test"', 'name = "dev"'), 13, "two phases are named 'dev'"),
        (lambda t: t + "\n[extra]\nx = 1\n", 18, "'extra' is not a key of a benchmark file"),
    ],
)
def test_a_file_that_contradicts_itself_or_the_service_is_refused_at_its_line(world, edit, line, says) -> None:
    c, _ = world
    message = _refusal(edit(TWO_PHASES), c)
    assert message.startswith(f"b.toml, line {line}: ") and says in message, message


def test_a_test_set_already_used_is_refused_and_nothing_is_written(world) -> None:
    c, _ = world
    other = TWO_PHASES.replace("kitti-phases", "second").replace('"dev_gt"', '"other_gt"')
    message = _refusal(other, c)
    assert message.startswith("b.toml, line 14: ") and "already the test set of kitti-phases" in message
    assert c.get("/v1/benchmarks/second").status_code == 404  # the first phase was not made either


def test_a_team_of_two_shares_the_test_phase_quota_and_another_keeps_their_own(world) -> None:
    c, hosted = world
    alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
    team = _team(c, alice, "Two", "bob")
    assert team["members"] == ["alice", "bob"] and team["benchmark"] == "kitti-phases"
    assert _submit(c, alice).status_code == 202
    assert _submit(c, bob).status_code == 202
    for who in (alice, bob):  # the third is refused, whichever member sends it
        third = _submit(c, who)
        assert third.status_code == 429 and third.json()["error"]["code"] == "quota_exceeded"
    assert _submit(c, carol).status_code == 202  # another participant keeps their own quota
    mine = ok(c.get("/v1/benchmarks/kitti-phases/phases/test/submissions", headers=bearer(bob)))
    assert mine["quota"]["used"] == 2 and mine["quota"]["left"] == 0
    assert len(mine["items"]) == 1  # bob's own
    # the dev phase has a quota of its own
    assert _submit(c, alice, "/v1/benchmarks/kitti-phases/phases/dev/submissions").status_code == 202
    for phase, board in (("dev", "all"), ("test", "public")):
        answered = ok(c.get(f"/v1/benchmarks/kitti-phases/phases/{phase}/leaderboard"))
        assert answered["benchmark"] == "kitti-phases" and answered["phase"] == phase and answered["board"] == board
    csv = c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard", params={"format": "csv"})
    assert csv.status_code == 200 and csv.text.startswith("rank,method,")


def test_parallel_submissions_of_a_teams_members_admit_exactly_the_quota(world) -> None:
    c, hosted = world
    alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
    _team(c, alice, "Two", "bob")
    with ThreadPoolExecutor(12) as pool:
        answers = list(pool.map(lambda i: _submit(c, alice if i % 2 else bob), range(12)))
    statuses = sorted(r.status_code for r in answers)
    assert statuses == [202] * 2 + [429] * 10, [r.text[:200] for r in answers]


def test_a_member_who_submitted_alone_brings_no_extra_quota(world) -> None:
    c, hosted = world
    alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
    assert _submit(c, bob).status_code == 202  # alone, before the team
    _team(c, alice, "Two", "bob")
    assert _submit(c, alice).status_code == 202
    assert _submit(c, alice).status_code == 429


def test_teams_are_one_per_participant_within_the_size_of_people_who_take_part(world) -> None:
    c, hosted = world
    alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
    url = "/v1/benchmarks/kitti-phases/teams"
    ok(c.post(url, json={"name": "Two", "members": ["bob"]}, headers=bearer(alice)), 201)
    taken = c.post(url, json={"name": "Three", "members": ["bob"]}, headers=bearer(carol))
    assert taken.status_code == 409 and "bob already in a team" in taken.json()["error"]["message"]
    big = c.post(url, json={"name": "Big", "members": ["x1", "x2", "x3"]}, headers=bearer(carol))
    assert big.status_code == 422 and "at most 3 members" in big.json()["error"]["message"]
    ghost = c.post(url, json={"name": "Ghost", "members": ["nobody"]}, headers=bearer(carol))
    assert ghost.status_code == 422 and "'nobody' may not take part" in ghost.json()["error"]["message"]
    assert c.post(url, json={"name": "Two", "members": []}, headers=bearer(carol)).status_code == 409
    listed = ok(c.get(url, headers=bearer(carol)))
    assert [(t["name"], t["members"]) for t in listed["items"]] == [("Two", ["alice", "bob"])]
    assert listed["mine"] is None and ok(c.get(url, headers=bearer(bob)))["mine"]["name"] == "Two"
    assert c.get(url).status_code == 401  # an anonymous reader of the public benchmark sees no teams


def test_the_routes_without_a_phase_address_the_current_phase(world) -> None:
    c, hosted = world
    alice = hosted.tokens["alice"]
    accepted = _submit(c, alice, "/v1/benchmarks/kitti-phases/submissions")
    assert accepted.status_code == 202
    mine = ok(c.get("/v1/benchmarks/kitti-phases/phases/dev/submissions", headers=bearer(alice)))
    assert [s["phase"] for s in mine["items"]] == ["dev"]
    # the dev phase closes: the test phase is the current one
    closes = datetime.now(timezone.utc) - timedelta(seconds=1)
    opens = closes - timedelta(days=1)
    text = TWO_PHASES.replace(
        'quota = "5/1"', f'quota = "5/1"\nopens_at = {opens.isoformat()}\ncloses_at = {closes.isoformat()}'
    )
    apply_benchmark_file(c.app.state.benchmarks, text, caller=HOST)
    assert ok(c.get("/v1/benchmarks/kitti-phases"))["phase"] == "test"
    assert _submit(c, alice, "/v1/benchmarks/kitti-phases/submissions").status_code == 202
    test = ok(c.get("/v1/benchmarks/kitti-phases/submissions", headers=bearer(alice)))
    assert [s["phase"] for s in test["items"]] == ["test"] and test["quota"]["used"] == 1
    # the dev submission is still read at the benchmark's address
    sid = mine["items"][0]["id"]
    c.app.state.service.jobs.wait(sid, 120)
    own = ok(c.get(f"/v1/benchmarks/kitti-phases/submissions/{sid}", headers=bearer(alice)))
    assert own["phase"] == "dev" and own["status"] == "scored"
    assert "gt_count" in str(own["result"]) or own["result"]["ap"]  # open labels: the whole document


def test_a_benchmark_made_with_add_is_one_phase_whose_file_applies_unchanged(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"quota": "2/1", "split_percent": 30})
        bench = ok(c.get("/v1/benchmarks/bench"))
        assert bench["phase"] == "main" and [p["name"] for p in bench["phases"]] == ["main"]
        exported = export_benchmark_file(c.app.state.benchmarks, "bench", caller=HOST)
        doc = tomllib.loads(exported)
        assert [(p["name"], p["ground_truth"], p["quota"], p["split_percent"]) for p in doc["phases"]] == [
            ("main", "test-set", "2/1", 30)
        ]
        assert not apply_benchmark_file(c.app.state.benchmarks, exported, caller=HOST).changed
        assert ok(c.get("/v1/benchmarks/bench/phases/main/leaderboard"))["board"] == "public"
        assert _submit(c, hosted.tokens["alice"], "/v1/benchmarks/bench/phases/main/submissions").status_code == 202


def test_late_submissions_are_scored_after_the_close_and_never_ranked(world) -> None:
    c, hosted = world
    alice = hosted.tokens["alice"]
    closed = datetime.now(timezone.utc) - timedelta(seconds=1)
    window = f"opens_at = {(closed - timedelta(days=1)).isoformat()}\ncloses_at = {closed.isoformat()}"
    text = TWO_PHASES.replace('quota = "2/1"', f'quota = "2/1"\n{window}')
    apply_benchmark_file(c.app.state.benchmarks, text, caller=HOST)
    refused = _submit(c, alice)
    assert refused.status_code == 409 and "not open for submissions" in refused.json()["error"]["message"]
    apply_benchmark_file(c.app.state.benchmarks, text + "late_submissions = true\n", caller=HOST)
    late = _submit(c, alice)
    assert late.status_code == 202
    sid = late.json()["id"]
    assert c.app.state.service.jobs.wait(sid, 120).state == "done"
    own = ok(c.get(f"/v1/benchmarks/kitti-phases/submissions/{sid}", headers=bearer(alice)))
    assert own["phase"] == "test" and own["status"] == "scored" and own["scores"]["Car/3d/moderate/R40/strict"] > 0
    publish = c.post(
        f"/v1/benchmarks/kitti-phases/submissions/{sid}/publish", json={"method": "Late"}, headers=bearer(alice)
    )
    assert publish.status_code == 409  # never on the board
    assert ok(c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard"))["entries"] == []
    assert ok(c.get("/v1/benchmarks/kitti-phases/phases/test/submissions", headers=bearer(alice)))["quota"]["used"] == 1
