"""The leaderboard's intervals in process (SQLite): every entry's 95% interval, rank range and difference to the
next from the benchmark's resamples, equal to the library's on the same files; the participant's comparison
equal to ``kitti-eval compare --bootstrap`` with the board's seed; kept with each scoring, and for entries
that lack them computed by a job, null meanwhile; the public part until the reveal, the private part after
it."""

from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from server_benchmarks import Hosted, ok, submit
from server_helpers import ADMIN, app_client
from server_postgres import PostgresCluster, why_no_postgres
from sqlalchemy import update

from kitti_eval.analysis.bootstrap import frame_weights, interval95
from kitti_eval.analysis.ranking import resampled_key
from kitti_eval.cli import main
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.result import ValueKey
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.synth import generate, write_infos, write_results
from kitti_eval_server.benchmarks.intervals import RESAMPLES, board_seed, intervals_job_id
from kitti_eval_server.benchmarks.rules import part_frames
from kitti_eval_server.scoring.evaluator import EvalOptions
from kitti_eval_server.store.database import benchmarks

KEY = "Car/3d/moderate/R40/strict"
FRAMES = 300


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """A 300-frame test set and four results: three draws of one detector and a draw of a clearly worse one
    (its boxes 10 cm further off)."""
    where = tmp_path_factory.mktemp("board-files")
    infos, _ = generate(FRAMES, seed=21, dets_per_frame=12.0)
    write_infos(where / "gt.pkl", infos)
    out = {"gt": where / "gt.pkl"}
    for name, seed in (("a", 1), ("b", 2), ("c", 3)):
        out[name] = where / f"{name}.pkl"
        write_results(out[name], generate(FRAMES, seed=21, dets_per_frame=12.0, detector_seed=seed)[1])
    out["worse"] = where / "worse.pkl"
    write_results(out["worse"], generate(FRAMES, seed=21, dets_per_frame=12.0, detector_seed=4, location_noise=0.1)[1])
    return out


def _host(c: Any, files: dict[str, Path], **benchmark: Any) -> Hosted:
    hosted = Hosted()
    for user in ("alice", "bob", "carol"):
        ok(c.post("/v1/admin/users", json={"name": user}, headers=ADMIN), 201)
        hosted.tokens[user] = ok(c.post("/v1/admin/tokens", json={"user": user}, headers=ADMIN), 201)["token"]
    gt = {"file": ("gt.pkl", files["gt"].read_bytes())}
    ok(c.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=gt, headers=ADMIN), 201)
    body = {"name": "bench", "ground_truth": "test-set", "quota": "5/1", "public": True, **benchmark}
    ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
    return hosted


def _enter(c: Any, hosted: Hosted, who: str, path: Path, method: str | None = None) -> dict[str, Any]:
    sub = ok(submit(c, hosted.headers(who), path.read_bytes()), 201)
    if method:
        ok(
            c.post(
                f"/v1/benchmarks/bench/submissions/{sub['id']}/publish",
                headers=hosted.headers(who),
                json={"method": method},
            )
        )
    return sub


def _settled(c: Any, timeout_s: float = 120.0) -> dict[str, Any]:
    """The board once no entry's resampled keys are being computed."""
    deadline = time.monotonic() + timeout_s
    while True:
        board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
        if board["bootstrap"]["pending"] == 0:
            return board
        assert time.monotonic() < deadline, board["bootstrap"]
        time.sleep(0.1)


def _library_interval(gt_path: Path, pred: Path, frames: list[str] | None, seed: int) -> tuple[float, float] | None:
    """The interval the library gives for one result's key over ``frames`` (all when None)."""
    gt, dt = load_ground_truth(gt_path), load_detections(pred)
    if frames is not None:
        gt, dt = gt.subset(frames), dt.subset(frames)
    weights = frame_weights(gt.num_frames, RESAMPLES, seed)
    values = resampled_key(plan_evaluation(gt, dt, EvalOptions().config()), [ValueKey.parse(KEY)], weights)
    return interval95(values)


def _r4(pair: tuple[float, float] | None) -> list[float] | None:
    return None if pair is None else [round(pair[0], 4), round(pair[1], 4)]


def test_each_entry_has_its_interval_rank_range_and_difference_to_the_next(tmp_path, files) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        _check_board(c, files)


@pytest.mark.slow
@pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")
def test_the_same_on_postgres(tmp_path, files) -> None:
    with PostgresCluster() as cluster:
        with app_client(tmp_path / "data", database_url=cluster.url, auth="accounts", auth_max_failures=10**6) as c:
            assert c.app.state.service.store.dialect == "postgresql"
            _check_board(c, files)


def _check_board(c: Any, files: dict[str, Path]) -> None:
    """Three entries, two draws of one detector and a worse one: the board's bootstrap, each entry's interval (the
    library's with the benchmark's seed), rank ranges, differences to the next, and the CSV."""
    hosted = _host(c, files)
    made = {
        who: _enter(c, hosted, who, files[name], method)
        for who, name, method in (("alice", "a", "A"), ("bob", "worse", "W"), ("carol", "b", "B"))
    }
    board = _settled(c)
    seed = board_seed("bench")
    assert board["bootstrap"] == {
        "method": "paired bootstrap over frames",
        "resamples": 1000,
        "seed": seed,
        "part": "whole",
        "level": 0.95,
        "pending": 0,
    }
    entries = board["entries"]
    assert [e["method"] for e in entries][2] == "W" and [e["rank"] for e in entries] == [1, 2, 3]
    # the same resamples for every entry: each interval is the library's with the benchmark's seed
    for e in entries:
        path = {"A": files["a"], "W": files["worse"], "B": files["b"]}[e["method"]]
        assert e["interval"] == _r4(_library_interval(files["gt"], path, None, seed)), e["method"]
        assert e["interval"][0] < e["key"] < e["interval"][1]
    # two draws of one detector are told apart by noise only; the worse one is third in every resample
    assert entries[0]["rank_range"] == [1, 2] and entries[1]["rank_range"] == [1, 2]
    assert entries[2]["rank_range"] == [3, 3]
    assert [e["differs_from_next"] for e in entries] == [False, True, None]
    # sorted otherwise, an entry keeps its own
    by_method = ok(c.get("/v1/benchmarks/bench/leaderboard", params={"sort": "method", "order": "asc"}))
    assert {e["id"]: e for e in by_method["entries"]} == {e["id"]: e for e in entries}
    # the CSV: four columns more, at the end
    rows = list(csv.reader(io.StringIO(c.get("/v1/benchmarks/bench/leaderboard", params={"format": "csv"}).text)))
    assert rows[0][-4:] == ["interval_low", "interval_high", "rank_best", "rank_worst"]
    for row, e in zip(rows[1:], entries):
        assert row[1] == e["method"]
        assert [float(x) for x in row[-4:-2]] == e["interval"] and [int(x) for x in row[-2:]] == e["rank_range"]
    assert made["bob"]["comparison"]["leader"]["difference"] < 0


def test_the_comparison_equals_kitti_eval_compare_with_the_boards_seed(tmp_path, files, capsys) -> None:
    """The board's paired interval of a difference is `kitti-eval compare A B --bootstrap 1000 --seed S`'s for
    the same pair: the same draws (frame_weights over the test set's frames with the board's seed) and the same
    arithmetic, so equal once both are rounded to the 4 places the board shows."""
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = _host(c, files)
        leader = _enter(c, hosted, "alice", files["a"], "A")
        first = _enter(c, hosted, "bob", files["worse"])
        second = _enter(c, hosted, "bob", files["c"])
        seed = board_seed("bench")
        comparison = ok(c.get(f"/v1/benchmarks/bench/submissions/{second['id']}", headers=hosted.headers("bob")))[
            "comparison"
        ]

        def cli(a: Path, b: Path) -> dict[str, Any]:
            argv = ["compare", str(a), str(b), "--gt", str(files["gt"]), "--bootstrap", "1000"]
            assert main([*argv, "--seed", str(seed), "--format", "json"]) == 0
            doc = json.loads(capsys.readouterr().out)
            (value,) = [v for v in doc["values"] if v["key"] == KEY]
            return value

        to_leader, to_first = cli(files["a"], files["c"]), cli(files["worse"], files["c"])
        assert comparison["part"] == "whole" and comparison["seed"] == seed and comparison["pending"] is False
        assert comparison["leader"]["id"] == leader["id"] and comparison["leader"]["method"] == "A"
        assert comparison["leader"]["interval"] == [round(x, 4) for x in to_leader["interval95"]]
        assert comparison["leader"]["difference"] == pytest.approx(to_leader["delta"], abs=2e-4)
        best = comparison["previous_best"]
        assert best["id"] == first["id"] and best["interval"] == [round(x, 4) for x in to_first["interval95"]]
        assert best["significant"] is True and best["difference"] > 10  # the better draw, after the worse one
        # the first submission has no earlier one; nobody else's unpublished submission is compared with
        alone = ok(c.get(f"/v1/benchmarks/bench/submissions/{first['id']}", headers=hosted.headers("bob")))
        assert alone["comparison"]["previous_best"] is None
        assert alone["comparison"]["leader"]["id"] == leader["id"]


def test_null_while_computed_then_computed_for_entries_that_lack_them(tmp_path, files) -> None:
    from sqlalchemy import delete, select

    from kitti_eval_server.store.database import jobs, submission_resamples

    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = _host(c, files)
        subs = [_enter(c, hosted, who, files[n], n) for who, n in (("alice", "a"), ("bob", "b"))]
        before = _settled(c)
        service = c.app.state.service
        service.workers.stop(5)
        try:
            with service.store.engine.begin() as conn:  # as a database from before the intervals would be
                conn.execute(delete(submission_resamples))
                conn.execute(delete(jobs).where(jobs.c.kind == "intervals"))
            board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
            assert board["bootstrap"]["pending"] == 2
            assert all(e["interval"] is None and e["rank_range"] is None for e in board["entries"])
            assert all(e["differs_from_next"] is None for e in board["entries"])
            assert [e["key"] for e in board["entries"]] == [e["key"] for e in before["entries"]]
            queued = []
            for sub in subs:  # the board queued the job of each, once
                row = service.store.benchmark_store.get_submission(sub["id"])
                queued.append(service.jobs.get(intervals_job_id(row.id, row.scored_at, board_seed("bench"), 1000)))
            assert [j.state for j in queued] == ["queued", "queued"]
            ok(c.get("/v1/benchmarks/bench/leaderboard"))
            assert service.jobs.counts(kind="intervals")["queued"] == 2
            mine = ok(c.get(f"/v1/benchmarks/bench/submissions/{subs[1]['id']}", headers=hosted.headers("bob")))
            assert mine["comparison"]["pending"] is True and mine["comparison"]["leader"]["interval"] is None
        finally:
            service.workers.start()
        assert _settled(c)["entries"] == before["entries"]
        # scored again: the kept values are dropped with the old scoring and computed for the new one
        rescored = ok(c.post("/v1/benchmarks/bench/rescore", headers=ADMIN), 202)
        for job_id in rescored["jobs"]:
            assert service.jobs.wait(job_id, 120).state == "done"
        after = _settled(c)
        assert after["entries"] == before["entries"]
        with service.store.engine.connect() as conn:
            kept = conn.execute(select(submission_resamples.c.submission_id, submission_resamples.c.scored_at)).all()
        assert sorted(sid for sid, _ in kept) == sorted(s["id"] for s in subs)
        for sid, scored_at in kept:
            row = service.store.benchmark_store.get_submission(sid)
            assert row.scored_at is not None and scored_at.replace(tzinfo=None) == row.scored_at.replace(tzinfo=None)
            assert row.scored_at.isoformat() != next(s for s in subs if s["id"] == sid)["scored_at"]


#: the split of the reveal test's benchmark
SPLIT_SEED = "5eed" * 8


def test_the_public_part_until_the_reveal_then_the_private_one(tmp_path, files) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = _host(c, files, split_percent=50)
        # a fixed split (the service draws a secret one): whether W's gap to A is significant on a half of the
        # frames depends on the half, and the claims below are about one split, the same in every run
        with c.app.state.service.store.engine.begin() as conn:
            conn.execute(update(benchmarks).where(benchmarks.c.name == "bench").values(split_seed=SPLIT_SEED))
        a = _enter(c, hosted, "alice", files["a"], "A")
        w = _enter(c, hosted, "bob", files["worse"], "W")
        seed = board_seed("bench")
        split_seed = c.app.state.service.store.benchmark_store.get_benchmark("bench").split_seed
        assert split_seed == SPLIT_SEED
        gt = load_ground_truth(files["gt"])
        parts = part_frames(split_seed, gt.frame_ids, 50)
        assert 100 < len(parts["public"]) < 200
        for phase, part in (("public", "public"), ("private", "private")):
            if phase == "private":
                ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
                ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
                board = ok(c.get("/v1/benchmarks/bench/leaderboard"))  # computed with the scoring: no wait
                assert board["bootstrap"]["pending"] == 0
            else:
                board = _settled(c)
            assert board["board"] == phase and board["bootstrap"]["part"] == part
            for e, path in zip(board["entries"], (files["a"], files["worse"])):
                assert e["interval"] == _r4(_library_interval(files["gt"], path, parts[part], seed)), (phase, e)
            mine = ok(c.get(f"/v1/benchmarks/bench/submissions/{w['id']}", headers=hosted.headers("bob")))
            leader = mine["comparison"]["leader"]
            assert mine["comparison"]["part"] == part and leader["id"] == a["id"]
            assert leader["key"] == board["entries"][0]["key"] and leader["significant"] is True
            assert np.isclose(leader["difference"], board["entries"][1]["key"] - board["entries"][0]["key"], atol=2e-4)
