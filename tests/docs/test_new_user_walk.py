"""A new user's first walk, with the docs' own commands in the order the docs give them: in a folder holding what
a clone of this repository holds, the README's quick start (the demo), then docs/service/benchmarks.md as an
admin hosting a benchmark would go through it: the service started as the page starts it (accounts mode, a new
data folder), the admin's commands, a participant's submission, a second participant's, and the leaderboard with
the two entries, printed as the page says it prints."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from doc_examples import ROOT, examples, run_bash, take
from server_helpers import READY_TIMEOUT_S, free_port

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        shutil.which("bash") is None or shutil.which("curl") is None or shutil.which("git") is None,
        reason="needs bash, curl and git",
    ),
]

PAGE = "docs/service/benchmarks.md"
(SERVE,) = take(PAGE, "the admin starts the service in accounts mode")
ADMIN_STEPS, PARTICIPANT, SECOND = take(PAGE, "then registers the test set sealed", 3)


def _printed() -> str:
    """The output the page shows for the second participant's block (the text block after it)."""
    after = [e for e in examples(PAGE) if e.line > SECOND.line]
    assert after and after[0].lang == "text"
    return after[0].code


def _clone(into: Path) -> Path:
    """The files a clone of this checkout holds (tracked, and new files not ignored), copied."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout.decode()
    for name in filter(None, listed.split("\0")):
        source = ROOT / name
        if source.is_file():
            (into / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, into / name)
    return into


def test_a_new_user_goes_from_a_clone_to_a_board_with_two_entries(tmp_path: Path) -> None:
    clone = _clone(tmp_path / "kitti-eval")
    data, port = tmp_path / "srv" / "kitti-eval", free_port()
    url = f"http://127.0.0.1:{port}"

    # the README's quick start, past the install (the tests run in this checkout's installation)
    quick = next(e for e in examples("README.md") if e.lang == "bash").code.splitlines()[0]
    assert quick.split("#")[0].strip() == 'pip install -e ".[test]" && kitti-eval demo'
    assert "Car AP_R40@0.70, 0.70, 0.70:" in run_bash("kitti-eval demo", clone).stdout

    def as_here(code: str) -> str:
        return code.replace("/srv/kitti-eval", str(data)).replace("http://127.0.0.1:8000", url)

    # the service, as the page starts it: the command itself, on a port of the test's own, from the admin's home
    # (python -m puts the working folder first on the worker processes' path: from the clone they would run its
    # sources, another kitti_eval than the installed one the test means, and compile its kernels afresh)
    serve = as_here(SERVE.code).split("#")[0].strip()
    assert serve.startswith("kitti-eval serve --auth accounts")
    env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        server = subprocess.Popen(
            ["bash", "-c", f"exec {serve} --port {port}"], cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT
        )
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            assert server.poll() is None, log.read_text()
            try:
                if httpx.get(f"{url}/readyz", timeout=5).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        assert f"auth accounts, database {data.resolve() / 'kitti-eval.db'}, " in log.read_text()

        # the admin's commands, the participant's, the second participant's: one shell, in the page's order
        walk = run_bash(as_here(ADMIN_STEPS.code + PARTICIPANT.code + SECOND.code), clone, timeout=600)
        board = httpx.get(f"{url}/v1/benchmarks/kitti-3d/leaderboard", timeout=30).json()
        unknown = httpx.get(f"{url}/v1/evaluations", timeout=30).status_code
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert "valid: 200 frames" in walk.stdout
    assert walk.stdout.endswith(_printed()), walk.stdout[-500:]  # the board, as the page prints it
    assert [(e["rank"], e["method"], e["participant"]) for e in board["entries"]] == [
        (1, "My detector", "alice"),
        (2, "Weaker detector", "bob"),
    ]
    assert unknown == 401  # accounts mode: nothing but the public board without a token
