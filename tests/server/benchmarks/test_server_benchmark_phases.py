"""A benchmark defined by a file (phases, teams), in process (SQLite): applying the same file twice leaves one
benchmark and changes nothing, a change of quota or dates is applied, a file that contradicts itself or the
service is refused at its line; each phase has its submissions and board, the routes without a phase address the
current one; a team's members share each phase's quota, exactly under parallel submissions."""

from __future__ import annotations

import tomllib
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta, timezone

import pytest
from server_benchmarks import bearer, host, ok
from server_helpers import ADMIN, app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file, export_benchmark_file
from kitti_eval_server.errors import BadRequest


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = phased_world(c)
        apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST, source="kitti-phases.toml")
        yield c, hosted


def _submit(c, token: str, path: str = "/v1/benchmarks/kitti-phases/phases/test/submissions"):
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post(path, params={"wait": 0}, files=files, headers=bearer(token))


def _team(c, hosted, maker: str, name: str, *members: str):
    """``maker`` makes the team ``name`` inviting ``members``, who join it."""
    body = {"name": name, "members": list(members)}
    ok(c.post("/v1/benchmarks/kitti-phases/teams", json=body, headers=bearer(hosted.tokens[maker])), 201)
    team = None
    for member in members:
        joined = c.post(f"/v1/benchmarks/kitti-phases/teams/{name}/join", headers=bearer(hosted.tokens[member]))
        team = ok(joined)
    return team


def _refusal(text: str, c) -> str:
    with pytest.raises(BadRequest) as e:
        apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST, source="b.toml")
    return e.value.message


def test_applying_the_file_twice_leaves_one_benchmark_and_changes_nothing(world) -> None:
    c, _ = world
    again = apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST, source="kitti-phases.toml")
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
    exported = export_benchmark_file(c.app.state.benchmarks.catalog, "kitti-phases", caller=HOST)
    doc = tomllib.loads(exported)
    assert doc["name"] == "kitti-phases" and doc["team_size"] == 3 and doc["key"] == ["Car/3d/moderate/R40/strict"]
    assert [(p["name"], p["ground_truth"], p["quota"]) for p in doc["phases"]] == [
        ("dev", "dev_gt", "5/1"),
        ("test", "test_gt", "2/1"),
    ]
    assert doc["phases"][1]["split_percent"] == 50 and "split_percent" not in doc["phases"][0]
    assert not apply_benchmark_file(c.app.state.benchmarks.catalog, exported, caller=HOST).changed


def test_a_change_of_quota_and_dates_is_applied(world) -> None:
    c, _ = world
    closes = datetime.now(timezone.utc) + timedelta(days=30)
    changed = TWO_PHASES.replace('quota = "2/1"', f'quota = "4/2"\ncloses_at = {closes.isoformat()}')
    applied = apply_benchmark_file(c.app.state.benchmarks.catalog, changed, caller=HOST)
    assert applied.lines == ("phase dev: unchanged", "phase test: changed closes_at, config (quota)")
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


def test_the_first_phase_stays_first(world) -> None:
    c, _ = world
    dev = 'name = "dev"\nground_truth = "dev_gt"\nquota = "5/1"\n'
    test = 'name = "test"\nground_truth = "test_gt"\nquota = "2/1"\nsplit_percent = 50\n'
    swapped = TWO_PHASES.replace(dev, "@@").replace(test, dev).replace("@@", test)
    assert swapped.index('name = "test"') < swapped.index('name = "dev"')
    message = _refusal(swapped, c)
    assert message.startswith("b.toml, line 14: the phase 'dev' was the first phase of 'kitti-phases'"), message


def test_a_test_set_already_used_is_refused_and_nothing_is_written(world) -> None:
    c, _ = world
    other = TWO_PHASES.replace("kitti-phases", "second").replace('"dev_gt"', '"other_gt"')
    message = _refusal(other, c)
    assert message.startswith("b.toml, line 14: ") and "already the test set of kitti-phases" in message
    assert c.get("/v1/benchmarks/second").status_code == 404  # the first phase was not made either


def test_a_team_of_two_shares_the_test_phase_quota_and_another_keeps_their_own(world) -> None:
    c, hosted = world
    alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
    team = _team(c, hosted, "alice", "Two", "bob")
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
    _team(c, hosted, "alice", "Two", "bob")
    with ThreadPoolExecutor(12) as pool:
        answers = list(pool.map(lambda i: _submit(c, alice if i % 2 else bob), range(12)))
    # accepted: 202 (or 201 when its scoring ended before the answer); refused: 429
    statuses = sorted(201 if r.status_code == 202 else r.status_code for r in answers)
    assert statuses == [201] * 2 + [429] * 10, [r.text[:200] for r in answers]


def test_a_member_who_submitted_alone_brings_no_extra_quota(world) -> None:
    c, hosted = world
    alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
    assert _submit(c, bob).status_code == 202  # alone, before the team
    _team(c, hosted, "alice", "Two", "bob")
    assert _submit(c, alice).status_code == 202
    assert _submit(c, alice).status_code == 429


def test_a_team_is_joined_by_those_it_invited_one_team_each_within_its_size(world) -> None:
    c, hosted = world
    alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
    url = "/v1/benchmarks/kitti-phases/teams"
    made = ok(c.post(url, json={"name": "Two", "members": ["bob"]}, headers=bearer(alice)), 201)
    assert made["members"] == ["alice"] and made["invited"] == ["bob"]  # an invitation binds nobody
    big = c.post(url, json={"name": "Big", "members": ["x1", "x2", "x3"]}, headers=bearer(carol))
    assert big.status_code == 422 and "at most 3 members" in big.json()["error"]["message"]
    assert _submit(c, bob).status_code == 202 and _submit(c, alice).status_code == 202
    assert _submit(c, alice).status_code == 202  # until bob joins, alice's quota is her own
    ok(c.post(url, json={"name": "Three", "members": ["bob"]}, headers=bearer(carol)), 201)
    assert ok(c.get(url, headers=bearer(bob)))["invitations"] == ["Three", "Two"]
    assert c.post(f"{url}/Two/join", headers=bearer(carol)).status_code == 404  # not invited there
    joined = ok(c.post(f"{url}/Two/join", headers=bearer(bob)))
    assert joined["members"] == ["alice", "bob"] and joined["invited"] == []
    again = c.post(f"{url}/Three/join", headers=bearer(bob))  # his other invitations were dropped
    assert again.status_code == 404
    assert _submit(c, bob).status_code == 429  # the team's quota of 2: alice's two and bob's one count
    in_one = c.post(url, json={"name": "Other", "members": []}, headers=bearer(alice))
    assert in_one.status_code == 409 and "you are in a team" in in_one.json()["error"]["message"]
    ghost = c.post(url, json={"name": "Ghost", "members": ["nobody"]}, headers=bearer(carol))
    assert ghost.status_code == 409  # carol is in Three already
    listed = ok(c.get(url, headers=bearer(carol)))
    assert [(t["name"], t["members"]) for t in listed["items"]] == [("Three", ["carol"]), ("Two", ["alice", "bob"])]
    assert "invited" not in listed["items"][0] and listed["mine"]["invited"] == []
    assert c.get(url).status_code == 401  # an anonymous reader of the public benchmark sees no teams


def test_a_member_who_leaves_keeps_the_board_naming_the_team_and_frees_no_quota(world) -> None:
    c, hosted = world
    alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
    url = "/v1/benchmarks/kitti-phases/teams"
    _team(c, hosted, "alice", "Two", "bob")
    sid = ok(_submit(c, bob), 202)["id"]  # for the team
    assert c.app.state.service.jobs.wait(sid, 120).state == "done"
    path = f"/v1/benchmarks/kitti-phases/submissions/{sid}/publish"
    ok(c.post(path, json={"method": "Bob's"}, headers=bearer(bob)))
    left = ok(c.post(f"{url}/leave", headers=bearer(bob)))
    assert left == {"benchmark": "kitti-phases", "left": "Two", "members": ["alice"]}
    assert ok(c.get(url, headers=bearer(bob)))["mine"] is None
    board = ok(c.get("/v1/benchmarks/kitti-phases/phases/test/leaderboard"))
    assert [(e["participant"], e["team"]) for e in board["entries"]] == [("bob", "Two")]
    # leaving frees no quota (2 a day): bob's submission counts against the team's and his own
    mine = "/v1/benchmarks/kitti-phases/phases/test/submissions"
    assert ok(c.get(mine, headers=bearer(alice)))["quota"]["used"] == 1
    assert ok(c.get(mine, headers=bearer(bob)))["quota"]["used"] == 1
    alone = ok(_submit(c, bob), 202)["id"]
    assert _submit(c, bob).status_code == 429
    assert _submit(c, alice).status_code == 202
    assert _submit(c, alice).status_code == 429
    assert ok(c.get(mine, headers=bearer(alice)))["quota"]["used"] == 2
    record = c.app.state.benchmarks.catalog.benchmark_store.get_submission(alone)
    assert record.team is None  # made alone, after leaving
    assert c.post(f"{url}/leave", headers=bearer(bob)).status_code == 404  # in no team now
    ok(c.post(f"{url}/leave", headers=bearer(alice)))  # its last member: the team keeps its name
    carol = hosted.tokens["carol"]
    assert [(t["name"], t["members"]) for t in ok(c.get(url, headers=bearer(carol)))["items"]] == [("Two", [])]
    taken = c.post(url, json={"name": "Two", "members": []}, headers=bearer(carol))
    assert taken.status_code == 409


def test_no_one_leaves_a_team_once_the_benchmark_s_last_phase_has_closed(world) -> None:
    c, hosted = world
    _team(c, hosted, "alice", "Two", "bob")
    closed = datetime.now(timezone.utc) - timedelta(seconds=1)
    window = f"opens_at = {(closed - timedelta(days=1)).isoformat()}\ncloses_at = {closed.isoformat()}"
    text = TWO_PHASES.replace('quota = "2/1"', f'quota = "2/1"\n{window}')
    apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST)
    refused = c.post("/v1/benchmarks/kitti-phases/teams/leave", headers=bearer(hosted.tokens["bob"]))
    assert refused.status_code == 409 and "no longer change" in refused.json()["error"]["message"]
    listed = ok(c.get("/v1/benchmarks/kitti-phases/teams", headers=bearer(hosted.tokens["bob"])))
    assert listed["mine"]["members"] == ["alice", "bob"]


def test_whom_a_team_invites_takes_part_and_a_full_team_takes_no_one(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = phased_world(c, users=("alice", "bob", "carol", "dave"))
        apply_benchmark_file(
            c.app.state.benchmarks.catalog, TWO_PHASES.replace("team_size = 3", "team_size = 2"), caller=HOST
        )
        url = "/v1/benchmarks/kitti-phases/teams"
        ghost = c.post(url, json={"name": "Ghost", "members": ["nobody"]}, headers=hosted.headers("alice"))
        assert ghost.status_code == 422 and "one of those invited may not join" in ghost.json()["error"]["message"]
        ok(c.post(url, json={"name": "Pair", "members": ["bob"]}, headers=hosted.headers("alice")), 201)
        ok(c.post("/v1/admin/users", json={"name": "boss", "admin": True}, headers=ADMIN), 201)
        boss = ok(c.post("/v1/admin/tokens", json={"user": "boss"}, headers=ADMIN), 201)["token"]
        admin = c.post(url, json={"name": "Admins", "members": []}, headers=bearer(boss))
        assert admin.status_code == 403  # an admin submits baselines, in no team
        too_many = c.post(url, json={"name": "Trio", "members": ["bob", "dave"]}, headers=hosted.headers("carol"))
        assert too_many.status_code == 422 and "at most 2 members" in too_many.json()["error"]["message"]
        # the file's team size shrinks below a team's members and invitations: no one joins a full team
        ok(c.post(f"{url}/Pair/join", headers=hosted.headers("bob")))
        ok(c.post(url, json={"name": "Duo", "members": ["dave"]}, headers=hosted.headers("carol")), 201)
        apply_benchmark_file(
            c.app.state.benchmarks.catalog, TWO_PHASES.replace("team_size = 3", "team_size = 1"), caller=HOST
        )
        assert c.post(f"{url}/Duo/join", headers=hosted.headers("dave")).status_code == 409  # takes no teams now
        apply_benchmark_file(
            c.app.state.benchmarks.catalog, TWO_PHASES.replace("team_size = 3", "team_size = 2"), caller=HOST
        )
        assert ok(c.post(f"{url}/Duo/join", headers=hosted.headers("dave")))["members"] == ["carol", "dave"]


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
    apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST)
    assert ok(c.get("/v1/benchmarks/kitti-phases"))["phase"] == "test"
    assert [(b["name"], b["phase"]) for b in ok(c.get("/v1/benchmarks"))["items"]] == [("kitti-phases", "test")]
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
        exported = export_benchmark_file(c.app.state.benchmarks.catalog, "bench", caller=HOST)
        doc = tomllib.loads(exported)
        assert [(p["name"], p["ground_truth"], p["quota"], p["split_percent"]) for p in doc["phases"]] == [
            ("main", "test-set", "2/1", 30)
        ]
        assert not apply_benchmark_file(c.app.state.benchmarks.catalog, exported, caller=HOST).changed
        assert ok(c.get("/v1/benchmarks/bench/phases/main/leaderboard"))["board"] == "public"
        assert _submit(c, hosted.tokens["alice"], "/v1/benchmarks/bench/phases/main/submissions").status_code == 202


def test_late_submissions_are_scored_after_the_close_and_never_ranked(world) -> None:
    c, hosted = world
    alice = hosted.tokens["alice"]
    closed = datetime.now(timezone.utc) - timedelta(seconds=1)
    window = f"opens_at = {(closed - timedelta(days=1)).isoformat()}\ncloses_at = {closed.isoformat()}"
    text = TWO_PHASES.replace('quota = "2/1"', f'quota = "2/1"\n{window}')
    apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST)
    refused = _submit(c, alice)
    assert refused.status_code == 409 and "not open for submissions" in refused.json()["error"]["message"]
    apply_benchmark_file(c.app.state.benchmarks.catalog, text + "late_submissions = true\n", caller=HOST)
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


def test_a_phase_on_open_labels_shows_its_participant_their_frames_and_a_sealed_one_does_not(world) -> None:
    from server_helpers import GOLDEN

    from kitti_eval.analysis.diagnostics import FrameQuestion, frame_stats, frames_document
    from kitti_eval.io.loaders import load_detections, load_ground_truth
    from kitti_eval_server.scoring.evaluator import EvalOptions

    c, hosted = world
    alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
    dev = _submit(c, alice, "/v1/benchmarks/kitti-phases/phases/dev/submissions").json()["id"]
    test = _submit(c, alice).json()["id"]
    for sid in (dev, test):
        assert c.app.state.service.jobs.wait(sid, 120).state == "done"
    frames = ok(
        c.get(
            f"/v1/benchmarks/kitti-phases/submissions/{dev}/frames",
            params={"class": "Car", "worst": 5},
            headers=bearer(alice),
        )
    )
    gt, dt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl"), load_detections(GOLDEN / "result.pkl")
    expected = frames_document(frame_stats(gt, dt, EvalOptions().config(), FrameQuestion("Car")), worst=5)
    assert frames["frames"] == expected["frames"] and len(frames["frames"]) == 5 and frames["submission"] == dev
    sealed = c.get(f"/v1/benchmarks/kitti-phases/submissions/{test}/frames", headers=bearer(alice))
    assert sealed.status_code == 403 and sealed.json()["error"]["code"] == "sealed"
    assert c.get(f"/v1/benchmarks/kitti-phases/submissions/{dev}/frames", headers=bearer(bob)).status_code == 404


def test_the_client_submits_to_a_phase_it_names_and_checks_against_that_phases_frames(world, tmp_path) -> None:
    """``Client.submit(..., phase=)`` (``kitti-eval submit --phase``) sends to that phase, checked first against
    the frames its own route lists; without a phase, the current one; a phase that does not exist is refused."""
    import httpx

    from kitti_eval.client import Client
    from kitti_eval.errors import ServiceError

    c, hosted = world

    def forward(request: httpx.Request) -> httpx.Response:
        answer = c.request(
            request.method, request.url.raw_path.decode(), content=request.read(), headers=request.headers
        )
        return httpx.Response(answer.status_code, headers=answer.headers, content=answer.content)

    predictions = tmp_path / "result.pkl"
    predictions.write_bytes(golden_bytes("result.pkl"))
    with Client("https://testserver", hosted.tokens["alice"], transport=httpx.MockTransport(forward)) as client:
        test_frames = client.frames("kitti-phases", phase="test")
        assert test_frames == client.frames("kitti-phases") and len(test_frames) > 10  # both phases: one set's frames
        sent = client.submit(predictions, "kitti-phases", phase="test", wait=False)
        assert [s.id for s in client.submissions("kitti-phases", phase="test")] == [sent.id]
        assert client.submissions("kitti-phases") == [] and client.submissions("kitti-phases", phase="dev") == []
        assert client.quota("kitti-phases", phase="test").left == 1 and client.quota("kitti-phases").left == 5
        with pytest.raises(ServiceError):
            client.frames("kitti-phases", phase="nope")
    assert ok(c.get("/v1/benchmarks/kitti-phases/phases/test/frames"))["phase"] == "test"
    assert c.get("/v1/benchmarks/kitti-phases/phases/nope/frames").status_code == 404


def test_an_account_an_invitation_made_takes_part_in_every_phase_of_its_benchmark(world) -> None:
    c, _ = world
    invitations = c.app.state.service.invitations
    code = invitations.add("kitti-phases", uses=1, expires_days=None, project=None, caller=HOST)[1]
    token = ok(c.post(f"/v1/join/{code}", json={"name": "ivy"}), 201)["token"]
    for phase in ("dev", "test"):
        assert _submit(c, token, f"/v1/benchmarks/kitti-phases/phases/{phase}/submissions").status_code == 202
