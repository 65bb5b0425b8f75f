"""A benchmark's rules hold: the reveal only after the benchmark opened and closed, and never undone by a
reopen; the published selection frozen at the close (and capped per participant); participants see the public
part until the reveal; the test set stays sealed."""

from __future__ import annotations

import sqlite3
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta, timezone

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, GOLDEN, app_client, assert_error, golden_bytes

from kitti_eval.cli import main


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


def test_a_participant_publishes_at_most_max_published_entries(client) -> None:
    c = client
    hosted = host(c, benchmark={"quota": "10/1", "max_published": 2})
    assert ok(c.get("/v1/benchmarks/bench"))["max_published"] == 2
    ids = [ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"] for _ in range(3)]
    ok(_publish(c, hosted, "alice", ids[0]))
    ok(_publish(c, hosted, "alice", ids[1]))
    assert_error(_publish(c, hosted, "alice", ids[2]), 409, "at most 2", "withdraw")
    assert_error(_publish(c, hosted, "root", ids[2]), 409, "at most 2")  # the participant's cap, whoever asks
    ok(_publish(c, hosted, "alice", ids[1], "renamed"))  # publishing a published entry again takes no new place
    ok(_withdraw(c, hosted, "alice", ids[0]))
    ok(_publish(c, hosted, "alice", ids[2]))
    bob = ok(submit(c, hosted.headers("bob"), golden_bytes("result.pkl")), 201)["id"]
    ok(_publish(c, hosted, "bob", bob))  # a cap per participant
    methods = sorted(e["method"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"])
    assert methods == ["m", "m", "renamed"]
    body = {"name": "b2", "ground_truth": "test-set", "max_published": 0}
    assert_error(c.post("/v1/benchmarks", json=body, headers=ADMIN), 422)
    assert (
        ok(c.post("/v1/benchmarks", json={"name": "b3", "ground_truth": "test-set"}, headers=ADMIN), 201)[
            "max_published"
        ]
        is None
    )


def test_parallel_publishes_never_pass_the_cap(client) -> None:
    c = client
    hosted = host(c, benchmark={"quota": "10/1", "max_published": 1})
    ids = [ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"] for _ in range(4)]
    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(lambda sid: _publish(c, hosted, "alice", sid), ids))
    assert sorted(r.status_code for r in answers) == [200, 409, 409, 409], [r.text[:200] for r in answers]
    assert len(ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]) == 1


def test_max_published_from_the_cli(tmp_path, monkeypatch, capsys) -> None:
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))
    gt = str(GOLDEN / "kitti_infos_val.pkl")
    assert main(["admin", "ground-truth", "add", "test-set", gt, "--sealed"]) == 0
    assert main(["admin", "benchmark", "add", "b0", "--ground-truth", "test-set", "--max-published", "0"]) == 1
    assert "max_published" in capsys.readouterr().err
    assert main(["admin", "benchmark", "add", "kitti-3d", "--ground-truth", "test-set", "--max-published", "2"]) == 0
    assert "at most 2 published per participant" in capsys.readouterr().out
    with app_client(tmp_path / "data", auth="accounts") as c:
        ok(c.post("/v1/admin/users", json={"name": "u"}, headers=ADMIN), 201)
        token = ok(c.post("/v1/admin/tokens", json={"user": "u"}, headers=ADMIN), 201)["token"]
        assert ok(c.get("/v1/benchmarks/kitti-3d", headers={"Authorization": f"Bearer {token}"}))["max_published"] == 2


def test_a_database_from_before_max_published_is_upgraded(tmp_path) -> None:
    data = tmp_path / "data"
    with app_client(data, auth="accounts") as c:
        hosted = host(c)
        sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    db = sqlite3.connect(data / "kitti-eval.db")
    db.execute("ALTER TABLE benchmarks DROP COLUMN max_published")
    db.commit()
    db.close()
    with app_client(data, auth="accounts") as c:
        assert ok(c.get("/v1/benchmarks/bench"))["max_published"] is None
        ok(_publish(c, hosted, "alice", sid))
        body = {"name": "capped", "ground_truth": "test-set", "max_published": 1}
        assert ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)["max_published"] == 1
