"""``/v1/gates/evaluations``: an evaluation a gate asks for without keeping it, a read-only token's. Its document is
the stored evaluation's for the same file; nothing of it is stored as an evaluation (no list, no comparison, no
frames); its result is read once by its owner alone; a benchmark's test set is refused; an unread result is
dropped after its time, with the inputs of a gate job that ended without one."""

from __future__ import annotations

import time
from datetime import datetime, timedelta, timezone

from server_benchmarks import bearer, host, ok
from server_helpers import ADMIN, app_client, assert_error

from kitti_eval.demo import demo_paths
from kitti_eval_server.store import GateResult

#: the demo's predictions, against the demo's ground truth (registered by the service, shared)
_FILES = {"predictions": ("result.pkl.gz", demo_paths()[1].read_bytes(), "application/octet-stream")}


def _world(c):
    hosted = host(c)
    ok(c.post("/v1/admin/projects", json={"name": "lab"}, headers=ADMIN), 201)
    ok(c.post("/v1/admin/members", json={"user": "alice", "project": "lab"}, headers=ADMIN), 201)
    reader = ok(c.post("/v1/admin/tokens", json={"user": "alice", "read_only": True}, headers=ADMIN), 201)["token"]
    return hosted, reader


def _job(c, job_id: str, token: str) -> dict:
    deadline = time.monotonic() + 120
    while True:
        job = ok(c.get(f"/v1/jobs/{job_id}", headers=bearer(token)))
        if job["state"] in ("done", "failed", "cancelled"):
            return job
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_a_read_only_token_has_an_evaluation_made_that_is_kept_nowhere(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        hosted, reader = _world(c)
        alice, bob = bearer(hosted.tokens["alice"]), bearer(hosted.tokens["bob"])
        # a read-only token may not upload an evaluation, and may have one made for a gate
        assert c.post("/v1/evaluations", data={"gt": "demo"}, files=_FILES, headers=bearer(reader)).status_code == 403
        r = c.post("/v1/gates/evaluations", data={"gt": "demo"}, files=_FILES, headers=bearer(reader))
        gated = ok(r, 201)
        assert r.headers["X-Evaluation-Kept"] == "false" and gated["evaluation"]["kept"] is False
        stored = ok(c.post("/v1/evaluations", data={"gt": "demo"}, files=_FILES, headers=alice), 201)
        same = {k: v for k, v in gated.items() if k not in ("id", "evaluation")}
        assert same == {k: v for k, v in stored.items() if k not in ("id", "evaluation")}
        assert same["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] > 0
        # nothing of it is an evaluation: not listed (not even to an admin), not readable, not framed
        listed = ok(c.get("/v1/evaluations", headers=ADMIN))["items"]
        assert [e["id"] for e in listed] == [stored["id"]]
        assert c.get(f"/v1/evaluations/{gated['id']}", headers=alice).status_code == 404
        assert c.get(f"/v1/evaluations/{gated['id']}/frames", headers=alice).status_code == 404
        # read once: the answer was the one reading
        assert c.get(f"/v1/gates/evaluations/{gated['id']}", headers=bearer(reader)).status_code == 404
        with c.app.state.service.store.engine.connect() as conn:
            from sqlalchemy import text

            assert conn.execute(text("SELECT count(*) FROM gate_results")).scalar_one() == 0
            assert conn.execute(text("SELECT count(*) FROM job_inputs")).scalar_one() == 0

        # answered later: the job's result_location gives it once, to its owner alone (the same user's other
        # token is its owner too); another's is as absent as a missing one
        queued = ok(c.post("/v1/gates/evaluations?wait=0", data={"gt": "demo"}, files=_FILES, headers=alice), 202)
        assert c.get(f"/v1/jobs/{queued['id']}", headers=bob).status_code == 404
        job = _job(c, queued["id"], reader)
        assert job["kind"] == "gate" and job["result_location"] == f"/v1/gates/evaluations/{queued['id']}"
        assert "evaluation" not in job
        assert_error(c.get(job["result_location"], headers=bob), 404, "no gate result", "read once")
        assert c.get(job["result_location"], headers=ADMIN).status_code == 404
        later = ok(c.get(job["result_location"], headers=bearer(reader)))
        assert {k: v for k, v in later.items() if k not in ("id", "evaluation")} == same
        assert c.get(job["result_location"], headers=bearer(reader)).status_code == 404
        assert c.get("/v1/gates/evaluations/x").status_code == 401  # no token


def test_a_gate_evaluation_refuses_what_an_evaluation_refuses(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        hosted, reader = _world(c)
        r = c.post("/v1/gates/evaluations", data={"gt": "test-set"}, files=_FILES, headers=bearer(reader))
        assert_error(r, 403, "test set of benchmark 'bench'")
        r = c.post("/v1/gates/evaluations", data={"gt": "nothing"}, files=_FILES, headers=bearer(reader))
        assert r.status_code == 404
        r = c.post(
            "/v1/gates/evaluations", data={"gt": "demo", "classes": "Tram"}, files=_FILES, headers=bearer(reader)
        )
        assert r.status_code == 422
        bad = {"predictions": ("result.pkl", b"not a pickle", "application/octet-stream")}
        r = c.post("/v1/gates/evaluations", data={"gt": "demo"}, files=bad, headers=bearer(reader))
        assert_error(r, 422, "result.pkl")
        assert c.post("/v1/gates/evaluations", data={"gt": "demo"}, files=_FILES).status_code == 401
        assert ok(c.get("/v1/evaluations", headers=ADMIN))["items"] == []


def test_an_unread_result_is_dropped_after_its_time_with_a_failed_jobs_inputs(tmp_path) -> None:
    with app_client(tmp_path / "data", auth="accounts") as c:
        hosted, reader = _world(c)
        service = c.app.state.service
        store = service.store.gate_result_store
        old = datetime.now(timezone.utc) - timedelta(seconds=service.gate_evaluations.kept_s + 1)
        with service.store.db.writing() as conn:
            store.add_gate_result_in(conn, GateResult("0" * 32, "alice", old, {"id": "0" * 32}))
        # too old to be read, even by its owner
        assert c.get(f"/v1/gates/evaluations/{'0' * 32}", headers=bearer(reader)).status_code == 404
        with service.store.db.writing() as conn:
            store.add_gate_result_in(conn, GateResult("1" * 32, "alice", old, {"id": "1" * 32}))
        bad = {"predictions": ("result.pkl", b"not a pickle", "application/octet-stream")}
        failed = ok(c.post("/v1/gates/evaluations?wait=0", data={"gt": "demo"}, files=bad, headers=bearer(reader)), 202)
        assert _job(c, failed["id"], reader)["state"] == "failed"
        from sqlalchemy import text

        def count(table: str) -> int:
            with service.store.engine.connect() as conn:
                return int(conn.execute(text(f"SELECT count(*) FROM {table}")).scalar_one())

        assert count("gate_results") == 0  # the next request dropped the stale one
        assert count("job_inputs") == 1  # the failed job's, kept while it may be run again
        assert store.drop_gate_results(made_before=datetime.now(timezone.utc) + timedelta(seconds=1)) == 0
        assert count("job_inputs") == 0
        assert_error(c.post(f"/v1/admin/jobs/{failed['id']}/rerun", headers=ADMIN), 409, "inputs", "are gone")
