"""``kitti-eval submit``, ``kitti-eval --service`` and ``gate --service`` against a real service (uvicorn in a
subprocess): a service that comes up after the client started, a file refused before anything is sent, a
service killed (SIGKILL) while the file is being received and again after the submission was accepted, the
quota, a service that never answers; the document printed equals the local run's."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, GOLDEN, ROOT, LiveServer, free_port, golden_bytes, golden_txt, tar_of

from kitti_eval.cli import main

pytestmark = pytest.mark.slow

_TIMEOUT_S = 300


def _cli(args: list[str], token: str | None, config_dir: Path) -> subprocess.Popen[str]:
    """``python -m kitti_eval.cli ARGS`` as a user runs it: the token in $KITTI_EVAL_TOKEN."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    env["KITTI_EVAL_CONFIG_DIR"] = str(config_dir)
    if token:
        env["KITTI_EVAL_TOKEN"] = token
    return subprocess.Popen(
        [sys.executable, "-m", "kitti_eval.cli", *args],
        cwd=ROOT,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=_TIMEOUT_S)
    return proc.returncode, out, err


def _mine(server: LiveServer, token: str) -> dict[str, Any]:
    with server.client() as c:
        return dict(ok(c.get("/v1/benchmarks/bench/submissions", headers={"Authorization": f"Bearer {token}"})))


def _submission_jobs(server: LiveServer) -> list[dict[str, Any]]:
    with server.client() as c:
        return [j for j in ok(c.get("/v1/admin/jobs", headers=ADMIN))["items"] if j["kind"] == "submission"]


def _assert_the_devkits_scores(scores: dict[str, float | None]) -> None:
    """Each score (R40, strict IoU) is the golden small case's official devkit number (the sealed set is its ground
    truth, the file its result.pkl): 1e-4 on float32 pickles, and the service rounds to 4 decimals."""
    official = json.loads((GOLDEN / "expected.json").read_text())["official_cpp"]["ap_r40"]
    assert scores
    for column, value in scores.items():
        cls, metric, difficulty, recall, oset = column.split("/")
        assert (recall, oset) == ("R40", "strict"), column
        reference = official[cls]["2d" if metric == "bbox" else metric][difficulty]
        assert value == pytest.approx(reference, abs=1.5e-4), column


def test_submit_waits_for_a_service_that_comes_up_4_s_after_it_started(tmp_path) -> None:
    server = LiveServer(tmp_path / "data", auth="accounts").start()
    try:
        with server.client() as c:
            hosted = host(c)
        port = server.port
        server.stop()
        pred = tmp_path / "result.pkl"
        pred.write_bytes(golden_bytes("result.pkl"))
        started = time.monotonic()
        proc = _cli(
            ["submit", str(pred), "--benchmark", "bench", "--service", server.url, "--format", "json"],
            hosted.tokens["alice"],
            tmp_path / "config",
        )
        time.sleep(4)
        assert proc.poll() is None, "the client gave up on a service that was not up yet"
        server.start(port=port)
        code, out, err = _finish(proc)
        assert code == 0, err
        assert time.monotonic() - started >= 4
        view = json.loads(out)
        assert view["status"] == "scored" and view["benchmark"] == "bench"
        _assert_the_devkits_scores(view["scores"])
        assert view["scores"]["Car/3d/moderate/R40/strict"] > 0
        mine = _mine(server, hosted.tokens["alice"])
        assert mine["quota"]["used"] == 1 and [s["id"] for s in mine["items"]] == [view["id"]]
        assert len(_submission_jobs(server)) == 1
        assert "trying again" in err  # it said what it was doing
    finally:
        server.stop()


def _not_a_pickle() -> bytes:
    return b"this is not a pickle\n" * 100


def _frames_missing() -> bytes:
    """The golden result as txt files, three test frames left out and one frame that is not a test frame."""
    files = golden_txt("pred.tar.gz")
    for name in sorted(files)[:3]:
        del files[name]
    files["999999.txt"] = next(iter(files.values()))
    return tar_of(files)


@pytest.mark.parametrize(("name", "make"), [("result.pkl", _not_a_pickle), ("result.tar.gz", _frames_missing)])
def test_a_refused_file_is_refused_here_with_the_validators_sentences_and_nothing_is_counted(
    tmp_path, name, make
) -> None:
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = host(c)
        pred = tmp_path / name
        pred.write_bytes(make())
        token = hosted.tokens["alice"]
        code, out, err = _finish(
            _cli(["submit", str(pred), "--benchmark", "bench", "--service", server.url], token, tmp_path)
        )
        assert code == 1, err
        assert out == ""
        v_code, _, v_err = _finish(
            _cli(["validate", str(pred), "--benchmark", f"{server.url}/benchmarks/bench"], token, tmp_path)
        )
        assert v_code == 1 and v_err.strip()
        assert v_err in err  # the validator's sentences, as kitti-eval validate prints them
        assert _mine(server, token)["quota"] == {"submissions": 3, "days": 1.0, "used": 0, "left": 3, "next_at": None}
        assert _submission_jobs(server) == []


def test_login_no_wait_and_the_quota(tmp_path) -> None:
    """A wrong token is refused by ``login`` (exit 2, nothing saved); the right one is saved and sent by
    ``submit`` without $KITTI_EVAL_TOKEN; ``--no-wait`` prints the accepted submission's id; past the quota,
    exit 4 saying when the next submission is accepted, nothing counted; a run again with the first run's
    ``--idempotency-key`` is answered with its submission."""
    config = tmp_path / "config"
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        with server.client() as c:
            hosted = host(c, benchmark={"quota": "2/2"})
        login = ["login", "--service", server.url]
        wrong = _cli(login, None, config)
        code, _, err = _finish_with_input(wrong, "not-a-token\n")
        assert code == 2 and "the token is not valid" in err
        assert not (config / "services.json").exists()
        code, _, err = _finish_with_input(_cli(login, None, config), hosted.tokens["alice"] + "\n")
        assert code == 0 and f"the token is alice's: saved in {config / 'services.json'}" in err
        pred = tmp_path / "result.pkl"
        pred.write_bytes(golden_bytes("result.pkl"))
        args = ["submit", str(pred), "--benchmark", "bench", "--service", server.url]
        keyed = [*args, "--idempotency-key", "ci-run-1234"]
        code, out, err = _finish(_cli([*keyed, "--no-wait"], None, config))  # the saved token
        assert code == 0, err
        first = out.strip()
        assert [s["id"] for s in _mine(server, hosted.tokens["alice"])["items"]] == [first]
        with server.client() as c:
            ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl"), name="bench"), 201)
        code, out, err = _finish(_cli(args, None, config))
        assert code == 4, err
        assert "quota of 2 accepted submissions per 2 days is used" in err and "accepted from 20" in err
        # the first run's key again (its CI job run again): its own submission, scored, not refused nor counted
        code, out, err = _finish(_cli([*keyed, "--format", "json"], None, config))
        assert code == 0, err
        assert json.loads(out)["id"] == first and json.loads(out)["status"] == "scored"
        assert _mine(server, hosted.tokens["alice"])["quota"]["used"] == 2


def _finish_with_input(proc: subprocess.Popen[str], text: str) -> tuple[int, str, str]:
    out, err = proc.communicate(text, timeout=_TIMEOUT_S)
    return proc.returncode, out, err


def test_a_service_that_never_answers_exits_5_within_the_retry_time(tmp_path) -> None:
    pred = tmp_path / "result.pkl"
    pred.write_bytes(golden_bytes("result.pkl"))
    started = time.monotonic()
    url = f"http://127.0.0.1:{free_port()}"
    code, out, err = _finish(
        _cli(["submit", str(pred), "--benchmark", "bench", "--service", url, "--retry-for", "3"], "t", tmp_path)
    )
    assert code == 5, err
    assert time.monotonic() - started < 30
    assert f"{url}: no answer to GET /v1/benchmarks/bench/frames within 3 s" in err


# ------------------------------------------------------------------------------------------ killed mid-way


class _Proxy:
    """A TCP proxy in front of the service (whichever port it has now): tells ``on_sent`` every chunk a client
    sends, so a test can kill the service while a request's body is arriving."""

    def __init__(self, upstream: Callable[[], int], on_sent: Callable[[bytes], None]) -> None:
        self.upstream = upstream
        self.on_sent = on_sent
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        try:
            upstream = socket.create_connection(("127.0.0.1", self.upstream()), timeout=5)
        except OSError:
            client.close()
            return
        upstream.settimeout(None)
        threading.Thread(target=self._pump, args=(upstream, client, None), daemon=True).start()
        self._pump(client, upstream, self.on_sent)

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket, seen: Callable[[bytes], None] | None) -> None:
        try:
            while chunk := src.recv(16384):
                if seen is not None:
                    seen(chunk)
                dst.sendall(chunk)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def close(self) -> None:
        self.listener.close()


def test_a_service_killed_while_receiving_and_after_accepting_counts_the_submission_once(tmp_path) -> None:
    """SIGKILL once while the submission's body is arriving (32 KiB of 124 KiB received), started again
    without a worker, SIGKILL again once the submission is accepted (its job recorded, not scored), started
    again with its workers: ``kitti-eval submit`` (one run) ends scored, with one submission counted."""
    data_dir = tmp_path / "data"
    no_worker = {"auth": "accounts", "job_threads": "0", "worker_processes": "0"}
    servers = [LiveServer(data_dir, ready_path="/healthz", **no_worker).start()]
    with servers[0].client() as c:
        hosted = host(c)
    events: list[str] = []  # what happened, in order
    body_seen = [0]  # bytes of the submission's request forwarded on its connection
    lock = threading.Lock()

    def restart(**settings: Any) -> None:
        server = LiveServer(data_dir, **settings)
        server.start()
        servers.append(server)
        events.append(f"started {len(servers)}")

    def kill_after_acceptance() -> None:
        deadline = time.monotonic() + 120
        while not _submission_jobs(servers[-1]):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        servers[-1].kill()
        events.append("killed after acceptance")
        restart(auth="accounts")

    def restart_then_kill_after_acceptance() -> None:
        restart(**no_worker, ready_path="/healthz")
        kill_after_acceptance()

    def on_sent(chunk: bytes) -> None:
        with lock:
            if b"POST /v1/benchmarks/bench/submissions" in chunk:
                body_seen[0] = len(chunk) - chunk.index(b"POST")
                events.append(f"posting to server {len(servers)}")
            elif body_seen[0]:
                body_seen[0] += len(chunk)
            if "killed while receiving" not in events and body_seen[0] > 32 << 10:
                servers[-1].kill()
                events.append("killed while receiving")
                threading.Thread(target=restart_then_kill_after_acceptance).start()

    proxy = _Proxy(lambda: servers[-1].port, on_sent)
    pred = tmp_path / "result.pkl"
    pred.write_bytes(golden_bytes("result.pkl"))
    try:
        proc = _cli(
            ["submit", str(pred), "--benchmark", "bench", "--service", f"http://127.0.0.1:{proxy.port}"]
            + ["--format", "json", "--retry-for", "240"],
            hosted.tokens["alice"],
            tmp_path / "config",
        )
        code, out, err = _finish(proc)
        assert code == 0, (events, err, servers[-1].log())
        assert events[:2] == ["posting to server 1", "killed while receiving"], events
        assert "killed after acceptance" in events and len(servers) == 3, events
        # the same request sent again to each service started again: the accepted one, then the answered one
        assert events.index("posting to server 2") < events.index("killed after acceptance"), events
        assert "posting to server 3" in events, events
        view = json.loads(out)
        assert view["status"] == "scored"
        _assert_the_devkits_scores(view["scores"])
        mine = _mine(servers[-1], hosted.tokens["alice"])
        assert mine["quota"]["used"] == 1 and [s["id"] for s in mine["items"]] == [view["id"]]
        assert [j["id"] for j in _submission_jobs(servers[-1])] == [view["id"]]
    finally:
        proxy.close()
        for server in servers:
            server.stop()


# ------------------------------------------------------------------------------------------ --service


@pytest.fixture(scope="module")
def open_service(tmp_path_factory) -> Any:
    """A service without accounts, the golden small ground truth registered as ``small``."""
    with LiveServer(tmp_path_factory.mktemp("svc") / "data") as server:
        with server.client() as c:
            files = {"file": ("kitti_infos_val.pkl", golden_bytes("kitti_infos_val.pkl"))}
            ok(c.post("/v1/ground-truths", data={"name": "small"}, files=files, headers=ADMIN), 201)
        yield server


def _main(argv: list[str], out: Path) -> str:
    assert main([*argv, "--output", str(out), "--quiet"]) == 0
    return out.read_text()


@pytest.mark.parametrize("fmt", ["json", "table", "markdown"])
@pytest.mark.parametrize("flags", [[], ["--classes", "Car,Pedestrian", "--ranges", "0,30,inf", "--coco"]])
def test_service_prints_the_document_a_local_run_prints(open_service, tmp_path, fmt, flags) -> None:
    pred = GOLDEN / "result.pkl"
    here = _main(
        ["--gt", str(GOLDEN / "kitti_infos_val.pkl"), "--pred", str(pred), "--format", fmt, *flags], tmp_path / "a"
    )
    there = _main(
        ["--service", open_service.url, "--gt", "small", "--pred", str(pred), "--format", fmt, *flags], tmp_path / "b"
    )
    assert there == here
    if fmt == "json":
        assert json.loads(there)["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] > 0


@pytest.mark.parametrize("layout", ["archive", "folder"])
def test_service_evaluation_of_txt_files_with_curves_and_errors(open_service, tmp_path, layout) -> None:
    """A tar of txt files, or the folder of them (which the client sends as a tar)."""
    pred = GOLDEN / "pred.tar.gz"
    if layout == "folder":
        pred = tmp_path / "txt"
        pred.mkdir()
        for name, data in golden_txt("pred.tar.gz").items():
            (pred / Path(name).name).write_bytes(data)
        assert len(list(pred.glob("*.txt"))) > 10
    flags = ["--format", "json", "--curves", "--errors"]
    here = json.loads(_main(["--gt", str(GOLDEN / "kitti_infos_val.pkl"), "--pred", str(pred), *flags], tmp_path / "a"))
    there = json.loads(
        _main(["--service", open_service.url, "--gt", "small", "--pred", str(pred), *flags], tmp_path / "b")
    )
    assert there == here
    assert "curves" in there and "errors" in there


def test_service_refusals_exit_as_the_cli_does(open_service, tmp_path, capsys) -> None:
    bad = tmp_path / "result.pkl"
    bad.write_bytes(b"not a pickle")
    assert main(["--service", open_service.url, "--gt", "small", "--pred", str(bad), "--quiet"]) == 1
    assert "error: " in capsys.readouterr().err
    pred = str(GOLDEN / "result.pkl")
    assert main(["--service", open_service.url, "--gt", "nothing", "--pred", pred, "--quiet"]) == 2
    assert "nothing" in capsys.readouterr().err
    assert main(["--service", open_service.url, "--gt", "small", "--pred", pred, "--split", "x.txt"]) == 2
    assert "--split cannot be sent to a service" in capsys.readouterr().err


def test_gate_against_the_services_history(open_service, tmp_path, capsys) -> None:
    """The baseline is the newest evaluation labelled branch=main against the same ground truth; the verdict is
    the local gate's against the same documents."""
    service = ["--service", open_service.url, "--gt", "small"]
    assert (
        main(
            [
                *service,
                "--pred",
                str(GOLDEN / "result.pkl"),
                "--label",
                "branch=main",
                "--quiet",
                "-o",
                str(tmp_path / "m.json"),
                "--format",
                "json",
            ]
        )
        == 0
    )
    worse = GOLDEN / "pred.tar.gz"
    local_base = tmp_path / "base.json"
    local_base.write_text((tmp_path / "m.json").read_text())
    capsys.readouterr()
    rules = ["--max-drop", "0.5", "--min", "Car/3d/moderate >= 1", "--min", "Pedestrian/3d/moderate >= 99"]
    code_here = main(
        [
            "gate",
            "--gt",
            str(GOLDEN / "kitti_infos_val.pkl"),
            "--pred",
            str(worse),
            "--baseline",
            str(local_base),
            *rules,
        ]
    )
    here = capsys.readouterr().out
    md = tmp_path / "verdict.md"
    code_there = main(
        [
            "gate",
            *service,
            "--pred",
            str(worse),
            "--label",
            "branch=feature",
            "--baseline-label",
            "branch=main",
            *rules,
            "--markdown",
            str(md),
        ]
    )
    captured = capsys.readouterr()
    there = captured.out
    assert (code_there, there) == (code_here, here), captured.err
    assert code_here == 3 and "Pedestrian/3d/moderate" in here
    verdict = md.read_text()
    assert verdict.startswith("#") and "Pedestrian/3d/moderate" in verdict  # the failed rule, where CI shows it
    history = ok(open_service.client().get("/v1/evaluations", params={"label": "branch=feature"}))["items"]
    assert len(history) == 1 and history[0]["evaluation"]["labels"] == {"branch": "feature"}


def test_a_baseline_label_with_no_evaluation_is_said_before_anything_is_evaluated(open_service, capsys) -> None:
    """``--baseline-label`` naming a label no evaluation has: refused in one line before --pred is sent, so nothing
    is evaluated or stored (--pred used to be evaluated and kept first, and only then was the label looked up)."""
    before = ok(open_service.client().get("/v1/evaluations", params={"limit": 500}))["items"]
    code = main(
        [
            "gate",
            "--service",
            open_service.url,
            "--gt",
            "small",
            "--pred",
            str(GOLDEN / "result.pkl"),
            "--baseline-label",
            "branch=never-labelled",
            "--max-drop",
            "0",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "no evaluation labelled branch=never-labelled against small" in err, err
    after = ok(open_service.client().get("/v1/evaluations", params={"limit": 500}))["items"]
    assert len(after) == len(before)
