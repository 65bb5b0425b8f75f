"""The accounts example of docs/service/accounts.md, run as written against a live service in accounts mode (bash
and curl needed): the admin commands on the server's machine, then the member's uploads with the tokens they made."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from doc_examples import run_bash, take
from server_accounts import bearer
from server_helpers import ADMIN, LiveServer

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl"),
]
SETUP, MEMBER = take("docs/service/accounts.md", "# Accounts, projects and sealed test sets", 2)


def test_the_accounts_example_runs_as_written(tmp_path: Path) -> None:
    setup, member = SETUP.code, MEMBER.code
    assert "/srv/kitti-eval" in setup and "http://127.0.0.1:8000" in member
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        script = setup.replace("/srv/kitti-eval", str(server.data_dir)) + member.replace(
            "http://127.0.0.1:8000", server.url
        )
        script += '\necho; echo "TOKEN=$TOKEN"\n'
        proc = run_bash(script, ROOT)
        token = proc.stdout.strip().splitlines()[-1].removeprefix("TOKEN=")
        assert token.startswith("kte_"), proc.stdout[-300:]
        with server.client() as c:
            listed = c.get("/v1/evaluations", params={"gt": "test-set"}, headers=bearer(token))
            assert listed.status_code == 200, (listed.text, proc.stdout)
            mine = listed.json()["items"]
            assert len(mine) == 1 and mine[0]["evaluation"]["project"] == "lidar-team"
            frames = c.get(f"/v1/evaluations/{mine[0]['id']}/frames", headers=bearer(token))
            assert frames.status_code == 403 and frames.json()["error"]["code"] == "sealed"
            audit = c.get("/v1/admin/audit", headers=ADMIN).json()["items"]
            assert {"project.add", "user.add", "member.add", "token.add", "ground_truth.add"} <= {
                r["action"] for r in audit if r["actor"].startswith("cli:")
            }
    assert "alice\tmember\tlidar-team" in proc.stdout
