"""Shell examples of the service's pages and the README, run as written against a live service (bash and curl
needed)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from doc_examples import take
from server_helpers import LiveServer, upload

from kitti_eval.demo import demo_paths

ROOT = Path(__file__).resolve().parents[2]
(GATE_BY_CURL,) = take("docs/service/index.md", "Gate a CI job with one request")


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl")
def test_the_gate_by_curl_example_runs_on_a_fresh_service(tmp_path: Path) -> None:
    script = GATE_BY_CURL.code
    server = LiveServer(tmp_path / "data").start()
    try:
        script = script.replace("http://127.0.0.1:8000", server.url).replace("python -c", f"{sys.executable} -c")
        proc = subprocess.run(
            ["bash", "-c", "set -euo pipefail\n" + script], cwd=ROOT, capture_output=True, text=True, timeout=300
        )
    finally:
        server.stop()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    verdict = json.loads(proc.stdout)
    assert verdict["passed"] is True and verdict["checks"], verdict


START = take("docs/service/index.md", "From the repository root, in another shell:")[0]
README_CURL = take("README.md", "evaluate the demo predictions against the bundled")[0]
JOB = take("docs/service/jobs.md", "# Evaluations as jobs")[0]


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl")
def test_the_first_requests_run_on_a_fresh_service(tmp_path: Path) -> None:
    """The service's first page and the README upload the demo, read the history, one evaluation and a
    comparison; the jobs page uploads without waiting and follows the job. ``<id>`` and ``<other-id>`` name two
    evaluations the test made first."""
    with LiveServer(tmp_path / "data") as server:
        with server.client() as c:
            ids = [upload(c, demo_paths()[1].read_bytes()).json()["id"] for _ in range(2)]

        def run(script: str) -> str:
            script = script.replace("http://127.0.0.1:8000", server.url).replace("python -c", f"{sys.executable} -c")
            script = script.replace("<other-id>", ids[1]).replace("<id>", ids[0])
            proc = subprocess.run(
                ["bash", "-c", "set -euo pipefail\n" + script], cwd=ROOT, capture_output=True, text=True, timeout=300
            )
            assert proc.returncode == 0, proc.stdout + proc.stderr
            return proc.stdout

        first = run(START.code)
        assert first.count('"schema_version":1') >= 2  # the upload and the evaluation read back by its id
        assert "Car AP_R40@0.70, 0.70, 0.70:" in first  # ?format=table
        assert "| `Car/3d/moderate/R40/strict` | " in first  # the comparison, as Markdown
        assert f'"id":"{ids[0]}"' in first  # the history lists the evaluations
        assert "Car AP_R40@0.70, 0.70, 0.70:" in run(README_CURL.code)
        job, _ = json.JSONDecoder().raw_decode(run(JOB.code))  # the job as the upload left it; then the evaluation
        assert job["state"] in ("queued", "running", "done"), job
        with server.client() as c:  # "queued, running, then done"
            deadline = time.monotonic() + 120
            while (state := c.get(f"/v1/jobs/{job['id']}").json())["state"] != "done" and time.monotonic() < deadline:
                time.sleep(0.2)
            assert state["state"] == "done" and state["result_location"], state
            assert c.get(f"/v1/evaluations/{job['id']}").json()["schema_version"] == 1
