"""The "Hosting a benchmark" example (docs/service/benchmarks.md), run as written against a live service in accounts
mode (bash, curl and python3 needed): the admin's commands, then the participant's validate, submit and publish."""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import pytest
from doc_examples import run_bash, take
from server_helpers import ADMIN, LiveServer

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl"),
]
ADMIN_BLOCK, PARTICIPANT_BLOCK = take("docs/service/benchmarks.md", "then registers the test set sealed", 2)


def test_the_benchmark_example_runs_as_written(tmp_path: Path) -> None:
    admin, participant = ADMIN_BLOCK.code, PARTICIPANT_BLOCK.code
    assert "/srv/kitti-eval" in admin and "http://127.0.0.1:8000" in participant
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        script = admin.replace("/srv/kitti-eval", str(server.data_dir)) + participant.replace(
            "http://127.0.0.1:8000", server.url
        )
        proc = run_bash(script, tmp_path)
        assert "valid: 200 frames" in proc.stdout  # kitti-eval validate --benchmark
        rows = list(csv.reader(io.StringIO(proc.stdout[proc.stdout.index("rank,method") :])))
        assert rows[1][:5] == ["1", "My detector", "alice", "", "My lab"], proc.stdout  # no team
        with server.client() as c:
            board = c.get("/v1/benchmarks/kitti-3d/leaderboard").json()
            assert [e["method"] for e in board["entries"]] == ["My detector"]
            assert float(rows[1][7]) == board["entries"][0]["key"] > 0
            page = c.get("/benchmarks/kitti-3d")
            assert page.status_code == 200 and "My detector" in page.text and "<strong>Car 3D AP</strong>" in page.text
            actions = {r["action"] for r in c.get("/v1/admin/audit", headers=ADMIN).json()["items"]}
            assert {"benchmark.add", "ground_truth.add", "submission.add"} <= actions
