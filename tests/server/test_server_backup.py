"""``kitti-eval admin backup DIR`` while the service takes uploads, and ``restore DIR`` into an empty data folder
(and an empty PostgreSQL database): the restored service shows every board, submission and evaluation the
original showed at the moment of the copy, and finishes the jobs that were queued then. SQLite here; PostgreSQL
too when its binaries are installed (a throwaway cluster)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, golden_bytes, register, upload
from server_postgres import PostgresCluster, why_no_postgres

from kitti_eval.cli import main
from kitti_eval_server.store.schema import head

NO_PG = why_no_postgres()


def _settings(**more: Any) -> dict[str, Any]:
    return {"auth": "accounts", "register_demo": False, "warmup": False, **more}


def _populate(c: Any) -> dict[str, str]:
    """A public benchmark with two published submissions and a baseline; a project's evaluations."""
    hosted = host(c)
    for who in ("alice", "bob"):
        made = ok(submit(c, hosted.headers(who), golden_bytes("result.pkl")), 201)
        body = {"method": f"{who}-net"}
        ok(c.post(f"/v1/benchmarks/bench/submissions/{made['id']}/publish", json=body, headers=hosted.headers(who)))
    assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
    ok(c.post("/v1/admin/projects", json={"name": "vision"}, headers=ADMIN), 201)
    ok(c.post("/v1/admin/members", json={"user": "alice", "project": "vision"}, headers=ADMIN), 201)
    return hosted.tokens


def _upload(c: Any, tokens: dict[str, str], epoch: int) -> str:
    fields = {"model": "m", "epoch": str(epoch), "project": "vision"}
    headers = {"Authorization": f"Bearer {tokens['alice']}"}
    r = upload(c, golden_bytes("result.pkl"), gt="small", fields=fields, headers=headers, params={"wait": "0"})
    assert r.status_code in (201, 202), r.text
    return str(r.json()["id"])  # the evaluation's, which is its job's


def _idle(c: Any) -> None:
    deadline = time.monotonic() + 300
    while any(ok(c.get(f"/v1/admin/jobs?state={s}", headers=ADMIN))["items"] for s in ("queued", "running")):
        assert time.monotonic() < deadline
        time.sleep(0.1)


def _answers(c: Any, tokens: dict[str, str]) -> dict[str, Any]:
    out = {}
    for who, path in [
        ("anyone", "/v1/benchmarks/bench/leaderboard"),
        ("alice", "/v1/benchmarks/bench/submissions"),
        ("bob", "/v1/benchmarks/bench/submissions"),
        ("alice", "/v1/evaluations?limit=100"),
        ("admin", "/v1/evaluations?limit=100"),
        ("admin", "/v1/ground-truths"),
        ("admin", "/v1/admin/users"),
    ]:
        headers = {} if who == "anyone" else {"Authorization": f"Bearer {tokens.get(who, ADMIN['Authorization'][7:])}"}
        out[f"{who} {path}"] = ok(c.get(path, headers=headers))
    return out


def _round_trip(tmp_path: Path, where: list[str], restored_where: list[str], **db: Any) -> None:
    data, copy_at_rush, copy_quiet = tmp_path / "data", tmp_path / "backup-rush", tmp_path / "backup-quiet"
    with app_client(data, **_settings(**db.get("original", {}))) as c:
        tokens = _populate(c)
        _idle(c)
        before = {e["id"] for e in _answers(c, tokens)["admin /v1/evaluations?limit=100"]["items"]}
        sent: list[str] = []
        failures: list[BaseException] = []

        def uploads() -> None:
            try:
                for epoch in range(8):
                    sent.append(_upload(c, tokens, epoch))
            except BaseException as e:  # noqa: BLE001 - reported below
                failures.append(e)

        rush = threading.Thread(target=uploads)
        rush.start()
        while len(sent) < 2 and rush.is_alive():
            time.sleep(0.01)
        assert main(["admin", *where, "backup", str(copy_at_rush)]) == 0  # while the uploads go on
        rush.join()
        assert not failures, failures
        _idle(c)
        after = _answers(c, tokens)
        assert main(["admin", *where, "backup", str(copy_quiet)]) == 0
        originals = {
            e["id"]: ok(c.get(f"/v1/evaluations/{e['id']}", headers=ADMIN))
            for e in after["admin /v1/evaluations?limit=100"]["items"]
        }
        assert set(sent) <= set(originals) and len(originals) == len(before) + 8

    manifest = json.loads((copy_at_rush / "manifest.json").read_text())
    assert ("kitti-eval.db" if not db else "database.dump") in manifest["files"]
    assert manifest["schema_revision"] == head() and manifest["backend"] == ("postgresql" if db else "sqlite")

    # the copy taken during the uploads: a moment of the service, its queued jobs finished after the restore
    assert main(["admin", *restored_where(tmp_path / "restored-rush"), "restore", str(copy_at_rush)]) == 0
    with app_client(tmp_path / "restored-rush", **_settings(**db.get("restored_rush", {}))) as c:
        _idle(c)
        got = _answers(c, tokens)
        for key in (
            "anyone /v1/benchmarks/bench/leaderboard",
            "alice /v1/benchmarks/bench/submissions",
            "bob /v1/benchmarks/bench/submissions",
            "admin /v1/ground-truths",
            "admin /v1/admin/users",
        ):
            assert got[key] == after[key], key  # nothing of these changed during the uploads
        restored = {e["id"]: e for e in got["admin /v1/evaluations?limit=100"]["items"]}
        assert before < set(restored) <= set(originals)  # every one before the copy, and some of the rush
        for eid in restored:  # each the same evaluation (those queued at the copy evaluated after the restore)
            full = ok(c.get(f"/v1/evaluations/{eid}", headers=ADMIN))
            assert full["ap"] == originals[eid]["ap"]
            same = ("labels", "project", "ground_truth", "predictions")
            assert {k: full["evaluation"][k] for k in same} == {k: originals[eid]["evaluation"][k] for k in same}

    # the copy taken at rest: every answer the same
    assert main(["admin", *restored_where(tmp_path / "restored-quiet"), "restore", str(copy_quiet)]) == 0
    with app_client(tmp_path / "restored-quiet", **_settings(**db.get("restored_quiet", {}))) as c:
        assert _answers(c, tokens) == after


def test_backup_during_uploads_and_restore_on_sqlite(tmp_path: Path) -> None:
    _round_trip(tmp_path, ["--data-dir", str(tmp_path / "data")], lambda d: ["--data-dir", str(d)])


def test_restore_refuses_a_folder_with_a_database_and_a_damaged_copy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "data"
    with app_client(data, **_settings()):
        pass
    assert main(["admin", "--data-dir", str(data), "backup", str(tmp_path / "b")]) == 0
    assert main(["admin", "--data-dir", str(data), "backup", str(tmp_path / "b")]) == 1  # not an empty folder
    assert "is not an empty folder" in capsys.readouterr().err
    assert main(["admin", "--data-dir", str(data), "restore", str(tmp_path / "b")]) == 1
    assert f"{data / 'kitti-eval.db'} exists: restore into a data folder without a database" in capsys.readouterr().err
    with open(tmp_path / "b" / "kitti-eval.db", "r+b") as f:
        f.seek(200)
        f.write(b"\x00" * 16)
    assert main(["admin", "--data-dir", str(tmp_path / "new"), "restore", str(tmp_path / "b")]) == 1
    assert "its sha256 differs" in capsys.readouterr().err
    assert not (tmp_path / "new" / "kitti-eval.db").exists()


@pytest.fixture(scope="module")
def postgres() -> Any:
    if NO_PG:
        pytest.skip(NO_PG)
    with PostgresCluster() as cluster:
        yield cluster


def test_backup_during_uploads_and_restore_on_postgresql(postgres: Any, tmp_path: Path) -> None:
    import psycopg

    base = postgres.url.rpartition("/")[0]
    with psycopg.connect(host="127.0.0.1", port=postgres.port, user="postgres", autocommit=True) as conn:
        for name in ("original", "restored_rush", "restored_quiet"):
            conn.execute(f"CREATE DATABASE {name}")
    db = {name: {"database_url": f"{base}/{name}"} for name in ("original", "restored_rush", "restored_quiet")}
    targets = {"restored-rush": f"{base}/restored_rush", "restored-quiet": f"{base}/restored_quiet"}
    _round_trip(
        tmp_path,
        ["--database-url", f"{base}/original", "--data-dir", str(tmp_path / "data")],
        lambda d: ["--database-url", targets[d.name], "--data-dir", str(d)],
        **db,
    )
