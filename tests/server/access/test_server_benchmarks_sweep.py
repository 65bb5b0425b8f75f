"""Every benchmark route swept with hostile requests (``test_server_sweep``'s drawing) by every kind of caller:
no token, each participant, the admin token. No answer >= 500; no box value of the sealed test set in any body
(the needles of ``test_server_accounts_sweep``); no participant's unpublished result or submission id in a body
sent to anyone but that participant or an admin. ``KITTI_EVAL_SWEEP_EXAMPLES`` sets the examples per route and
caller (default 12 here)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, golden_bytes, golden_txt, zip_of
from test_server_accounts_sweep import ROLE_SWEEP, _request_text, _send, leaked
from test_server_sweep import ENDPOINTS, KNOWN, request_for

BENCHMARK_ENDPOINTS = [e for e in ENDPOINTS if "benchmarks" in e.path]
KEY = "Car/3d/moderate/R40/strict"


def _weaker(files: dict[str, bytes]) -> dict[str, bytes]:
    """The same results with every other line dropped: another AP, so bob's result is told apart from alice's."""
    out = {}
    for member, content in files.items():
        lines = content.decode().splitlines()
        out[member.rsplit("/", 1)[-1]] = ("\n".join(lines[::2]) + "\n").encode() if lines else b""
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    data = tmp_path_factory.mktemp("benchmark-sweep") / "data"
    with app_client(data, auth="accounts", auth_max_failures=1_000_000, max_upload_mb=2) as c:
        hosted = host(c, benchmark={"quota": "1000/1"})
        mine = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
        ok(
            c.post(
                f"/v1/benchmarks/bench/submissions/{mine['id']}/publish",
                headers=hosted.headers("alice"),
                json={"method": "a"},
            )
        )
        hidden = ok(submit(c, hosted.headers("bob"), zip_of(_weaker(golden_txt("pred.tar.gz"))), "weak.zip"), 201)
        assert hidden["scores"][KEY] != mine["scores"][KEY]
        secrets = [hidden["id"], f"{hidden['scores'][KEY]}", "weak.zip", hidden["sha256"]]
        KNOWN.evaluation = mine["id"]
        KNOWN.values = ["bench", "test-set", mine["id"], hidden["id"], "alice", "bob", "000001", "000007", KEY]
        yield c, hosted, secrets


@pytest.mark.parametrize("role", ["none", "alice", "admin"])
@pytest.mark.parametrize("endpoint", BENCHMARK_ENDPOINTS, ids=lambda e: e.id)
def test_no_sealed_box_and_no_unpublished_result_leaves_any_benchmark_route(world, endpoint, role) -> None:
    c, hosted, secrets = world
    headers: dict[str, str] = {"none": {}, "alice": hosted.headers("alice"), "admin": ADMIN}[role]

    @ROLE_SWEEP
    @given(st.data())
    def sweep(data: st.DataObject) -> None:
        request = data.draw(request_for(endpoint), label="request")
        response = _send(c, request, headers)
        assert response.status_code < 500, (request["url"][:200], response.text[:300])
        assert not leaked(response.text), (request["method"], request["url"][:200], leaked(response.text)[:5])
        if role != "admin":
            sent = _request_text(request)
            for secret in secrets:
                if secret not in sent:
                    assert secret not in response.text, (secret, request["method"], request["url"][:200])

    sweep()


def test_and_directly(world) -> None:
    """The routes that do answer, asked plainly: the board, the page, the CSV, alice's own submissions."""
    c, hosted, secrets = world
    alice = hosted.headers("alice")
    paths = [
        "/v1/benchmarks",
        "/v1/benchmarks/bench",
        "/v1/benchmarks/bench/frames",
        "/v1/benchmarks/bench/leaderboard",
        "/v1/benchmarks/bench/leaderboard?format=csv",
        "/benchmarks/bench",
        "/v1/benchmarks/bench/submissions",
        f"/v1/benchmarks/bench/submissions/{secrets[0]}",
    ]
    answered: list[Any] = []
    for path in paths:
        for headers in ({}, alice):
            response = c.get(path, headers=headers)
            assert response.status_code < 500 and not leaked(response.text)
            assert not any(s in response.text for s in secrets if s not in path), path
            answered.append(response.status_code)
    assert answered.count(200) >= 12  # most of them answered, with something in them
    own = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
    assert len(own["items"]) == 1 and own["items"][0]["participant"] == "alice"


def test_before_the_reveal_no_participant_sees_a_private_or_whole_set_score(tmp_path) -> None:
    """A benchmark with a public/private split: every benchmark route and page a participant or an anonymous
    reader can ask, asked plainly, shows the public part's scores and neither the private part's nor the whole
    set's, until the reveal; then they appear."""
    with app_client(tmp_path / "data", auth="accounts") as c:
        hosted = host(c, benchmark={"quota": "10/1", "split_percent": 50})
        alice = hosted.headers("alice")
        sid = ok(submit(c, alice, golden_bytes("result.pkl")), 201)["id"]
        ok(c.post(f"/v1/benchmarks/bench/submissions/{sid}/publish", headers=alice, json={"method": "a"}))
        (full,) = ok(c.get("/v1/benchmarks/bench/submissions/all", headers=ADMIN))["items"]
        public, private, whole = full["parts"]["public"][KEY], full["parts"]["private"][KEY], full["scores"][KEY]
        assert len({public, private, whole}) == 3  # three numbers, told apart
        hidden = [f"{private}", f"{whole}"]
        paths = [
            "/v1/benchmarks",
            "/v1/benchmarks/bench",
            "/v1/benchmarks/bench/leaderboard",
            "/v1/benchmarks/bench/leaderboard?format=csv",
            "/benchmarks/bench",
            "/v1/benchmarks/bench/submissions",
            f"/v1/benchmarks/bench/submissions/{sid}",
        ]
        shown_public = False
        for path in paths:
            for headers in ({}, alice):
                text = c.get(path, headers=headers).text
                assert not any(h in text for h in hidden), (path, bool(headers))
                shown_public |= f"{public}" in text
        assert shown_public
        ok(c.post("/v1/benchmarks/bench/close", headers=ADMIN))
        ok(c.post("/v1/benchmarks/bench/reveal", headers=ADMIN))
        assert f"{private}" in c.get("/v1/benchmarks/bench/leaderboard").text
        assert f"{whole}" in c.get(f"/v1/benchmarks/bench/submissions/{sid}", headers=alice).text
