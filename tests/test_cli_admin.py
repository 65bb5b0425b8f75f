"""``kitti-eval admin`` on the server's machine: what it writes is what the service then enforces."""

from __future__ import annotations

import subprocess
import sys

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
        code = main(["admin", *argv])
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


def test_without_the_server_extra_a_clear_error() -> None:
    code = (
        "import sys; sys.modules['kitti_eval_server'] = None\n"  # as if the package were not installed
        "from kitti_eval.cli import main\n"
        "sys.exit(main(['admin', 'user', 'list']))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "server extra" in proc.stderr and "Traceback" not in proc.stderr
