"""A phase's life (scheduled, open, closed, revealed) is decided in one place that every surface obeys: the
machine's transitions, and the route, the admin command, the benchmark file and the time passing walked through
them; a revealed phase is never reopened by its file; teams change only while the benchmark runs, and the board
names the team an entry counted for when it was accepted; a team's invitation refused names nobody."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import pytest
from server_benchmarks import bearer, ok
from server_helpers import ADMIN, app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval.cli import main
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file
from kitti_eval_server.benchmarks.lifecycle import TRANSITIONS, PhaseState, check_change, state_of
from kitti_eval_server.errors import BadRequest, Conflict

NOW = datetime(2026, 6, 1, tzinfo=timezone.utc)
DAY = timedelta(days=1)
S, O, C, R = PhaseState.SCHEDULED, PhaseState.OPEN, PhaseState.CLOSED, PhaseState.REVEALED


@dataclass(frozen=True)
class _Row:
    opens_at: datetime
    closes_at: datetime | None
    closed: bool = False
    revealed: bool = False


#: a row in each state at NOW
ROWS = {
    S: _Row(NOW + DAY, NOW + 2 * DAY),
    O: _Row(NOW - DAY, NOW + DAY),
    C: _Row(NOW - 2 * DAY, NOW - DAY),
    R: _Row(NOW - 2 * DAY, NOW - DAY, revealed=True),
}

#: the changes of a row that take it from a state to another (the surfaces' writes)
MOVES = {
    "close": {"closed": True},
    "reopen": {"closed": False},
    "reveal": {"revealed": True},
    "later closes_at": {"closes_at": NOW + 5 * DAY},
    "earlier closes_at": {"closes_at": NOW - DAY / 2},
    "no closes_at": {"closes_at": None},
    "earlier opens_at": {"opens_at": NOW - 3 * DAY},
    "later opens_at": {"opens_at": NOW + DAY / 2},
}


def test_each_state_is_computed_from_the_row_and_the_time() -> None:
    assert {state: state_of(row, NOW) for state, row in ROWS.items()} == {S: S, O: O, C: C, R: R}
    assert state_of(ROWS[O], NOW + DAY) is C  # the time passing closes it
    assert state_of(ROWS[S], NOW + DAY) is O  # and opens it
    assert state_of(_Row(NOW - DAY, None, closed=True), NOW) is C  # closed by hand
    assert state_of(_Row(NOW + DAY, None, closed=True), NOW) is C  # closed by hand before it opens
    assert state_of(_Row(NOW - 2 * DAY, NOW + DAY, revealed=True), NOW) is R  # a later closes_at does not reopen it


@pytest.mark.parametrize(("state", "move"), list(itertools.product(ROWS, MOVES)))
def test_every_change_of_every_state_is_allowed_only_as_the_machine_says(state, move) -> None:
    row = ROWS[state]
    after = state_of(_replace(row, MOVES[move]), NOW)
    allowed = (
        (state is after and not (state is R and move not in ("close", "reveal")))
        or ((state, after) in TRANSITIONS and not (after is R and NOW < row.opens_at))
        or (state is C and after is S and NOW < row.opens_at)
    )
    if allowed:
        assert check_change("p", row, MOVES[move], now=NOW) == (state, after)
    else:
        with pytest.raises(Conflict):
            check_change("p", row, MOVES[move], now=NOW)


def test_the_transitions_are_those_of_a_phase_and_none_leaves_the_reveal() -> None:
    assert TRANSITIONS == {(S, O), (S, C), (O, C), (C, O), (C, R)}
    for name, move in MOVES.items():
        if name not in ("close", "reveal"):  # it stays closed and revealed: anything else is refused
            with pytest.raises(Conflict):
                check_change("p", ROWS[R], move, now=NOW)
    with pytest.raises(Conflict, match="not opened"):  # closed by hand before it opened: nothing to reveal
        check_change("p", _Row(NOW + DAY, None, closed=True), {"revealed": True}, now=NOW)
    with pytest.raises(Conflict, match="closed"):  # open: closed first
        check_change("p", ROWS[O], {"revealed": True}, now=NOW)


def _replace(row: _Row, changes: dict) -> _Row:
    return _Row(**{**row.__dict__, **changes})


# -------------------------------------------------------------------------------- the service's surfaces


def _at(delta: timedelta) -> str:
    return (datetime.now(timezone.utc) + delta).strftime("%Y-%m-%dT%H:%M:%SZ")


def _file(*, dev: tuple[timedelta, timedelta], test: tuple[timedelta, timedelta | None], team_size: int = 3) -> str:
    """TWO_PHASES with the phases' dates (from now), the test phase's quota 5 a day; its opens_at is on line 18,
    its closes_at on line 19."""
    text = TWO_PHASES.replace("team_size = 3", f"team_size = {team_size}")
    text = text.replace('quota = "5/1"', f'quota = "5/1"\nopens_at = {_at(dev[0])}\ncloses_at = {_at(dev[1])}')
    closes = f"\ncloses_at = {_at(test[1])}" if test[1] is not None else ""
    return text.replace('quota = "2/1"', f'quota = "5/1"\nopens_at = {_at(test[0])}{closes}')


def _apply(c, text: str):
    return apply_benchmark_file(c.app.state.benchmarks.catalog, text, caller=HOST, source="kitti-phases.toml")


def _state(c, phase: str = "test") -> str:
    one = ok(c.get(f"/v1/benchmarks/kitti-phases/phases/{phase}"))["state"]
    listed = {p["name"]: p["state"] for p in ok(c.get("/v1/benchmarks/kitti-phases"))["phases"]}
    assert listed[phase] == one  # the phase's own answer and the benchmark's entry agree
    return one


def _submit(c, token: str, phase: str = "test"):
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post(f"/v1/benchmarks/kitti-phases/phases/{phase}/submissions", files=files, headers=bearer(token))


TEST_ROW = "kitti-phases~test"
PHASE = "/v1/benchmarks/kitti-phases/phases/test"


@pytest.fixture()
def world(tmp_path, monkeypatch):
    data = tmp_path / "data"
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(data))
    with app_client(data, auth="accounts", auth_max_failures=1_000_000) as c:
        yield c, phased_world(c)


def test_every_surface_walks_a_phase_through_its_states(world, capsys) -> None:
    c, hosted = world
    alice = hosted.tokens["alice"]
    # the file: the test phase is scheduled (it opens in a day)
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(DAY, 30 * DAY)))
    assert _state(c, "dev") == "closed" and _state(c) == "scheduled"
    assert _submit(c, alice).status_code == 409
    assert c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN).status_code == 409  # nothing to reveal
    # the file: scheduled -> open (an earlier opens_at, the time having passed)
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, 30 * DAY)))
    assert _state(c) == "open"
    assert _submit(c, alice).status_code in (201, 202)
    assert c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN).status_code == 409  # open: close it first
    with pytest.raises(BadRequest, match=r"kitti-phases.toml, line 18: .*does not go back to being scheduled"):
        _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(DAY, 30 * DAY)))  # open -> scheduled
    # the route: open -> closed -> open
    assert ok(c.post(f"/v1/benchmarks/{TEST_ROW}/close", headers=ADMIN))["state"] == "closed"
    assert _state(c) == "closed" and _submit(c, alice).status_code == 409
    assert ok(c.post(f"/v1/benchmarks/{TEST_ROW}/reopen", headers=ADMIN))["state"] == "open"
    # the admin command: open -> closed -> open
    assert main(["admin", "benchmark", "close", TEST_ROW]) == 0
    assert f"benchmark {TEST_ROW}: closed" in capsys.readouterr().out and _state(c) == "closed"
    assert main(["admin", "benchmark", "reopen", TEST_ROW]) == 0
    assert f"benchmark {TEST_ROW}: open" in capsys.readouterr().out and _state(c) == "open"
    # the time passing: its closes_at comes (written as the file would, a second from now)
    c.app.state.benchmarks.catalog.benchmark_store.update_benchmark(
        TEST_ROW, closes_at=datetime.now(timezone.utc) - timedelta(seconds=1)
    )
    assert _state(c) == "closed" and _submit(c, alice).status_code == 409
    # the file: closed -> open (a later closes_at, before the reveal)
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, 30 * DAY)))
    assert _state(c) == "open"
    # the file: open -> closed (an earlier closes_at); then the admin command reveals it
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, -DAY / 2)))
    assert _state(c) == "closed"
    assert main(["admin", "benchmark", "reveal", TEST_ROW]) == 0
    assert f"benchmark {TEST_ROW}: revealed, board private" in capsys.readouterr().out
    assert _state(c) == "revealed"
    # none out of revealed: not the route, not the admin command, not the file, whatever its dates
    assert c.post(f"/v1/benchmarks/{TEST_ROW}/reopen", headers=ADMIN).status_code == 409
    assert main(["admin", "benchmark", "reopen", TEST_ROW]) == 1
    assert "stay closed" in capsys.readouterr().err
    for later, line in (((-DAY, 30 * DAY), 19), ((-DAY, None), 14), ((-2 * DAY, -DAY / 4), 19)):  # 14: [[phases]]
        with pytest.raises(BadRequest, match=rf"kitti-phases.toml, line {line}: the phase 'test' is revealed"):
            _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=later))
    assert _state(c) == "revealed"


def test_applying_the_file_never_reopens_a_revealed_phase(world) -> None:
    """A phase closed by its closes_at and revealed stays revealed when the file says a later closes_at: the
    file is refused at its line before anything is written, and nobody submits to the phase."""
    c, hosted = world
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-2 * DAY, -DAY)))
    ok(c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN))
    with pytest.raises(BadRequest, match=r"line 19: the phase 'test' is revealed"):
        _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-2 * DAY, 30 * DAY)))
    phase = ok(c.get("/v1/benchmarks/kitti-phases/phases/test"))
    assert phase["state"] == "revealed" and phase["open"] is False and phase["board"] == "private"
    assert datetime.fromisoformat(phase["closes_at"]) < datetime.now(timezone.utc)  # nothing was written
    assert _submit(c, hosted.tokens["carol"]).status_code == 409


def test_teams_change_only_while_the_benchmark_runs_and_the_board_keeps_each_entrys_team(world) -> None:
    c, hosted = world
    alice, bob, carol = (hosted.tokens[u] for u in ("alice", "bob", "carol"))
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, 30 * DAY)))
    url = "/v1/benchmarks/kitti-phases/teams"
    # alice and bob each submit alone and publish; then they make a team while the benchmark runs
    alone = {}
    for who, token in (("alice", alice), ("bob", bob)):
        sid = ok(_submit(c, token), 201)["id"]
        ok(
            c.post(
                f"/v1/benchmarks/kitti-phases/submissions/{sid}/publish", json={"method": who}, headers=bearer(token)
            )
        )
        alone[who] = sid
    ok(c.post(url, json={"name": "Pair", "members": ["bob"]}, headers=bearer(alice)), 201)
    ok(c.post(f"{url}/Pair/join", headers=bearer(bob)))
    together = ok(_submit(c, bob), 201)["id"]  # accepted for the team (its quota of 2: alice's alone counts)
    ok(c.post(f"/v1/benchmarks/kitti-phases/submissions/{together}/publish", json={"method": "t"}, headers=bearer(bob)))
    board = ok(c.get(f"{PHASE}/leaderboard"))
    teams = {e["id"]: e["team"] for e in board["entries"]}
    assert teams == {alone["alice"]: None, alone["bob"]: None, together: "Pair"}  # joined after the first two
    # the last phase closes, then is revealed: no team is made, joined or invited into
    ok(c.post(url, json={"name": "Late", "members": []}, headers=bearer(carol)), 201)  # while it runs
    ok(c.post(f"/v1/benchmarks/{TEST_ROW}/close", headers=ADMIN))
    for state in ("closed", "revealed"):
        made = c.post(url, json={"name": "After", "members": []}, headers=bearer(hosted.tokens["carol"]))
        assert made.status_code == 409 and "its teams no longer change" in made.json()["error"]["message"]
        if state == "closed":
            ok(c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN))
    final = ok(c.get(f"{PHASE}/leaderboard"))
    assert final["board"] == "private" and {e["id"]: e["team"] for e in final["entries"]} == teams


def test_two_who_spent_their_quotas_cannot_merge_after_the_final_ranking(world) -> None:
    c, hosted = world
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, 30 * DAY)))
    ok(c.post(f"/v1/benchmarks/{TEST_ROW}/close", headers=ADMIN))
    ok(c.post(f"/v1/benchmarks/{TEST_ROW}/reveal", headers=ADMIN))
    url = "/v1/benchmarks/kitti-phases/teams"
    made = c.post(url, json={"name": "Merged", "members": ["bob"]}, headers=bearer(hosted.tokens["alice"]))
    assert made.status_code == 409
    assert ok(c.get(url, headers=bearer(hosted.tokens["bob"])))["items"] == []


def test_a_refused_invitation_names_nobody_whoever_is_refused(world) -> None:
    c, hosted = world
    _apply(c, _file(dev=(-3 * DAY, -2 * DAY), test=(-DAY, 30 * DAY)))
    ok(c.post("/v1/admin/users", json={"name": "boss", "admin": True}, headers=ADMIN), 201)
    url = "/v1/benchmarks/kitti-phases/teams"
    ok(c.post(url, json={"name": "Taken", "members": []}, headers=bearer(hosted.tokens["carol"])), 201)
    answers = set()
    for invited in (["bob", "no-such-user"], ["no-such-user", "bob"], ["boss"], ["carol"], ["bob", "carol"]):
        refused = c.post(url, json={"name": "Probe", "members": invited}, headers=bearer(hosted.tokens["alice"]))
        assert refused.status_code == 422
        message = refused.json()["error"]["message"]
        assert not any(name in message for name in ("bob", "no-such-user", "boss", "carol"))
        answers.add(message)
    assert len(answers) == 1  # one refusal, whoever it is about
    assert ok(c.get(url, headers=bearer(hosted.tokens["alice"])))["mine"] is None  # and nothing was made
