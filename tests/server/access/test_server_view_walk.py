"""Every view of a benchmark, a submission, a job and a board, for every kind of caller (an admin, the
participant, another project's member, the participant's read-only token, an anonymous visitor), before and
after the reveal: each view holds exactly the fields of its allow-list, and a caller who may not see it is
told it is not there."""

from __future__ import annotations

import pickle
from typing import Any

import pytest
from server_accounts import make_teams
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, golden_bytes

from kitti_eval_server.benchmarks.rules import part_frames
from kitti_eval_server.benchmarks.views import (
    BENCHMARK_FIELDS,
    BOARD_FIELDS,
    ENTRY_FIELDS,
    OWN_SUBMISSION_FIELDS,
    RESULT_FIELDS,
    SUBMISSION_FIELDS,
    TEST_SET_FIELDS,
)
from kitti_eval_server.jobs.workers import JOB_FIELDS

CALLERS = ("admin", "participant", "other-project", "read-only", "anonymous")
_TOKENS = {"admin": "root", "participant": "alice", "other-project": "bob", "read-only": "alice-ro"}
#: what the single benchmark's view adds for an admin
_ADMIN_BENCHMARK = (*TEST_SET_FIELDS, "rescoring")
_MINE = ("items", "quota", "baselines")
_COMPARISON = ("method", "resamples", "seed", "part", "level", "key", "pending", "previous_best", "leader")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    with app_client(tmp_path_factory.mktemp("walk") / "data", auth="accounts", auth_max_failures=10**6) as c:
        teams = make_teams(c)
        body = {"name": "walk", "ground_truth": "sealed-a", "public": True, "split_percent": 50, "quota": "5/1"}
        ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        alice = teams.headers("alice")
        sid = ok(submit(c, alice, golden_bytes("result.pkl"), name="walk"), 201)["id"]
        ok(c.post(f"/v1/benchmarks/walk/submissions/{sid}/publish", json={"method": "m"}, headers=alice))
        yield c, teams, sid


def headers_of(teams: Any, who: str) -> dict[str, str]:
    return teams.headers(_TOKENS[who]) if who in _TOKENS else {}


def exactly(view: dict[str, Any], fields: tuple[str, ...], what: str) -> None:
    assert set(view) == set(fields), (
        f"{what}: more {sorted(set(view) - set(fields))}, less {sorted(set(fields) - set(view))}"
    )


def walk(c: Any, teams: Any, sid: str, who: str) -> None:
    h = headers_of(teams, who)
    names_test_set = who in ("admin", "participant", "read-only")
    described = ok(c.get("/v1/benchmarks/walk", headers=h))
    exactly(
        described,
        _ADMIN_BENCHMARK if who == "admin" else TEST_SET_FIELDS if names_test_set else BENCHMARK_FIELDS,
        f"{who}: benchmark",
    )
    (listed,) = ok(c.get("/v1/benchmarks", headers=h))["items"]
    exactly(listed, TEST_SET_FIELDS if names_test_set else BENCHMARK_FIELDS, f"{who}: benchmarks")
    board = ok(c.get("/v1/benchmarks/walk/leaderboard", headers=h))
    exactly(board, BOARD_FIELDS, f"{who}: board")
    (entry,) = board["entries"]
    exactly(entry, ENTRY_FIELDS, f"{who}: board entry")

    mine = c.get("/v1/benchmarks/walk/submissions", headers=h)
    own = c.get(f"/v1/benchmarks/walk/submissions/{sid}", headers=h)
    job = c.get(f"/v1/jobs/{sid}", headers=h)
    if who == "anonymous":
        assert (mine.status_code, own.status_code, job.status_code) == (401, 401, 401)
        return
    exactly(mine.json(), _MINE, f"{who}: own list")
    if who in ("participant", "read-only"):
        (item,) = mine.json()["items"]
        exactly(item, SUBMISSION_FIELDS, f"{who}: own list item")
        seen = ok(own)
        exactly(seen, (*OWN_SUBMISSION_FIELDS, "comparison"), f"{who}: own submission")
        exactly(seen["result"], RESULT_FIELDS, f"{who}: own result")
        exactly(seen["comparison"], _COMPARISON, f"{who}: comparison")
        exactly(ok(job), tuple(k for k in JOB_FIELDS if k not in ("evaluation", "error")), f"{who}: job")
        return
    assert mine.json()["items"] == []
    assert own.status_code == 404  # nobody but its participant reads a submission, an admin neither: submissions/all
    if who == "admin":
        (item,) = ok(c.get("/v1/benchmarks/walk/submissions/all", headers=h))["items"]
        exactly(item, SUBMISSION_FIELDS, "admin: every submission")
        assert job.status_code == 200
    else:
        assert job.status_code == 404
        assert c.get("/v1/benchmarks/walk/submissions/all", headers=h).status_code == 403


def test_every_view_for_every_caller_before_and_after_the_reveal(world) -> None:
    c, teams, sid = world
    for who in CALLERS:
        walk(c, teams, sid, who)
    ok(c.post("/v1/benchmarks/walk/close", headers=ADMIN))
    ok(c.post("/v1/benchmarks/walk/reveal", headers=ADMIN))
    for who in CALLERS:
        walk(c, teams, sid, who)


def test_two_submissions_differing_in_the_private_part_look_alike_until_the_reveal(tmp_path) -> None:
    """Submissions that differ only in frames of the private part: their participant views are the same until
    the reveal (no AP of the private part is shown), then differ only in the AP values of the whole set and of
    the private part."""
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=10**6) as c:
        hosted = host(c, benchmark={"split_percent": 50})
        seed = c.app.state.service.store.benchmark_store.get_benchmark("bench").split_seed
        annos = pickle.loads(golden_bytes("result.pkl"))  # the test's own golden file
        private = set(part_frames(seed, [a["frame_id"] for a in annos], 50)["private"])
        for anno in annos:  # the same boxes, 30 cm off, in every private frame: the private part's AP drops
            if anno["frame_id"] in private:
                anno["location"] = anno["location"] + [0.3, 0.0, 0.3]
        ids = {}
        for who, data in (("alice", golden_bytes("result.pkl")), ("bob", pickle.dumps(annos))):
            ids[who] = ok(submit(c, hosted.headers(who), data), 201)["id"]

        def views() -> list[dict[str, Any]]:
            out = []
            for who, sid in ids.items():
                seen = ok(c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=hosted.headers(who)))
                out.append(
                    {
                        k: v
                        for k, v in seen.items()
                        if k not in ("id", "participant", "created_at", "sha256", "size", "scored_at")
                    }
                )
            return out

        before = views()
        assert before[0] == before[1]
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
        after = views()
        differ = {k for k in after[0] if after[0][k] != after[1][k]}
        assert differ == {"scores", "parts", "result", "comparison"}, differ
        assert after[0]["parts"]["public"] == after[1]["parts"]["public"]
        assert after[0]["parts"]["private"] != after[1]["parts"]["private"]
        a, b = after[0]["result"], after[1]["result"]
        assert {k for k in a if a[k] != b[k]} == {"ap"}
        assert after[0]["comparison"]["key"] != after[1]["comparison"]["key"]
