"""A benchmark submission the quota refuses is answered before its file is received (a live server: the answer
to a client waiting for ``100 Continue``, and the body of one that is not, are what is tested).
"""

from __future__ import annotations

import json
import socket
from datetime import datetime

import httpx
import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, LiveServer, golden_bytes

PATH = "/v1/benchmarks/bench/submissions"
BOUNDARY = "kitti-eval-test-boundary"


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("early") / "data", auth="accounts", auth_max_failures=1_000_000) as s:
        with httpx.Client(base_url=s.url, timeout=120) as c:
            hosted = host(c, benchmark={"quota": "1/1"})
            first = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
            ro = ok(c.post("/v1/admin/tokens", json={"user": "alice", "read_only": True}, headers=ADMIN), 201)
            hosted.tokens["alice-ro"] = ro["token"]
            # a public benchmark on a test set of a project the user "outsider" is not a member of
            ok(c.post("/v1/admin/projects", json={"name": "team"}, headers=ADMIN), 201)
            ok(c.post("/v1/admin/users", json={"name": "outsider"}, headers=ADMIN), 201)
            token = ok(c.post("/v1/admin/tokens", json={"user": "outsider"}, headers=ADMIN), 201)
            hosted.tokens["outsider"] = token["token"]
            form = {"name": "team-set", "project": "team", "sealed": "true"}
            files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
            ok(c.post("/v1/ground-truths", data=form, files=files, headers=ADMIN), 201)
            body = {"name": "team-bench", "ground_truth": "team-set", "quota": "3/1", "public": True}
            ok(c.post("/v1/benchmarks", json=body, headers=ADMIN), 201)
        yield s, hosted, first


def _multipart(content: bytes) -> bytes:
    head = (
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="predictions"; filename="result.pkl"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    return head + content + f"\r\n--{BOUNDARY}--\r\n".encode()


def _head(token: str, length: int, *, expect: bool, path: str = PATH) -> bytes:
    lines = [
        f"POST {path}?wait=0 HTTP/1.1",
        "Host: 127.0.0.1",
        f"Authorization: Bearer {token}",
        f"Content-Type: multipart/form-data; boundary={BOUNDARY}",
        f"Content-Length: {length}",
    ]
    if expect:
        lines.append("Expect: 100-continue")
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def _response(sock: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """One HTTP response read off the socket: status, headers (lower-case names), body (by Content-Length)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed before a response: {data!r}"
        data += chunk
    head, rest = data.split(b"\r\n\r\n", 1)
    status_line, *header_lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in header_lines)}
    length = int(headers.get("content-length", "0"))
    while len(rest) < length:
        chunk = sock.recv(65536)
        assert chunk
        rest += chunk
    return int(status_line.split()[1]), headers, rest[:length]


def _submissions(server: LiveServer, headers: dict[str, str]) -> list[dict]:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        return ok(c.get(PATH, headers=headers))["items"]


def test_a_client_waiting_for_continue_is_refused_without_sending_its_file(live) -> None:
    server, hosted, first = live
    body = _multipart(bytes(50 << 20))  # never sent
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(_head(hosted.tokens["alice"], len(body), expect=True))
        status, headers, raw = _response(sock)
        assert status == 429  # not "100 Continue": the file is not asked for
        error = json.loads(raw)["error"]
        assert error["code"] == "quota_exceeded" and "quota of 1 accepted submission per day" in error["message"]
        retry_at = datetime.fromisoformat(error["retry_at"])
        assert abs((retry_at - datetime.fromisoformat(first["created_at"])).total_seconds() - 86400) < 1
        assert 86000 <= int(headers["retry-after"]) <= 86401
        assert headers["connection"] == "close"
        assert sock.recv(1) == b""  # and the connection is closed, with the body never read
    assert [s["id"] for s in _submissions(server, hosted.headers("alice"))] == [first["id"]]


def test_another_client_is_answered_after_its_body_on_a_connection_that_stays_open(live) -> None:
    server, hosted, first = live
    body = _multipart(bytes(8 << 20))
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(_head(hosted.tokens["alice"], len(body), expect=False) + body)
        status, headers, raw = _response(sock)
        assert status == 429 and json.loads(raw)["error"]["code"] == "quota_exceeded"
        assert headers.get("connection") != "close"
        # the same connection serves the next request
        get = f"GET {PATH} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {hosted.tokens['alice']}\r\n\r\n"
        sock.sendall(get.encode())
        status, _, raw = _response(sock)
        assert status == 200 and [s["id"] for s in json.loads(raw)["items"]] == [first["id"]]


def test_whom_the_route_refuses_otherwise_is_answered_by_the_route(live) -> None:
    """A read-only token of the same participant is told 403 (the route's access), not the quota; a
    participant under the quota is sent ``100 Continue`` and accepted."""
    server, hosted, _ = live
    with httpx.Client(base_url=server.url, timeout=120) as c:
        refused = submit(c, hosted.headers("alice-ro"), golden_bytes("result.pkl"))
        assert refused.status_code == 403 and "read-only" in refused.json()["error"]["message"]
    body = _multipart(golden_bytes("result.pkl"))
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as sock:
        sock.sendall(_head(hosted.tokens["bob"], len(body), expect=True))
        assert sock.recv(64).startswith(b"HTTP/1.1 100 ")
        sock.sendall(body)
        status, _, raw = _response(sock)
        assert status == 202 and json.loads(raw)["state"] in ("queued", "running", "done"), raw[:300]
    assert [s["id"] for s in _submissions(server, hosted.headers("bob"))] == [json.loads(raw)["id"]]


def test_who_reads_a_public_benchmark_but_does_not_take_part_is_refused_without_sending_its_file(live) -> None:
    """A member of another project reads a public benchmark but does not take part in it: told 403 before the file
    is asked for, as the quota is, in the route's words (the project is not named)."""
    server, hosted, _ = live
    body = _multipart(bytes(50 << 20))  # never sent
    path = "/v1/benchmarks/team-bench/submissions"
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(_head(hosted.tokens["outsider"], len(body), expect=True, path=path))
        status, headers, raw = _response(sock)
        assert status == 403  # not "100 Continue"
        message = json.loads(raw)["error"]["message"]
        assert "takes part from the members of its test set's project" in message and "team" not in message.split()
        assert headers["connection"] == "close"
    with httpx.Client(base_url=server.url, timeout=120) as c:
        assert ok(c.get(path, headers=hosted.headers("outsider")))["items"] == []
