"""The "A class or a workshop: invitations" example (docs/service/benchmarks.md), run as written against a live
service in accounts mode (bash, curl and python3 needed): the benchmark's file, the host's commands up to the
invitation's link, then a participant's join over JSON, login and first submission."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from doc_examples import run_bash, take
from server_helpers import ADMIN, LiveServer

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl"),
]
_AFTER = "## A class or a workshop: invitations"
(FILE,) = take("docs/service/benchmarks.md", _AFTER, 1, lang="toml")
HOST_BLOCK, PARTICIPANT_BLOCK = take("docs/service/benchmarks.md", _AFTER, 2)


def test_the_invitation_example_runs_as_written(tmp_path: Path) -> None:
    (tmp_path / "workshop.toml").write_text(FILE.code)
    host, participant = HOST_BLOCK.code, PARTICIPANT_BLOCK.code
    assert "/srv/kitti-eval" in host and "http://127.0.0.1:8000" in host
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        script = f"export XDG_CONFIG_HOME={tmp_path / 'config'}\n" + (host + participant).replace(
            "/srv/kitti-eval", str(server.data_dir)
        ).replace("http://127.0.0.1:8000", server.url)
        proc = run_bash(script, tmp_path)
        assert f"{server.url}/join/" in proc.stdout
        listed = [line for line in proc.stdout.splitlines() if "\tworkshop\t" in line]
        assert len(listed) == 1 and listed[0].split("\t")[2:] == ["open", "left 39", listed[0].split("\t")[4], "ana"]
        with server.client() as c:
            mine = c.get("/v1/benchmarks/workshop/submissions/all", headers=ADMIN).json()
            items = mine["items"] if isinstance(mine, dict) else mine
            assert [s["participant"] for s in items] == ["ana"]
            users = {u["name"]: u["projects"] for u in c.get("/v1/admin/users", headers=ADMIN).json()["items"]}
            assert users == {"ana": ["workshop"]}
