"""A benchmark's rules hold: the reveal only after the benchmark opened and closed, and never undone by a
reopen; the published selection frozen at the close (and capped per participant); participants see the public
part until the reveal; the test set stays sealed."""

from __future__ import annotations

import json
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta, timezone

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, GOLDEN, app_client, assert_error, golden_bytes
from sqlalchemy import update
from unversioned import as_unversioned

from kitti_eval.cli import main
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval_server.benchmarks import in_public_part
from kitti_eval_server.benchmarks.views import RESULT_FIELDS
from kitti_eval_server.scoring.evaluator import EvalOptions, evaluate_document
from kitti_eval_server.store import ground_truths


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
    body = {"name": "ended", "ground_truth": "test-set", "split_percent": 50, "share_test_set": True}
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
    assert_error(_publish(c, hosted, "root", other), 404)  # an admin publishes no participant's entry
    ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
    board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
    assert board["board"] == "private" and [e["id"] for e in board["entries"]] == [chosen]


def test_a_passed_closes_at_freezes_the_selection_too(client) -> None:
    c = client
    hosted = host(c)
    sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    ok(_publish(c, hosted, "alice", sid))
    c.app.state.service.store.benchmark_store.update_benchmark(
        "bench", closes_at=datetime.now(timezone.utc) - timedelta(seconds=1)
    )
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
    assert_error(_publish(c, hosted, "root", ids[2]), 404)  # only its participant publishes an entry
    ok(_publish(c, hosted, "alice", ids[1], "renamed"))  # publishing a published entry again takes no new place
    ok(_withdraw(c, hosted, "alice", ids[0]))
    ok(_publish(c, hosted, "alice", ids[2]))
    bob = ok(submit(c, hosted.headers("bob"), golden_bytes("result.pkl")), 201)["id"]
    ok(_publish(c, hosted, "bob", bob))  # a cap per participant
    methods = sorted(e["method"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"])
    assert methods == ["m", "m", "renamed"]
    body = {"name": "b2", "ground_truth": "test-set", "max_published": 0, "share_test_set": True}
    assert_error(c.post("/v1/benchmarks", json=body, headers=ADMIN), 422)
    assert (
        ok(
            c.post(
                "/v1/benchmarks", json={"name": "b3", "ground_truth": "test-set", "share_test_set": True}, headers=ADMIN
            ),
            201,
        )["max_published"]
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
    assert main(["admin", "--create", "ground-truth", "add", "test-set", gt, "--sealed"]) == 0
    assert main(["admin", "benchmark", "add", "b0", "--ground-truth", "test-set", "--max-published", "0"]) == 1
    assert "max_published" in capsys.readouterr().err
    assert main(["admin", "benchmark", "add", "kitti-3d", "--ground-truth", "test-set", "--max-published", "2"]) == 0
    assert "at most 2 published per participant" in capsys.readouterr().out
    with app_client(tmp_path / "data", auth="accounts") as c:
        ok(c.post("/v1/admin/users", json={"name": "u"}, headers=ADMIN), 201)
        token = ok(c.post("/v1/admin/tokens", json={"user": "u"}, headers=ADMIN), 201)["token"]
        assert ok(c.get("/v1/benchmarks/kitti-3d", headers={"Authorization": f"Bearer {token}"}))["max_published"] == 2


def test_a_database_from_before_max_published_public_result_and_baselines_is_upgraded(tmp_path) -> None:
    data = tmp_path / "data"
    with app_client(data, auth="accounts") as c:
        hosted = host(c)
        sid = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)["id"]
    db = sqlite3.connect(data / "kitti-eval.db")
    db.execute("ALTER TABLE benchmarks DROP COLUMN max_published")
    db.execute("ALTER TABLE submissions DROP COLUMN public_result")
    db.execute("ALTER TABLE submissions DROP COLUMN baseline")
    as_unversioned(db.execute)  # an unversioned release's: upgraded at start, as told
    db.commit()
    db.close()
    with app_client(data, auth="accounts", db_upgrade=True) as c:
        assert ok(c.get("/v1/benchmarks/bench"))["max_published"] is None
        assert ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=hosted.headers("alice")))["result"]
        ok(_publish(c, hosted, "alice", sid))
        entries = ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]
        assert [(e["id"], e["rank"], e["baseline"]) for e in entries] == [(sid, 1, False)]  # an old row: no baseline
        baseline = ok(submit(c, hosted.headers("root"), golden_bytes("result.pkl")), 201)
        assert baseline["baseline"] is True
        body = {"name": "capped", "ground_truth": "test-set", "max_published": 1, "share_test_set": True}
        assert ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)["max_published"] == 1


# ------------------------------------------------------------------------------- what participants see

KEY = "Car/3d/moderate/R40/strict"


def _ap(doc) -> float:
    return float(doc["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"])


def _fresh(seed: str) -> dict[str, float]:
    """The key's AP of the golden result.pkl on the whole test set and on each part of the split."""
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "result.pkl")
    public = [f for f in gt.frame_ids if in_public_part(seed, f, 50)]
    private = [f for f in gt.frame_ids if f not in public]
    config = EvalOptions().config()
    parts = {"all": list(gt.frame_ids), "public": public, "private": private}
    return {p: round(_ap(evaluate_document(gt.subset(fr), dt.subset(fr), config)), 4) for p, fr in parts.items()}


def test_participants_see_the_public_part_until_the_reveal(client) -> None:
    c = client
    hosted = host(c, benchmark={"split_percent": 50})
    alice = hosted.headers("alice")
    made = ok(submit(c, alice, golden_bytes("result.pkl")), 201)
    want = _fresh(c.app.state.service.store.benchmark_store.get_benchmark("bench").split_seed)
    assert len(set(want.values())) == 3  # the three scores are told apart
    one = ok(c.get(f"/v1/benchmarks/bench/submissions/{made['id']}", headers=alice))
    (listed,) = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))["items"]
    for seen in (made, one, listed):
        assert seen["scored_on"] == "public" and seen["scores"][KEY] == want["public"], seen
        assert seen["parts"] is None
    for seen in (made, one):  # the aggregate document is the public part's
        assert _ap(seen["result"]) == pytest.approx(want["public"], abs=1e-4)
        assert set(seen["result"]) == set(RESULT_FIELDS) and seen["result"]["frames"] == 50
        assert not {"num_gt", "frames_without_predictions", "curves", "warnings"} & set(seen["result"])
    for text in (str(want["all"]), str(want["private"])):
        assert text not in json.dumps([made, one, listed])
    # an admin's list holds everything
    (full,) = ok(c.get("/v1/benchmarks/bench/submissions/all", headers=ADMIN))["items"]
    assert full["scored_on"] == "all" and full["scores"][KEY] == want["all"]
    assert {p: s[KEY] for p, s in full["parts"].items()} == {"public": want["public"], "private": want["private"]}
    # after the reveal, the whole set and both parts
    ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
    ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
    one = ok(c.get(f"/v1/benchmarks/bench/submissions/{made['id']}", headers=alice))
    assert one["scored_on"] == "all" and one["scores"][KEY] == want["all"]
    assert _ap(one["result"]) == pytest.approx(want["all"], abs=1e-4)
    assert {p: s[KEY] for p, s in one["parts"].items()} == {"public": want["public"], "private": want["private"]}
    (listed,) = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))["items"]
    assert listed["scores"][KEY] == want["all"] and listed["parts"]["private"][KEY] == want["private"]


def test_a_submission_scored_before_the_public_document_was_kept_shows_no_result_until_the_reveal(client) -> None:
    c = client
    hosted = host(c, benchmark={"split_percent": 50})
    made = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
    c.app.state.service.store.benchmark_store.update_submission(made["id"], public_result=None)
    one = ok(c.get(f"/v1/benchmarks/bench/submissions/{made['id']}", headers=hosted.headers("alice")))
    assert one["result"] is None and one["scores"] == made["scores"]


def test_without_a_split_the_whole_set_is_the_public_part(client) -> None:
    c = client
    hosted = host(c)
    made = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
    fresh = _fresh("unused")["all"]
    assert made["scored_on"] == "all" and made["scores"][KEY] == fresh and made["parts"] is None
    assert _ap(made["result"]) == pytest.approx(fresh, abs=1e-4)


# ------------------------------------------------------------------------------------- the sealed set


def test_a_benchmarks_test_set_is_registered_again_only_sealed(client, tmp_path, monkeypatch, capsys) -> None:
    c = client
    host(c)
    files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
    assert c.delete("/v1/ground-truths/test-set", headers=ADMIN).status_code == 204
    refused = c.post("/v1/ground-truths", data={"name": "test-set"}, files=files, headers=ADMIN)
    assert_error(refused, 409, "benchmark", "'bench'", "sealed")
    assert c.get("/v1/ground-truths/test-set", headers=ADMIN).status_code == 404  # nothing was registered
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):  # the CLI on the same data folder
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))
    assert main(["admin", "ground-truth", "add", "test-set", str(GOLDEN / "kitti_infos_val.pkl")]) == 1
    assert "'bench'" in capsys.readouterr().err
    ok(c.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=files, headers=ADMIN), 201)
    ok(c.post("/v1/ground-truths", data={"name": "other"}, files=files, headers=ADMIN), 201)  # no benchmark's


def test_a_test_set_that_is_not_sealed_is_refused_where_submissions_are_scored(client) -> None:
    c = client
    hosted = host(c)
    alice = hosted.headers("alice")
    ok(submit(c, alice, golden_bytes("result.pkl")), 201)
    with c.app.state.service.store.engine.begin() as conn:  # a row changed behind the service's back
        conn.execute(update(ground_truths).where(ground_truths.c.name == "test-set").values(sealed=False))
    assert_error(c.get("/v1/benchmarks/bench/frames", headers=alice), 409, "not sealed", "'bench'")
    assert_error(submit(c, alice, golden_bytes("result.pkl")), 409, "not sealed")
    assert_error(c.post("/v1/benchmarks/bench/rescore", headers=ADMIN), 409, "not sealed")
    assert ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))["quota"]["used"] == 1  # nothing counted


def test_the_benchmarks_using_a_ground_truth(client) -> None:
    c = client
    host(c)
    body = {"name": "again", "ground_truth": "test-set", "share_test_set": True}
    ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
    benchmarks = c.app.state.benchmarks
    assert [b.name for b in benchmarks.catalog.using_ground_truth("test-set")] == ["again", "bench"]
    assert benchmarks.catalog.using_ground_truth("demo") == []
    assert [b.name for b in c.app.state.service.store.benchmark_store.benchmarks_using("test-set")] == [
        "again",
        "bench",
    ]
