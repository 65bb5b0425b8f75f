"""A benchmark's rules hold: the reveal only after the benchmark opened and closed, and never undone by a
reopen; the published selection frozen at the close (and capped per participant); participants see the public
part until the reveal; the test set stays sealed."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, assert_error, golden_bytes


def _at(delta: timedelta) -> str:
    return (datetime.now(timezone.utc) + delta).isoformat()


@pytest.fixture()
def client(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        yield c


# ---------------------------------------------------------------------------------------------- reveal


def test_reveal_needs_the_benchmark_opened_and_closed(client) -> None:
    c = client
    host(c, benchmark={"split_percent": 50, "opens_at": _at(timedelta(days=1))})
    # not open yet (so not taking submissions), but not closed either: nothing to reveal
    assert_error(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN), 409, "not opened")
    ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
    assert_error(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN), 409, "not opened")  # closed before it opened
    assert ok(c.get("/v1/benchmarks/bench"))["revealed"] is False


def test_reveal_while_open_is_refused_and_a_passed_closes_at_is_a_close(client) -> None:
    c = client
    host(c, benchmark={"split_percent": 50})
    assert_error(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN), 409, "closed")
    body = {"name": "ended", "ground_truth": "test-set", "split_percent": 50}
    body |= {"opens_at": _at(-timedelta(days=2)), "closes_at": _at(-timedelta(days=1))}
    ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
    assert ok(c.post("/v1/benchmarks/ended/reveal", headers=ADMIN))["board"] == "private"  # no explicit close needed


def test_a_revealed_benchmark_is_not_reopened(client) -> None:
    c = client
    hosted = host(c, benchmark={"split_percent": 50})
    ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
    ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
    err = assert_error(c.post("/v1/benchmarks/bench/reopen", headers=ADMIN), 409)
    assert err["message"] == "revealed benchmarks stay closed: the private part's scores are out"
    info = ok(c.get("/v1/benchmarks/bench"))
    assert info["open"] is False and info["revealed"] is True and info["board"] == "private"
    assert_error(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 409, "not open")


# ------------------------------------------------------------------------------------- the selection


def _publish(c, hosted, who: str, sid: str, method: str = "m"):
    return c.post(
        f"/v1/benchmarks/bench/submissions/{sid}/publish", headers=hosted.headers(who), json={"method": method}
    )


def _withdraw(c, hosted, who: str, sid: str):
    return c.post(f"/v1/benchmarks/bench/submissions/{sid}/withdraw", headers=hosted.headers(who))


def test_the_published_selection_freezes_at_the_close(client) -> None:
    c = client
    hosted = host(c, benchmark={"split_percent": 50})
    alice = hosted.headers("alice")
    chosen = ok(submit(c, alice, golden_bytes("result.pkl")), 201)["id"]
    other = ok(submit(c, alice, golden_bytes("result.pkl")), 201)["id"]
    ok(_publish(c, hosted, "alice", chosen, "chosen"))
    ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
    assert_error(_publish(c, hosted, "alice", other), 409, "closed")
    assert_error(_withdraw(c, hosted, "alice", chosen), 409, "closed")
    assert_error(_publish(c, hosted, "root", other), 409, "closed")  # an admin neither
    ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
    board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
    assert board["board"] == "private" and [e["id"] for e in board["entries"]] == [chosen]


def test_a_passed_closes_at_freezes_the_selection_too(client) -> None:
    c = client
    hosted = host(c)
    sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    ok(_publish(c, hosted, "alice", sid))
    c.app.state.service.store.update_benchmark("bench", closes_at=datetime.now(timezone.utc) - timedelta(seconds=1))
    assert_error(_withdraw(c, hosted, "alice", sid), 409, "closed")
    assert [e["id"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]] == [sid]
