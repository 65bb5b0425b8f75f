"""Make the databases of the previous release that tests/server/store/test_migrations.py upgrades.

Run with the previous release's code first on the path (its packages and its tests/helpers), not this
checkout's: the point is a database that code wrote. From a copy of the release's tree (``git archive``)::

    git archive 52ef4fa | tar -x -C /tmp/prev && ln -s server /tmp/prev/kitti_eval_server
    FIXTURES=$CHECKOUT/tests/server/store/previous_release
    cd /tmp && PYTHONPATH=/tmp/prev:/tmp/prev/tests/helpers python $FIXTURES/make.py $FIXTURES

It writes ``sqlite.db.gz`` (the SQLite file) and ``postgresql.sql.gz`` (``pg_dump --inserts`` of the same
records made on a throwaway PostgreSQL cluster), and beside each what that release answered for them
(``*.expected.json``: the boards, the submissions, the evaluations, the users, as each caller saw them), which
the upgraded database must answer the same.
"""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from server_benchmarks import host, ok, submit
from server_helpers import ADMIN, app_client, golden_bytes, register, upload


def records(database_url: str | None, data_dir: Path) -> dict[str, Any]:
    """Accounts, a sealed test set and its public benchmark with two participants' published submissions and an
    admin's baseline, a shared ground truth with evaluations; what each caller is shown of them."""
    settings: dict[str, Any] = {"auth": "accounts", "register_demo": False, "warmup": False}
    if database_url:
        settings["database_url"] = database_url
    with app_client(data_dir, **settings) as c:
        hosted = host(c)
        alice, bob, root = (hosted.headers(u) for u in ("alice", "bob", "root"))
        for who, headers in (("alice", alice), ("bob", bob)):
            made = ok(submit(c, headers, golden_bytes("result.pkl")), 201)
            body = {"method": f"{who}-net", "description": f"{who}'s method"}
            ok(c.post(f"/v1/benchmarks/bench/submissions/{made['id']}/publish", json=body, headers=headers))
        base = ok(submit(c, root, golden_bytes("result.pkl")), 201)
        ok(c.post(f"/v1/benchmarks/bench/submissions/{base['id']}/publish", json={"method": "baseline"}, headers=root))
        ok(submit(c, alice, golden_bytes("result.pkl")), 201)  # kept private
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        ok(c.post("/v1/admin/projects", json={"name": "vision"}, headers=ADMIN), 201)
        ok(c.post("/v1/admin/members", json={"user": "alice", "project": "vision"}, headers=ADMIN), 201)
        for epoch in ("1", "2"):
            fields = {"model": "m", "epoch": epoch, "project": "vision"}
            r = upload(c, golden_bytes("result.pkl"), gt="small", fields=fields, headers=alice)
            assert r.status_code == 201, r.text
        deadline = time.monotonic() + 300
        while (
            ok(c.get("/v1/admin/jobs?state=queued", headers=ADMIN))["items"]
            or ok(c.get("/v1/admin/jobs?state=running", headers=ADMIN))["items"]
        ):
            assert time.monotonic() < deadline
            time.sleep(0.2)
        return answers(c, hosted.tokens)


def answers(c: Any, tokens: dict[str, str]) -> dict[str, Any]:
    """What the service answers about the records (the test asks the upgraded database the same)."""
    out: dict[str, Any] = {"tokens": tokens, "admin": ADMIN["Authorization"].split()[-1], "asked": {}}
    asks = [
        ("anyone", "/v1/benchmarks/bench/leaderboard"),
        ("alice", "/v1/benchmarks/bench/submissions"),
        ("bob", "/v1/benchmarks/bench/submissions"),
        ("root", "/v1/benchmarks/bench/submissions"),
        ("admin", "/v1/evaluations"),
        ("alice", "/v1/evaluations"),
        ("admin", "/v1/ground-truths"),
        ("admin", "/v1/admin/users"),
        ("admin", "/v1/benchmarks"),
    ]
    for who, path in asks:
        headers = {} if who == "anyone" else {"Authorization": f"Bearer {tokens.get(who, out['admin'])}"}
        r = c.get(path, headers=headers)
        assert r.status_code == 200, (path, r.text)
        out["asked"][f"{who} {path}"] = r.json()
    return out


def main(out: Path) -> None:
    import kitti_eval_server

    assert "site-packages" not in kitti_eval_server.__file__, "run with the previous release's code on the path"
    work = Path(tempfile.mkdtemp(prefix="previous-release-"))
    try:
        expected = records(None, work / "sqlite")
        with open(work / "sqlite" / "kitti-eval.db", "rb") as f, gzip.open(out / "sqlite.db.gz", "wb", 9) as g:
            shutil.copyfileobj(f, g)
        (out / "sqlite.expected.json").write_text(json.dumps(expected, indent=1, sort_keys=True) + "\n")

        from server_postgres import PostgresCluster

        with PostgresCluster() as pg:
            expected = records(pg.url, work / "postgresql")
            dump = subprocess.run(
                [
                    str(pg.bindir / "pg_dump"),
                    "--inserts",
                    "--no-owner",
                    "--no-privileges",
                    "-h",
                    "127.0.0.1",
                    "-p",
                    str(pg.port),
                    "-U",
                    "postgres",
                    "postgres",
                ],
                capture_output=True,
                check=True,
            ).stdout
        with gzip.open(out / "postgresql.sql.gz", "wb", 9) as g:
            g.write(dump)
        (out / "postgresql.expected.json").write_text(json.dumps(expected, indent=1, sort_keys=True) + "\n")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
