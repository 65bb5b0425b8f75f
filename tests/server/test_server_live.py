"""Against a real uvicorn (``uvicorn kitti_eval_server.main:app``) started on 127.0.0.1 and a free port.

Concurrency: the server is sized so that all 32 simultaneous uploads are admitted (2 evaluating, 32 more
allowed to wait), and the client counts every non-201 as an error, a 503 included: no retries.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from server_helpers import ADMIN, ROOT, LiveServer, free_port, golden_bytes, register, wait_ready
from server_payloads import hostile_pickles

CONCURRENT = 32


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    server = LiveServer(
        tmp_path_factory.mktemp("live") / "data", max_concurrent_evals=2, max_queued_evals=CONCURRENT, max_upload_mb=8
    )
    with server:
        with server.client() as c:
            assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        yield server


def post(client: httpx.Client, data: bytes, gt: str = "small", **fields: str) -> httpx.Response:
    return client.post(
        "/v1/evaluations",
        data={"gt": gt, **fields},
        files={"predictions": ("result.pkl", data, "application/octet-stream")},
    )


def test_started_with_one_command_demo_ready(live) -> None:
    with live.client() as c:
        assert c.get("/healthz").json() == {"status": "ok"}
        assert c.get("/readyz").json() == {"status": "ready"}
        assert "demo" in [g["name"] for g in c.get("/v1/ground-truths").json()["items"]]
        assert "/v1/evaluations" in c.get("/openapi.json").json()["paths"]
        r = c.post(
            "/v1/evaluations",
            data={"gt": "demo"},
            files={"predictions": ("result.pkl.gz", (ROOT / "kitti_eval/data/demo/result.pkl.gz").read_bytes())},
        )
        assert r.status_code == 201, r.text
        assert r.json()["frames"] == 200


def test_32_concurrent_uploads_all_succeed(live) -> None:
    run = uuid.uuid4().hex
    data = golden_bytes("result.pkl")
    barrier = threading.Barrier(CONCURRENT)

    def one(i: int) -> tuple[int, dict]:
        with live.client(timeout=120) as c:
            barrier.wait(30)
            r = post(c, data, label=f"run={run}", epoch=str(i))
            return r.status_code, (r.json() if r.headers.get("content-type", "").startswith("application/json") else {})

    started = time.perf_counter()
    with ThreadPoolExecutor(CONCURRENT) as pool:
        outcomes = list(pool.map(one, range(CONCURRENT)))
    elapsed = time.perf_counter() - started
    statuses = [s for s, _ in outcomes]
    errors = [s for s in statuses if s != 201]
    assert errors == [], f"{len(errors)} errors: {statuses}"
    ids = {body["id"] for _, body in outcomes}
    assert len(ids) == CONCURRENT
    first = {k: v for k, v in outcomes[0][1].items() if k not in ("id", "evaluation")}
    assert all({k: v for k, v in b.items() if k not in ("id", "evaluation")} == first for _, b in outcomes)
    with live.client() as c:
        listed = c.get("/v1/evaluations", params={"label": f"run={run}", "limit": 100}).json()["items"]
    assert {i["id"] for i in listed} == ids
    print(f"\n32 concurrent uploads: {elapsed:.2f} s")


def test_hostile_and_malformed_uploads_do_not_hurt_the_live_server(live, tmp_path) -> None:
    canary = tmp_path / "CANARY"
    payloads = hostile_pickles(canary, tmp_path / "missing.npy")
    with live.client() as c:
        for name in (
            "os.system, protocol 2",
            "builtins.getattr(__import__('os'), 'system') chain",
            "subprocess.Popen",
            "torch._utils._rebuild_tensor_v2, hand-written",
            "gzip-wrapped os.system",
            "deep nesting: 100k nested lists",
            "huge allocation: one buffer reused as 300 arrays",
        ):
            r = post(c, payloads[name])
            assert r.status_code == 422, (name, r.text)
            assert set(r.json()) == {"error"} and "Traceback" not in r.text
        for data in (b"", b"\x80\x04\x95garbage", b"PK\x03\x04broken"):
            assert post(c, data).status_code == 422
        big = c.post(
            "/v1/evaluations", data={"gt": "small"}, files={"predictions": ("big.pkl", b"\x80\x04" + b"\0" * (9 << 20))}
        )
        assert big.status_code == 413 and big.json()["error"]["code"] == "payload_too_large"
        assert post(c, golden_bytes("result.pkl")).status_code == 201
    assert not canary.exists()


def test_admin_token_on_the_live_server(live) -> None:
    data = golden_bytes("kitti_infos_val.pkl")
    with live.client() as c:
        assert register(c, "live-gt", data, "i.pkl", headers={}).status_code == 401
        assert register(c, "live-gt", data, "i.pkl", headers={"Authorization": "Bearer wrong"}).status_code == 403
        assert register(c, "live-gt", data, "i.pkl").status_code == 201
        assert c.delete("/v1/ground-truths/live-gt").status_code == 401
        assert c.delete("/v1/ground-truths/live-gt", headers=ADMIN).status_code == 204


@pytest.mark.slow
def test_sigkill_right_after_acknowledged_uploads_loses_none(tmp_path) -> None:
    data_dir = tmp_path / "data"
    server = LiveServer(data_dir, max_concurrent_evals=2, max_queued_evals=16).start()
    acked: list[tuple[str, dict]] = []
    lock = threading.Lock()
    stop = threading.Event()
    payload = golden_bytes("result.pkl")

    def sender(worker: int) -> None:
        with server.client(timeout=30) as c:
            for i in range(200):  # bounded; ends at the kill
                if stop.is_set():
                    return
                try:
                    r = post(c, payload, gt="demo", model=f"w{worker}", epoch=str(i))
                except httpx.TransportError:
                    return
                if r.status_code == 201:
                    with lock:
                        acked.append((r.json()["id"], r.json()))

    threads = [threading.Thread(target=sender, args=(w,)) for w in range(6)]
    try:
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while len(acked) < 20 and time.monotonic() < deadline:
            time.sleep(0.005)
        server.kill()  # SIGKILL while the senders are still uploading
        with lock:
            acknowledged = list(acked)
        stop.set()
        for t in threads:
            t.join(30)
        with lock:  # a response read between the snapshot and the kill was acknowledged too
            acknowledged = list(acked)
        assert len(acknowledged) >= 20
        restarted = LiveServer(data_dir).start()
        try:
            with restarted.client() as c:
                for eid, body in acknowledged:
                    got = c.get(f"/v1/evaluations/{eid}")
                    assert got.status_code == 200, (eid, got.text)
                    assert got.json() == body
                total = c.get("/v1/evaluations", params={"limit": 500}).json()["items"]
                assert {eid for eid, _ in acknowledged} <= {i["id"] for i in total}
        finally:
            restarted.stop()
    finally:
        stop.set()
        server.stop()


@pytest.mark.slow
def test_serve_entry_point_runs_the_service(tmp_path) -> None:
    port = free_port()
    args = ["--port", str(port), "--data-dir", str(tmp_path / "d"), "--log-level", "warning"]
    env_code = f"import sys; from kitti_eval_server.main import serve; sys.exit(serve({args!r}))"
    proc = subprocess.Popen(
        [sys.executable, "-c", env_code], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5) as c:
            wait_ready(c.get)
            assert c.get("/v1/ground-truths/demo").status_code == 200
        assert (tmp_path / "d" / "kitti-eval.db").exists()
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    assert proc.returncode in (0, -15)  # uvicorn re-raises SIGTERM after a clean shutdown
