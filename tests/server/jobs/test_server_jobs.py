"""Evaluations as durable jobs, through the API: accepted at once, run by workers with a lease, answered when
done (201 as before), or polled (202 and the job's Location); a lost worker's job taken over and stored once;
a job accepted before a restart run after it."""

from __future__ import annotations

import threading
import time

from server_accounts import make_teams
from server_helpers import ADMIN, app_client, assert_error, golden_bytes, upload
from unversioned import as_unversioned

from kitti_eval_server.jobs.workers import Workers


def _until_ended(c, job_id: str, headers: dict[str, str] | None = None, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        job = c.get(f"/v1/jobs/{job_id}", headers=headers or {}).json()
        if job["state"] in ("done", "failed", "cancelled"):
            return job
        assert time.monotonic() < deadline, job
        time.sleep(0.05)


def _scores(doc: dict) -> dict:
    """The evaluation document without what tells two evaluations apart (id, time)."""
    return {k: v for k, v in doc.items() if k not in ("id", "evaluation")}


def test_wait_zero_answers_at_once_and_the_job_leads_to_the_same_evaluation(tmp_path) -> None:
    with app_client(tmp_path / "data") as c:
        pred = golden_bytes("result.pkl")
        now = upload(c, pred)
        assert now.status_code == 201  # the default waits for the result, as every client expects
        later = upload(c, pred, params={"wait": "0"})
        assert later.status_code == 202, later.text
        job = later.json()
        assert later.headers["location"] == f"/v1/jobs/{job['id']}" and job["kind"] == "evaluation"
        assert job["state"] in ("queued", "running", "done")
        ended = _until_ended(c, job["id"])
        assert ended["state"] == "done" and ended["attempts"] == 1 and ended["evaluation"] == job["id"]
        stored = c.get(ended["result_location"]).json()
        assert _scores(stored) == _scores(now.json()) and stored["ap"]


def test_an_input_refused_by_a_worker_is_answered_as_before(tmp_path) -> None:
    with app_client(tmp_path / "data") as c:
        r = upload(c, b"\x80\x04not a pickle at all")
        err = assert_error(r, 422)
        assert err["code"] in ("invalid_input", "unknown_format", "unsafe_pickle"), err
        later = upload(c, b"\x80\x04not a pickle at all", params={"wait": "0"})
        assert later.status_code == 202, later.text  # once seen failing under load with an answer without an id
        ended = _until_ended(c, later.json()["id"])
        assert ended["state"] == "failed" and ended["attempts"] == 1  # a refusal is not tried again
        assert ended["error"]["status"] == 422 and ended["error"]["message"] == err["message"]


def test_a_job_is_its_owners_and_the_admins(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        teams = make_teams(c)
        r = upload(c, golden_bytes("result.pkl"), gt="gt-a", params={"wait": "0"}, headers=teams.headers("alice"))
        job_id = r.json()["id"]
        assert c.get(f"/v1/jobs/{job_id}", headers=teams.headers("alice")).status_code == 200
        assert c.get(f"/v1/jobs/{job_id}", headers=teams.headers("root")).status_code == 200
        assert c.get(f"/v1/jobs/{job_id}", headers=teams.headers("bob")).status_code == 404
        assert c.get(f"/v1/jobs/{job_id}").status_code == 401


def test_a_lost_workers_job_is_taken_over_and_stored_once(tmp_path) -> None:
    """A worker that claimed the job and stopped (no heartbeat: killed) loses it when its lease runs out; the
    next worker runs it; the first one's late result is not stored."""
    with app_client(tmp_path / "data", ready=False, job_threads=0, job_lease_s=0.5) as c:
        service = c.app.state.service
        job_id = upload(c, golden_bytes("result.pkl"), params={"wait": "0"}).json()["id"]
        lost = service.jobs.claim("lost-worker")
        assert lost is not None and lost.id == job_id
        record, write = service.evaluations.execute(job_id, lost.payload)  # it got this far, then stopped
        workers = Workers(service.jobs, {"evaluation": service._run_evaluation}, threads=1, idle_s=0.05)
        workers.start()
        try:
            ended = _until_ended(c, job_id)
        finally:
            workers.stop(10)
        assert ended["state"] == "done" and ended["attempts"] == 2
        assert service.jobs.finish(job_id, "lost-worker", record.id, within=write) is False  # too late
        listed = c.get("/v1/evaluations").json()["items"]
        assert [e["id"] for e in listed].count(job_id) == 1


def test_a_job_accepted_before_a_restart_runs_after_it(tmp_path) -> None:
    with app_client(tmp_path / "data", ready=False, job_threads=0) as c:
        job_id = upload(c, golden_bytes("result.pkl"), params={"wait": "0"}).json()["id"]
        assert c.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"
        assert c.get(f"/v1/jobs/{job_id}").json()["position"] == 1
    with app_client(tmp_path / "data") as c:  # the same database, workers this time
        ended = _until_ended(c, job_id)
        assert ended["state"] == "done"
        assert c.get(f"/v1/evaluations/{job_id}").status_code == 200


def test_admins_list_cancel_and_rerun_jobs(tmp_path) -> None:
    """Every owner's jobs, by state, newest first; a queued job cancelled, then run again; an ended evaluation
    run again only while its inputs are kept and it is not done; each change audited."""
    with app_client(tmp_path / "data", ready=False, job_threads=0) as c:
        service = c.app.state.service
        ids = [upload(c, golden_bytes("result.pkl"), params={"wait": "0"}).json()["id"] for _ in range(3)]
        assert c.get("/v1/admin/jobs").status_code == 401  # open mode: the admin token
        listed = c.get("/v1/admin/jobs", headers=ADMIN).json()
        assert [j["id"] for j in listed["items"]] == ids[::-1] and listed["next_offset"] is None
        assert listed["counts"] == {"queued": 3, "running": 0, "done": 0, "failed": 0, "cancelled": 0}
        assert {(j["owner"], j["state"], j["attempts"], j["max_attempts"]) for j in listed["items"]} == {
            ("anyone", "queued", 0, 3)
        }
        page = c.get("/v1/admin/jobs", params={"state": "queued", "limit": 2}, headers=ADMIN).json()
        assert [j["id"] for j in page["items"]] == ids[:0:-1] and page["next_offset"] == 2
        assert c.get("/v1/admin/jobs", params={"state": "lost"}, headers=ADMIN).status_code == 422

        cancelled = c.post(f"/v1/admin/jobs/{ids[0]}/cancel", headers=ADMIN)
        assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled", cancelled.text
        assert_error(c.post(f"/v1/admin/jobs/{ids[0]}/cancel", headers=ADMIN), 409, "nothing to cancel")
        assert_error(c.post(f"/v1/admin/jobs/{ids[1]}/rerun", headers=ADMIN), 409, "queued")
        assert_error(c.post("/v1/admin/jobs/nope/cancel", headers=ADMIN), 404)
        assert c.post(f"/v1/admin/jobs/{ids[1]}/cancel").status_code == 401
        again = c.post(f"/v1/admin/jobs/{ids[0]}/rerun", headers=ADMIN).json()
        assert again["state"] == "queued" and again["attempts"] == 0 and again["position"] is None

        workers = Workers(service.jobs, {"evaluation": service._run_evaluation}, threads=1, idle_s=0.05)
        workers.start()
        try:
            ended = [_until_ended(c, i) for i in ids]
        finally:
            workers.stop(10)
        assert [e["state"] for e in ended] == ["done"] * 3
        assert_error(c.post(f"/v1/admin/jobs/{ids[0]}/rerun", headers=ADMIN), 409, "done")
        assert [e["id"] for e in c.get("/v1/evaluations").json()["items"]].count(ids[0]) == 1
        audit = c.get("/v1/admin/audit", headers=ADMIN).json()["items"]
        assert [(a["action"], a["target"], a["actor"]) for a in audit if a["action"].startswith("job.")] == [
            ("job.rerun", ids[0], "admin-token"),
            ("job.cancel", ids[0], "admin-token"),
        ]


def test_a_failed_evaluation_runs_again_with_its_inputs_and_a_waiting_request_learns_of_a_cancel(tmp_path) -> None:
    with app_client(tmp_path / "data", ready=False, job_threads=0) as c:
        service = c.app.state.service
        job_id = upload(c, b"\x80\x04not a pickle at all", params={"wait": "0"}).json()["id"]
        workers = Workers(service.jobs, {"evaluation": service._run_evaluation}, threads=1, idle_s=0.05)
        workers.start()
        try:
            assert _until_ended(c, job_id)["state"] == "failed"
            rerun = c.post(f"/v1/admin/jobs/{job_id}/rerun", headers=ADMIN)
            assert rerun.status_code == 200, rerun.text  # its inputs were kept: it runs, and is refused again
            ended = _until_ended(c, job_id)
            assert ended["state"] == "failed" and ended["attempts"] == 1 and ended["error"]["status"] == 422
        finally:
            workers.stop(10)
        answers: list = []
        request = threading.Thread(
            target=lambda: answers.append(upload(c, golden_bytes("result.pkl"), params={"wait": "30"}))
        )
        request.start()
        deadline = time.monotonic() + 30
        while not (queued := service.jobs.list(state="queued")):
            assert time.monotonic() < deadline
            time.sleep(0.02)
        service.job_admin.cancel(queued[0].id, service.policy.command_line("ops"))
        request.join(30)
        err = assert_error(answers[0], 409, "cancelled")  # the waiting request is told, not left to poll
        assert err["code"] == "cancelled"
        listed = c.get("/v1/admin/jobs", params={"state": "cancelled"}, headers=ADMIN).json()["items"]
        assert [j["id"] for j in listed] == [queued[0].id]


def test_the_upload_form_runs_through_the_queue_too(tmp_path) -> None:
    """The web form accepts a job as the API does: with no worker to run it within the wait, it sends the
    browser to the evaluation's page, which says it is queued (with its place) and reloads itself without a
    script until the scores are there."""
    with app_client(tmp_path / "data", job_threads=0, wait_s=0, ready=False) as c:
        files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
        sent = c.post("/ui/evaluations", data={"gt": "demo"}, files=files, follow_redirects=False)
        (job,) = c.app.state.service.jobs.list()
        assert sent.status_code == 303 and sent.headers["location"] == f"/evaluations/{job.id}", sent.text[:500]
        assert job.kind == "evaluation" and job.state == "queued"
        page = c.get(f"/evaluations/{job.id}")
        assert page.status_code == 200 and 'data-state="queued"' in page.text and "1st in line" in page.text
        assert '<meta http-equiv="refresh" content="2">' in page.text
        c.app.state.service.workers.threads = 1
        c.app.state.service.workers.start()
        ended = c.app.state.service.jobs.wait(job.id, 120)
        assert ended is not None and ended.state == "done"
        done = c.get(f"/evaluations/{job.id}")
        assert done.status_code == 200 and "http-equiv" not in done.text and 'id="state"' not in done.text


def test_a_refused_upload_s_page_says_why_and_stops_reloading(tmp_path) -> None:
    with app_client(tmp_path / "data") as c:
        job = upload(c, b"\x80\x04not a pickle at all", params={"wait": "0"}).json()
        assert _until_ended(c, job["id"])["state"] == "failed"
        page = c.get(f"/evaluations/{job['id']}")
        assert page.status_code == 422 and 'data-state="failed"' in page.text and "http-equiv" not in page.text
        assert "The evaluation was refused" in page.text
    with app_client(tmp_path / "accounts", auth="accounts") as c:  # someone else's job is not there for you
        teams = make_teams(c)
        r = upload(c, golden_bytes("result.pkl"), gt="gt-a", params={"wait": "0"}, headers=teams.headers("alice"))
        assert c.get(f"/evaluations/{r.json()['id']}", headers=teams.headers("bob")).status_code == 404


def test_busy_evaluators_refuse_nothing_only_the_queues_limits_do(tmp_path) -> None:
    """With no worker running, uploads are accepted (202) up to the queue's limits: a user's jobs (429
    too_many_queued, another user still accepted), all jobs (503 queue_full), the inputs' bytes (503), each
    with Retry-After; a refused request keeps nothing."""
    pred = golden_bytes("result.pkl")
    with app_client(tmp_path / "data", auth="accounts", max_queued_per_caller=3, max_queued_jobs=5) as c:
        teams = make_teams(c)
        service = c.app.state.service
        service.workers.stop(5)
        before = service.jobs.counts()["queued"]
        alice, bob = teams.headers("alice"), teams.headers("bob")
        now = {"wait": "0"}
        answers = [upload(c, pred, gt="gt-a", headers=alice, params=now).status_code for _ in range(3)]
        assert answers == [202, 202, 202]  # nothing runs, nothing is refused for it
        mine = upload(c, pred, gt="gt-a", headers=alice, params=now)
        err = assert_error(mine, 429, "KITTI_EVAL_MAX_QUEUED_PER_CALLER")
        assert err["code"] == "too_many_queued" and mine.headers["retry-after"]
        room = 5 - before - 3
        assert [upload(c, pred, gt="gt-b", headers=bob, params=now).status_code for _ in range(room)] == [202] * room
        full = upload(c, pred, gt="gt-b", headers=bob, params=now)
        assert assert_error(full, 503, "KITTI_EVAL_MAX_QUEUED_JOBS")["code"] == "queue_full"
        assert full.headers["retry-after"] == "2"
        assert service.jobs.counts()["queued"] == 5
        service.workers.start()
        deadline = time.monotonic() + 120
        while service.jobs.counts()["queued"] or service.jobs.counts()["running"]:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert upload(c, pred, gt="gt-a", headers=alice).status_code == 201  # room again
    with app_client(tmp_path / "bytes", max_queued_input_mb=1.5 * len(pred) / (1 << 20)) as c:
        service = c.app.state.service
        service.workers.stop(5)
        assert upload(c, pred, params={"wait": "0"}).status_code == 202
        over = upload(c, pred, params={"wait": "0"})
        assert assert_error(over, 503, "KITTI_EVAL_MAX_QUEUED_INPUT_MB")["code"] == "queue_full"
        assert service.jobs.counts()["queued"] == 1
        service.workers.start()


def test_past_the_waiting_requests_bound_a_request_is_answered_202_at_once(tmp_path) -> None:
    with app_client(tmp_path / "data", max_queued_evals=0) as c:
        response = upload(c, golden_bytes("result.pkl"))
        assert response.status_code == 202, response.text
        ended = _until_ended(c, response.json()["id"])
        assert ended["state"] == "done"


def test_kept_predictions_are_written_once_when_accepted_and_an_uploaded_ground_truth_s_go_with_their_job(
    tmp_path,
) -> None:
    """Predictions the service keeps (evaluated against a registered ground truth) are written to the kept files
    when the job is accepted, and the job's input refers to them: the job copies and deletes nothing of them,
    an upload of the same file writes nothing again, and the admission counts their bytes while the job waits.
    Predictions evaluated against an uploaded ground truth are the job's own, and go when it is done."""
    import hashlib

    from sqlalchemy import select

    from kitti_eval_server.store.database import job_inputs, prediction_files

    pred = golden_bytes("result.pkl")
    sha = hashlib.sha256(pred).hexdigest()
    with app_client(tmp_path / "data", ready=False, job_threads=0, keep_predictions=True) as c:
        service = c.app.state.service
        store = service.store

        def inputs() -> list[tuple]:
            query = select(job_inputs.c.job_id, job_inputs.c.name, job_inputs.c.kept, job_inputs.c.content)
            with store.engine.connect() as conn:
                return sorted((r[0], r[1], bool(r[2]), len(r[3])) for r in conn.execute(query))

        def kept() -> list[str]:
            with store.engine.connect() as conn:
                return [r[0] for r in conn.execute(select(prediction_files.c.sha256))]

        first, second = (upload(c, pred, params={"wait": "0"}).json()["id"] for _ in range(2))
        assert kept() == [sha]  # once, however often it is uploaded
        assert inputs() == sorted([(first, "predictions", True, 0), (second, "predictions", True, 0)])
        assert store.job_input_store.job_input_bytes() == 2 * len(pred)
        read = store.job_input_store.job_input(first, "predictions")
        assert read is not None and read.kept and read.content == pred and read.sha256 == sha
        gt_file = ("infos.pkl", golden_bytes("kitti_infos_val.pkl"))
        own = upload(c, pred, gt=None, gt_file=gt_file, params={"wait": "0"}).json()["id"]
        assert sorted(name for job, name, flag, _ in inputs() if job == own and not flag) == ["gt_file", "predictions"]
        service.workers.threads = 1
        service.workers.start()
        for job_id in (first, second, own):
            ended = service.jobs.wait(job_id, 120)
            assert ended is not None and ended.state == "done", ended
        assert inputs() == [] and kept() == [sha] and store.job_input_store.job_input_bytes() == 0
        frames = c.get(f"/v1/evaluations/{first}/frames")  # the kept file is what the frames are read from
        assert frames.status_code == 200, frames.text
        assert store.ground_truth_store.prediction_content(sha) == pred


def test_a_job_accepted_before_kept_inputs_runs_after_the_upgrade_and_keeps_its_predictions(tmp_path) -> None:
    """A database from before: no ``kept`` column, a queued job's predictions in its own input row. The column is
    added by the upgrade at start-up, and the job runs from its row and keeps the file as a job did then."""
    import hashlib
    import sqlite3

    data = tmp_path / "data"
    pred = golden_bytes("result.pkl")
    with app_client(data, ready=False, job_threads=0, keep_predictions=True) as c:
        job_id = upload(c, pred, params={"wait": "0"}).json()["id"]
    db = sqlite3.connect(data / "kitti-eval.db")
    db.execute(
        "UPDATE job_inputs SET content = (SELECT content FROM prediction_files p WHERE p.sha256 = job_inputs.sha256)"
    )
    db.execute("DELETE FROM prediction_files")
    db.execute("ALTER TABLE job_inputs DROP COLUMN kept")
    as_unversioned(db.execute)  # an unversioned release's: upgraded at start, as told
    db.commit()
    db.close()
    with app_client(data, ready=False, job_threads=1, keep_predictions=True, db_upgrade=True) as c:
        store = c.app.state.service.store
        ended = c.app.state.service.jobs.wait(job_id, 120)
        assert ended is not None and ended.state == "done", ended
        assert store.ground_truth_store.prediction_content(hashlib.sha256(pred).hexdigest()) == pred
        assert c.get(f"/v1/evaluations/{job_id}/frames").status_code == 200
        again = upload(c, pred)  # a new acceptance keeps nothing twice
        assert again.status_code == 201 and again.json()["ap"] == c.get(f"/v1/evaluations/{job_id}").json()["ap"]


def test_a_worker_hands_memory_back_when_it_has_no_next_job_not_between_jobs(tmp_path, monkeypatch) -> None:
    """Jobs back to back reuse the pages the last one freed (handing them back and faulting them in again cost
    about 4% of an evaluation); once the queue is empty they go back to the system, once."""
    import kitti_eval_server.jobs.workers as workers_module

    with app_client(tmp_path / "data", ready=False, job_threads=0) as c:
        service = c.app.state.service
        ids = [upload(c, golden_bytes("result.pkl"), params={"wait": "0"}).json()["id"] for _ in range(3)]
        released: list[list[str]] = []  # the jobs done at each hand-back

        def release() -> None:
            released.append([i for i in ids if service.jobs.get(i).state == "done"])

        monkeypatch.setattr(workers_module, "release_memory", release)
        workers = Workers(service.jobs, {"evaluation": service._run_evaluation}, threads=1, idle_s=0.05)
        workers.start()
        try:
            for job_id in ids:
                assert _until_ended(c, job_id)["state"] == "done"
            deadline = time.monotonic() + 10
            while not released and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.3)  # idle polls meanwhile hand nothing back again
        finally:
            workers.stop(10)
        assert released == [ids]
