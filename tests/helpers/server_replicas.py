"""Several uvicorn replicas of the service on one database, as behind a load balancer, and a client that spreads
uploads over them round-robin.

Each replica has its own data folder (nothing on disk is shared, as on separate machines) and the same database
URL and admin token. Run as a script it measures uploads per second through 1 and through 3 replicas::

    .venv/bin/python tests/helpers/server_replicas.py [uploads] [concurrency]
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
from server_helpers import LiveServer

__all__ = ["Replicas", "Ack", "spread_uploads"]


class Replicas:
    """``n`` :class:`LiveServer` processes on one database, started at the same time (so they also race to
    create the tables and register the demo, as replicas rolled out together do)."""

    def __init__(self, root: Path, database_url: str, n: int = 3, **settings: Any) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.servers = [LiveServer(root / f"replica-{i}", database_url=database_url, **settings) for i in range(n)]

    def start(self) -> Replicas:
        errors: list[BaseException] = []

        def start_one(server: LiveServer) -> None:
            try:
                server.start()
            except BaseException as e:  # noqa: BLE001 - reported below, with every replica's log
                errors.append(e)

        threads = [threading.Thread(target=start_one, args=(s,)) for s in self.servers]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            self.stop()
            raise RuntimeError(f"{len(errors)} of {len(self.servers)} replicas did not start:\n{errors[0]}")
        return self

    def stop(self) -> None:
        for server in self.servers:
            server.stop()

    def __enter__(self) -> Replicas:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __getitem__(self, i: int) -> LiveServer:
        return self.servers[i]

    def __len__(self) -> int:
        return len(self.servers)

    def logs(self) -> str:
        return "\n".join(f"--- replica {i}:\n{s.log()}" for i, s in enumerate(self.servers))


@dataclass(frozen=True)
class Ack:
    """One upload's answer: which replica, the status (None: no answer, the connection failed), the body."""

    replica: int
    status: int | None
    body: dict[str, Any] | None


def spread_uploads(
    urls: Sequence[str],
    count: int,
    form: Callable[[int], dict[str, Any]],
    files: Callable[[int], dict[str, Any]],
    *,
    concurrency: int,
    on_answer: Callable[[Ack], None] | None = None,
    timeout: float = 120,
) -> list[Ack]:
    """``count`` uploads to ``POST /v1/evaluations``, upload ``i`` to ``urls[i % len(urls)]``, ``concurrency``
    at a time. A connection that fails (a replica killed) is an answer with status None, not an exception."""
    local = threading.local()

    def client() -> httpx.Client:
        if not hasattr(local, "client"):
            local.client = httpx.Client(timeout=timeout)
        c: httpx.Client = local.client
        return c

    def send(i: int) -> Ack:
        replica = i % len(urls)
        try:
            r = client().post(f"{urls[replica]}/v1/evaluations", data=form(i), files=files(i))
        except httpx.TransportError:
            ack = Ack(replica, None, None)
        else:
            is_json = r.headers.get("content-type", "").startswith("application/json")
            ack = Ack(replica, r.status_code, r.json() if is_json else None)
        if on_answer is not None:
            on_answer(ack)
        return ack

    with ThreadPoolExecutor(concurrency) as pool:
        return list(pool.map(send, range(count)))


def _throughput(uploads: int, concurrency: int) -> None:  # pragma: no cover - a measurement, run by hand
    import tempfile

    from server_postgres import PostgresCluster

    from kitti_eval.demo import demo_paths

    predictions = demo_paths()[1].read_bytes()  # the bundled demo: 200 frames, against the `demo` ground truth
    with PostgresCluster() as pg, tempfile.TemporaryDirectory() as tmp:
        for n in (1, 3):
            settings = dict(max_concurrent_evals=2, max_queued_evals=uploads)
            with Replicas(Path(tmp) / f"n{n}", pg.url, n, **settings) as replicas:
                urls = [s.url for s in replicas.servers]
                rates = []
                for attempt in range(4):  # the first round warms each replica's caches and is not counted
                    started = time.perf_counter()
                    acks = spread_uploads(
                        urls,
                        uploads,
                        lambda i, n=n: {"gt": "demo", "label": f"bench=n{n}"},
                        lambda i: {"predictions": ("result.pkl.gz", predictions)},
                        concurrency=concurrency,
                    )
                    elapsed = time.perf_counter() - started
                    assert all(a.status == 201 for a in acks), {a.status for a in acks}
                    if attempt:
                        rates.append(uploads / elapsed)
                figures = ", ".join(f"{r:.1f}" for r in rates)
                print(f"{n} replica(s), {uploads} uploads {concurrency} at a time: {figures} uploads/s")


if __name__ == "__main__":  # pragma: no cover
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    args = [int(a) for a in sys.argv[1:]]
    _throughput(*(args + [60, 12][len(args) :]))
