"""Three replicas of the service on one PostgreSQL behave as one service.

Each replica is a real uvicorn with its own data folder (nothing on disk shared, as on three machines), the
same database URL and the same admin token. Uploads spread over them round-robin; every acknowledged (201)
evaluation must then read the same, list the same and gate the same through every replica; a ground truth
replaced under the same name must give the new numbers everywhere at once; and a replica killed with SIGKILL
in the middle of uploads must lose none of the evaluations it acknowledged.

Skipped, with the reason, when no PostgreSQL binaries are installed (Debian: ``apt-get install postgresql``).
"""

from __future__ import annotations

import threading
import uuid
from typing import Any

import httpx
import psycopg
import pytest
from server_helpers import ADMIN, golden_bytes, golden_txt, tar_of, zip_of
from server_postgres import PostgresCluster, why_no_postgres
from server_replicas import Ack, Replicas, spread_uploads

from kitti_eval_server.store import Store

pytestmark = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")

UPLOADS = 60
CAR_3D = ("strict", "R40", "Car", "3d", "moderate")


@pytest.fixture(scope="module")
def postgres():
    with PostgresCluster() as cluster:
        yield cluster


@pytest.fixture(scope="module")
def replicas(postgres, tmp_path_factory):
    """Three replicas started together on an empty database: they race to create the tables and to register
    the demo, as replicas rolled out at the same time do. Enough queue places that 60 concurrent uploads over
    three replicas are all admitted (a 503 is not an acknowledgement, only noise here)."""
    with Replicas(tmp_path_factory.mktemp("replicas"), postgres.url, 3, max_queued_evals=UPLOADS) as started:
        yield started


@pytest.fixture(scope="module")
def registered(replicas) -> dict[str, str]:
    """Two ground truths registered through replica 0 only: {name: sha256}."""
    out = {}
    with replicas[0].client() as c:
        for name, content, filename in (
            ("small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl"),
            ("small-txt", golden_bytes("label_2.tar.gz"), "label_2.tar.gz"),
        ):
            r = c.post("/v1/ground-truths", data={"name": name}, files={"file": (filename, content)}, headers=ADMIN)
            assert r.status_code == 201, r.text
            out[name] = r.json()["sha256"]
    return out


def ap(doc: dict[str, Any], key: tuple[str, ...] = CAR_3D) -> float:
    value: Any = doc["ap"]
    for part in key:
        value = value[part]
    return float(value)


def replica_clients(replicas: Replicas) -> list[httpx.Client]:
    return [s.client() for s in replicas.servers]


def upload_form(run: str) -> tuple[Any, Any]:
    """Even uploads: result.pkl against the infos pickle; odd ones: a zip of txt results against the txt labels."""
    pickle_predictions = golden_bytes("result.pkl")
    zip_predictions = zip_of(golden_txt("pred.tar.gz"))

    def form(i: int) -> dict[str, Any]:
        return {"gt": "small" if i % 2 == 0 else "small-txt", "label": [f"run={run}", f"upload={i}"]}

    def files(i: int) -> dict[str, Any]:
        if i % 2 == 0:
            return {"predictions": ("result.pkl", pickle_predictions)}
        return {"predictions": ("pred.zip", zip_predictions)}

    return form, files


def assert_same_everywhere(clients: list[httpx.Client], acked: list[dict[str, Any]], run: str) -> None:
    """Every acknowledged evaluation reads back, as acknowledged, through every client; each lists the same
    evaluations in the same order; each gates each one with the same verdict."""
    ids = {a["id"] for a in acked}
    listings = []
    for c in clients:
        for body in acked:
            r = c.get(f"/v1/evaluations/{body['id']}")
            assert r.status_code == 200, (str(c.base_url), r.text)
            assert r.json() == body, str(c.base_url)
        listed = c.get("/v1/evaluations", params={"label": f"run={run}", "limit": 500}).json()["items"]
        assert ids <= {i["id"] for i in listed}, str(c.base_url)
        listings.append([i["id"] for i in listed])
    assert all(listing == listings[0] for listing in listings)

    baselines = {a["evaluation"]["ground_truth"]["sha256"]: a for a in reversed(acked)}
    for body in acked:
        baseline = baselines[body["evaluation"]["ground_truth"]["sha256"]]
        rules = {
            "evaluation": body["id"],
            "baseline": baseline["id"],
            "min": ["Car/3d/moderate >= 1"],
            "max_drop": ["0"],
        }
        verdicts = [c.post("/v1/gates", json=rules) for c in clients]
        assert [v.status_code for v in verdicts] == [200] * len(clients), [v.text for v in verdicts]
        assert all(v.json() == verdicts[0].json() for v in verdicts)
        floor = next(ch for ch in verdicts[0].json()["checks"] if ch["rule"] == "Car/3d/moderate/R40/strict >= 1")
        assert floor["current"] == pytest.approx(ap(body), abs=1e-9)


def fresh_database(cluster: PostgresCluster) -> str:
    """A new, empty database on the cluster; its SQLAlchemy URL (psycopg 3)."""
    name = f"db_{uuid.uuid4().hex}"
    with psycopg.connect(
        host="127.0.0.1", port=cluster.port, user="postgres", dbname="postgres", autocommit=True
    ) as conn:
        conn.execute(f"CREATE DATABASE {name}")
    return f"postgresql+psycopg://postgres@127.0.0.1:{cluster.port}/{name}"


def test_servers_creating_the_schema_at_once_all_succeed(postgres) -> None:
    """PostgreSQL's CREATE TABLE races with itself (a unique violation in its catalog): without a lock, servers
    started together on an empty database crashed at start-up, all but one."""

    def create(store: Store, start: threading.Barrier, failures: list[BaseException]) -> None:
        start.wait()
        try:
            store.create_schema()
        except Exception as e:  # noqa: BLE001 - collected and reported
            failures.append(e)

    for _ in range(3):
        url = fresh_database(postgres)
        stores = [Store(url) for _ in range(4)]
        start = threading.Barrier(len(stores))
        failures: list[BaseException] = []
        threads = [threading.Thread(target=create, args=(s, start, failures)) for s in stores]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        try:
            assert not failures, failures[0]
            assert stores[0].ground_truth_store.list_ground_truths() == []
        finally:
            for store in stores:
                store.dispose()


def test_replicas_started_together_share_one_schema_and_one_demo(replicas, postgres) -> None:
    for server in replicas.servers:
        with server.client() as c:
            assert c.get("/readyz").status_code == 200
            assert [g["name"] for g in c.get("/v1/ground-truths").json()["items"]] == ["demo"]


def test_every_acknowledged_evaluation_is_the_same_through_every_replica(replicas, registered) -> None:
    # the files registered through replica 0 are in the database; each replica unpacks its own copy
    local = [f"{registered['small']}.pkl", registered["small-txt"]]  # a pickle, and an archive's txt folder
    stored = [[s.data_dir / "ground-truths" / name for name in local] for s in replicas.servers]
    assert all(path.exists() for path in stored[0])
    assert not any(path.exists() for path in stored[1] + stored[2])  # replicas 1 and 2 have only the database

    run = uuid.uuid4().hex
    form, files = upload_form(run)
    acks = spread_uploads([s.url for s in replicas.servers], UPLOADS, form, files, concurrency=UPLOADS)
    assert [a.status for a in acks] == [201] * UPLOADS, [(a.status, a.body) for a in acks if a.status != 201]
    acked = [a.body for a in acks if a.body is not None]
    assert all(path.exists() for path in stored[1] + stored[2])  # each unpacked its own copy from the database

    # the same inputs give the same numbers whichever replica evaluated them
    for parity in (0, 1):
        docs = [b for i, b in enumerate(acked) if i % 2 == parity]
        assert all(d["ap"] == docs[0]["ap"] for d in docs)
    assert ap(acked[0]) > 0 and ap(acked[1]) > 0

    clients = replica_clients(replicas)
    try:
        assert_same_everywhere(clients, acked, run)
    finally:
        for c in clients:
            c.close()


def test_a_replaced_ground_truth_never_yields_old_numbers(replicas) -> None:
    """Delete a ground truth through one replica and register other content under the same name: every
    replica, each holding the old content loaded in memory and unpacked on disk, answers with the new."""
    labels = golden_txt("label_2.tar.gz")
    changed = {}
    for i, (name, data) in enumerate(sorted(labels.items())):
        lines = data.decode().splitlines(keepends=True)
        if i % 2 == 0:  # half the frames lose their first Car
            first_car = next((k for k, line in enumerate(lines) if line.startswith("Car ")), None)
            if first_car is not None:
                del lines[first_car]
        changed[name] = "".join(lines).encode()
    contents = [tar_of(labels), tar_of(changed)]
    predictions = zip_of(golden_txt("pred.tar.gz"))
    clients = replica_clients(replicas)
    try:
        expected = []
        for content in contents:  # each content's numbers, from a ground truth sent with the request
            r = clients[0].post(
                "/v1/evaluations",
                files={"predictions": ("pred.zip", predictions), "gt_file": ("labels.tar.gz", content)},
            )
            assert r.status_code == 201, r.text
            expected.append((r.json()["evaluation"]["ground_truth"]["sha256"], r.json()["ap"]))
        assert expected[0][0] != expected[1][0]
        assert ap({"ap": expected[0][1]}) != pytest.approx(ap({"ap": expected[1][1]}), abs=1e-6)

        previous: list[str] = []
        for cycle in range(4):
            sha, numbers = expected[cycle % 2]
            admin = clients[cycle % len(clients)]
            r = admin.post(
                "/v1/ground-truths",
                data={"name": "swap"},
                files={"file": ("labels.tar.gz", contents[cycle % 2])},
                headers=ADMIN,
            )
            assert r.status_code == 201, r.text
            assert r.json()["sha256"] == sha
            current = []
            for c in clients:
                assert c.get("/v1/ground-truths/swap").json()["sha256"] == sha, str(c.base_url)
                r = c.post(
                    "/v1/evaluations",
                    data={"gt": "swap", "label": "ground_truth=swap"},
                    files={"predictions": ("pred.zip", predictions)},
                )
                assert r.status_code == 201, (str(c.base_url), r.text)
                assert r.json()["evaluation"]["ground_truth"]["sha256"] == sha, str(c.base_url)
                assert r.json()["ap"] == numbers, f"cycle {cycle}: {c.base_url} evaluated against the old content"
                current.append(r.json()["id"])
                for old in previous:  # the old evaluations stay, but their frames are gone with their content
                    assert c.get(f"/v1/evaluations/{old}/frames").status_code == 409, str(c.base_url)
                assert c.get(f"/v1/evaluations/{current[-1]}/frames").status_code == 200, str(c.base_url)
            assert admin.delete("/v1/ground-truths/swap", headers=ADMIN).status_code == 204
            for c in clients:  # gone everywhere at once
                assert c.get("/v1/ground-truths/swap").status_code == 404, str(c.base_url)
                r = c.post("/v1/evaluations", data={"gt": "swap"}, files={"predictions": ("pred.zip", predictions)})
                assert r.status_code == 404, (str(c.base_url), r.text)
            previous = current
    finally:
        for c in clients:
            c.close()


@pytest.mark.slow
def test_a_replica_killed_during_uploads_loses_nothing_it_acknowledged(replicas, registered) -> None:
    """Runs last: it kills replica 2 (and starts it again at the end)."""
    victim = replicas[2]
    acked_before_kill = 3
    acked_by_victim: list[str] = []
    lock = threading.Lock()
    killed = threading.Event()

    def on_answer(ack: Ack) -> None:
        if ack.replica != 2 or ack.status != 201:
            return
        with lock:
            acked_by_victim.append(ack.body["id"] if ack.body else "")
            if len(acked_by_victim) == acked_before_kill and not killed.is_set():
                victim.kill()  # SIGKILL, with the uploads of the other senders in flight
                killed.set()

    run = uuid.uuid4().hex
    form, files = upload_form(run)
    acks = spread_uploads([s.url for s in replicas.servers], UPLOADS, form, files, concurrency=12, on_answer=on_answer)
    assert killed.is_set()
    by_victim = [a for a in acks if a.replica == 2]
    assert any(a.status is None for a in by_victim)  # uploads it was sent after (or while) it died got no answer
    assert all(a.status in (201, None) for a in by_victim)
    assert all(a.status == 201 for a in acks if a.replica != 2), [a.status for a in acks if a.replica != 2]
    acked = [a.body for a in acks if a.status == 201 and a.body is not None]
    assert len({a["id"] for a in acked if a["id"] in acked_by_victim}) >= acked_before_kill

    survivors = replica_clients(replicas)[:2]
    try:
        assert_same_everywhere(survivors, acked, run)
    finally:
        for c in survivors:
            c.close()

    victim.stop()  # (closes its log)
    victim.start()  # restarted, it reads what the others stored meanwhile
    with victim.client() as c:
        listed = c.get("/v1/evaluations", params={"label": f"run={run}", "limit": 500}).json()["items"]
        assert {a["id"] for a in acked} <= {i["id"] for i in listed}
