"""A submission to a phase that its team's quota refuses is answered before its file is received (a live server,
the benchmark applied from its file by ``kitti-eval admin benchmark apply``): a client waiting for ``100 Continue``
is told 429 and never sends its file, whichever member of the team it is."""

from __future__ import annotations

import json
import socket

import httpx
from server_benchmarks import bearer, ok
from server_helpers import LiveServer, golden_bytes
from server_phases import TWO_PHASES, phased_world
from test_server_refuse_before_body import _head, _multipart, _response

from kitti_eval.cli import main

PATH = "/v1/benchmarks/kitti-phases/phases/test/submissions"


def test_a_teams_used_quota_is_answered_before_the_file(tmp_path) -> None:
    with LiveServer(tmp_path / "data", auth="accounts", auth_max_failures=1_000_000) as server:
        with httpx.Client(base_url=server.url, timeout=120) as c:
            hosted = phased_world(c)
            path = tmp_path / "kitti-phases.toml"
            path.write_text(TWO_PHASES)
            assert main(["admin", "--data-dir", str(server.data_dir), "benchmark", "apply", str(path)]) == 0
            alice, bob = hosted.tokens["alice"], hosted.tokens["bob"]
            team = {"name": "Two", "members": ["bob"]}
            ok(c.post("/v1/benchmarks/kitti-phases/teams", json=team, headers=bearer(alice)), 201)
            ok(c.post("/v1/benchmarks/kitti-phases/teams/Two/join", headers=bearer(bob)))
            for token in (alice, bob):  # the team's quota of 2
                files = {"predictions": ("result.pkl", golden_bytes("result.pkl"), "application/octet-stream")}
                sent = c.post(PATH, params={"wait": 0}, files=files, headers=bearer(token))
                assert sent.status_code in (201, 202), sent.text
        body = _multipart(bytes(50 << 20))  # never sent
        for token in (alice, bob):
            with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
                sock.sendall(_head(token, len(body), expect=True, path=PATH))
                status, headers, raw = _response(sock)
                assert status == 429  # not "100 Continue": the file is not asked for
                assert json.loads(raw)["error"]["code"] == "quota_exceeded"
                assert headers["connection"] == "close" and sock.recv(1) == b""
        # the dev phase's quota is another: its file is asked for (100 Continue)
        dev = "/v1/benchmarks/kitti-phases/phases/dev/submissions"
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
            sock.sendall(_head(alice, len(body), expect=True, path=dev))
            assert sock.recv(64).startswith(b"HTTP/1.1 100")
