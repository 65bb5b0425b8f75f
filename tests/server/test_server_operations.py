"""What an operator sees: /metrics scraped and matched against the requests made, request ids, access logs."""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterator
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families
from server_helpers import ADMIN, ADMIN_TOKEN, LogRecords, golden_bytes, register, upload

from kitti_eval.demo import demo_paths
from kitti_eval_server.observability import JsonFormatter, wants_json


def scrape(client: Any, **headers: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    r = client.get("/metrics", headers=headers)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    out = {}
    for family in text_string_to_metric_families(r.text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def value(samples: dict, name: str, **labels: str) -> float:
    return samples.get((name, tuple(sorted(labels.items()))), 0.0)


@pytest.fixture
def access() -> Iterator[LogRecords]:
    handler = LogRecords()
    logger = logging.getLogger("kitti_eval.server.access")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)  # under pytest the root logger is configured: the service leaves it alone
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def test_the_counters_match_the_requests_made(service_client: Any) -> None:
    with service_client() as client:
        before = scrape(client)
        for _ in range(3):
            assert client.get("/healthz").status_code == 200
        pred = demo_paths()[1].read_bytes()
        assert upload(client, pred, "result.pkl.gz").status_code == 201
        assert upload(client, pred, "result.pkl.gz").status_code == 201
        assert upload(client, b"not a pickle at all", "result.pkl").status_code == 422
        assert client.get("/v1/evaluations/nope").status_code == 404
        after = scrape(client)

    def delta(name: str, **labels: str) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    requests = "kitti_eval_http_requests_total"
    assert delta(requests, route="/healthz", method="GET", status="200") == 3
    assert delta(requests, route="/v1/evaluations", method="POST", status="201") == 2
    assert delta(requests, route="/v1/evaluations", method="POST", status="422") == 1
    assert delta(requests, route="/v1/evaluations/{evaluation_id}", method="GET", status="404") == 1
    assert delta("kitti_eval_evaluations_total", outcome="ok") == 2
    assert delta("kitti_eval_evaluations_total", outcome="refused") == 1
    assert delta("kitti_eval_evaluations_total", outcome="failed") == 0
    # errors by their code: what a dashboard alerts on (database_unavailable, insufficient_storage, ...)
    assert delta("kitti_eval_http_errors_total", code="unknown_format") == 1
    assert delta("kitti_eval_http_errors_total", code="not_found") == 1
    assert delta("kitti_eval_evaluation_duration_seconds_count", outcome="ok") == 2
    assert delta("kitti_eval_http_request_duration_seconds_count", route="/healthz", method="GET") == 3
    # every byte of the three uploads arrived (and a little multipart framing around each)
    sent = 2 * len(pred) + len(b"not a pickle at all")
    assert sent < delta("kitti_eval_http_received_bytes_total") < sent + 3 * 1000
    # the demo ground truth: loaded once, then found in memory
    assert delta("kitti_eval_ground_truth_cache_lookups_total", result="hit") >= 1
    assert value(after, "kitti_eval_ground_truth_cache_entries") >= 1
    assert value(after, "kitti_eval_ground_truth_cache_bytes") > 1000
    assert value(after, "kitti_eval_kernels_warm") == 1.0
    assert value(after, "kitti_eval_evaluations_in_progress") == 0
    assert value(after, "kitti_eval_bodies_receiving") == 0


def test_an_answer_given_before_the_router_counts_under_its_route(service_client: Any) -> None:
    """A body refused before the application ran (413 for a declared length past the cap) is counted under the
    route it was sent to; ``unmatched`` is kept for paths no route serves."""
    with service_client(max_upload_mb=1) as client:
        before = scrape(client)
        big = client.post("/v1/evaluations", content=b"x" * (2 << 20), headers={"content-type": "text/plain"})
        assert big.status_code == 413
        assert client.post("/v1/no-such-route", content=b"{}").status_code == 404
        after = scrape(client)

    def delta(**labels: str) -> float:
        name = "kitti_eval_http_requests_total"
        return value(after, name, **labels) - value(before, name, **labels)

    assert delta(route="/v1/evaluations", method="POST", status="413") == 1
    assert delta(route="unmatched", method="POST", status="413") == 0
    assert delta(route="unmatched", method="POST", status="404") == 1


def test_a_busy_answer_is_a_rejection_for_want_of_body_turns_not_of_evaluation_places() -> None:
    """A 503 ``busy`` (every turn to send a body taken) is counted as ``reason="bodies"`` even on the evaluation
    route; a 503 of the evaluation route for another reason (the queue full) as ``evaluations``."""
    import anyio

    from kitti_eval_server.observability import Metrics, RequestMiddleware

    def answering(code: str):
        async def app(scope, receive, send) -> None:
            body = json.dumps({"error": {"code": code, "message": "m"}}).encode()
            await send(
                {"type": "http.response.start", "status": 503, "headers": [(b"content-type", b"application/json")]}
            )
            await send({"type": "http.response.body", "body": body})

        return app

    async def post(app) -> None:
        async def receive() -> dict:
            return {"type": "http.request", "body": b""}

        async def send(message: dict) -> None:
            pass

        await app({"type": "http", "method": "POST", "path": "/v1/evaluations", "headers": []}, receive, send)

    metrics = Metrics()
    for code in ("busy", "busy", "queue_full"):
        anyio.run(post, RequestMiddleware(answering(code), metrics=metrics, log_json=lambda: True))
    rejected = {s.labels["reason"]: s.value for f in metrics.registry.collect() for s in f.samples
                if s.name == "kitti_eval_admission_rejected_total"}  # fmt: skip
    assert rejected == {"bodies": 2.0, "evaluations": 1.0}


def test_metrics_can_be_off_or_need_their_token(service_client: Any) -> None:
    with service_client(metrics="off") as client:
        r = client.get("/metrics")
        assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    with service_client(metrics_token="scrape-me") as client:
        assert client.get("/metrics").status_code == 401
        assert client.get("/metrics", headers=ADMIN).status_code == 403  # the admin token is not the scraper's
        assert scrape(client, authorization="Bearer scrape-me")


def test_an_unexpected_failure_is_answered_inside_the_request_layer(service_client: Any, monkeypatch: Any) -> None:
    """A bug's 500 carries the request id and is counted and logged like every answer (the server's own
    last-resort handler sits outside the request layer and would do none of that)."""
    with service_client() as client:
        monkeypatch.setattr(client.app.state.service.store.evaluation_store, "list_evaluations", lambda **kw: [][1])
        r = client.get("/v1/evaluations", headers={"X-Request-ID": "bug-1"})
        assert r.status_code == 500 and r.headers["x-request-id"] == "bug-1"
        assert r.json() == {
            "error": {
                "code": "internal_error",
                "message": "internal error; the server log has the details",
                "request_id": "bug-1",
            }
        }
        samples = scrape(client)
    assert value(samples, "kitti_eval_http_requests_total", route="/v1/evaluations", method="GET", status="500") == 1
    assert value(samples, "kitti_eval_http_errors_total", code="internal_error") == 1


def test_request_ids_are_returned_and_in_every_error(client: Any) -> None:
    r = client.get("/healthz", headers={"X-Request-ID": "ci-run-42.step_3"})
    assert r.headers["x-request-id"] == "ci-run-42.step_3"
    r = client.get("/healthz")
    assert re.fullmatch(r"[0-9a-f]{32}", r.headers["x-request-id"])
    r = client.get("/healthz", headers={"X-Request-ID": "bad id\twith spaces"})  # not sane: replaced
    assert re.fullmatch(r"[0-9a-f]{32}", r.headers["x-request-id"])
    r = client.get("/v1/evaluations/nope", headers={"X-Request-ID": "abc"})
    assert r.status_code == 404 and r.headers["x-request-id"] == "abc"
    assert r.json()["error"]["request_id"] == "abc"
    assert int(r.headers["content-length"]) == len(r.content)
    r = upload(client, b"junk", "result.pkl", headers={"X-Request-ID": "u1"})
    assert r.status_code == 422 and r.json()["error"]["request_id"] == "u1"


def test_one_access_line_a_request_never_a_token(service_client: Any, access: LogRecords) -> None:
    with service_client(log_format="json") as client:
        access.records.clear()
        assert register(client, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        r = upload(client, golden_bytes("result.pkl"), gt="small", headers={"X-Request-ID": "eval-1"})
        assert r.status_code == 201
        client.get("/v1/evaluations?limit=5&token=secret-in-query")
    lines = [json.loads(JsonFormatter().format(rec)) for rec in access.records]
    assert [(x["method"], x["route"], x["status"]) for x in lines] == [
        ("POST", "/v1/ground-truths", 201),
        ("POST", "/v1/evaluations", 201),
        ("GET", "/v1/evaluations", 200),
    ]
    evaluation = lines[1]
    assert evaluation["request_id"] == "eval-1" and evaluation["evaluation_id"] == r.json()["id"]
    assert evaluation["bytes_in"] > len(golden_bytes("result.pkl")) and evaluation["duration_ms"] > 0
    assert set(evaluation) == {
        "time", "level", "logger", "request_id", "method", "route", "status", "duration_ms", "bytes_in", "bytes_out",
        "evaluation_id",
    }  # fmt: skip
    text = "\n".join(JsonFormatter().format(rec) for rec in access.records)
    assert ADMIN_TOKEN not in text and "secret-in-query" not in text


def test_text_lines_on_a_terminal_json_elsewhere() -> None:
    class Tty:
        def isatty(self) -> bool:
            return True

    assert wants_json("auto", Tty()) is False
    assert wants_json("auto", object()) is True
    assert wants_json("text", object()) is False and wants_json("json", Tty()) is True


def test_several_worker_processes_are_summed(tmp_path: Any) -> None:
    """With PROMETHEUS_MULTIPROC_DIR (prometheus-client's multiprocess mode), what two worker processes counted
    is summed in the scrape whichever process answers it."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(tmp_path)}
    count = (
        "import sys; from kitti_eval_server.observability import Metrics; m = Metrics(); "
        "[m.requests.labels('/healthz', 'GET', '200').inc() for _ in range(int(sys.argv[1]))]; "
        "m.evaluations.labels('ok').inc()"
    )
    for n in ("2", "5"):
        subprocess.run([sys.executable, "-c", count, n], env=env, check=True, timeout=60)
    render = (
        "import sys; from kitti_eval_server.observability import Metrics; sys.stdout.write(Metrics().render().decode())"
    )
    out = subprocess.run(
        [sys.executable, "-c", render], env=env, check=True, timeout=60, capture_output=True, text=True
    )
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(out.stdout)
        for s in family.samples
    }
    assert value(samples, "kitti_eval_http_requests_total", route="/healthz", method="GET", status="200") == 7
    assert value(samples, "kitti_eval_evaluations_total", outcome="ok") == 2


@pytest.mark.slow
@pytest.mark.parametrize("via_serve", [True, False], ids=["kitti-eval serve", "uvicorn"])
def test_sigterm_during_uploads_drains_then_stops(tmp_path: Any, via_serve: bool) -> None:
    """SIGTERM while 20 uploads are on their way: /readyz is 503 at once, each upload is answered 201 (and
    stored) or 503 shutting_down, or finds the connection closed; nothing half-written; the next start is
    clean. Under ``kitti-eval serve`` and under plain uvicorn (the Docker image's command) alike."""
    import signal
    import threading
    import time

    import httpx
    from server_helpers import LiveServer

    from kitti_eval.synth import generate

    infos, results = generate(1500, seed=9)  # about half a second an evaluation
    data_dir = tmp_path / "data"
    server = LiveServer(data_dir, via_serve=via_serve, max_concurrent_evals=2, max_queued_evals=30).start()
    outcomes: list[tuple[str, Any]] = []
    lock = threading.Lock()
    payload = pickle_bytes(results)
    try:
        with server.client() as c:
            assert register(c, "big", pickle_bytes(infos), "infos.pkl").status_code == 201

        def send(k: int) -> None:
            try:
                with server.client(timeout=120) as c:
                    r = upload(c, payload, gt="big", fields={"model": f"m{k}"})
                with lock:
                    outcomes.append((str(r.status_code), r.json()))
            except httpx.TransportError as e:
                with lock:
                    outcomes.append(("closed", type(e).__name__))

        threads = [threading.Thread(target=send, args=(k,)) for k in range(20)]
        for t in threads:
            t.start()
        # the signal lands when at least 10 uploads have arrived and are admitted (running or waiting)
        deadline = time.monotonic() + 120
        with server.client() as c:
            while scrape(c).get(("kitti_eval_evaluations_in_progress", ()), 0) < 10:
                assert time.monotonic() < deadline
                time.sleep(0.02)
        assert server.proc is not None
        server.proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        with httpx.Client(base_url=server.url, timeout=30) as c:
            readyz = c.get("/readyz")
            late = upload(c, payload[:1000], gt="big")  # while the admitted ones finish: refused
        for t in threads:
            t.join(120)
        server.proc.wait(60)
        stopped_in = time.monotonic() - t0
    finally:
        server.stop()
    assert readyz.status_code == 503 and "shutting down" in readyz.json()["error"]["message"], server.log()
    assert late.status_code == 503 and late.json()["error"]["code"] == "shutting_down"
    assert late.headers["retry-after"] == "2" and late.headers["connection"] == "close"
    assert server.proc.returncode in (0, -15), server.log()
    kinds = {k for k, _ in outcomes}
    assert len(outcomes) == 20 and kinds <= {"201", "503", "closed"}, outcomes
    assert all(body["error"]["code"] == "shutting_down" for k, body in outcomes if k == "503")
    acked = {body["id"]: body for k, body in outcomes if k == "201"}
    assert len(acked) >= 10 and stopped_in < 60  # every admitted one finished
    assert not any((data_dir / "tmp").glob("*/"))  # no scratch folder left behind
    restarted = LiveServer(data_dir).start()
    try:
        with restarted.client() as c:
            stored = c.get("/v1/evaluations", params={"limit": 100}).json()["items"]
            assert {e["id"] for e in stored} == set(acked)  # every 201 stored, nothing else
            for eid, body in acked.items():
                assert c.get(f"/v1/evaluations/{eid}").json() == body
    finally:
        restarted.stop()
    assert "removed" not in restarted.log()  # no scratch folders of a dead process to clean up


def pickle_bytes(obj: Any) -> bytes:
    import pickle

    return pickle.dumps(obj, protocol=4)


def test_metrics_in_accounts_mode(service_client: Any) -> None:
    """Accounts mode: /metrics needs an admin's token (401 as JSON for a scraper without one, 403 for a
    participant's: the metrics count every tenant's activity), unless the operator gave it a token of its own,
    which then is the only key to it."""
    from server_accounts import add_token, bearer

    with service_client(auth="accounts") as client:
        r = client.get("/metrics")
        assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized"
        client.post("/v1/admin/users", json={"name": "ops", "admin": True}, headers=ADMIN)
        _, token = add_token(client, "ops", read_only=True)
        assert scrape(client, **bearer(token))
        assert scrape(client, authorization=ADMIN["Authorization"])
        client.post("/v1/admin/users", json={"name": "participant", "admin": False}, headers=ADMIN)
        for read_only in (True, False):
            _, token = add_token(client, "participant", read_only=read_only)
            r = client.get("/metrics", headers=bearer(token))
            assert r.status_code == 403 and "the metrics are for admins" in r.json()["error"]["message"]
    with service_client(auth="accounts", metrics_token="scrape-me") as client:
        assert scrape(client, authorization="Bearer scrape-me")
        assert client.get("/metrics").status_code == 401
        assert client.get("/metrics", headers={"Authorization": "Bearer kte_0_wrong"}).status_code == 403


def test_the_queue_and_the_workers_in_the_metrics(service_client: Any) -> None:
    """Jobs by state, the runs of this process's workers by kind and outcome, the workers alive here and seen on
    the database."""
    with service_client() as client:
        before = scrape(client)
        assert upload(client, golden_bytes("result.pkl")).status_code == 201
        assert upload(client, golden_bytes("result.pkl")).status_code == 201
        assert upload(client, b"not a pickle at all", "result.pkl").status_code == 422
        after = scrape(client)

    def delta(name: str, **labels: str) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    jobs = {state: value(after, "kitti_eval_jobs", state=state) for state in ("queued", "running", "done", "failed")}
    assert jobs == {"queued": 0, "running": 0, "done": 2, "failed": 1}
    assert value(after, "kitti_eval_jobs_oldest_queued_age_seconds") == 0
    duration = "kitti_eval_job_duration_seconds_count"
    assert delta(duration, kind="evaluation", outcome="done") == 2
    assert delta(duration, kind="evaluation", outcome="refused") == 1  # the input's fault: not tried again
    assert delta("kitti_eval_job_attempts_sum", kind="evaluation", outcome="done") == 2  # each at its first
    assert value(after, "kitti_eval_job_workers_alive") == 2  # KITTI_EVAL_JOB_THREADS
    assert value(after, "kitti_eval_job_worker_processes_alive") == 0
    assert value(after, "kitti_eval_job_workers_seen") == 2  # this process's, seen on the database


def test_no_worker_no_readiness(service_client: Any) -> None:
    """With no worker thread and no worker process of its own, the service is ready only while a worker process
    beat its row on the database within the last minute; a queued job's age shows meanwhile."""
    import time
    from datetime import datetime, timedelta, timezone

    from kitti_eval_server.jobs.queue import JobQueue

    with service_client(job_threads=0, ready=False) as client:
        service = client.app.state.service
        assert service.warm.wait(timeout=120)
        r = client.get("/readyz")
        assert r.status_code == 503 and "no worker runs evaluations" in r.json()["error"]["message"], r.text
        assert upload(client, golden_bytes("result.pkl"), params={"wait": "0"}).status_code == 202
        long_ago = datetime.now(timezone.utc) - timedelta(minutes=2)
        JobQueue.of(service.store, clock=lambda: long_ago).worker_beat(
            "elsewhere:1", host="elsewhere", pid=1, threads=3, started_at=long_ago
        )
        assert client.get("/readyz").status_code == 503  # seen two minutes ago: gone, as far as anyone knows
        time.sleep(0.05)
        samples = scrape(client)
        assert value(samples, "kitti_eval_jobs", state="queued") == 1
        assert value(samples, "kitti_eval_jobs_oldest_queued_age_seconds") > 0
        assert value(samples, "kitti_eval_job_workers_seen") == 0
        assert value(samples, "kitti_eval_job_workers_alive") == 0
        now = datetime.now(timezone.utc)
        service.jobs.worker_beat("elsewhere:1", host="elsewhere", pid=1, threads=3, started_at=long_ago)
        service.jobs.worker_beat("other:2", host="other", pid=2, threads=1, started_at=now)
        assert client.get("/readyz").status_code == 200
        assert value(scrape(client), "kitti_eval_job_workers_seen") == 4
        service.jobs.worker_gone("elsewhere:1")
        service.jobs.worker_gone("other:2")
        assert client.get("/readyz").status_code == 503


def test_own_worker_processes_count_for_the_readiness_once_they_take_jobs(service_client: Any) -> None:
    """A worker process of the service's own pool that is running but has not yet recorded itself on the database
    (it records itself once its kernels are warm and it takes jobs) does not make the service ready; its row
    does, and so does another machine's worker while no process of the pool is running."""
    import socket
    from datetime import datetime, timezone

    class Pool:  # what the readiness reads of a WorkerPool: its processes' ids, how many are running
        pids = [4_000_001]
        alive = 1

    with service_client(job_threads=0, ready=False) as client:
        service = client.app.state.service
        assert service.warm.wait(timeout=120)
        service.pool = Pool()
        try:
            now = datetime.now(timezone.utc)
            r = client.get("/readyz")
            assert r.status_code == 503 and "worker processes are starting" in r.json()["error"]["message"], r.text
            service.jobs.worker_beat("elsewhere:7", host="elsewhere", pid=4_000_001, threads=1, started_at=now)
            assert client.get("/readyz").status_code == 503  # the same pid on another machine is not the pool's
            name = f"{socket.gethostname()}:4000001"
            service.jobs.worker_beat(name, host=socket.gethostname(), pid=4_000_001, threads=1, started_at=now)
            assert client.get("/readyz").status_code == 200
            service.jobs.worker_gone(name)
            Pool.alive = 0  # the pool's processes died: another machine's worker runs the jobs meanwhile
            assert client.get("/readyz").status_code == 200
            service.jobs.worker_gone("elsewhere:7")
            r = client.get("/readyz")
            assert r.status_code == 503 and "no worker runs evaluations" in r.json()["error"]["message"], r.text
        finally:
            service.pool = None


def test_a_database_the_service_cannot_use_refuses_the_start_in_one_line(tmp_path: Any) -> None:
    """Not reached, refused, or a URL whose password holds an '@': one line naming the database (without its
    password) and the driver's reason, not a traceback; a password with URL characters gets a hint."""
    from server_helpers import app_client, free_port

    from kitti_eval_server.errors import StartupRefused

    port = free_port()  # nothing listens there
    for url, hinted in [
        (f"postgresql://kitti:secret@127.0.0.1:{port}/kitti", False),
        (f"postgresql://kitti:ab@c/d#e@127.0.0.1:{port}/kitti", True),
    ]:
        with pytest.raises(StartupRefused) as refused, app_client(tmp_path / "data", warmup=False, database_url=url):
            pass
        message = refused.value.message
        assert message.startswith("cannot use the database postgresql+psycopg://kitti:***@"), message
        assert "secret" not in message and "ab@c" not in message and "\n" not in message
        assert ("given as PGPASSWORD" in message) == hinted, message
        assert hinted or "refused" in message.lower(), message  # the driver's reason


def test_probes_are_counted_not_logged_at_the_default_level(service_client: Any, access: LogRecords) -> None:
    def probes(samples: dict) -> dict[str, float]:
        out: dict[str, float] = {}
        for (name, labels), v in samples.items():
            route = dict(labels).get("route")
            if name == "kitti_eval_http_requests_total" and route in ("/healthz", "/readyz", "/metrics"):
                out[route] = out.get(route, 0.0) + v
        return out

    with service_client(log_format="json") as client:
        before = probes(scrape(client))
        access.records.clear()
        for _ in range(3):
            for probe in ("/healthz", "/readyz", "/metrics"):
                client.get(probe)
        assert client.get("/v1/evaluations").status_code == 200
        after = probes(scrape(client))
        logged = [(r.access["method"], r.access["route"]) for r in access.records]  # type: ignore[attr-defined]
        assert logged == [("GET", "/v1/evaluations")]  # the probes: none at INFO
        # each counted (/metrics: the three, and the scrape before them)
        assert {k: after[k] - before.get(k, 0.0) for k in after} == {"/healthz": 3, "/readyz": 3, "/metrics": 4}
        logging.getLogger("kitti_eval.server.access").setLevel(logging.DEBUG)  # asked for: each one is logged
        access.records.clear()
        client.get("/healthz")
    (record,) = access.records
    assert record.levelno == logging.DEBUG and record.access["route"] == "/healthz"  # type: ignore[attr-defined]
