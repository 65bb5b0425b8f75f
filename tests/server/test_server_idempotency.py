"""Idempotency keys on POST /v1/evaluations and POST /v1/benchmarks/NAME/submissions, on SQLite and PostgreSQL:
the same caller sending the same key with the same file gets the first answer again (the same id, the job as it
is now), never a second record or a second count against the quota: sent again in turn, four copies at once,
and after the service was killed between committing and answering; the same key with another file is refused,
naming the key; keys expire after KITTI_EVAL_IDEMPOTENCY_KEY_HOURS."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from server_benchmarks import host, ok
from server_helpers import ADMIN, LiveServer, app_client, assert_error, golden_bytes, upload
from server_postgres import PostgresCluster, why_no_postgres

_PG_SKIP = pytest.mark.skipif(why_no_postgres() is not None, reason=why_no_postgres() or "")


@pytest.fixture(scope="module")
def cluster() -> Iterator[PostgresCluster | None]:
    if why_no_postgres() is not None:
        yield None
        return
    with PostgresCluster() as started:
        yield started


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=_PG_SKIP)])
def database(request: Any, cluster: PostgresCluster | None) -> dict[str, str]:
    """The settings of a fresh database: SQLite in the data folder, or a new PostgreSQL database."""
    if request.param == "sqlite":
        return {}
    assert cluster is not None
    from sqlalchemy import create_engine, text

    name = f"idem_{uuid.uuid4().hex[:12]}"
    engine = create_engine(cluster.url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text(f"CREATE DATABASE {name}"))
    engine.dispose()
    return {"database_url": cluster.url.rsplit("/", 1)[0] + "/" + name}


def _key() -> dict[str, str]:
    return {"Idempotency-Key": str(uuid.uuid4())}


def _submit(client: Any, who: dict[str, str], data: bytes, key: dict[str, str], **params: str) -> httpx.Response:
    files = {"predictions": ("result.pkl", data, "application/octet-stream")}
    return client.post("/v1/benchmarks/bench/submissions", files=files, headers={**who, **key}, params=params)


def _with_project(client: Any, user: str) -> dict[str, str]:
    """Makes ``user`` a member of a project of their own (an evaluation in accounts mode belongs to one)."""
    ok(client.post("/v1/admin/projects", json={"name": f"{user}-p"}, headers=ADMIN), 201)
    ok(client.post("/v1/admin/members", json={"user": user, "project": f"{user}-p"}, headers=ADMIN), 201)
    return {"project": f"{user}-p"}


def _jobs(client: Any) -> list[dict[str, Any]]:
    return list(ok(client.get("/v1/admin/jobs", headers=ADMIN))["items"])


def _other_pickle() -> bytes:
    """The golden result.pkl with one byte of its padding changed: another file, read the same."""
    data = bytearray(golden_bytes("result.pkl"))
    return bytes(data) + b"."  # a pickle stops at its STOP opcode: what follows is not read


def test_an_evaluation_sent_again_with_its_key_is_the_first_one(tmp_path, database) -> None:
    with app_client(tmp_path / "data", **database) as c:
        key = _key()
        first = upload(c, golden_bytes("result.pkl"), headers=key)
        assert first.status_code == 201, first.text
        again = upload(c, golden_bytes("result.pkl"), headers=key)
        assert again.status_code == 201, again.text
        assert again.json()["id"] == first.json()["id"]
        assert again.json()["ap"] == first.json()["ap"]
        assert len(c.get("/v1/evaluations").json()["items"]) == 1
        assert len(_jobs(c)) == 1
        # another key (or none) is another evaluation of the same file
        assert upload(c, golden_bytes("result.pkl"), headers=_key()).json()["id"] != first.json()["id"]
        assert upload(c, golden_bytes("result.pkl")).json()["id"] != first.json()["id"]
        assert len(_jobs(c)) == 3


def test_the_same_key_with_another_request_is_refused_naming_it(tmp_path, database) -> None:
    key = {"Idempotency-Key": "deadline-retry-1"}
    with app_client(tmp_path / "open", **database) as c:
        first = ok(upload(c, golden_bytes("result.pkl"), headers=key), 201)
        err = assert_error(upload(c, _other_pickle(), headers=key), 422, "'deadline-retry-1'", first["id"])
        assert err["code"] == "idempotency_key_reused"
        # other fields with the same file are another request too
        assert_error(upload(c, golden_bytes("result.pkl"), fields={"model": "m"}, headers=key), 422, "another request")
        assert len(_jobs(c)) == 1
        for bad in ("", "a" * 256, "caf\u00e9".encode("latin-1"), "two words"):
            assert_error(upload(c, golden_bytes("result.pkl"), headers={"Idempotency-Key": bad}), 400, "1-255")
        # the draft writes the key as a structured-field string: the quotes are not part of it
        quoted = upload(c, golden_bytes("result.pkl"), headers={"Idempotency-Key": '"q-1"'})
        plain = upload(c, golden_bytes("result.pkl"), headers={"Idempotency-Key": "q-1"})
        assert quoted.status_code == plain.status_code == 201 and quoted.json()["id"] == plain.json()["id"]
    with app_client(tmp_path / "accounts", auth="accounts", **database) as c:
        hosted = host(c)
        alice, bob = hosted.headers("alice"), hosted.headers("bob")
        sub = ok(_submit(c, alice, golden_bytes("result.pkl"), key, wait="600"), 201)
        err = assert_error(_submit(c, alice, _other_pickle(), key, wait="600"), 422, "'deadline-retry-1'", sub["id"])
        assert err["code"] == "idempotency_key_reused"
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=alice))
        assert [s["id"] for s in mine["items"]] == [sub["id"]] and mine["quota"]["used"] == 1
        # the same key is another caller's own key
        theirs = ok(_submit(c, bob, _other_pickle(), key, wait="600"), 201)
        assert theirs["id"] != sub["id"] and theirs["participant"] == "bob"


def test_a_submission_sent_again_counts_once_even_past_the_quota(tmp_path, database) -> None:
    """The third of a quota of three, sent again, is answered with itself (not 429, before or after its body),
    and the quota counts it once; a fourth with a new key is refused."""
    with app_client(tmp_path / "data", auth="accounts", **database) as c:
        hosted = host(c)
        who = hosted.headers("alice")
        keys = [_key() for _ in range(3)]
        ids = [ok(_submit(c, who, golden_bytes("result.pkl"), k, wait="600"), 201)["id"] for k in keys]
        again = _submit(c, who, golden_bytes("result.pkl"), keys[2], wait="600")
        assert again.status_code == 201, again.text
        assert again.json()["id"] == ids[2] and again.json()["status"] == "scored"
        continued = c.post(
            "/v1/benchmarks/bench/submissions",
            files={"predictions": ("result.pkl", golden_bytes("result.pkl"))},
            headers={**who, **keys[0], "Expect": "100-continue"},
        )
        assert continued.status_code == 201 and continued.json()["id"] == ids[0]
        mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=who))
        assert mine["quota"]["used"] == 3 and len(mine["items"]) == 3
        assert_error(_submit(c, who, golden_bytes("result.pkl"), _key()), 429, "quota")


@pytest.mark.slow
def test_four_copies_at_once_make_one_evaluation_and_one_submission(tmp_path, database) -> None:
    server = LiveServer(tmp_path / "data", auth="accounts", **database).start()
    try:
        with server.client() as c:
            hosted = host(c, benchmark={"quota": "2/1"})
            project = _with_project(c, "alice")
        who = hosted.headers("alice")
        eval_key, sub_key = _key(), _key()
        answers: dict[str, list[httpx.Response]] = {"evaluation": [], "submission": []}
        lock = threading.Lock()
        go = threading.Barrier(8)

        def send(kind: str) -> None:
            with server.client(timeout=120) as c:
                go.wait()
                if kind == "evaluation":
                    r = upload(c, golden_bytes("result.pkl"), fields=project, headers={**who, **eval_key})
                else:
                    r = _submit(c, who, golden_bytes("result.pkl"), sub_key, wait="120")
            with lock:
                answers[kind].append(r)

        threads = [threading.Thread(target=send, args=(k,)) for k in ("evaluation", "submission") for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(180)
        for kind, got in answers.items():
            assert [r.status_code for r in got] == [201] * 4, [r.text for r in got]
            assert len({r.json()["id"] for r in got}) == 1, kind
        with server.client() as c:
            jobs = _jobs(c)
            assert sorted(j["kind"] for j in jobs if j["kind"] != "intervals") == ["evaluation", "submission"]
            assert len(ok(c.get("/v1/evaluations", headers=who))["items"]) == 1
            mine = ok(c.get("/v1/benchmarks/bench/submissions", headers=who))
            assert mine["quota"]["used"] == 1 and len(mine["items"]) == 1
    except httpx.TransportError:
        raise AssertionError(f"server failed:\n{server.log()}") from None
    finally:
        server.stop()


@pytest.mark.slow
def test_sent_again_after_the_service_was_killed_between_committing_and_answering(tmp_path, database) -> None:
    """The service is killed (SIGKILL) with the job committed and the answer not sent (no worker runs it, so the
    request is still waiting for it); started again, the same request with the same key is the same job."""
    data_dir = tmp_path / "data"
    quiet = {"auth": "accounts", "job_threads": "0", "worker_processes": "0", **database}
    server = LiveServer(data_dir, ready_path="/healthz", **quiet).start()
    try:
        with server.client() as c:
            hosted = host(c)
            project = _with_project(c, "alice")
        who = hosted.headers("alice")
        eval_key, sub_key = _key(), _key()
        lost: list[BaseException] = []

        def send(kind: str) -> None:
            try:
                with server.client(timeout=120) as c:
                    if kind == "evaluation":
                        upload(
                            c,
                            golden_bytes("result.pkl"),
                            fields=project,
                            headers={**who, **eval_key},
                            params={"wait": "600"},
                        )
                    else:
                        _submit(c, who, golden_bytes("result.pkl"), sub_key, wait="600")
            except httpx.TransportError as e:  # the service died before answering
                lost.append(e)

        threads = [threading.Thread(target=send, args=(k,)) for k in ("evaluation", "submission")]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        with server.client() as c:
            while len(committed := _jobs(c)) < 2:
                assert time.monotonic() < deadline, "the jobs were not committed"
                time.sleep(0.05)
        assert {j["state"] for j in committed} == {"queued"}
        server.kill()
        for t in threads:
            t.join(30)
        assert len(lost) == 2, "a request was answered before the kill"
        server = LiveServer(data_dir, auth="accounts", **database).start()
        with server.client(timeout=120) as c:
            evaluation = upload(
                c, golden_bytes("result.pkl"), fields=project, headers={**who, **eval_key}, params={"wait": "600"}
            )
            submission = _submit(c, who, golden_bytes("result.pkl"), sub_key, wait="600")
            assert evaluation.status_code == 201 and submission.status_code == 201, (evaluation.text, submission.text)
            ids = {j["kind"]: j["id"] for j in committed}
            assert evaluation.json()["id"] == ids["evaluation"]
            assert submission.json()["id"] == ids["submission"] and submission.json()["status"] == "scored"
            kinds = sorted(j["kind"] for j in _jobs(c) if j["kind"] != "intervals")  # a scoring queues its intervals
            assert kinds == ["evaluation", "submission"]
            assert ok(c.get("/v1/benchmarks/bench/submissions", headers=who))["quota"]["used"] == 1
    except httpx.TransportError:
        raise AssertionError(f"server failed:\n{server.log()}") from None
    finally:
        server.stop()


def test_a_key_is_kept_as_long_as_the_setting_says(tmp_path, database) -> None:
    """Kept a day by default; past KITTI_EVAL_IDEMPOTENCY_KEY_HOURS the same key is a new request's (and the
    expired row is removed when the caller's next key is recorded)."""
    from kitti_eval_server import Settings

    assert Settings().idempotency_key_hours == 24
    with app_client(tmp_path / "data", idempotency_key_hours=1 / 3600, **database) as c:  # one second
        key = _key()
        first = ok(upload(c, golden_bytes("result.pkl"), headers=key), 201)
        assert ok(upload(c, golden_bytes("result.pkl"), headers=key), 201)["id"] == first["id"]
        time.sleep(1.2)
        later = ok(upload(c, _other_pickle(), headers=key), 201)  # another file: the key is free again
        assert later["id"] != first["id"]
        store = c.app.state.service.store
        from sqlalchemy import func, select

        from kitti_eval_server.store.database import idempotency_keys

        with store.engine.connect() as conn:
            assert conn.execute(select(func.count()).select_from(idempotency_keys)).scalar_one() == 1


def test_the_upload_form_sent_twice_makes_one_evaluation(tmp_path) -> None:
    """The web form carries a key drawn when the page is shown: sent again (a double click, the browser sending
    it again), it leads to the same evaluation; the page shown again has a new key."""
    import re

    with app_client(tmp_path / "data") as c:
        keys = [re.search(r'name="idempotency_key" value="([^"]+)"', c.get("/").text) for _ in range(2)]
        assert keys[0] is not None and keys[1] is not None and keys[0].group(1) != keys[1].group(1)
        form = {"gt": "demo", "idempotency_key": keys[0].group(1)}
        sent = [
            c.post("/ui/evaluations", data=form, files={"predictions": ("r.pkl", golden_bytes("result.pkl"))})
            for _ in range(2)
        ]
        assert [r.status_code for r in sent] == [200, 200] and sent[0].url == sent[1].url
        assert str(sent[0].url).rsplit("/", 1)[1] == c.get("/v1/evaluations").json()["items"][0]["id"]
        assert len(c.get("/v1/evaluations").json()["items"]) == 1
