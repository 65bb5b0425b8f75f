"""The service behind a proxy and in front of hostile clients: client addresses, metric labels, messages about
registered ground truths, log lines, distance bins, and open mode on a database that holds accounts."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pickle
import random
import re
import string
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from server_accounts import add_token, bearer
from server_helpers import ADMIN, ADMIN_TOKEN, LogRecords, app_client, assert_error, golden_bytes, upload, wait_ready

from kitti_eval.demo import demo_paths
from kitti_eval_server import Settings, create_app
from kitti_eval_server.access.auth import client_of
from kitti_eval_server.errors import StartupRefused
from kitti_eval_server.observability import JsonFormatter, TextFormatter

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

PROXY = "10.0.0.1"
WRONG = bearer("kte_0123456789abcdef_not-the-secret")


@contextlib.contextmanager
def peer_client(data_dir: Path, peer: str, **settings: Any) -> Iterator[TestClient]:
    """A TestClient whose requests come from the socket address ``peer`` (as a proxy's would)."""
    settings.setdefault("admin_token", ADMIN_TOKEN)
    app = create_app(Settings(data_dir=data_dir, warmup=False, **settings))
    with TestClient(app, raise_server_exceptions=False, client=(peer, 40000)) as client:
        wait_ready(client.get)
        yield client


def _scope(peer: str, trusted: str, *forwarded: str) -> dict[str, Any]:
    state = SimpleNamespace(trusted_proxies=Settings(trusted_proxies=trusted).trusted_networks)
    headers = [(b"x-forwarded-for", value.encode()) for value in forwarded]
    return {"type": "http", "client": (peer, 1234), "headers": headers, "app": SimpleNamespace(state=state)}


# ------------------------------------------------------------------------------------------ trusted proxies


@pytest.mark.parametrize(
    ("peer", "trusted", "forwarded", "client"),
    [
        (PROXY, "", ["203.0.113.5"], PROXY),  # trust nobody (the default): the header is ignored
        (PROXY, "10.0.0.1", ["203.0.113.5"], "203.0.113.5"),
        (PROXY, "10.0.0.0/8", ["203.0.113.5"], "203.0.113.5"),
        (PROXY, "10.0.0.0/8", [], PROXY),  # a trusted peer sending no header is the client
        ("198.51.100.7", "10.0.0.0/8", ["203.0.113.5"], "198.51.100.7"),  # spoofed by an untrusted peer
        # a chain of proxies: the right-most address that is not a trusted proxy; what the client wrote on the
        # left of it is not believed
        (PROXY, "10.0.0.0/8", ["192.0.2.66, 203.0.113.5, 10.0.0.2"], "203.0.113.5"),
        (PROXY, "10.0.0.0/8,172.16.0.0/12", ["203.0.113.5, 172.17.0.3", "10.9.8.7"], "203.0.113.5"),
        (PROXY, "10.0.0.0/8", ["junk, 203.0.113.5"], "203.0.113.5"),
        (PROXY, "10.0.0.0/8", ["10.0.0.3, 10.0.0.2"], "10.0.0.3"),  # all of them proxies: the left-most
        (PROXY, "10.0.0.0/8", ["203.0.113.5, not-an-address"], PROXY),  # invalid: the peer
        (PROXY, "10.0.0.0/8", ["203.0.113.5:4711"], PROXY),
        (PROXY, "10.0.0.0/8", [""], PROXY),
        (PROXY, "10.0.0.0/8", ["2001:db8::7"], "2001:db8::7"),
        ("::ffff:10.0.0.1", "10.0.0.0/8", ["203.0.113.5"], "203.0.113.5"),  # a dual-stack socket's peer
        ("fd00::1", "fd00::/64", ["203.0.113.5, fd00::2"], "203.0.113.5"),
    ],
)
def test_client_address_behind_trusted_proxies(peer: str, trusted: str, forwarded: list[str], client: str) -> None:
    assert client_of(_scope(peer, trusted, *forwarded)) == client


def test_trusted_proxies_setting_is_checked() -> None:
    assert Settings(trusted_proxies=" 10.0.0.5, fd00::/64 ").trusted_proxies == "10.0.0.5/32,fd00::/64"
    assert Settings().trusted_networks == ()
    for bad in ("proxy.example", "10.0.0.1/8", "10.0.0.0/33"):
        with pytest.raises(ValueError, match="is not an IP address or network"):
            Settings(trusted_proxies=bad)


def _refuse(client: TestClient, forwarded: str) -> int:
    return client.get("/v1/evaluations", headers={**WRONG, "X-Forwarded-For": forwarded}).status_code


def _refused_clients(client: TestClient) -> list[str]:
    """The client of each refused token in the audit log, newest first (read on the service: behind an
    untrusted proxy the admin's own requests are locked out too)."""
    rows = client.app.state.service.audit.entries()  # type: ignore[attr-defined]
    return [r.client for r in rows if r.action == "token.refused"]


def test_behind_a_trusted_proxy_each_client_has_its_own_failure_count_and_audit_rows(tmp_path: Path) -> None:
    limits = {"auth": "accounts", "auth_max_failures": 3}
    with peer_client(tmp_path / "data", PROXY, trusted_proxies="10.0.0.0/8", **limits) as c:
        assert c.post("/v1/admin/users", json={"name": "bea"}, headers=ADMIN).status_code == 201
        _, token = add_token(c, "bea")
        assert [_refuse(c, "203.0.113.5") for _ in range(4)] == [401, 401, 401, 429]
        # another client behind the same proxy is not locked out, and may still be refused on its own
        ok = c.get("/v1/evaluations", headers={**bearer(token), "X-Forwarded-For": "203.0.113.6"})
        assert ok.status_code == 200
        assert _refuse(c, "198.51.100.1, 203.0.113.6, 10.0.0.2") == 401
        assert _refused_clients(c) == ["203.0.113.6", *["203.0.113.5"] * 3]
    # the same proxy without the setting: every client behind it is the proxy, and one locks out the others
    with peer_client(tmp_path / "untrusted", PROXY, **limits) as c:
        assert c.post("/v1/admin/users", json={"name": "bea"}, headers=ADMIN).status_code == 201
        _, token = add_token(c, "bea")
        assert [_refuse(c, "203.0.113.5") for _ in range(3)] == [401, 401, 401]
        assert c.get("/v1/evaluations", headers={**bearer(token), "X-Forwarded-For": "203.0.113.6"}).status_code == 429
        assert _refused_clients(c) == [PROXY] * 3


def test_a_forwarded_header_from_an_untrusted_peer_is_ignored(tmp_path: Path) -> None:
    with peer_client(tmp_path / "data", "198.51.100.7", auth="accounts", trusted_proxies=PROXY) as c:
        assert _refuse(c, "203.0.113.9") == 401
        assert _refused_clients(c) == ["198.51.100.7"]


# ------------------------------------------------------------------------------------------ metric labels


def _series(text: str, metric: str) -> set[str]:
    return {line.split(" ")[0] for line in text.splitlines() if line.startswith(metric + "{")}


def test_random_methods_and_paths_add_a_bounded_number_of_metric_series(tmp_path: Path) -> None:
    rng = random.Random(7)
    with peer_client(tmp_path / "data", "127.0.0.1") as c:
        c.get("/v1/evaluations")
        before = c.get("/metrics").text
        tokens = ["".join(rng.choices(string.ascii_uppercase, k=12)) for _ in range(50)]
        paths = [
            rng.choice(["/", "/v1/evaluations/", "/v1/ground-truths/", "/static/", "/ui/", "/v1/"])
            + "".join(rng.choices(string.ascii_lowercase + string.digits, k=16))
            for _ in range(50)
        ]
        for method, path in zip(tokens, paths):
            assert c.request(method, path).status_code in (404, 405)
        after = c.get("/metrics").text
    for metric in ("kitti_eval_http_requests_total", "kitti_eval_http_request_duration_seconds_count"):
        new = _series(after, metric) - _series(before, metric)
        assert 1 <= len(new) <= 8, new  # method "other" on a handful of routes, by status
        labels = " ".join(new)
        assert not any(t in labels for t in tokens) and not any(p.rsplit("/", 1)[-1] in labels for p in paths)
        methods = {m for line in _series(after, metric) for m in re.findall(r'method="([^"]*)"', line)}
        assert methods <= {"GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "other"}, methods
        assert "other" in methods


# ------------------------------------------------------------------------------------------ registered ground truths


def _lidar_only_infos() -> tuple[bytes, list[str]]:
    """The golden infos as a LiDAR-only set has them (no 2D box, alpha, truncation, occlusion); its frame ids."""
    infos = pickle.loads(golden_bytes("kitti_infos_val.pkl"))
    for info in infos:
        for key in ("truncated", "occluded", "alpha", "bbox"):
            del info["annos"][key]
    return pickle.dumps(infos), [str(info["image"]["image_idx"]) for info in infos]


def test_messages_about_a_registered_ground_truth_name_no_server_path_and_a_sealed_ones_no_frame(
    tmp_path: Path,
) -> None:
    data_dir = tmp_path / "data"
    content, frames = _lidar_only_infos()
    predictions = golden_bytes("result.pkl")
    with app_client(data_dir, warmup=False) as c:
        for name, sealed in (("lidar-sealed", "true"), ("lidar-open", "false")):
            files = {"file": ("infos.pkl", content)}
            r = c.post("/v1/ground-truths", data={"name": name, "sealed": sealed}, files=files, headers=ADMIN)
            assert r.status_code == 201, r.text
        warm = assert_error(upload(c, predictions, gt="lidar-sealed"), 422, "the ground truth 'lidar-sealed'")
    with app_client(data_dir, warmup=False) as c:  # a new process: the sets are loaded from the server's copies
        cold = assert_error(upload(c, predictions, gt="lidar-sealed"), 422, "the ground truth 'lidar-sealed'")
        unsealed = assert_error(upload(c, predictions, gt="lidar-open"), 422, "the ground truth 'lidar-open'")
        assert upload(c, predictions, gt="lidar-sealed", fields={"lidar_only": "true"}).status_code == 201
    for err in (warm, cold, unsealed):
        text = json.dumps({k: v for k, v in err.items() if k != "request_id"})
        assert str(data_dir) not in text and str(data_dir.resolve()) not in text and "ground-truths/" not in text
        assert "lidar_only=true" in err["message"] and err["code"] == "invalid_input" and err["field"] == "bbox"
    for err in (warm, cold):
        text = json.dumps({k: v for k, v in err.items() if k != "request_id"})
        assert "frame" not in err and not [f for f in frames if f in text], err
    assert unsealed["frame"] == frames[0]  # a set that is not sealed: the first frame without 2D boxes


# ------------------------------------------------------------------------------------------ log lines


@pytest.fixture
def service_log() -> Iterator[LogRecords]:
    """The records of the service's loggers (under pytest the root logger is configured, so the service
    installs no handler of its own: the test formats the records with the service's formatters)."""
    handler = LogRecords()
    logger = logging.getLogger("kitti_eval.server")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def test_a_request_path_cannot_forge_a_log_line(tmp_path: Path, service_log: LogRecords) -> None:
    forged = "/v1/evaluations/x%0Afake%20line%0D%0AINFO:%20%20%20%20%20kitti-eval:%20audit%5C%E2%80%A8"
    with peer_client(tmp_path / "data", "127.0.0.1", auth="accounts") as c:
        service_log.records.clear()
        assert c.get(forged, headers=WRONG).status_code == 401  # refused: an audit line and an access line
        assert c.get(forged, headers=ADMIN).status_code == 404
        records = list(service_log.records)
    audit = [r for r in records if r.getMessage().startswith("audit:")]
    access = [r for r in records if r.name == "kitti_eval.server.access"]
    assert len(audit) == 1 and len(access) == 2 and len(records) == 3, [r.getMessage() for r in records]
    text = [TextFormatter("%(message)s").format(r) for r in records]
    for line in text:  # each record is exactly one line, whatever the path held
        assert "\n" not in line and "\r" not in line and "\u2028" not in line, line
    assert "/v1/evaluations/x\\nfake line\\r\\nINFO:     kitti-eval: audit\\\\\\u2028" in text[0]
    for r in records:  # JSON lines were safe already: json.dumps escapes every control character
        assert "\n" not in JsonFormatter().format(r)


# ------------------------------------------------------------------------------------------ distance bins


def test_at_most_eight_distance_bins(client: Any) -> None:
    demo = demo_paths()[1].read_bytes()
    eight = "0,10,20,30,40,50,60,70,inf"
    r = upload(client, demo, "result.pkl.gz", fields={"ranges": eight, "classes": "Car"})
    assert r.status_code == 201, r.text
    assert [x["label"] for x in r.json()["ranges"]] == [*(f"{lo}-{lo + 10}m" for lo in range(0, 70, 10)), "70m+"]
    for nine in ("0,10,20,30,40,50,60,70,80,inf", ",".join(str(i) for i in range(100_000))):
        err = assert_error(upload(client, demo, "result.pkl.gz", fields={"ranges": nine}), 422, "at most 8 distance")
        assert err["code"] == "invalid_request" and "9 edges" in err["message"]
    err = assert_error(upload(client, demo, "result.pkl.gz", fields={"ranges": "0,10,20,30,40,50,60,70,80,inf"}), 422)
    assert err["message"].endswith("got 9")


# ------------------------------------------------------------------------------------------ open mode and accounts


def _make_accounts(data_dir: Path) -> None:
    with app_client(data_dir, auth="accounts", warmup=False) as c:
        assert c.post("/v1/admin/users", json={"name": "ann"}, headers=ADMIN).status_code == 201
        add_token(c, "ann")


def test_open_mode_refuses_to_start_on_a_database_that_holds_accounts(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir, warmup=False) as c:  # open mode on a database without accounts: as before
        assert c.get("/v1/evaluations").status_code == 200
    _make_accounts(data_dir)
    with pytest.raises(StartupRefused) as refused, app_client(data_dir, warmup=False):
        pass
    assert "1 user, 1 token not revoked" in refused.value.message
    assert "KITTI_EVAL_AUTH=accounts" in refused.value.message
    assert "KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS=true" in refused.value.message
    with app_client(data_dir, warmup=False, allow_open_with_accounts=True) as c:  # told to: it starts
        assert c.get("/v1/evaluations").status_code == 200
    with app_client(data_dir, auth="accounts", warmup=False) as c:
        assert c.get("/v1/evaluations").status_code == 401


@pytest.mark.slow
def test_kitti_eval_serve_says_why_it_refuses_to_start(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    _make_accounts(data_dir)
    env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    env.update(KITTI_EVAL_ADMIN_TOKEN=ADMIN_TOKEN, KITTI_EVAL_WARMUP="false", KITTI_EVAL_LOG_FORMAT="text")
    command = [sys.executable, "-m", "kitti_eval.cli", "serve", "--data-dir", str(data_dir), "--port", "0"]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert "KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS=true" in done.stderr
    assert "Traceback" not in done.stderr and 'File "' not in done.stderr, done.stderr
    assert done.stderr.count("KITTI_EVAL_ALLOW_OPEN_WITH_ACCOUNTS") == 1, done.stderr
