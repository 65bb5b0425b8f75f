"""A participant's path with ``kitti-eval`` alone, against a real service (uvicorn in a subprocess): a run of
``submit`` killed (SIGKILL) after the service accepted its file, run again, counts once and ``--new`` counts
again; alice makes a team inviting bob, bob joins, alice submits, lists her submissions, publishes one and reads
the board, which names the team."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from server_benchmarks import host, ok
from server_helpers import ADMIN, ROOT, LiveServer, app_client, golden_bytes
from server_phases import HOST, TWO_PHASES, phased_world

from kitti_eval.cli import main
from kitti_eval.demo import demo_paths
from kitti_eval_server.benchmarks.benchmark_file import apply_benchmark_file

pytestmark = pytest.mark.slow

_TIMEOUT_S = 300
_NO_WORKER = {"auth": "accounts", "job_threads": "0", "worker_processes": "0"}


def _env(token: str | None, config_dir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    env["KITTI_EVAL_CONFIG_DIR"] = str(config_dir)
    if token:
        env["KITTI_EVAL_TOKEN"] = token
    return env


def _cli(args: list[str], token: str, config_dir: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "kitti_eval.cli", *args],
        cwd=ROOT,
        env=_env(token, config_dir),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=_TIMEOUT_S)
    return proc.returncode, out, err


def _submission_jobs(server: LiveServer) -> list[dict[str, Any]]:
    with server.client() as c:
        return [j for j in ok(c.get("/v1/admin/jobs", headers=ADMIN))["items"] if j["kind"] == "submission"]


def _quota(server: LiveServer, token: str) -> dict[str, Any]:
    with server.client() as c:
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers={"Authorization": f"Bearer {token}"}))
    return dict(mine["quota"])


def test_a_submit_killed_after_the_service_accepted_its_file_counts_once_when_run_again(tmp_path) -> None:
    """The service has no worker: the submission stays queued, its run of ``submit`` follows it; SIGKILL once
    the service recorded it; the service started again with its workers; the same command again is answered
    with that submission, scored (exit 0), one submission used; ``--new`` makes a second."""
    data_dir, config = tmp_path / "data", tmp_path / "config"
    server = LiveServer(data_dir, ready_path="/healthz", **_NO_WORKER).start()
    try:
        with server.client() as c:
            hosted = host(c)
        token = hosted.tokens["alice"]
        pred = tmp_path / "result.pkl"
        pred.write_bytes(golden_bytes("result.pkl"))
        command = ["submit", str(pred), "--benchmark", "bench", "--service", server.url, "--format", "json"]
        proc = _cli(command, token, config)
        deadline = time.monotonic() + 120
        while not _submission_jobs(server):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        proc.kill()  # SIGKILL: no handler of the client runs
        proc.wait(timeout=10)
        (accepted,) = _submission_jobs(server)
        assert _quota(server, token)["used"] == 1
        server.stop()
        server = LiveServer(data_dir, auth="accounts").start(port=server.port)

        code, out, err = _finish(_cli(command, token, config))
        assert code == 0, err
        view = json.loads(out)
        assert view["id"] == accepted["id"] and view["status"] == "scored"
        assert "counted once" in err
        assert _quota(server, token)["used"] == 1
        assert [j["id"] for j in _submission_jobs(server)] == [accepted["id"]]

        code, out, err = _finish(_cli([*command, "--new"], token, config))
        assert code == 0, err
        assert json.loads(out)["id"] != accepted["id"]
        assert _quota(server, token)["used"] == 2
    finally:
        server.stop()


def _as(who: str, hosted: Any, config: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv("KITTI_EVAL_TOKEN", hosted.tokens[who])
    monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(config / who))


def _run(argv: list[str], capsys: Any) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_teams_whole_path_with_the_command_line_alone(tmp_path, capsys, monkeypatch) -> None:
    """alice makes the team lidar-lab inviting bob, bob joins; alice submits (told the phase, the team's quota
    left, the page and how to publish), lists her submissions, publishes one and reads the board, which names
    the team; withdrawn, it is off the board; published again, it names the team after alice leaves it."""
    data_dir, config = tmp_path / "data", tmp_path / "config"
    with app_client(data_dir, auth="accounts") as c:
        hosted = phased_world(c, ("alice", "bob"))
        apply_benchmark_file(c.app.state.benchmarks.catalog, TWO_PHASES, caller=HOST, source="kitti-phases.toml")
    with LiveServer(data_dir, auth="accounts") as server:
        service = ["--service", server.url]
        bench = ["--benchmark", "kitti-phases"]
        _as("alice", hosted, config, monkeypatch)
        monkeypatch.delenv("KITTI_EVAL_TOKEN")  # alice's token saved by login, which says whose it is
        monkeypatch.setattr("sys.stdin", io.StringIO(hosted.tokens["alice"] + "\n"))
        code, out, err = _run(["login", *service], capsys)
        assert code == 0 and "the token is alice's: saved in" in err, err
        code, out, err = _run(["team", "create", "lidar-lab", *bench, "--invite", "bob", *service], capsys)
        assert code == 0, err
        assert out == "lidar-lab: alice (invited: bob)\n"
        _as("bob", hosted, config, monkeypatch)
        code, out, err = _run(["team", "show", *bench, *service], capsys)
        assert code == 0, err
        assert "your team: none" in out and "invited to: lidar-lab" in out
        code, out, err = _run(["team", "join", "lidar-lab", *bench, *service], capsys)
        assert code == 0, err
        assert out.startswith("lidar-lab: alice, bob")
        code, out, err = _run(["team", "join", "lidar-lab", *bench, *service], capsys)
        assert code == 2 and "lidar-lab" in err  # joined already: the service refuses

        _as("alice", hosted, config, monkeypatch)
        pred = tmp_path / "result.pkl"
        pred.write_bytes(golden_bytes("result.pkl"))
        code, out, err = _run(["submit", str(pred), *bench, *service, "--format", "json", "--quiet"], capsys)
        assert code == 0, err
        first = json.loads(out)["id"]
        code, out, err = _run(["submit", str(pred), *bench, *service, "--new"], capsys)
        assert code == 0, err
        assert "phase dev: scored; the team lidar-lab has 3 of 5 left today" in err
        second = out.splitlines()[0].split()[1]
        assert f"its page: {server.url}/benchmarks/kitti-phases/submissions/{second}" in err
        assert f'kitti-eval publish {second} --benchmark kitti-phases --method "YOUR METHOD"' in err

        code, out, err = _run(["submissions", "kitti-phases", *service], capsys)
        assert code == 0, err
        assert "the team lidar-lab has 3 of 5 left today" in err
        rows = out.splitlines()[1:]
        assert [r.split()[0] for r in rows] == [second, first]
        assert all(r.split()[1] == "scored" and r.split()[3] == "no" for r in rows)
        code, out, err = _run(["submissions", "kitti-phases", *service, "--format", "json"], capsys)
        assert [s["id"] for s in json.loads(out)] == [second, first]

        code, out, err = _run(["publish", second, *bench, "--method", "PointPillars", *service], capsys)
        assert code == 0, err
        assert "is on the board of kitti-phases as 'PointPillars'" in err
        code, out, err = _run(["board", "kitti-phases", *service], capsys)
        assert code == 0, err
        (row,) = out.splitlines()[2:]
        assert row.split()[:3] == ["1", row.split()[1], "PointPillars"] and "lidar-lab" in row
        code, out, err = _run(["board", "kitti-phases", *service, "--format", "json"], capsys)
        (entry,) = json.loads(out)["entries"]
        assert (entry["id"], entry["team"], entry["method"]) == (second, "lidar-lab", "PointPillars")
        code, out, err = _run(["board", "kitti-phases", "--format", "csv"], capsys)  # the service login saved
        assert code == 0 and "PointPillars" in out and "lidar-lab" in out

        code, out, err = _run(["withdraw", second, *bench, *service], capsys)
        assert code == 0, err
        code, out, err = _run(["board", "kitti-phases", *service, "--format", "json"], capsys)
        assert json.loads(out)["entries"] == []

        # alice leaves the team: the entry she made for it is still the team's on the board
        code, out, err = _run(["publish", second, *bench, "--method", "PointPillars", *service], capsys)
        assert code == 0, err
        code, out, err = _run(["team", "leave", *bench, *service], capsys)
        assert code == 0 and out == "lidar-lab: bob\n" and "left the team lidar-lab of kitti-phases" in err, err
        code, out, err = _run(["board", "kitti-phases", *service, "--format", "json"], capsys)
        (entry,) = json.loads(out)["entries"]
        assert (entry["id"], entry["participant"], entry["team"]) == (second, "alice", "lidar-lab")
        code, out, err = _run(["team", "leave", *bench, *service], capsys)
        assert code == 2 and "you are in no team of 'kitti-phases'" in err


def _evaluations(server: LiveServer) -> list[dict[str, Any]]:
    with server.client() as c:
        return list(ok(c.get("/v1/evaluations", headers=ADMIN))["items"])


def test_gate_with_a_read_only_token_passes_and_fails_as_with_one_that_writes_and_stores_nothing(
    tmp_path, capsys, monkeypatch
) -> None:
    """The token that writes stores its evaluation (labelled branch=main); the read-only one has --pred evaluated
    without keeping it, says so, and gives the same verdicts (0 passed, 3 failed) and the same output, against a
    floor and against the history's baseline; the history holds the writer's evaluations alone. A benchmark's test
    set is refused to it as to an upload."""
    demo = demo_paths()[1]
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = host(c)
            ok(c.post("/v1/admin/projects", json={"name": "lab"}, headers=ADMIN), 201)
            ok(c.post("/v1/admin/members", json={"user": "alice", "project": "lab"}, headers=ADMIN), 201)
            body = {"user": "alice", "read_only": True}
            reader = ok(c.post("/v1/admin/tokens", json=body, headers=ADMIN), 201)["token"]
        monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(tmp_path / "config"))
        gate = ["gate", "--service", server.url, "--gt", "demo", "--pred", str(demo)]
        floors = {0: ["--min", "Car/3d/moderate >= 1"], 3: ["--min", "Car/3d/moderate >= 99.5"]}
        against_main = ["--baseline-label", "branch=main", "--max-drop", "0"]

        monkeypatch.setenv("KITTI_EVAL_TOKEN", hosted.tokens["alice"])
        written: dict[int, str] = {}
        for expected, rules in floors.items():
            code, written[expected], err = _run([*gate, *rules, "--label", "branch=main"], capsys)
            assert code == expected and "stored as evaluation" in err, err
        code, written[-1], err = _run([*gate, *against_main], capsys)
        assert code == 0 and "baseline: evaluation" in err, err
        stored = _evaluations(server)
        assert len(stored) == 3

        monkeypatch.setenv("KITTI_EVAL_TOKEN", reader)
        for expected, rules in floors.items():
            code, out, err = _run([*gate, *rules], capsys)
            assert (code, out) == (expected, written[expected]), err
            assert "not stored: the token is read-only" in err and "stored as evaluation" not in err
        code, out, err = _run([*gate, *against_main, "--label", "branch=x"], capsys)
        assert (code, out) == (0, written[-1]), err
        assert "--label branch=x is not stored" in err and "baseline: evaluation" in err
        # a benchmark's test set is refused as an evaluation against it is
        code, out, err = _run([*gate[:4], "test-set", *gate[5:], *floors[0]], capsys)
        assert code == 2 and out == "" and "the test set of benchmark 'bench'" in err, err
        assert _evaluations(server) == stored  # nothing of the read-only gates is in the history

        # the login of a read-only token says what it may do
        monkeypatch.setattr("sys.stdin", io.StringIO(reader + "\n"))
        code, out, err = _run(["login", "--service", server.url], capsys)
        assert code == 0 and "the token is alice's, read-only (it may read and gate, not submit nor store" in err
