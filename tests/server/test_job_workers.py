"""Workers and worker processes under faults: a job that fails again and again is failed with its reason after
its attempts; a draining worker lets its running job finish, or past its grace gives it back to the queue; a
worker process killed mid-batch loses nothing and stores nothing twice; SIGTERM drains ``kitti-eval worker``,
which exits 0 with nothing left running, and ends an idle one, warm or still warming its kernels, and an idle
``kitti-eval serve`` within seconds."""

from __future__ import annotations

import errno
import json
import logging
import os
import pickle
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from server_helpers import ROOT, app_client, register, upload

from kitti_eval.synth import generate
from kitti_eval_server.jobs.pool import WorkerPool
from kitti_eval_server.jobs.queue import JobQueue
from kitti_eval_server.jobs.workers import Workers
from kitti_eval_server.store import Store


def _queue(tmp_path: Path, **kwargs: Any) -> JobQueue:
    store = Store(f"sqlite:///{tmp_path / 'jobs.db'}")
    store.create_schema()
    return JobQueue.of(store, **kwargs)


def test_a_database_away_while_a_job_ends_neither_loses_the_job_nor_kills_the_worker(tmp_path) -> None:
    """Recording a job's end fails twice (the database is away); the worker tries again and the job is done,
    once; the same thread then runs the next job."""
    queue = _queue(tmp_path, lease_s=5)
    first, second = queue.enqueue("evaluation", {}, owner="me"), queue.enqueue("evaluation", {}, owner="me")
    finish, failures = queue.finish, [0]

    def flaky(*args: Any, **kwargs: Any) -> bool:
        if failures[0] < 2:
            failures[0] += 1
            raise ConnectionError("the database is away")
        return finish(*args, **kwargs)

    queue.finish = flaky  # type: ignore[method-assign]
    workers = Workers(queue, {"evaluation": lambda job: (job.id, lambda conn: None)}, threads=1, idle_s=0.02)
    workers.start()
    try:
        ended = [queue.wait(job.id, 30) for job in (first, second)]
    finally:
        workers.stop(5)
    assert [(e.state, e.attempts) for e in ended if e is not None] == [("done", 1), ("done", 1)]
    assert failures == [2]


def test_a_job_that_keeps_failing_is_failed_with_its_reason(tmp_path, caplog) -> None:
    """A fault of the machine is tried again, up to the job's attempts; then the job is failed with the error a
    client would have been answered. One log line a run: the job, its kind, the outcome, the seconds."""
    queue = _queue(tmp_path, lease_s=5, max_attempts=3)
    job = queue.enqueue("evaluation", {}, owner="me")

    def full_disk(job: Any) -> Any:
        raise OSError(errno.ENOSPC, "No space left on device")

    runs: list[tuple[str, str, int]] = []
    workers = Workers(queue, {"evaluation": full_disk}, threads=1, idle_s=0.02)
    workers.on_ended = lambda kind, outcome, seconds, attempt: runs.append((kind, outcome, attempt))
    with caplog.at_level(logging.INFO, logger="kitti_eval.server"):
        workers.start()
        try:
            ended = queue.wait(job.id, 30)
        finally:
            workers.stop(5)
    assert ended is not None and ended.state == "failed" and ended.attempts == 3
    error = json.loads(ended.error or "")
    assert error["status"] == 507 and error["code"] == "insufficient_storage", error
    assert runs == [("evaluation", "retried", 1), ("evaluation", "retried", 2), ("evaluation", "failed", 3)]
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith(f"job {job.id} evaluation ")]
    assert [re.sub(r"in [0-9.]+ s", "in S s", line.split(":")[0]) for line in lines] == [
        f"job {job.id} evaluation retried in S s (attempt 1 of 3)",
        f"job {job.id} evaluation retried in S s (attempt 2 of 3)",
        f"job {job.id} evaluation failed in S s (attempt 3 of 3)",
    ]
    assert all("insufficient_storage" in line for line in lines)


@pytest.mark.parametrize("grace_s", [10.0, 0.2], ids=["finishes", "released"])
def test_a_draining_worker_finishes_its_job_or_gives_it_back(tmp_path, grace_s: float) -> None:
    """Stopped while a 1 s job runs: within the grace the job finishes and is stored; past it the job goes back
    to the queue, its attempt not counted, and the late result is not stored."""
    queue = _queue(tmp_path, lease_s=5)
    job = queue.enqueue("evaluation", {}, owner="me")
    started, stored = threading.Event(), []

    def slow(job: Any) -> Any:
        started.set()
        time.sleep(1.0)
        return "result", lambda conn: stored.append(job.id)

    workers = Workers(queue, {"evaluation": slow}, threads=1, idle_s=0.02)
    outcomes: list[str] = []
    workers.on_ended = lambda kind, outcome, seconds, attempt: outcomes.append(outcome)
    workers.start()
    assert started.wait(10)
    released = workers.stop(grace_s)
    after = queue.get(job.id)
    assert after is not None
    if grace_s > 1:
        assert released == 0 and after.state == "done" and stored == [job.id] and outcomes == ["done"]
    else:
        assert released == 1 and after.state == "queued" and after.attempts == 0 and after.worker is None
        deadline = time.monotonic() + 10
        while not outcomes:  # the thread ends its job, and finds it no longer its own
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert outcomes == ["released"] and stored == []
        assert queue.get(job.id).state == "queued"  # type: ignore[union-attr]


# ------------------------------------------------------------------------------------------ worker processes


def _pickled(obj: Any) -> bytes:
    return pickle.dumps(obj, protocol=4)


#: an evaluation of a KITTI-val-sized set that takes a few seconds: every option that costs, 7 distance bins
SLOW_OPTIONS = {"errors": "true", "coco": "true", "curves": "true", "ranges": "0,10,20,30,40,50,60,inf"}


def _accept(
    data_dir: Path, n: int, *, fields: dict[str, str] | None = None, database_url: str | None = None
) -> list[str]:
    """``n`` evaluations of a KITTI-val-sized set accepted by a service without workers: their job ids."""
    infos, results = generate(3769, seed=5)
    with app_client(data_dir, ready=False, job_threads=0, warmup=False, database_url=database_url) as c:
        assert register(c, "val", _pickled(infos), "infos.pkl").status_code == 201
        pred = _pickled(results)
        ids = []
        for k in range(n):
            r = upload(c, pred, gt="val", params={"wait": "0"}, fields={"model": f"m{k}", **(fields or {})})
            assert r.status_code == 202, r.text
            ids.append(r.json()["id"])
    return ids


def _worker(
    data_dir: Path, *args: str, database_url: str | None = None, **env: str
) -> tuple[subprocess.Popen[bytes], Path]:
    """``kitti-eval worker --data-dir DATA_DIR ARGS`` (or ``--database-url``) in a process of its own, its log in
    a file."""
    log_path = data_dir.parent / f"worker-{time.monotonic_ns()}.log"
    environ = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    environ.update({"KITTI_EVAL_LOG_FORMAT": "text", **env})
    where = ["--database-url", database_url] if database_url else ["--data-dir", str(data_dir)]
    command = [sys.executable, "-m", "kitti_eval.cli", "worker", *where, *args]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(command, cwd=ROOT, env=environ, stdout=log, stderr=subprocess.STDOUT)
    return proc, log_path


def _until(condition: Any, timeout_s: float, what: str, log_path: Path) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        found = condition()
        if found:
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not within {timeout_s} s:\n{log_path.read_text()[-4000:]}")
        time.sleep(0.01)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path) -> Iterator[str | None]:
    """None (the data folder's SQLite), or the URL of a throwaway PostgreSQL."""
    if request.param == "sqlite":
        yield None
        return
    from server_postgres import PostgresCluster, why_no_postgres

    missing = why_no_postgres()
    if missing:
        pytest.skip(missing)
    with PostgresCluster() as cluster:
        yield cluster.url.replace("postgresql://", "postgresql+psycopg://", 1)


@pytest.mark.slow
def test_a_worker_process_killed_mid_batch_loses_nothing_and_stores_nothing_twice(tmp_path, database) -> None:
    """20 evaluations, 2 worker processes; one is killed with SIGKILL while it runs a job: its job is taken
    over once its lease has run out, the pool starts another process, and every job is done exactly once. On
    SQLite and on PostgreSQL (where the claims lock rows with SKIP LOCKED)."""
    data_dir = tmp_path / "data"
    ids = _accept(data_dir, 20, fields={"errors": "true"}, database_url=database)  # most of a second each
    store = Store(database or f"sqlite:///{data_dir / 'kitti-eval.db'}")
    queue = JobQueue.of(store)
    # a lease of 3 s: short, so the killed process's job is taken over soon, but longer than the moment a job's end
    # holds SQLite's lock while it stores the evaluation and its frames (a 1 s lease lapsed under a loaded machine's
    # heartbeats, and a live worker's job was taken over)
    proc, log_path = _worker(data_dir, "--processes", "2", database_url=database, KITTI_EVAL_JOB_LEASE_S="3")
    try:

        def running_after_some_done() -> Any:
            counts = queue.counts()
            running = queue.list(state="running")
            return running[0] if counts["done"] >= 3 and running else None

        seen = _until(running_after_some_done, 120, "a job running after 3 done", log_path)
        pid = int(seen.worker.split(":")[1])
        assert pid != proc.pid  # a process of the pool, not the command itself
        os.kill(pid, signal.SIGKILL)
        # the job the killed process held when it died (the one seen running, unless it had just ended it)
        held = [j for j in queue.list(state="running") if j.worker.split(":")[1] == str(pid)]
        assert len(held) == 1, (seen, held)
        victim = held[0]
        _until(lambda: queue.counts()["done"] == 20, 180, "all 20 done", log_path)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, log_path.read_text()[-4000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    jobs = {i: queue.get(i) for i in ids}
    assert {j.state for j in jobs.values()} == {"done"}  # type: ignore[union-attr]
    taken_over = jobs[victim.id]
    assert taken_over is not None and taken_over.attempts == 2 and taken_over.worker != victim.worker
    assert sorted(j.attempts for j in jobs.values()).count(1) == 19  # type: ignore[union-attr]
    stored = store.evaluation_store.list_evaluations(limit=1000)
    assert sorted(e.id for e in stored) == sorted(ids)  # each once: none lost, none twice
    text = log_path.read_text()
    assert f"worker process {pid} exited with -9" in text
    assert len(re.findall(r"job [0-9a-f]{32} evaluation done in", text)) == 20
    store.dispose()


@pytest.mark.slow
@pytest.mark.parametrize("grace", ["60", "0"], ids=["the job finishes", "past the grace the job goes back"])
def test_sigterm_drains_a_worker_and_it_exits_0(tmp_path, grace: str) -> None:
    """SIGTERM while a job runs: the worker takes no other, its running job finishes and is stored (or, past
    ``--grace``, goes back to the queue, its attempt not counted), every process exits, the command with 0."""
    data_dir = tmp_path / "data"
    first, second = _accept(data_dir, 2, fields=SLOW_OPTIONS)
    store = Store(f"sqlite:///{data_dir / 'kitti-eval.db'}")
    queue = JobQueue.of(store)
    proc, log_path = _worker(data_dir, "--processes", "1", "--grace", grace)
    try:
        running = _until(lambda: queue.list(state="running"), 120, "a running job", log_path)[0]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(90) == 0, log_path.read_text()[-4000:]
    finally:
        if proc.poll() is None:
            proc.kill()
    pid = int(running.worker.split(":")[1])
    assert not _alive(pid)  # nothing left running
    assert running.id == first
    ran, other = queue.get(first), queue.get(second)
    assert ran is not None and other is not None
    assert other.state == "queued" and other.attempts == 0  # never taken: the worker was draining
    assert queue.counts()["running"] == 0
    text = log_path.read_text()
    if grace == "60":
        assert ran.state == "done" and ran.attempts == 1
        assert [e.id for e in store.evaluation_store.list_evaluations(limit=10)] == [first]
        assert f"job {first} evaluation done in" in text
    else:
        assert ran.state == "queued" and ran.attempts == 0 and ran.worker is None
        assert store.evaluation_store.list_evaluations(limit=10) == []
        assert f"job {first} evaluation released" in text
    assert "kitti-eval worker: stopped" in text and f"worker process {pid}: stopped" in text
    store.dispose()


def _catches_sigterm(pid: int) -> bool:
    """The process has a handler of its own for SIGTERM (its SigCgt mask in /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = next(int(line.split()[1], 16) for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def _stopped_within(proc: subprocess.Popen[bytes], log_path: Path, limit_s: float) -> float:
    """SIGTERM to ``proc``: the seconds until it exited 0, at most ``limit_s`` (``docker stop`` and compose's
    ``down`` wait for this, then kill)."""
    sent = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        code = proc.wait(limit_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"still running {limit_s} s after SIGTERM:\n{log_path.read_text()[-3000:]}") from None
    assert code == 0, log_path.read_text()[-3000:]
    return time.monotonic() - sent


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads a process's signal handlers in /proc")
def test_an_idle_worker_or_one_still_warming_its_kernels_ends_within_seconds_of_sigterm(tmp_path) -> None:
    """``docker stop`` of a worker container, and compose's ``down``, send SIGTERM and wait: with no job running
    the worker must end within seconds, polling or still warming its kernels (a worker process compiling them,
    where no cache fits, went on for the whole warm-up, a minute where every core compiles, before it drained)."""
    data_dir = tmp_path / "data"
    with app_client(data_dir, ready=False, job_threads=0, warmup=False):
        pass  # the service's database, with its tables
    store = Store(f"sqlite:///{data_dir / 'kitti-eval.db'}")
    queue = JobQueue.of(store)
    try:
        # polling for jobs: recorded on the database, then SIGTERM
        proc, log_path = _worker(data_dir, "--processes", "1")
        _until(lambda: queue.workers_seen(60), 120, "a worker process on the database", log_path)
        assert _stopped_within(proc, log_path, 5.0) < 5.0
        # still warming: an empty kernel cache, SIGTERM once the worker process catches it (it is starting)
        cold = tmp_path / "empty-numba-cache"
        cold.mkdir()
        proc, log_path = _worker(data_dir, "--processes", "1", NUMBA_CACHE_DIR=str(cold))
        started = _until(
            lambda: re.search(r"worker processes of 1 thread\(s\): \[(\d+)\]", log_path.read_text()),
            120,
            "the worker process",
            log_path,
        )
        pid = int(started.group(1))
        _until(lambda: _catches_sigterm(pid), 120, "the worker process's SIGTERM handler", log_path)
        assert not queue.workers_seen(60), "warm already: the test needs a worker process still starting"
        assert _stopped_within(proc, log_path, 5.0) < 5.0
        assert not _alive(pid)
        assert f"worker process {pid}: stopped while starting" in log_path.read_text()
    finally:
        store.dispose()


def test_a_worker_stopped_as_its_processes_start_exits_0_at_once(tmp_path) -> None:
    """SIGTERM as soon as ``kitti-eval worker`` has started its process, still importing (no handler of its own
    yet): the process ends by that signal, holding no job, and the command exits 0 within seconds, not 1 for
    a process that "did not stop cleanly"."""
    data_dir = tmp_path / "data"
    with app_client(data_dir, ready=False, job_threads=0, warmup=False):
        pass  # the service's database, with its tables
    proc, log_path = _worker(data_dir, "--processes", "1")
    _until(lambda: "worker processes of 1 thread(s)" in log_path.read_text(), 120, "the worker process", log_path)
    assert _stopped_within(proc, log_path, 5.0) < 5.0
    assert "kitti-eval worker: stopped" in log_path.read_text()
    assert "did not exit cleanly" not in log_path.read_text()


def test_an_idle_serve_ends_within_seconds_of_sigterm(tmp_path) -> None:
    """``kitti-eval serve`` (the image's command) with a worker process of its own, nothing running: SIGTERM
    ends it, its drain and its worker process's, within seconds (``docker stop`` waits for it)."""
    from server_helpers import LiveServer

    server = LiveServer(tmp_path / "data", via_serve=True, job_threads=0, worker_processes=1).start()
    try:
        assert server.proc is not None
        sent = time.monotonic()
        server.proc.send_signal(signal.SIGTERM)
        code = server.proc.wait(60)
        took = time.monotonic() - sent
    finally:
        server.stop()
    assert code in (0, -signal.SIGTERM), server.log()  # uvicorn raises the signal again once it has stopped
    assert took < 5.0, f"{took:.1f} s after SIGTERM:\n{server.log()[-3000:]}"
    assert "worker process" in server.log() and "stopped (0 running job(s) released)" in server.log()


@pytest.mark.slow
def test_serve_starts_its_own_worker_processes_and_drains_them(tmp_path) -> None:
    """``KITTI_EVAL_WORKER_PROCESSES=2`` with no worker thread: the evaluations run in the 2 processes the server
    started, which the metrics count; SIGTERM stops the server and its processes with it."""
    from server_helpers import LiveServer, golden_bytes
    from test_server_operations import scrape, value

    data_dir = tmp_path / "data"
    server = LiveServer(data_dir, via_serve=True, job_threads=0, worker_processes=2).start()
    try:
        with server.client() as c:
            answers = [upload(c, golden_bytes("result.pkl")) for _ in range(4)]
            assert [r.status_code for r in answers] == [201] * 4, answers[0].text
            samples = scrape(c)
        assert value(samples, "kitti_eval_job_worker_processes_alive") == 2
        assert value(samples, "kitti_eval_job_workers_alive") == 0
        assert value(samples, "kitti_eval_job_workers_seen") == 2
        store = Store(f"sqlite:///{data_dir / 'kitti-eval.db'}")
        jobs = [JobQueue.of(store).get(r.json()["id"]) for r in answers]
        pids = {int(j.worker.split(":")[1]) for j in jobs if j is not None and j.worker}
        assert pids and server.proc is not None and server.proc.pid not in pids  # run by the worker processes
        server.proc.send_signal(signal.SIGTERM)
        assert server.proc.wait(60) in (0, -15), server.log()
    finally:
        server.stop()
    assert not any(_alive(pid) for pid in pids)
    assert JobQueue.of(store).workers_seen(3600) == []  # each process removed its row as it stopped
    store.dispose()


def test_a_worker_process_runs_the_installed_service_whatever_folder_it_starts_in(tmp_path: Path) -> None:
    """``python -m`` puts the working folder first on the import path: started inside another checkout, a worker
    would run that checkout's service, not the one the web process runs. The pool's command does not."""
    other = tmp_path / "kitti_eval_server"
    (other / "commands").mkdir(parents=True)
    marker = tmp_path / "the-other-checkout-ran"
    for name in ("__init__.py", "commands/__init__.py", "commands/process.py"):
        (other / name).write_text(f"open({str(marker)!r}, 'w').close()\n")
    pool = WorkerPool(1, threads=1, grace_s=1.0, work_dir=tmp_path / "work", database_url="sqlite://")
    command = [*pool._command()[:3], "--help"]  # the interpreter and how it starts the module, then --help
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "One worker process of kitti-eval." in run.stdout
    assert not marker.exists()


def test_a_job_past_its_time_limit_is_failed_once_with_its_reason_and_its_worker_is_free_again(tmp_path) -> None:
    """A job that runs on and on is failed at its time limit, not tried again (whatever attempts are left), with
    the reason a client is answered; the next job runs at once, on a new thread in the worker's place, while the
    late one ends on its own and stores nothing."""
    queue = _queue(tmp_path, lease_s=5, max_attempts=3)
    stuck, after = queue.enqueue("evaluation", {"n": 1}, owner="me"), queue.enqueue("evaluation", {"n": 2}, owner="me")
    release, stored, runs = threading.Event(), [], []

    def handler(job: Any) -> Any:
        if job.payload["n"] == 1:
            release.wait(30)  # the evaluation that would not end
        return job.id, lambda conn: stored.append(job.id)

    workers = Workers(queue, {"evaluation": handler}, threads=1, idle_s=0.02, timeout_s=0.5)
    workers.on_ended = lambda kind, outcome, seconds, attempt: runs.append((outcome, attempt))
    workers.start()
    try:
        failed, done = queue.wait(stuck.id, 20), queue.wait(after.id, 20)
        assert failed is not None and failed.state == "failed" and failed.attempts == 1
        error = json.loads(failed.error or "")
        assert error["code"] == "job_timeout" and error["status"] == 422
        assert "ran past the time limit of 0.5 s (KITTI_EVAL_JOB_TIMEOUT_S)" in error["message"]
        assert done is not None and done.state == "done" and stored == [after.id]  # while the stuck one still runs
        assert not release.is_set() and workers.busy == 1
        release.set()
        deadline = time.monotonic() + 10
        while len(runs) < 2 or workers.alive != 1:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    finally:
        release.set()
        workers.stop(5)
    assert sorted(runs) == [("done", 1), ("timed_out", 1)]
    assert stored == [after.id]  # the late result is not stored
    assert queue.get(stuck.id).state == "failed"  # type: ignore[union-attr]
