"""``kitti-eval serve`` starts a worker process before it imports the web application, and the service's pool
takes it over (:mod:`kitti_eval_server.jobs.spawn`): only when it is the process the pool would start itself, and
none is left behind when the service does not start."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from server_helpers import free_port

from kitti_eval_server.jobs import pool as pool_module
from kitti_eval_server.jobs import spawn
from kitti_eval_server.jobs.pool import WorkerPool

SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]


@pytest.fixture
def sleepers(monkeypatch) -> Iterator[None]:
    """Worker processes that only sleep (a real one takes 2 s of CPU to start), for the pool and the early start."""
    monkeypatch.setattr(spawn, "child_command", lambda *a: list(SLEEPER))
    monkeypatch.setattr(pool_module, "child_command", lambda *a: list(SLEEPER))
    yield
    spawn.discard_early()


def _early(tmp_path: Path, processes: int = 2, grace_s: float = 5.0, url: str = "sqlite://") -> None:
    spawn.start_early(processes, 1, grace_s, tmp_path / "work", url)


def test_the_pool_takes_over_the_process_started_early_and_starts_the_others(sleepers, tmp_path) -> None:
    _early(tmp_path)
    (first,) = spawn._early.procs  # type: ignore[union-attr]
    pool = WorkerPool(2, threads=1, grace_s=5.0, work_dir=tmp_path / "work", database_url="sqlite://")
    pool.start()
    try:
        assert pool.pids[0] == first.pid and len(set(pool.pids)) == 2 and pool.alive == 2
        assert spawn._early is None  # taken: not stopped by a later discard
        spawn.discard_early()
        assert first.poll() is None
    finally:
        pool.stop(0.5)
    assert first.poll() is not None and pool.alive == 0  # stopped as the pool's own


@pytest.mark.parametrize(
    "other",
    [
        {"grace_s": 9.0},
        {"url": "sqlite:////elsewhere.db"},
        {"processes": 3},
    ],
    ids=["grace", "database", "processes"],
)
def test_a_process_started_for_another_pool_is_stopped_not_taken(sleepers, tmp_path, other) -> None:
    _early(tmp_path, **other)
    (early,) = spawn._early.procs  # type: ignore[union-attr]
    pool = WorkerPool(2, threads=1, grace_s=5.0, work_dir=tmp_path / "work", database_url="sqlite://")
    pool.start()
    try:
        assert early.poll() is not None  # stopped
        assert early.pid not in pool.pids and pool.alive == 2
    finally:
        pool.stop(0.5)


def test_processes_no_service_took_are_stopped(sleepers, tmp_path) -> None:
    _early(tmp_path)
    (early,) = spawn._early.procs  # type: ignore[union-attr]
    spawn.discard_early()
    assert early.poll() is not None and spawn._early is None


def test_nothing_is_started_early_where_the_folder_cannot_be_made(sleepers, tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    spawn.start_early(2, 1, 5.0, blocker / "work", "sqlite://")
    assert spawn._early is None


def _children_of(pid: int) -> list[int]:
    """Processes started with ``--parent pid`` (worker processes of that service)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                argv = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"--parent" in argv and argv[argv.index(b"--parent") + 1 : argv.index(b"--parent") + 2] == [
                str(pid).encode()
            ]:
                found.append(int(entry.name))
    return found


def test_private_files_hides_what_is_made_from_other_users_and_gives_the_umask_back(tmp_path) -> None:
    from kitti_eval_server.data_folder import private_files

    before = os.umask(0o022)
    try:
        with private_files():
            (tmp_path / "folder").mkdir()
            (tmp_path / "folder" / "file").write_text("sealed")
        assert os.umask(0o022) == 0o022  # given back
    finally:
        os.umask(before)
    assert (tmp_path / "folder").stat().st_mode & 0o777 == 0o750
    assert (tmp_path / "folder" / "file").stat().st_mode & 0o777 == 0o640


def _serve(tmp_path: Path, *args: str) -> tuple[subprocess.Popen[bytes], Path]:
    env = {**os.environ, "KITTI_EVAL_LOG_FORMAT": "json", "KITTI_EVAL_ADMIN_TOKEN": "t" * 32}
    for name in ("KITTI_EVAL_WORKER_PROCESSES", "KITTI_EVAL_JOB_THREADS"):
        env.pop(name, None)
    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        argv = [sys.executable, "-m", "kitti_eval.cli", "serve", *args]
        umask = os.umask(0o022)  # as a login shell's
        try:
            return subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=tmp_path), log
        finally:
            os.umask(umask)


def test_serve_starts_a_worker_with_the_command_and_its_pool_runs_it(tmp_path) -> None:
    """The real command: one worker process started before the application's imports, taken over by the pool
    (its log says so), the evaluation run, and no worker process left once the service stopped."""
    port = free_port()
    proc, log = _serve(tmp_path, "--port", str(port), "--data-dir", str(tmp_path / "data"))
    try:
        deadline = time.monotonic() + 300
        while True:
            assert proc.poll() is None, log.read_text()[-4000:]
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, log.read_text()[-4000:]
            time.sleep(0.2)
        children = _children_of(proc.pid)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=90)
    started = [json.loads(line)["message"] for line in log.read_text().splitlines() if "worker processes of" in line]
    assert len(started) == 1 and "(1 started with the command, " in started[0], started
    pids = json.loads(started[0].split(": ", 1)[1].split(" (")[0])
    assert len(pids) >= 1 and sorted(pids) == sorted(children)  # the pool's, all of them its service's
    assert _children_of(proc.pid) == []
    # what the service wrote is not readable by other users, whatever the umask it was started with (022 here)
    data = tmp_path / "data"
    made = [data / "kitti-eval.db", data / "ground-truths", *(data / "ground-truths").rglob("*")]
    assert len(made) >= 3 and all(p.stat().st_mode & 0o007 == 0 for p in made), [
        (str(p), oct(p.stat().st_mode)) for p in made
    ]


def test_a_service_that_does_not_start_leaves_no_worker_behind(tmp_path) -> None:
    """A data folder whose subfolder cannot be made (a file in its place): the service refuses to start (exit 2,
    one sentence) and the worker process started with the command is gone too."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "ground-truths").write_text("not a folder")
    proc, log = _serve(tmp_path, "--port", str(free_port()), "--data-dir", str(data))
    assert proc.wait(timeout=120) == 2, log.read_text()[-4000:]
    assert "ground-truths in the data folder cannot be written" in log.read_text()
    assert _children_of(proc.pid) == []
