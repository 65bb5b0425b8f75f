"""The job queue (kitti_eval_server.jobs.queue) on SQLite and, when PostgreSQL's binaries are installed, on a throwaway
PostgreSQL cluster: each test runs on both (the PostgreSQL one skipped, with the reason, otherwise).

Times come from a clock the tests move by hand, so leases run out exactly when a test says; only the waits and
the processes racing for jobs use the real one.
"""

from __future__ import annotations

import importlib
import json
import multiprocessing
import queue as queue_module
import threading
import time
import uuid
from collections import Counter
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import psycopg
import pytest
from server_postgres import PostgresCluster, why_no_postgres
from sqlalchemy import Column, MetaData, String, Table, create_engine, func, insert, inspect, select
from sqlalchemy.engine import Connection

from kitti_eval_server.jobs.queue import JobQueue
from kitti_eval_server.store import Store, jobs, metadata

#: what a job's `within` writes (its evaluation record, in the service): one row per job that finished
outputs_metadata = MetaData()
outputs = Table(
    "job_outputs",
    outputs_metadata,
    Column("job_id", String(32), nullable=False),
    Column("worker", String(128), nullable=False),
)

START = datetime(2026, 3, 1, 12, 0, 0, tzinfo=timezone.utc)


class Clock:
    """A clock the test moves: ``advance(seconds)``."""

    def __init__(self) -> None:
        self.now = START

    def __call__(self) -> datetime:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += timedelta(seconds=seconds)


@pytest.fixture(scope="module")
def postgres() -> Iterator[PostgresCluster]:
    reason = why_no_postgres()
    if reason is not None:
        pytest.skip(reason)
    with PostgresCluster() as cluster:
        yield cluster


def fresh_postgres_database(cluster: PostgresCluster) -> str:
    name = f"jobs_{uuid.uuid4().hex}"
    with psycopg.connect(
        host="127.0.0.1", port=cluster.port, user="postgres", dbname="postgres", autocommit=True
    ) as conn:
        conn.execute(f"CREATE DATABASE {name}")
    return f"postgresql+psycopg://postgres@127.0.0.1:{cluster.port}/{name}"


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A new database with the service's schema and the outputs table."""
    if request.param == "sqlite":
        address = f"sqlite:///{tmp_path / 'jobs.db'}"
    else:
        address = fresh_postgres_database(request.getfixturevalue("postgres"))
    store = Store(address)
    store.create_schema()
    outputs_metadata.create_all(store.engine)
    store.dispose()
    return address


@pytest.fixture
def store(url: str) -> Iterator[Store]:
    s = Store(url)
    yield s
    s.dispose()


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def queue(store: Store, clock: Clock) -> JobQueue:
    return JobQueue.of(store, lease_s=30.0, max_attempts=3, clock=clock)


def writes_output(job_id: str, worker: str):
    def within(conn: Connection) -> None:
        conn.execute(insert(outputs).values(job_id=job_id, worker=worker))

    return within


def written(store: Store) -> list[tuple[str, str]]:
    with store.engine.connect() as conn:
        return sorted((r.job_id, r.worker) for r in conn.execute(select(outputs)))


# ------------------------------------------------------------------------------------------------ the life


def test_a_job_is_enqueued_claimed_and_finished(queue: JobQueue, store: Store, clock: Clock) -> None:
    job = queue.enqueue("evaluation", {"gt": "demo", "pred": "abc"}, owner="alice", group="g1")
    assert job.state == "queued" and job.kind == "evaluation" and job.owner == "alice" and job.group == "g1"
    assert (job.attempts, job.max_attempts, job.worker, job.lease_until) == (0, 3, None, None)
    assert (job.accepted_at, job.started_at, job.finished_at) == (START, None, None)
    assert (job.result_id, job.error, job.payload) == (None, None, {"gt": "demo", "pred": "abc"})
    assert queue.get(job.id) == job  # committed as returned (times in UTC, the payload as given)

    clock.advance(2)
    claimed = queue.claim("w1")
    assert claimed is not None and claimed.id == job.id
    assert (claimed.state, claimed.worker, claimed.attempts) == ("running", "w1", 1)
    assert claimed.started_at == START + timedelta(seconds=2)
    assert claimed.lease_until == START + timedelta(seconds=32)
    assert queue.get(job.id) == claimed
    assert queue.claim("w2") is None  # nothing else to take

    clock.advance(3)
    assert queue.finish(job.id, "w1", "result-1", within=writes_output(job.id, "w1")) is True
    done = queue.get(job.id)
    assert done is not None
    assert (done.state, done.result_id, done.worker, done.lease_until) == ("done", "result-1", "w1", None)
    assert done.finished_at == START + timedelta(seconds=5) and done.started_at == claimed.started_at
    assert written(store) == [(job.id, "w1")]
    assert queue.finish(job.id, "w1", "result-2", within=writes_output(job.id, "w1")) is False  # once
    assert written(store) == [(job.id, "w1")] and queue.get(job.id) == done
    assert queue.get("no-such-job") is None


def test_enqueueing_an_id_again_returns_the_job_recorded(queue: JobQueue) -> None:
    first = queue.enqueue("submission", {"n": 1}, owner="alice", job_id="sub-1")
    again = queue.enqueue("submission", {"n": 2}, owner="bob", job_id="sub-1")
    assert again == first and again.payload == {"n": 1}
    assert queue.counts()["queued"] == 1
    with pytest.raises(ValueError, match="unknown kind"):
        queue.enqueue("mining", {}, owner="alice")


def test_jobs_are_claimed_first_in_first_out(queue: JobQueue, clock: Clock) -> None:
    singles = []
    for i in range(3):
        singles.append(queue.enqueue("evaluation", {"i": i}, owner="alice"))
        clock.advance(1)
    batch = queue.enqueue_many("rescore", [{"i": i} for i in range(3, 8)], owner="root", group="bench")
    assert [j.accepted_at for j in batch] == [START + timedelta(seconds=3, microseconds=i) for i in range(5)]
    clock.advance(1)
    last = queue.enqueue("submission", {"i": 8}, owner="bob")
    # the kinds asked for: the oldest of them, whatever is older of another kind
    only = queue.claim("w", kinds=["submission", "rescore"])
    assert only is not None and only.id == batch[0].id
    order = [only.id]
    while (job := queue.claim("w")) is not None:
        order.append(job.id)
    assert order == [batch[0].id, *(j.id for j in singles), *(j.id for j in batch[1:]), last.id]
    assert queue.enqueue_many("rescore", [], owner="root") == []


# ------------------------------------------------------------------------------------------------ leases


def test_a_lapsed_lease_is_taken_over_and_the_first_worker_writes_nothing(
    queue: JobQueue, store: Store, clock: Clock
) -> None:
    job = queue.enqueue("evaluation", {}, owner="alice")
    assert queue.claim("w1") is not None
    clock.advance(29.9)
    assert queue.claim("w2") is None  # the lease holds
    clock.advance(0.2)
    taken = queue.claim("w2")
    assert taken is not None and taken.id == job.id
    assert (taken.worker, taken.attempts, taken.started_at) == ("w2", 2, START)  # started at its first claim
    assert taken.lease_until == START + timedelta(seconds=60.1)
    # the lost worker comes back: it no longer holds the job, and its result is not written
    assert queue.heartbeat(job.id, "w1") is False
    assert queue.finish(job.id, "w1", "r-w1", within=writes_output(job.id, "w1")) is False
    assert written(store) == []
    assert queue.fail(job.id, "w1", "boom", retry=True) is False and queue.release(job.id, "w1") is False
    assert queue.get(job.id) == taken
    assert queue.finish(job.id, "w2", "r-w2", within=writes_output(job.id, "w2")) is True
    assert written(store) == [(job.id, "w2")]
    done = queue.get(job.id)
    assert done is not None and (done.state, done.result_id, done.attempts) == ("done", "r-w2", 2)


def test_a_lapsed_job_is_taken_before_the_queued_ones_of_its_kinds(queue: JobQueue, clock: Clock) -> None:
    """A lapsed job was at the head of the queue when first claimed: it goes first, even before an older job
    given back since; a claim for other kinds leaves it."""
    given_back = queue.enqueue("evaluation", {}, owner="alice")
    clock.advance(1)
    lapsing = queue.enqueue("rescore", {}, owner="root")
    queue.claim("w0")
    queue.claim("w1")
    assert queue.release(given_back.id, "w0") is True
    clock.advance(31)
    other = queue.claim("w2", kinds=["evaluation"])
    assert other is not None and other.id == given_back.id
    assert queue.release(given_back.id, "w2") is True
    taken = queue.claim("w3")
    assert taken is not None and (taken.id, taken.worker, taken.attempts) == (lapsing.id, "w3", 2)
    following = queue.claim("w4")
    assert following is not None and following.id == given_back.id


def test_a_failing_within_rolls_back_and_the_job_stays_its_workers(queue: JobQueue, store: Store) -> None:
    job = queue.enqueue("evaluation", {}, owner="alice")
    claimed = queue.claim("w1")

    def within(conn: Connection) -> None:
        writes_output(job.id, "w1")(conn)
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        queue.finish(job.id, "w1", "r1", within=within)
    assert written(store) == [] and queue.get(job.id) == claimed
    assert queue.finish(job.id, "w1", "r1", within=writes_output(job.id, "w1")) is True
    assert written(store) == [(job.id, "w1")]


def test_a_heartbeat_keeps_the_job(queue: JobQueue, clock: Clock) -> None:
    job = queue.enqueue("evaluation", {}, owner="alice")
    queue.claim("w1")
    clock.advance(20)
    assert queue.heartbeat(job.id, "w1") is True
    beaten = queue.get(job.id)
    assert beaten is not None and beaten.lease_until == START + timedelta(seconds=50)
    clock.advance(20)  # 40 s after the claim: past the first lease, within the second
    assert queue.claim("w2") is None
    clock.advance(10.5)
    taken = queue.claim("w2")
    assert taken is not None and taken.worker == "w2"
    assert queue.heartbeat(job.id, "w2") is True and queue.heartbeat("no-such-job", "w2") is False


def test_a_job_whose_worker_is_lost_max_attempts_times_fails(store: Store, clock: Clock) -> None:
    queue = JobQueue.of(store, lease_s=10, max_attempts=2, clock=clock)
    lost = queue.enqueue("evaluation", {}, owner="alice")
    clock.advance(1)
    later = queue.enqueue("evaluation", {}, owner="alice")
    first = queue.claim("w1")
    assert first is not None and first.id == lost.id
    clock.advance(11)
    second = queue.claim("w2")
    assert second is not None and (second.id, second.attempts) == (lost.id, 2)
    clock.advance(11)
    # the lapsed job used its attempts: it fails, and the claim takes the next job
    third = queue.claim("w3")
    assert third is not None and third.id == later.id and third.attempts == 1
    failed = queue.get(lost.id)
    assert failed is not None
    assert (failed.state, failed.attempts, failed.worker) == ("failed", 2, "w2")
    error = json.loads(failed.error or "")
    assert (error["status"], error["code"]) == (500, "worker_lost")
    assert error["message"].startswith("the worker was lost 2 times; a job is taken over once")
    assert failed.finished_at == START + timedelta(seconds=23) and failed.lease_until is None
    assert queue.heartbeat(lost.id, "w2") is False
    assert queue.counts() == {"queued": 0, "running": 1, "done": 0, "failed": 1, "cancelled": 0}
    # with nothing else to take, the claim still fails the lost one and answers None
    one = JobQueue.of(store, lease_s=10, max_attempts=1, clock=clock)
    alone = one.enqueue("rescore", {}, owner="root")
    taken = queue.claim("w4", kinds=["rescore"])
    assert taken is not None and taken.id == alone.id
    clock.advance(11)
    assert one.claim("w5", kinds=["rescore"]) is None
    ended = one.get(alone.id)
    assert ended is not None and ended.state == "failed"
    assert json.loads(ended.error or "")["message"].startswith("the worker was lost 1 time;")


def test_a_job_whose_worker_is_lost_is_taken_over_once_whatever_attempts_are_left(store: Store, clock: Clock) -> None:
    """A lost worker may have been killed by its job (out of memory): the job is taken over once, and failed
    (``worker_lost``) when the worker that took it over is lost too, though attempts are left."""
    queue = JobQueue.of(store, lease_s=10, max_attempts=5, clock=clock)
    job = queue.enqueue("evaluation", {}, owner="alice")
    assert queue.claim("w1") is not None
    clock.advance(11)
    again = queue.claim("w2")
    assert again is not None and (again.id, again.attempts) == (job.id, 2)
    last = json.loads(again.error or "")  # shown to admins as the job's last error while it runs
    assert (last["code"], last["lost"], last["message"]) == ("worker_lost", 1, "the worker was lost 1 time")
    clock.advance(11)
    assert queue.claim("w3") is None
    failed = queue.get(job.id)
    assert failed is not None and (failed.state, failed.attempts) == ("failed", 2)
    error = json.loads(failed.error or "")
    assert (error["status"], error["code"], error["lost"]) == (500, "worker_lost", 2)
    assert "the worker was lost 2 times; a job is taken over once when its worker is lost" in error["message"]
    # a job taken over that ends well ends without the note
    other = queue.enqueue("evaluation", {}, owner="alice")
    assert queue.claim("w4") is not None
    clock.advance(11)
    assert queue.claim("w5") is not None
    assert queue.finish(other.id, "w5", other.id) is True
    done = queue.get(other.id)
    assert done is not None and (done.state, done.error) == ("done", None)


def test_a_lost_job_past_its_time_limit_is_failed_not_taken_over(store: Store, clock: Clock) -> None:
    queue = JobQueue.of(store, lease_s=10, max_attempts=3, clock=clock, time_limit_s=60)
    job = queue.enqueue("evaluation", {}, owner="alice")
    assert queue.claim("w1") is not None
    for _ in range(7):  # its worker beats its lease for 63 s, past the limit, then is lost
        clock.advance(9)
        assert queue.heartbeat(job.id, "w1") is True
    clock.advance(11)
    assert queue.claim("w2") is None
    failed = queue.get(job.id)
    assert failed is not None and (failed.state, failed.attempts) == ("failed", 1)
    error = json.loads(failed.error or "")
    assert (error["status"], error["code"]) == (422, "job_timeout")
    assert "ran past the time limit of 60 s (KITTI_EVAL_JOB_TIMEOUT_S)" in error["message"]


# ------------------------------------------------------------------------------------------------ endings


def test_a_failure_with_retry_queues_the_job_again_until_its_attempts_are_used(store: Store, clock: Clock) -> None:
    queue = JobQueue.of(store, max_attempts=2, clock=clock)
    job = queue.enqueue("submission", {}, owner="alice")
    queue.claim("w1")
    clock.advance(1)
    assert queue.fail(job.id, "w1", "database gone", retry=True) is True
    again = queue.get(job.id)
    assert again is not None
    assert (again.state, again.attempts, again.worker, again.lease_until) == ("queued", 1, None, None)
    assert (again.error, again.finished_at, again.started_at) == ("database gone", None, START)
    assert queue.position(job.id) == 1
    retaken = queue.claim("w2")
    assert retaken is not None and (retaken.id, retaken.attempts) == (job.id, 2)
    clock.advance(1)
    assert queue.fail(job.id, "w2", "database gone again", retry=True) is True  # no attempt left
    failed = queue.get(job.id)
    assert failed is not None
    assert (failed.state, failed.error, failed.worker, failed.attempts) == ("failed", "database gone again", "w2", 2)
    assert failed.finished_at == START + timedelta(seconds=2)
    assert queue.claim("w3") is None
    # no retry: failed at once
    other = queue.enqueue("submission", {}, owner="alice")
    queue.claim("w3")
    assert queue.fail(other.id, "w4", "not mine", retry=False) is False
    assert queue.fail(other.id, "w3", "bad predictions", retry=False) is True
    ended = queue.get(other.id)
    assert ended is not None and (ended.state, ended.error, ended.attempts) == ("failed", "bad predictions", 1)


def test_a_released_job_is_queued_again_without_counting_the_attempt(queue: JobQueue, clock: Clock) -> None:
    job = queue.enqueue("evaluation", {}, owner="alice")
    queue.claim("w1")
    clock.advance(5)
    assert queue.release(job.id, "w2") is False
    assert queue.release(job.id, "w1") is True
    back = queue.get(job.id)
    assert back is not None
    assert (back.state, back.attempts, back.worker, back.lease_until) == ("queued", 0, None, None)
    assert back.accepted_at == START and queue.position(job.id) == 1  # keeps its place
    assert queue.release(job.id, "w1") is False
    again = queue.claim("w2")
    assert again is not None and (again.attempts, again.started_at) == (1, START)


def test_cancelling_a_queued_or_running_job(queue: JobQueue, store: Store, clock: Clock) -> None:
    waiting = queue.enqueue("evaluation", {}, owner="alice")
    clock.advance(1)
    running = queue.enqueue("evaluation", {}, owner="alice")
    clock.advance(1)
    cancelled = queue.cancel(waiting.id)
    assert cancelled is not None and cancelled.state == "cancelled"
    assert cancelled.finished_at == START + timedelta(seconds=2)
    assert queue.get(waiting.id) == cancelled
    assert queue.cancel(waiting.id) == cancelled  # already ended: left as it is
    taken = queue.claim("w1")
    assert taken is not None and taken.id == running.id  # the cancelled job is not taken
    stopped = queue.cancel(running.id)
    assert stopped is not None and (stopped.state, stopped.worker, stopped.lease_until) == ("cancelled", "w1", None)
    # its worker learns it at its next heartbeat, and its result is not written
    assert queue.heartbeat(running.id, "w1") is False
    assert queue.finish(running.id, "w1", "r", within=writes_output(running.id, "w1")) is False
    assert queue.fail(running.id, "w1", "stopped", retry=True) is False
    assert written(store) == [] and queue.get(running.id) == stopped
    clock.advance(60)
    assert queue.claim("w2") is None  # a cancelled job's lease is not taken over
    assert queue.cancel("no-such-job") is None
    done = queue.enqueue("evaluation", {}, owner="alice")
    queue.claim("w3")
    queue.finish(done.id, "w3", "r3")
    after = queue.cancel(done.id)
    assert after is not None and after.state == "done" and after.result_id == "r3"


def test_rerunning_an_ended_job_queues_it_as_new(store: Store, clock: Clock) -> None:
    queue = JobQueue.of(store, max_attempts=1, clock=clock)
    failed = queue.enqueue("rescore", {"s": 1}, owner="root", group="bench")
    clock.advance(1)
    done = queue.enqueue("rescore", {"s": 2}, owner="root", group="bench")
    queue.claim("w1")
    queue.fail(failed.id, "w1", "boom", retry=True)  # no attempt left: failed
    queue.claim("w1")
    queue.finish(done.id, "w1", "r2")
    clock.advance(10)
    waiting = queue.enqueue("rescore", {"s": 3}, owner="root", group="bench")
    clock.advance(1)
    again = queue.rerun(failed.id)
    assert again is not None
    assert (again.state, again.attempts, again.error, again.result_id, again.worker) == ("queued", 0, None, None, None)
    assert (again.started_at, again.finished_at, again.lease_until) == (None, None, None)
    assert again.accepted_at == START + timedelta(seconds=12) and again.payload == {"s": 1}
    assert queue.get(failed.id) == again
    assert queue.position(waiting.id) == 1 and queue.position(failed.id) == 2  # at the end of the queue
    redone = queue.rerun(done.id)
    assert redone is not None and (redone.state, redone.result_id) == ("queued", None)
    assert queue.rerun(waiting.id) == queue.get(waiting.id)  # queued: left as it is
    taken = queue.claim("w2")
    assert taken is not None and taken.id == waiting.id
    assert queue.rerun(waiting.id) == taken  # running: left as it is
    assert queue.rerun("no-such-job") is None
    cancelled = queue.cancel(queue.enqueue("rescore", {}, owner="root").id)
    assert cancelled is not None and cancelled.state == "cancelled"
    rerun = queue.rerun(cancelled.id)
    assert rerun is not None and rerun.state == "queued"


# ------------------------------------------------------------------------------------------------ views


def test_positions_counts_and_the_oldest_queued_age(queue: JobQueue, clock: Clock) -> None:
    assert queue.oldest_queued_age_s() is None
    assert queue.counts() == {"queued": 0, "running": 0, "done": 0, "failed": 0, "cancelled": 0}
    a = queue.enqueue("evaluation", {}, owner="alice")
    clock.advance(1.5)
    b, c = queue.enqueue_many("rescore", [{}, {}], owner="root", group="bench")
    clock.advance(1)
    d = queue.enqueue("submission", {}, owner="alice", group="bench")
    assert [queue.position(j.id) for j in (a, b, c, d)] == [1, 2, 3, 4]
    assert queue.oldest_queued_age_s() == pytest.approx(2.5)
    queue.claim("w1")
    assert [queue.position(j.id) for j in (a, b, c, d)] == [None, 1, 2, 3]
    assert queue.oldest_queued_age_s() == pytest.approx(1.0)
    queue.finish(a.id, "w1", "r")
    queue.cancel(c.id)
    assert queue.position(c.id) is None and queue.position(d.id) == 2 and queue.position("nope") is None
    assert queue.counts() == {"queued": 2, "running": 0, "done": 1, "failed": 0, "cancelled": 1}
    assert queue.counts(owner="alice") == {"queued": 1, "running": 0, "done": 1, "failed": 0, "cancelled": 0}
    assert queue.counts(group="bench") == {"queued": 2, "running": 0, "done": 0, "failed": 0, "cancelled": 1}
    assert queue.counts(owner="root", group="bench") == {
        "queued": 1,
        "running": 0,
        "done": 0,
        "failed": 0,
        "cancelled": 1,
    }
    clock.advance(7)
    assert queue.oldest_queued_age_s() == pytest.approx(8.0)


def test_jobs_are_listed_newest_first(queue: JobQueue, clock: Clock) -> None:
    made = []
    for i, (kind, owner, group) in enumerate(
        [
            ("evaluation", "alice", None),
            ("submission", "alice", "bench"),
            ("rescore", "root", "bench"),
            ("rescore", "root", "other"),
            ("evaluation", "bob", None),
        ]
    ):
        made.append(queue.enqueue(kind, {"i": i}, owner=owner, group=group))
        clock.advance(1)
    queue.claim("w1")

    def ids(**filters: object) -> list[int]:
        return [j.payload["i"] for j in queue.list(**filters)]

    assert ids() == [4, 3, 2, 1, 0]
    assert ids(state="queued") == [4, 3, 2, 1] and ids(state="running") == [0]
    assert ids(kind="rescore") == [3, 2] and ids(owner="alice") == [1, 0] and ids(group="bench") == [2, 1]
    assert ids(kind="rescore", group="bench") == [2] and ids(owner="carol") == []
    assert ids(limit=2) == [4, 3] and ids(limit=2, offset=2) == [2, 1] and ids(offset=4) == [0]
    assert queue.list(state="running")[0] == queue.get(made[0].id)


# ------------------------------------------------------------------------------------------------ waiting


def test_wait_wakes_at_once_for_a_job_finished_in_this_process(store: Store) -> None:
    queue = JobQueue.of(store)
    job = queue.enqueue("evaluation", {}, owner="alice")
    other = JobQueue.of(store)  # another queue of the process (the executor's, say)
    other.claim("w1")

    def finish_soon() -> None:
        time.sleep(0.3)
        other.finish(job.id, "w1", "r1")

    threading.Thread(target=finish_soon).start()
    started = time.monotonic()
    done = queue.wait(job.id, 30, poll_s=20)  # the database is not read again for 20 s: only the wake-up helps
    elapsed = time.monotonic() - started
    assert done is not None and (done.state, done.result_id) == ("done", "r1")
    assert 0.25 < elapsed < 3, elapsed
    # a cancellation wakes it too, and an ended job is answered at once
    second = queue.enqueue("evaluation", {}, owner="alice")
    threading.Timer(0.3, queue.cancel, args=(second.id,)).start()
    cancelled = queue.wait(second.id, 30, poll_s=20)
    assert cancelled is not None and cancelled.state == "cancelled"
    started = time.monotonic()
    assert queue.wait(job.id, 30, poll_s=20) == done and time.monotonic() - started < 1


def test_wait_reads_the_database_for_a_job_ended_elsewhere(store: Store) -> None:
    queue = JobQueue.of(store)
    job = queue.enqueue("evaluation", {}, owner="alice")
    queue.claim("w1")

    def finish_elsewhere() -> None:  # as another process would: through the store, with no wake-up here
        time.sleep(0.3)
        store.job_store.complete_job(job.id, "w1", "r1", datetime.now(timezone.utc))

    threading.Thread(target=finish_elsewhere).start()
    started = time.monotonic()
    done = queue.wait(job.id, 30, poll_s=0.05)
    elapsed = time.monotonic() - started
    assert done is not None and done.state == "done" and 0.25 < elapsed < 3, elapsed


def test_wait_times_out_with_the_job_as_it_is(queue: JobQueue) -> None:
    job = queue.enqueue("evaluation", {}, owner="alice")
    started = time.monotonic()
    assert queue.wait(job.id, 0.3) == job
    assert 0.3 <= time.monotonic() - started < 2
    assert queue.wait("no-such-job", 5) is None


# ------------------------------------------------------------------------------------------------ the schema


def test_an_existing_database_gets_the_jobs_table(tmp_path: Path) -> None:
    """A database made before the queue existed: create_schema adds the table and its indexes."""
    address = f"sqlite:///{tmp_path / 'old.db'}"
    engine = create_engine(address)
    base = importlib.import_module("kitti_eval_server.store.migrations.versions.0001_base").metadata.tables
    # the tables of that release: the base revision's, never those of a later revision
    metadata.create_all(engine, tables=[t for t in metadata.sorted_tables if t.name != "jobs" and t.name in base])
    assert "jobs" not in inspect(engine).get_table_names()
    engine.dispose()
    store = Store(address)
    store.create_schema()
    found = inspect(store.engine)
    assert {c["name"] for c in found.get_columns("jobs")} == {c.name for c in jobs.columns}
    assert {i["name"] for i in found.get_indexes("jobs")} == {"ix_jobs_claim", "ix_jobs_owner", "ix_jobs_group"}
    queue = JobQueue.of(store)
    job = queue.enqueue("evaluation", {}, owner="alice")
    claimed = queue.claim("w1")
    assert claimed is not None and claimed.id == job.id and queue.get(job.id) == claimed
    store.dispose()


# ------------------------------------------------------------------------------------------------ racing


def claim_until_empty(url: str, worker: str, start: Any, results: Any) -> None:
    """A worker process: claim and finish (writing its output in the same transaction) until nothing is left;
    puts (worker, the ids claimed, the answers of finish, seconds from the start to the end) on ``results``."""
    store = Store(url)
    queue = JobQueue.of(store)
    claimed, finished = [], []
    start.wait()
    began = time.monotonic()
    while (job := queue.claim(worker)) is not None:
        claimed.append(job.id)
        finished.append(queue.finish(job.id, worker, job.id[::-1], within=writes_output(job.id, worker)))
    results.put((worker, claimed, finished, time.monotonic() - began))
    store.dispose()


def race(url: str, store: Store, processes: int, count: int) -> dict[str, list[str]]:
    """``count`` jobs, ``processes`` workers: every job claimed once and finished once, by whoever claimed it."""
    queue = JobQueue.of(store)
    ids = [j.id for j in queue.enqueue_many("evaluation", [{"n": n} for n in range(count)], owner="alice")]
    spawn = multiprocessing.get_context("spawn")
    start, results = spawn.Barrier(processes), spawn.Queue()
    workers = [
        spawn.Process(target=claim_until_empty, args=(url, f"worker-{i}", start, results)) for i in range(processes)
    ]
    for w in workers:
        w.start()
    reports = []
    deadline = time.monotonic() + 180
    try:
        while len(reports) < processes:
            try:
                reports.append(results.get(timeout=0.5))
            except queue_module.Empty:
                crashed = [w.exitcode for w in workers if w.exitcode not in (None, 0)]
                assert not crashed and time.monotonic() < deadline, f"workers ended with {crashed}"
    finally:
        for w in workers:
            w.join(30)
            if w.is_alive():
                w.kill()
    assert [w.exitcode for w in workers] == [0] * processes
    by_worker = {worker: claimed for worker, claimed, _, _ in reports}
    every = [job_id for claimed in by_worker.values() for job_id in claimed]
    assert sorted(every) == sorted(ids) and len(set(every)) == count  # each claimed exactly once
    assert all(all(f) for _, _, f, _ in reports)  # each finished by its claimer
    outputs_by_job = Counter(job_id for job_id, _ in written(store))
    assert set(outputs_by_job) == set(ids) and set(outputs_by_job.values()) == {1}  # each result written once
    holder = {job_id: worker for worker, claimed in by_worker.items() for job_id in claimed}
    assert all(holder[job_id] == worker for job_id, worker in written(store))
    for job in queue.list(limit=count + 1):
        assert (job.state, job.worker, job.result_id, job.attempts) == ("done", holder[job.id], job.id[::-1], 1)
    assert sum(1 for claimed in by_worker.values() if claimed) >= 2  # they did race
    seconds = max(s for *_, s in reports)
    print(f"{store.dialect}: {count} jobs claimed and finished by {processes} processes in {seconds:.2f} s")
    return by_worker


def test_four_processes_never_get_the_same_job(url: str, store: Store) -> None:
    race(url, store, processes=4, count=200)
    with store.engine.connect() as conn:
        assert conn.execute(select(func.count()).select_from(jobs)).scalar_one() == 200
