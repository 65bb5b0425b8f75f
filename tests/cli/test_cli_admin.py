"""``kitti-eval admin`` on the server's machine: what it writes is what the service then enforces."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from server_accounts import bearer
from server_helpers import ADMIN, GOLDEN, ROOT, app_client, assert_error, golden_bytes, upload

from kitti_eval.cli import main


@pytest.fixture
def admin(tmp_path, monkeypatch, capsys):
    """Runs ``kitti-eval admin ...`` against the data folder ``tmp_path/data``: (exit code, stdout, stderr)."""
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(["admin", "--create", *argv])  # the first command makes the database
        out, err = capsys.readouterr()
        return code, out, err

    return run


def test_what_the_cli_creates_the_service_enforces(admin, tmp_path) -> None:
    assert admin("project", "add", "team-a")[0] == 0
    assert admin("project", "add", "team-b")[0] == 0
    assert admin("user", "add", "alice")[0] == 0
    assert admin("user", "add", "bob")[0] == 0
    assert admin("member", "add", "alice", "team-a")[0] == 0
    assert admin("member", "add", "bob", "team-b")[0] == 0
    code, out, _ = admin("token", "add", "alice")
    assert code == 0
    alice = out.splitlines()[-1]  # the token is the last line
    assert alice.startswith("kte_") and len(alice) > 60
    bob = admin("token", "add", "bob", "--read-only", "--expires-days", "2")[1].splitlines()[-1]
    code, out, _ = admin("ground-truth", "add", "sealed-a", str(GOLDEN / "kitti_infos_val.pkl"), "--project", "team-a")
    assert code == 0 and "50 frames" in out
    code, out, _ = admin(
        "ground-truth", "add", "test-a", str(GOLDEN / "kitti_infos_val.pkl"), "--project", "team-a", "--sealed"
    )
    assert code == 0 and "sealed" in out
    code, out, _ = admin("user", "list")
    assert out.splitlines() == ["alice\tmember\tteam-a", "bob\tmember\tteam-b"]

    with app_client(tmp_path / "data", auth="accounts") as c:
        gts = {g["name"]: g for g in c.get("/v1/ground-truths", headers=bearer(alice)).json()["items"]}
        assert gts["test-a"]["sealed"] is True and gts["test-a"]["project"] == "team-a"
        assert gts["sealed-a"]["sealed"] is False
        assert {g["name"] for g in c.get("/v1/ground-truths", headers=bearer(bob)).json()["items"]} == {"demo"}
        c.headers.update(bearer(alice))
        r = upload(c, golden_bytes("result.pkl"), gt="test-a")
        del c.headers["Authorization"]
        assert r.status_code == 201, r.text
        assert_error(c.get(f"/v1/evaluations/{r.json()['id']}/frames", headers=bearer(alice)), 403, "sealed")
        assert_error(c.get(f"/v1/evaluations/{r.json()['id']}", headers=bearer(bob)), 404)
        c.headers.update(bearer(bob))
        assert_error(upload(c, golden_bytes("result.pkl"), gt="demo"), 403, "read-only")
        del c.headers["Authorization"]

        token_id = alice.split("_")[1]
        code, out, _ = admin("token", "revoke", token_id)  # the CLI, on the running service's database
        assert code == 0
        assert_error(c.get("/v1/evaluations", headers=bearer(alice)), 401)
        audit = c.get("/v1/admin/audit", params={"limit": 100}, headers=ADMIN).json()["items"]
        mine = [(r["action"], r["target"]) for r in audit if r["actor"].startswith("cli:")]
        assert ("token.revoke", f"alice ({token_id})") in mine and ("ground_truth.add", "test-a") in mine
        assert ("user.add", "alice") in mine and ("member.add", "bob -> team-b") in mine


def test_exit_codes(admin) -> None:
    assert admin("user", "add", "alice", "--admin")[0] == 0
    code, _, err = admin("user", "add", "alice")
    assert code == 1 and "exists" in err
    code, _, err = admin("user", "add", "../bad")
    assert code == 1 and "not valid" in err
    code, _, err = admin("member", "add", "alice", "no-project")
    assert code == 1 and "no project named 'no-project'" in err
    code, _, err = admin("token", "add", "nobody")
    assert code == 1 and "no user named 'nobody'" in err
    code, _, err = admin("token", "add", "alice", "--expires-days", "-1")
    assert code == 1 and "days" in err
    code, _, err = admin("token", "revoke", "0123456789abcdef")
    assert code == 1 and "no token" in err
    code, _, err = admin("ground-truth", "add", "x", "/no/such/file.pkl")
    assert code == 1 and "No such file" in err
    assert admin("user", "frobnicate")[0] == 2
    assert admin("token", "add")[0] == 2
    assert admin()[0] == 2


def test_a_missing_database_is_refused_unless_created(tmp_path, monkeypatch, capsys) -> None:
    """Without the service's data folder in the settings, the command used to make an empty database under the
    user's data folder and say `user frank`; the service then refused frank's tokens. Now every run names its
    database, and a missing one is an error until --create."""
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))
    db = tmp_path / "data" / "kitti-eval.db"
    assert main(["admin", "user", "add", "frank"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and not db.exists() and not (tmp_path / "data").exists()
    assert err.splitlines() == [
        f"kitti-eval admin: database {db}",
        f"kitti-eval admin: error: no kitti-eval database at {db}: give the service's settings (KITTI_EVAL_DATA_DIR "
        "or --data-dir, KITTI_EVAL_DATABASE_URL or --database-url), or --create to make a new one there",
    ]
    assert main(["admin", "--create", "user", "add", "frank"]) == 0
    out, err = capsys.readouterr()
    assert out == "user frank\n" and err == f"kitti-eval admin: database {db}\n" and db.is_file()
    assert main(["admin", "user", "list"]) == 0  # there now: no --create needed
    assert capsys.readouterr().out == "frank\tmember\t-\n"
    other = tmp_path / "elsewhere"
    assert main(["admin", "--data-dir", str(other), "user", "list"]) == 1
    assert f"no kitti-eval database at {other / 'kitti-eval.db'}" in capsys.readouterr().err


def test_the_database_is_named_without_its_password() -> None:
    from kitti_eval_server.settings import Settings

    named = Settings(database_url="postgresql://kitti:s3cret@db.example:5432/kitti").database_name
    assert named == "postgresql+psycopg://kitti:***@db.example:5432/kitti"  # the driver the settings chose
    assert Settings(data_dir=Path("/srv/kitti-eval")).database_name == "/srv/kitti-eval/kitti-eval.db"


def test_without_the_server_extra_a_clear_error() -> None:
    code = (
        "import sys; sys.modules['kitti_eval_server'] = None\n"  # as if the package were not installed
        "from kitti_eval.cli import main\n"
        "sys.exit(main(['admin', 'user', 'list']))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "server extra" in proc.stderr and "Traceback" not in proc.stderr


def test_benchmarks_from_the_cli(admin, tmp_path) -> None:
    gt = str(GOLDEN / "kitti_infos_val.pkl")
    assert admin("ground-truth", "add", "open-set", gt)[0] == 0
    code, _, err = admin("benchmark", "add", "b0", "--ground-truth", "open-set")
    assert code == 1 and "not sealed" in err
    assert admin("ground-truth", "add", "test-set", gt, "--sealed")[0] == 0
    code, _, err = admin("benchmark", "add", "b1", "--ground-truth", "test-set", "--quota", "3")
    assert code == 0  # N alone: per day
    code, _, err = admin("benchmark", "add", "b2", "--ground-truth", "test-set", "--quota", "x/y")
    assert code == 1 and "N/DAYS" in err
    code, _, err = admin("benchmark", "add", "b2", "--ground-truth", "test-set", "--key", "Car/4d/moderate")
    assert code == 1 and "metric" in err
    code, _, err = admin("benchmark", "add", "b3", "--ground-truth", "test-set")
    assert code == 1 and "already the test set of benchmark 'b1'" in err and "--share-test-set" in err
    code, out, _ = admin(
        "benchmark",
        "add",
        "kitti-3d",
        "--ground-truth",
        "test-set",
        "--share-test-set",
        "--quota",
        "2/7",
        "--public",
        "--key",
        "Car/3d/moderate",
        "--key",
        "Car/bev/moderate",
        "--column",
        "Car/3d/easy",
        "--column",
        "Car/bev/moderate/R11",
    )
    assert code == 0 and "key Car/3d/moderate/R40/strict + Car/bev/moderate/R40/strict, quota 2 per 7 days" in out
    assert admin("user", "add", "alice")[0] == 0
    token = admin("token", "add", "alice")[1].splitlines()[-1]
    with app_client(tmp_path / "data", auth="accounts") as c:
        info = c.get("/v1/benchmarks/kitti-3d").json()  # public: no token
        assert info["quota"] == {"submissions": 2, "days": 7.0}
        assert info["columns"] == ["Car/3d/easy/R40/strict", "Car/bev/moderate/R11/strict"]
        files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
        made = c.post("/v1/benchmarks/kitti-3d/submissions", files=files, headers=bearer(token)).json()
        published = c.post(
            f"/v1/benchmarks/kitti-3d/submissions/{made['id']}/publish", json={"method": "=cmd"}, headers=bearer(token)
        )
        assert published.status_code == 200
        scores = made["scores"]
    code, out, _ = admin("benchmark", "export", "kitti-3d")
    header, row = out.splitlines()
    assert header.startswith("rank,method,participant,team,affiliation,link,date,key (")
    cells = row.split(",")
    mean = round((scores["Car/3d/moderate/R40/strict"] + scores["Car/bev/moderate/R40/strict"]) / 2, 4)
    assert cells[:4] == ["1", "'=cmd", "alice", ""] and float(cells[7]) == mean  # no formula for a spreadsheet
    code, out, _ = admin("benchmark", "submissions", "kitti-3d")
    assert code == 0 and made["id"] in out and "published" in out
    assert admin("benchmark", "close", "kitti-3d")[1].startswith("benchmark kitti-3d: closed")
    assert admin("benchmark", "reopen", "kitti-3d")[1].startswith("benchmark kitti-3d: open")
    assert "1 submissions rescored, 0 failed" in admin("benchmark", "rescore", "kitti-3d")[1]
    assert admin("benchmark", "disqualify", "kitti-3d", made["id"])[0] == 0
    assert admin("benchmark", "export", "kitti-3d")[1].splitlines()[1:] == []
    assert "kitti-3d\ttest-set\topen\tpublic" in admin("benchmark", "list")[1]


def test_jobs_from_the_cli(admin, tmp_path) -> None:
    """``admin jobs list|cancel|rerun`` on the service's database: the same rules as the HTTP routes, audited as
    the command line's login."""
    with app_client(tmp_path / "data", ready=False, job_threads=0) as c:
        ids = [upload(c, golden_bytes("result.pkl"), params={"wait": "0"}).json()["id"] for _ in range(2)]
    code, out, err = admin("jobs", "list")
    assert code == 0 and [line.split("\t")[0] for line in out.splitlines()] == ids[::-1]
    assert out.splitlines()[0].split("\t")[1:5] == ["evaluation", "queued", "0/3", "anyone"]
    assert "2 queued" in err
    assert admin("jobs", "list", "--state", "running")[1] == ""
    code, out, _ = admin("jobs", "cancel", ids[0])
    assert code == 0 and out == f"job {ids[0]} cancelled\n"
    code, _, err = admin("jobs", "cancel", ids[0])
    assert code == 1 and "nothing to cancel" in err
    assert admin("jobs", "cancel", "nope")[0] == 1
    assert admin("jobs", "rerun", ids[1])[0] == 1  # queued: it runs without being told to
    code, out, _ = admin("jobs", "rerun", ids[0])
    assert code == 0 and out == f"job {ids[0]} queued again\n"
    assert admin("jobs", "list", "--state", "queued", "--limit", "1")[1].split("\t")[0] == ids[0]  # newest: at the end
    audit = [line.split("\t") for line in admin("audit")[1].splitlines()]
    assert [(a[1].startswith("cli:"), a[2], a[3]) for a in audit[:2]] == [
        (True, "job.rerun", ids[0]),
        (True, "job.cancel", ids[0]),
    ]


def test_a_refused_ground_truth_file_is_named(admin, tmp_path) -> None:
    """A file the library refuses is named in the one line that says why (the library's error, read once by
    :func:`kitti_eval.io.upload.read_upload`), whatever refuses it: the archive or what it holds."""
    import zipfile

    escaping = tmp_path / "labels.zip"
    with zipfile.ZipFile(escaping, "w") as zf:
        zf.writestr("../000000.txt", "Car 0 0 0 0 0 1 1 1 1 1 0 0 0 0\n")
    code, out, err = admin("ground-truth", "add", "gt", str(escaping))
    assert (code, out) == (1, "")
    assert (
        err.splitlines()[-1]
        == "kitti-eval admin: error: labels.zip: member '../000000.txt' points outside the archive ('..')"
    )
    broken = tmp_path / "infos.pkl"
    broken.write_bytes((GOLDEN / "kitti_infos_val.pkl").read_bytes()[:-100])
    code, _, err = admin("ground-truth", "add", "gt", str(broken))
    assert code == 1 and err.splitlines()[-1].startswith("kitti-eval admin: error: infos.pkl: ")
    assert admin("ground-truth", "add", "gt", str(GOLDEN / "kitti_infos_val.pkl"))[0] == 0  # the name is free
