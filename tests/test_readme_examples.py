"""Shell examples of the README, run as written against a live service (bash and curl needed)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from server_helpers import LiveServer

ROOT = Path(__file__).resolve().parents[1]


def _block_after(text: str, marker: str) -> str:
    start = text.index(marker)
    block = re.search(r"```bash\n(.*?)```", text[start:], re.S)
    assert block, f"no bash block after {marker!r}"
    return block.group(1)


@pytest.mark.skipif(shutil.which("bash") is None or shutil.which("curl") is None, reason="needs bash and curl")
def test_the_gate_by_curl_example_runs_on_a_fresh_service(tmp_path: Path) -> None:
    script = _block_after((ROOT / "README.md").read_text(), "Gate a CI job with one request")
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
