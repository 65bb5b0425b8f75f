"""The core flow on PostgreSQL (psycopg 3): a throwaway cluster, in-process and behind a real uvicorn.

Skipped, with the reason, when no PostgreSQL binaries are installed (Debian: ``apt-get install postgresql``).
"""

from __future__ import annotations

import threading

import httpx
import pytest
from server_helpers import (
    ADMIN,
    LiveServer,
    app_client,
    assert_error,
    golden_bytes,
    golden_txt,
    register,
    upload,
    zip_of,
)
from server_postgres import PostgresCluster, why_no_postgres
from unversioned import as_unversioned

pytestmark = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")


@pytest.fixture(scope="module")
def postgres():
    with PostgresCluster() as cluster:
        yield cluster


def test_core_flow_on_postgres(postgres, tmp_path) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir, database_url=postgres.url) as c:
        service = c.app.state.service
        assert service.store.dialect == "postgresql"
        assert not (data_dir / "kitti-eval.db").exists()
        assert [g["name"] for g in c.get("/v1/ground-truths").json()["items"]] == ["demo"]
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        assert register(c, "small-txt", golden_bytes("label_2.tar.gz"), "label_2.tar.gz").status_code == 201
        assert_error(register(c, "small", golden_bytes("kitti_infos_val.pkl"), "i.pkl"), 409)
        a = upload(c, golden_bytes("result.pkl"), gt="small", fields={"model": "m", "epoch": "1"})
        b = upload(
            c,
            zip_of(golden_txt("pred.tar.gz")),
            "pred.zip",
            gt="small-txt",
            fields={"model": "m", "epoch": "2", "label": "team=pg"},
        )
        assert a.status_code == 201 and b.status_code == 201, (a.text, b.text)
        a, b = a.json(), b.json()
        assert c.get(f"/v1/evaluations/{a['id']}").json() == a
        assert [i["id"] for i in c.get("/v1/evaluations", params={"model": "m"}).json()["items"]] == [b["id"], a["id"]]
        assert [i["id"] for i in c.get("/v1/evaluations", params={"gt": "small"}).json()["items"]] == [a["id"]]
        assert [i["id"] for i in c.get("/v1/evaluations", params={"label": "team=pg"}).json()["items"]] == [b["id"]]
        cmp = c.get(f"/v1/evaluations/{a['id']}/compare/{b['id']}").json()
        va = a["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
        vb = b["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
        delta = next(v["delta"] for v in cmp["values"] if v["key"] == "Car/3d/moderate/R40/strict")
        assert delta == pytest.approx(vb - va, abs=1e-12)
        assert "different ground truth" in cmp["notes"][0]
        assert c.delete("/v1/ground-truths/small", headers=ADMIN).status_code == 204
        assert_error(upload(c, golden_bytes("result.pkl"), gt="small"), 404)
    with app_client(data_dir, database_url=postgres.url) as c:  # a restart: everything is still there
        assert c.get(f"/v1/evaluations/{a['id']}").json() == a
        assert {g["name"] for g in c.get("/v1/ground-truths").json()["items"]} == {"demo", "small-txt"}
        assert c.get("/readyz").status_code == 200


@pytest.mark.slow
def test_concurrent_uploads_and_sigkill_on_postgres(postgres, tmp_path) -> None:
    data_dir = tmp_path / "data"
    server = LiveServer(data_dir, database_url=postgres.url, max_concurrent_evals=2, max_queued_evals=16).start()
    acked: list[str] = []
    lock = threading.Lock()
    try:

        def sender() -> None:
            with server.client(timeout=60) as c:
                for _ in range(3):
                    r = c.post(
                        "/v1/evaluations",
                        data={"gt": "demo", "label": "db=pg"},
                        files={"predictions": ("r.pkl", golden_bytes("result.pkl"))},
                    )
                    assert r.status_code == 201, r.text
                    with lock:
                        acked.append(r.json()["id"])

        threads = [threading.Thread(target=sender) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert len(acked) == 24
        server.kill()
        server = LiveServer(data_dir, database_url=postgres.url).start()
        with server.client() as c:
            listed = c.get("/v1/evaluations", params={"label": "db=pg", "limit": 100}).json()["items"]
            assert {i["id"] for i in listed} == set(acked)
            assert c.get(f"/v1/evaluations/{acked[0]}").status_code == 200
    except httpx.TransportError:
        raise AssertionError(f"server failed:\n{server.log()}") from None
    finally:
        server.stop()


def test_baselines_on_postgres_and_the_column_added_to_an_older_database(postgres, tmp_path) -> None:
    """An admin's baseline (no quota, no rank) on PostgreSQL; a database made before baselines (by an unversioned
    release) gets the column (``BOOLEAN NOT NULL DEFAULT FALSE``) from the base revision when it is upgraded at
    start-up, its rows reading as participants' submissions."""
    from server_benchmarks import host, ok, submit
    from sqlalchemy import create_engine, text

    url = postgres.url.rsplit("/", 1)[0] + "/baselines"
    admin_engine = create_engine(postgres.url, isolation_level="AUTOCOMMIT")
    with admin_engine.connect() as conn:
        conn.execute(text("CREATE DATABASE baselines"))
    admin_engine.dispose()
    with app_client(tmp_path / "data", database_url=url, auth="accounts") as c:
        hosted = host(c, benchmark={"quota": "1/1"})
        old = ok(submit(c, hosted.headers("alice"), golden_bytes("result.pkl")), 201)
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.execute(text("ALTER TABLE submissions DROP COLUMN baseline"))
        as_unversioned(lambda sql: conn.execute(text(sql)))
    engine.dispose()
    with app_client(tmp_path / "data", database_url=url, auth="accounts", db_upgrade=True) as c:
        root = hosted.headers("root")
        made = [ok(submit(c, root, golden_bytes("result.pkl")), 201) for _ in range(2)]  # over a quota of 1
        assert [m["baseline"] for m in made] == [True, True]
        for who, sid in (("alice", old["id"]), ("root", made[0]["id"])):
            body = {"method": who}
            ok(c.post(f"/v1/benchmarks/bench/submissions/{sid}/publish", json=body, headers=hosted.headers(who)))
        entries = ok(c.get("/v1/benchmarks/bench/leaderboard"))["entries"]
        assert [(e["method"], e["rank"], e["baseline"]) for e in entries] == [("alice", 1, False), ("root", None, True)]
        assert submit(c, hosted.headers("alice"), golden_bytes("result.pkl")).status_code == 429  # hers is used


def test_uploaded_files_are_stored_without_pglz(postgres, tmp_path) -> None:
    """A job's input is stored as it is (EXTERNAL: it lives until its job ends), the files kept for good with
    lz4 (PostgreSQL 14 and later); a database made with the defaults is changed by the base revision when it is
    upgraded at start-up, and its files still read back whole."""
    from sqlalchemy import create_engine, text

    url = postgres.url.rsplit("/", 1)[0] + "/storage"
    admin_engine = create_engine(postgres.url, isolation_level="AUTOCOMMIT")
    with admin_engine.connect() as conn:
        conn.execute(text("CREATE DATABASE storage"))
    admin_engine.dispose()
    query = text(
        "SELECT c.relname, a.attstorage, a.attcompression FROM pg_attribute a JOIN pg_class c ON a.attrelid = c.oid "
        "WHERE a.attname = 'content' AND c.relname IN ('job_inputs', 'prediction_files', 'ground_truth_files') "
        "ORDER BY c.relname"
    )
    engine = create_engine(url)

    def columns() -> list[tuple[str, str, str]]:
        with engine.connect() as conn:
            return [tuple(r) for r in conn.execute(query)]

    with app_client(tmp_path / "data", database_url=url, keep_predictions=True) as c:
        first = upload(c, golden_bytes("result.pkl"), gt="demo")
        assert first.status_code == 201, first.text
    expected = [("ground_truth_files", "x", "l"), ("job_inputs", "e", ""), ("prediction_files", "x", "l")]
    assert columns() == expected
    with engine.begin() as conn:  # as a database an unversioned release made before: pglz, compressed in line
        for table in ("job_inputs", "prediction_files", "ground_truth_files"):
            conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN content SET STORAGE EXTENDED"))
            if table != "job_inputs":
                conn.execute(text(f"ALTER TABLE {table} ALTER COLUMN content SET COMPRESSION pglz"))
        as_unversioned(lambda sql: conn.execute(text(sql)))
    with app_client(tmp_path / "data", database_url=url, keep_predictions=True, db_upgrade=True) as c:
        assert columns() == expected
        again = upload(c, golden_bytes("result.pkl"), gt="demo")
        assert again.status_code == 201 and again.json()["ap"] == first.json()["ap"]
        frame = c.get(f"/v1/evaluations/{first.json()['id']}/frames")  # the file kept before the change
        assert frame.status_code == 200, frame.text
    engine.dispose()


def test_a_database_not_encoded_in_utf8_is_refused_in_one_sentence(postgres, tmp_path) -> None:
    """SQL_ASCII (``initdb`` under the C locale): psycopg hands back bytes, and SQLAlchemy's first connection
    failed with ``TypeError: cannot use a string pattern on a bytes-like object``, a crash loop."""
    import psycopg

    from kitti_eval_server.errors import StartupRefused

    with psycopg.connect(host="127.0.0.1", port=postgres.port, user="postgres", autocommit=True) as conn:
        conn.execute("CREATE DATABASE ascii_db ENCODING 'SQL_ASCII' TEMPLATE template0")
    url = postgres.url.rpartition("/")[0] + "/ascii_db"
    with pytest.raises(StartupRefused) as refused, app_client(tmp_path / "data", database_url=url, warmup=False):
        pass
    message = refused.value.message
    assert message.startswith("the PostgreSQL database ascii_db is encoded in SQL_ASCII, not UTF8"), message
    assert "ENCODING 'UTF8'" in message and "\n" not in message
