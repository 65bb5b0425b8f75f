"""Hosted benchmarks in process (SQLite): validation before the quota, the atomic quota under 20 parallel
submissions, publishing, the leaderboard (JSON, CSV, sorting, the page), admin actions and rescoring."""

from __future__ import annotations

import csv
import io
import json
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, GOLDEN, app_client, golden_bytes, golden_txt, tar_of, zip_of

from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.io.submission import SubmissionRules, validate_submission
from kitti_eval_server.benchmarks import in_public_part, render_markdown
from kitti_eval_server.benchmarks.views import RESULT_FIELDS
from kitti_eval_server.scoring.evaluator import EvalOptions, evaluate_document
from kitti_eval_server.scoring.uploads import receive_upload


@pytest.fixture()
def world(tmp_path):
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        yield c, host(c)


def submit_now(c, headers):
    files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
    return c.post("/v1/benchmarks/bench/submissions", params={"wait": 0}, files=files, headers=headers)


def await_rescoring(c, job_ids, timeout_s: float = 120.0) -> None:
    queue = c.app.state.service.jobs
    for job_id in job_ids:
        ended = queue.wait(job_id, timeout_s)
        assert ended is not None and ended.state == "done", ended


def fresh_ap(gt_path, pred_path, column="Car/3d/moderate/R40/strict") -> float:
    gt, dt = load_ground_truth(gt_path), load_detections(pred_path)
    doc = evaluate_document(gt, dt, EvalOptions().config())
    cls, metric, difficulty, recall, oset = column.split("/")
    return round(float(doc["ap"][oset][recall][cls][metric][difficulty]), 4)


def test_an_invalid_submission_lists_the_validators_sentences_and_costs_nothing(world, tmp_path) -> None:
    c, hosted = world
    txt = golden_txt("pred.tar.gz")
    broken = dict(list(txt.items())[2:])  # two test frames missing
    first = next(iter(broken))
    broken[first] = b"Car 0 0 0 1 2 3\n"  # too few fields
    data = zip_of(broken)
    response = submit(c, hosted.headers("alice"), data, "broken.zip")
    body = response.json()
    assert response.status_code == 422 and body["error"]["code"] == "invalid_submission"
    path = tmp_path / "broken.zip"
    path.write_bytes(data)
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    expected = validate_submission(path, SubmissionRules(frames=tuple(gt.frame_ids))).lines()
    assert body["error"]["problems"] == expected and len(expected) == 2
    assert "2 test frames are missing: 000000, 000001" in expected
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))
    assert mine["items"] == [] and mine["quota"] == {
        "submissions": 3,
        "days": 1.0,
        "used": 0,
        "left": 3,
        "next_at": None,
    }


def test_twenty_parallel_submissions_against_a_quota_of_three_admit_exactly_three(world) -> None:
    c, hosted = world
    data = golden_bytes("result.pkl")
    with ThreadPoolExecutor(20) as pool:
        answers = list(pool.map(lambda _: submit(c, hosted.headers("alice"), data), range(20)))
    statuses = sorted(r.status_code for r in answers)
    assert statuses == [201] * 3 + [429] * 17, [r.text[:200] for r in answers if r.status_code not in (201, 429)]
    accepted = [r.json() for r in answers if r.status_code == 201]
    assert all(a["status"] == "scored" for a in accepted)
    refused = next(r for r in answers if r.status_code == 429)
    retry_at = datetime.fromisoformat(refused.json()["error"]["retry_at"])
    oldest = min(datetime.fromisoformat(a["created_at"]) for a in accepted)
    assert abs((retry_at - oldest).total_seconds() - 86400) < 1
    retry = int(refused.headers["Retry-After"])
    assert 86400 - 120 <= retry <= 86400 + 1
    assert (retry_at - datetime.now(timezone.utc)).total_seconds() == pytest.approx(retry, abs=120)
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=hosted.headers("alice")))
    assert len(mine["items"]) == 3 and mine["quota"]["left"] == 0
    assert mine["quota"]["next_at"] == retry_at.isoformat()  # the list says when the 429s say
    # another participant has a quota of their own
    assert submit(c, hosted.headers("bob"), data).status_code == 201


def test_results_publishing_and_the_leaderboard(world) -> None:
    c, hosted = world
    alice, bob = hosted.headers("alice"), hosted.headers("bob")
    a = ok(submit(c, alice, golden_bytes("result.pkl")), 201)
    b = ok(submit(c, bob, tar_of(golden_txt("pred.tar.gz")), "pred.tar.gz"), 201)
    expected = fresh_ap(GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl")
    assert a["scores"]["Car/3d/moderate/R40/strict"] == expected
    assert a["result"]["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] == pytest.approx(expected, abs=1e-4)
    assert set(a["result"]) == set(RESULT_FIELDS)  # no per-frame detail, no count of the sealed set's objects
    assert not {"num_gt", "frames_without_predictions", "curves", "warnings"} & set(a["result"])
    # nobody sees another participant's submission; the board shows only published entries
    assert c.get(f"/v1/benchmarks/bench/submissions/{a['id']}", headers=bob).status_code == 404
    assert ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"] == []
    ok(c.post(f"/v1/benchmarks/bench/submissions/{a['id']}/publish", headers=bob, json={"method": "x"}), 404)
    published = {"method": "PointPillars-ish", "affiliation": "Lab A", "link": "https://example.org/a"}
    ok(c.post(f"/v1/benchmarks/bench/submissions/{a['id']}/publish", headers=alice, json=published))
    ok(
        c.post(
            f"/v1/benchmarks/bench/submissions/{b['id']}/publish", headers=bob, json={"method": "B", "anonymous": True}
        )
    )
    board = ok(c.get("/v1/benchmarks/bench/leaderboard"))  # public: no token needed
    assert [e["method"] for e in board["entries"]] == ["PointPillars-ish", "B"]  # the same AP: by time
    first, second = board["entries"]
    assert first["rank"] == 1 and first["key"] == expected and first["participant"] == "alice"
    assert second["participant"] is None and second["affiliation"] is None and second["key"] == expected
    assert set(first["columns"]) == {
        f"{k}/3d/{d}/R40/strict" for k in ("Car", "Pedestrian", "Cyclist") for d in ("easy", "moderate", "hard")
    }
    assert "result" not in first
    # sorting by a column, and CSV
    by_method = ok(c.get("/v1/benchmarks/bench/leaderboard", params={"sort": "method", "order": "asc"}))
    assert [e["method"] for e in by_method["entries"]] == ["B", "PointPillars-ish"]
    text = c.get("/v1/benchmarks/bench/leaderboard", params={"format": "csv"}).text
    rows = list(csv.reader(io.StringIO(text)))
    header = [
        "rank",
        "method",
        "participant",
        "team",
        "affiliation",
        "link",
        "date",
        "key (Car/3d/moderate/R40/strict)",
    ]
    assert rows[0][:8] == header and "Car/3d/moderate/R40/strict" in rows[0][8:]  # the key and its column
    assert len(set(rows[0])) == len(rows[0])  # every column's name once
    assert rows[1][:4] == ["1", "PointPillars-ish", "alice", ""] and float(rows[1][7]) == expected  # no team
    # the page, without a token
    page = c.get("/benchmarks/bench")
    assert (
        page.status_code == 200 and "PointPillars-ish" in page.text and "<script" not in page.text.split("</head>")[1]
    )
    # withdrawing takes the entry off; disqualifying hides it
    ok(c.post(f"/v1/benchmarks/bench/submissions/{b['id']}/withdraw", headers=bob))
    assert [e["method"] for e in ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]] == ["PointPillars-ish"]
    ok(c.post(f"/v1/benchmarks/bench/submissions/{a['id']}/disqualify", headers=ADMIN))
    assert ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"] == []
    every = ok(c.get("/v1/benchmarks/bench/submissions/all", headers=hosted.headers("root")))["items"]
    assert {s["id"]: s["disqualified"] for s in every} == {a["id"]: True, b["id"]: False}


def test_a_private_benchmark_is_invisible_without_a_token_and_closing_stops_submissions(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"public": False})
        assert c.get("/v1/benchmarks/bench/leaderboard").status_code == 404
        assert c.get("/benchmarks/bench").status_code == 404
        assert ok(c.get("/v1/benchmarks/bench/leaderboard", headers=hosted.headers("alice")))["entries"] == []
        frames = ok(c.get("/v1/benchmarks/bench/frames", headers=hosted.headers("alice")))["frames"]
        assert len(frames) == 50 and frames[0] == "000000"
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        assert submit(c, hosted.headers("alice"), golden_bytes("result.pkl")).status_code == 409
        ok(c.post("/v1/benchmarks/bench/reopen", headers=ADMIN))
        assert submit(c, hosted.headers("alice"), golden_bytes("result.pkl")).status_code == 201
        assert c.post("/v1/benchmarks/bench/close", headers=hosted.headers("alice")).status_code == 403


def test_rescoring_after_the_ground_truth_changed_equals_fresh_evaluations(world, tmp_path) -> None:
    c, hosted = world
    alice, bob = hosted.headers("alice"), hosted.headers("bob")
    a = ok(submit(c, alice, golden_bytes("result.pkl")), 201)
    b = ok(submit(c, bob, tar_of(golden_txt("pred.tar.gz")), "pred.tar.gz"), 201)
    for sid, who in ((a["id"], alice), (b["id"], bob)):
        ok(c.post(f"/v1/benchmarks/bench/submissions/{sid}/publish", headers=who, json={"method": sid[:8]}))
    # the corrected test set: every frame's label files with the last Car of each frame dropped
    labels = golden_txt("label_2.tar.gz")
    changed = {}
    for member, content in labels.items():
        lines = content.decode().splitlines()
        cars = [i for i, line in enumerate(lines) if line.startswith("Car ")]
        if cars:
            del lines[cars[-1]]
        changed[member] = ("\n".join(lines) + "\n").encode()
    corrected = tar_of(changed)
    (tmp_path / "corrected").mkdir()
    for member, content in changed.items():
        (tmp_path / "corrected" / member.rsplit("/", 1)[-1]).write_bytes(content)
    assert c.delete("/v1/ground-truths/test-set", headers=ADMIN).status_code == 204
    files = {"file": ("label_2.tar.gz", corrected)}
    ok(c.post("/v1/ground-truths", data={"name": "test-set", "sealed": "true"}, files=files, headers=ADMIN), 201)
    done = ok(c.post("/v1/benchmarks/bench/rescore", headers=ADMIN), 202)
    assert done["queued"] == 2 and len(done["jobs"]) == 2
    await_rescoring(c, done["jobs"])
    assert ok(c.get("/v1/benchmarks/bench", headers=ADMIN))["rescoring"]["done"] == 2
    board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
    gt = load_ground_truth(tmp_path / "corrected")
    (tmp_path / "pred").mkdir()
    for member, content in golden_txt("pred.tar.gz").items():
        (tmp_path / "pred" / member.rsplit("/", 1)[-1]).write_bytes(content)
    for entry, pred in zip(
        sorted(board["entries"], key=lambda e: e["date"]), (GOLDEN / "result.pkl", tmp_path / "pred")
    ):
        doc = evaluate_document(gt, load_detections(pred), EvalOptions().config())
        for column, value in entry["columns"].items():
            cls, metric, difficulty, recall, oset = column.split("/")
            fresh = doc["ap"][oset][recall][cls][metric][difficulty]
            assert value == (None if fresh is None else round(float(fresh), 4)), column
    before = fresh_ap(GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl")
    assert board["entries"][0]["key"] != before  # the change moved the numbers


def test_the_public_part_is_drawn_from_a_secret_seed_and_the_private_board_follows_the_reveal(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"split_percent": 50})
        info = ok(c.get("/v1/benchmarks/bench"))
        assert info["board"] == "public" and "seed" not in json.dumps(info)
        a = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
        ok(
            c.post(
                f"/v1/benchmarks/bench/submissions/{a['id']}/publish",
                headers=hosted.headers("alice"),
                json={"method": "m"},
            )
        )
        store = c.app.state.service.store
        seed = store.benchmark_store.get_benchmark("bench").split_seed
        assert seed and seed not in c.get("/v1/benchmarks/bench/leaderboard").text
        gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
        dt = load_detections(GOLDEN / "result.pkl")
        public = [f for f in gt.frame_ids if in_public_part(seed, f, 50)]
        private = [f for f in gt.frame_ids if f not in public]
        assert 10 < len(public) < 40
        config = EvalOptions().config()
        want = {
            part: round(
                float(
                    evaluate_document(gt.subset(fr), dt.subset(fr), config)["ap"]["strict"]["R40"]["Car"]["3d"][
                        "moderate"
                    ]
                ),
                4,
            )
            for part, fr in (("public", public), ("private", private))
        }
        assert ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"][0]["key"] == want["public"]
        assert c.post("/v1/benchmarks/bench/reveal", headers=ADMIN).status_code == 409  # still open
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
        board = ok(c.get("/v1/benchmarks/bench/leaderboard"))
        assert board["board"] == "private" and board["entries"][0]["key"] == want["private"]


def test_markdown_descriptions_are_escaped() -> None:
    out = render_markdown("# Rules\n\n<script>alert(1)</script> **bold** [x](https://a.b/c)\n\n- one\n- two")
    assert "<script>" not in out and "&lt;script&gt;" in out
    assert "<strong>bold</strong>" in out and '<a href="https://a.b/c" rel="nofollow noopener">x</a>' in out
    assert "<ul><li>one</li><li>two</li></ul>" in out and out.startswith("<h3>Rules</h3>")
    assert "<a" not in render_markdown("[x](javascript:alert(1))")  # only http(s) links become links


def test_validate_against_a_benchmark_url_refuses_what_is_not_one() -> None:
    from server_helpers import free_port

    from kitti_eval.cli.validate import fetch_frames
    from kitti_eval.errors import ConfigError, InputError

    with pytest.raises(ConfigError, match="HOST/benchmarks/NAME"):
        fetch_frames("ftp://example.org/benchmarks/x")
    with pytest.raises(InputError, match="cannot fetch the frame ids"):
        fetch_frames(f"http://127.0.0.1:{free_port()}/benchmarks/bench")


def test_a_submission_is_accepted_at_once_and_scored_by_a_job(world) -> None:
    c, hosted = world
    alice = hosted.headers("alice")
    service = c.app.state.service
    service.workers.stop(5)  # no free evaluator: acceptance must not wait for one
    try:
        response = submit_now(c, alice)
        job = ok(response, 202)
        assert response.headers["Location"] == f"/v1/jobs/{job['id']}" and job["state"] == "queued"
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
        (accepted,) = mine["items"]
        assert accepted["id"] == job["id"] and accepted["status"] == "accepted" and accepted["scores"] is None
        assert mine["quota"]["used"] == 1
    finally:
        service.workers.start()
    await_rescoring(c, [job["id"]])
    (scored,) = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))["items"]
    assert scored["status"] == "scored" and scored["created_at"] == accepted["created_at"]
    assert scored["scores"]["Car/3d/moderate/R40/strict"] == fresh_ap(
        GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl"
    )
    assert ok(c.get(f"/v1/jobs/{job['id']}", headers=alice))["result_location"].endswith(job["id"])
    assert ok(submit(c, alice, golden_bytes("result.pkl")), 201)["status"] == "scored"


def test_a_submission_whose_scoring_fails_is_failed_and_not_counted(world, monkeypatch) -> None:
    from kitti_eval.errors import InputError

    c, hosted = world
    alice = hosted.headers("alice")
    service = c.app.state.service

    def refuse(*args, **kwargs):  # the file passed its check; its scoring fails on the input
        raise InputError("boxes with a negative size", frame="000007", field="dimensions")

    monkeypatch.setattr(service.benchmarks.scoring, "_scores", refuse)
    job = ok(submit_now(c, alice), 202)
    ended = service.jobs.wait(job["id"], 120)
    assert ended is not None and ended.state == "failed"
    seen = ok(c.get(f"/v1/jobs/{job['id']}", headers=alice))
    assert seen["error"]["status"] < 500
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
    assert [s["status"] for s in mine["items"]] == ["failed"] and mine["quota"]["used"] == 0


def test_a_file_its_scoring_job_cannot_read_is_refused_and_removed(world) -> None:
    """Acceptance reads nothing of the file; its job's check refuses an unreadable one as an upload is refused
    (422, the reader's message), and the submission is removed: it never counted."""
    from sqlalchemy import update

    from kitti_eval_server.store.database import job_inputs

    c, hosted = world
    alice = hosted.headers("alice")
    service = c.app.state.service
    service.workers.stop(5)
    try:
        job = ok(submit_now(c, alice), 202)
        with service.store.engine.begin() as conn:  # the job's input no longer loads (the kept file stays whole)
            unreadable = update(job_inputs).where(job_inputs.c.job_id == job["id"])
            conn.execute(unreadable.values(content=b"not a pickle", kept=False))
    finally:
        service.workers.start()
    ended = service.jobs.wait(job["id"], 120)
    assert ended is not None and ended.state == "failed" and ended.attempts == 1
    seen = ok(c.get(f"/v1/jobs/{job['id']}", headers=alice))
    assert seen["error"]["status"] == 422
    mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
    assert mine["items"] == [] and mine["quota"]["used"] == 0
    r = c.post(
        "/v1/benchmarks/bench/submissions",
        files={"predictions": ("x.pkl", b"not a pickle", "application/octet-stream")},
        headers=alice,
    )
    assert r.status_code == 422 and r.json()["error"]["message"] == seen["error"]["message"].replace(
        "result.pkl", "x.pkl"
    )


def test_rescoring_ten_submissions_returns_at_once_and_the_jobs_score_them(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as c:
        hosted = host(c, benchmark={"quota": "10/1"})
        alice = hosted.headers("alice")
        made = [ok(submit(c, alice, golden_bytes("result.pkl")), 201)["id"] for _ in range(10)]
        service = c.app.state.service
        service.workers.stop(5)
        try:
            done = ok(c.post("/v1/benchmarks/bench/rescore", headers=ADMIN), 202)
            assert done["queued"] == 10 and done["rescoring"]["queued"] == 10
            assert ok(c.get("/v1/benchmarks/bench", headers=ADMIN))["rescoring"]["queued"] == 10
            assert "rescoring" not in ok(c.get("/v1/benchmarks/bench", headers=alice))
        finally:
            service.workers.start()
        await_rescoring(c, done["jobs"])
        assert ok(c.get("/v1/benchmarks/bench", headers=ADMIN))["rescoring"]["done"] == 10
        expected = fresh_ap(GOLDEN / "kitti_infos_val.pkl", GOLDEN / "result.pkl")
        rows = {s["id"]: s for s in ok(c.get("/v1/benchmarks/bench/submissions/all", headers=ADMIN))["items"]}
        assert sorted(rows) == sorted(made)
        for row in rows.values():
            assert row["status"] == "scored" and row["scores"]["Car/3d/moderate/R40/strict"] == expected


def _verdicts(c, tmp_path, name: str, data: bytes) -> tuple[object, object]:
    """(what ``kitti-eval validate`` says of the file, what a submission's scoring job says of it on its one
    read): the problems, "valid", or the error raised (class and message)."""
    from kitti_eval_server.benchmarks import InvalidSubmission

    service = c.app.state.service
    bench = service.benchmarks.catalog.named("bench")
    _, gt = service.benchmarks.catalog.ground_truth_of(bench)
    path = tmp_path / name
    path.write_bytes(data)
    try:
        outcome = validate_submission(path, SubmissionRules(frames=tuple(gt.frame_ids)))
        cli: object = "valid" if outcome.ok else [line.replace(str(path), name) for line in outcome.lines()]
    except Exception as e:  # noqa: BLE001 - the class is the verdict
        cli = f"{type(e).__name__}: {str(e).replace(str(path), name)}"
    try:
        dt = service.benchmarks.scoring._checked(receive_upload(io.BytesIO(data), name, "predictions"), gt)
        job: object = "valid"
        assert set(dt.frame_ids) == set(gt.frame_ids)  # what is scored is every test frame
    except InvalidSubmission as e:
        job = e.problems
    except Exception as e:  # noqa: BLE001 - the class is the verdict: the library's, as the validator's
        job = f"{type(e).__name__}: {e}"
    return cli, job


def test_a_submissions_one_read_says_what_kitti_eval_validate_says(world, tmp_path) -> None:
    """The scoring job reads a submission once and checks it there: on valid files, files with every kind of
    problem, in every form, and unreadable or unsafe ones, its verdict is the validator's."""
    import os
    import pickle

    c, _ = world
    txt = golden_txt("pred.tar.gz")
    members = list(txt)
    problems = dict(list(txt.items())[2:])  # two test frames missing
    problems[members[2]] = b"Car 0 0 0 1 2 3\n"  # too few fields
    problems[members[3]] = b"Bus 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1 0.9\n"
    problems[members[4]] = b"Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 nan 1.5 20 0.1 0.9\n"
    problems[members[5]] = b"Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1 high\n"
    folder = members[0].rsplit("/", 1)[0] + "/" if "/" in members[0] else ""
    problems[folder + "999999.txt"] = b""
    problems[folder + "notes.txt"] = b"hello\n"
    results = pickle.loads(golden_bytes("result.pkl"))
    bad_class = [dict(r) for r in results[:-1]]
    bad_class[0]["name"] = bad_class[0]["name"].copy()
    bad_class[0]["name"][:] = "Bus"
    not_finite = [dict(r) for r in results]
    not_finite[1]["location"] = not_finite[1]["location"] + float("inf")
    cases = {
        "result.pkl": golden_bytes("result.pkl"),
        "pred.zip": zip_of(txt),
        "pred.tar.gz": golden_bytes("pred.tar.gz"),
        "problems.zip": zip_of(problems),
        "problems.tar.gz": tar_of(problems),
        "bad-class.pkl": pickle.dumps(bad_class, protocol=4),
        "not-finite.pkl": pickle.dumps(not_finite, protocol=4),
        "unsafe.pkl": pickle.dumps(os.system, protocol=4),
        "garbage.bin": b"\x00 not a submission",
        "empty.zip": zip_of({}),
    }
    seen = {}
    for name, data in cases.items():
        cli, job = _verdicts(c, tmp_path, name, data)
        assert job == cli, (name, cli, job)
        seen[name] = cli
    assert seen["result.pkl"] == seen["pred.zip"] == seen["pred.tar.gz"] == "valid"
    assert isinstance(seen["problems.zip"], list) and len(seen["problems.zip"]) == 6, seen["problems.zip"]
    assert isinstance(seen["bad-class.pkl"], list) and isinstance(seen["not-finite.pkl"], list)
    assert seen["unsafe.pkl"].startswith("UnsafePickleError")
