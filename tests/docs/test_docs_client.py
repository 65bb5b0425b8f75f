"""The client's examples, run as written against a live service in accounts mode: the participants page's
``kitti-eval login`` and ``submit`` and its Python example (docs/service/participants.md), and the CI recipes
of docs/cli/gates.md (GitHub Actions and GitLab CI): main's result recorded, a pull request gated against it,
the summary written; a pull request whose predictions lost a class fails the gate."""

from __future__ import annotations

import gzip
import os
import pickle
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
from doc_examples import Example, run_bash, take
from server_helpers import ADMIN, LiveServer

from kitti_eval.demo import demo_paths

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash"),
]
ADMIN_BLOCK = take("docs/service/benchmarks.md", "then registers the test set sealed")[0]
LOGIN_AND_SUBMIT = take("docs/service/participants.md", "## The client")[0]
PYTHON_CLIENT = take("docs/service/participants.md", "The same from Python", lang="python")[0]
GITHUB_RECIPE = take("docs/cli/gates.md", "A GitHub Actions workflow", lang="yaml")[0]
GITLAB_RECIPE = take("docs/cli/gates.md", "The same as GitLab CI jobs", lang="yaml")[0]
_DOCS_URL = "http://127.0.0.1:8000"
_CI_URL = "https://kitti-eval.example.org"


def _ok(response: Any, status: int = 200) -> Any:
    assert response.status_code == status, response.text[:2000]
    return response.json()


def test_the_participants_client_examples_run_as_written(tmp_path: Path) -> None:
    with LiveServer(tmp_path / "data", auth="accounts") as server:
        setup = ADMIN_BLOCK.code.replace("/srv/kitti-eval", str(server.data_dir))
        client = LOGIN_AND_SUBMIT.code.replace(_DOCS_URL, server.url)
        # the saved token goes to a config folder of the test's (platformdirs reads XDG_CONFIG_HOME)
        config = tmp_path / "config"
        script = f'export XDG_CONFIG_HOME={config}\n{setup}\n{client}\necho "TOKEN=$TOKEN"\n'
        proc = run_bash(script, tmp_path)
        assert "submission " in proc.stdout and ": scored, on the whole test set" in proc.stdout, proc.stdout
        key_line = next(line for line in proc.stdout.splitlines() if line.startswith("key "))
        assert float(key_line.split()[1]) > 0
        assert (config / "kitti-eval" / "services.json").is_file()
        token = proc.stdout.rsplit("TOKEN=", 1)[1].strip()

        (tmp_path / "result.pkl").write_bytes(demo_paths()[1].read_bytes())
        env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
        env["KITTI_EVAL_TOKEN"] = token
        env["KITTI_EVAL_CONFIG_DIR"] = str(config / "python")  # the submissions' keys it saves
        code = PYTHON_CLIENT.code.replace(_DOCS_URL, server.url)
        run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        lines = run.stdout.splitlines()
        assert lines[0].startswith("scored ") and float(lines[0].split()[1]) == float(key_line.split()[1])
        assert lines[1] == "Quota(submissions=3, days=1.0, used=2, left=1, next_at=None)"
        with server.client() as c:
            mine = _ok(c.get("/v1/benchmarks/kitti-3d/submissions", headers={"Authorization": f"Bearer {token}"}))
        assert mine["quota"]["used"] == 2 and len(mine["items"]) == 2


# ------------------------------------------------------------------------------------------ CI recipes


def _yaml_block(recipe: Example, first_line: str) -> dict[str, Any]:
    yaml = pytest.importorskip("yaml")
    assert recipe.code.startswith(first_line + "\n"), f"{recipe} no longer starts {first_line!r}"
    return dict(yaml.safe_load(recipe.code))


def _ci_service(tmp_path: Path) -> tuple[LiveServer, str, str]:
    """A live service in accounts mode: a CI account in the project ``detector``, the demo ground truth
    registered in that project as ``kitti-val``; the account's token that may write, and a read-only one."""
    server = LiveServer(tmp_path / "data", auth="accounts").start()
    with server.client() as c:
        _ok(c.post("/v1/admin/users", json={"name": "ci"}, headers=ADMIN), 201)
        _ok(c.post("/v1/admin/projects", json={"name": "detector"}, headers=ADMIN), 201)
        _ok(c.post("/v1/admin/members", json={"user": "ci", "project": "detector"}, headers=ADMIN), 201)
        token = _ok(c.post("/v1/admin/tokens", json={"user": "ci"}, headers=ADMIN), 201)["token"]
        body = {"user": "ci", "read_only": True}
        reader = _ok(c.post("/v1/admin/tokens", json=body, headers=ADMIN), 201)["token"]
        files = {"file": ("kitti_infos_val.pkl.gz", demo_paths()[0].read_bytes())}
        data = {"name": "kitti-val", "project": "detector"}
        _ok(c.post("/v1/ground-truths", data=data, files=files, headers=ADMIN), 201)
    return server, token, reader


def _without_pedestrians(path: Path) -> None:
    """The demo predictions with every Pedestrian box left out (a model that lost a class)."""
    results = pickle.loads(gzip.decompress(demo_paths()[1].read_bytes()))  # trusted: the package's demo
    for frame in results:
        keep = frame["name"] != "Pedestrian"
        for field, value in list(frame.items()):
            if hasattr(value, "shape") and value.shape[:1] == keep.shape:
                frame[field] = value[keep]
    path.write_bytes(pickle.dumps(results))


def _run(script: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    full = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    full["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{full.get('PATH', '')}"
    full.update(env)
    return subprocess.run(
        ["bash", "-c", "set -eo pipefail\n" + script], cwd=cwd, env=full, capture_output=True, text=True, timeout=300
    )


def _worse(script: str, pred: Path) -> str:
    demo = 'PRED="$(kitti-eval demo --where | sed -n 2p)"'
    assert demo in script
    return script.replace(demo, f'PRED="{pred}"')


def test_the_github_actions_recipe_records_main_and_gates_a_pull_request(tmp_path: Path) -> None:
    workflow = _yaml_block(GITHUB_RECIPE, "name: kitti-gate-service")
    job = workflow["jobs"]["gate"]
    steps = {step.get("name"): step for step in job["steps"]}
    assert 'pip install "kitti-eval[client]' in steps["Install the client"]["run"]
    record, gate = steps["Record main's result"]["run"], steps["Gate against main on the service"]["run"]
    # the main branch's step records with the token that may write, the pull request's gates with a read-only one
    assert steps["Record main's result"]["env"]["KITTI_EVAL_TOKEN"] == "${{ secrets.KITTI_EVAL_TOKEN }}"
    assert (
        steps["Gate against main on the service"]["env"]["KITTI_EVAL_TOKEN"] == "${{ secrets.KITTI_EVAL_GATE_TOKEN }}"
    )
    server, token, reader = _ci_service(tmp_path)
    try:
        assert job["env"]["KITTI_EVAL_SERVICE"] == _CI_URL
        base = {"KITTI_EVAL_SERVICE": server.url, "KITTI_EVAL_TOKEN": token, "GITHUB_SHA": "0123abc"}
        summary = tmp_path / "summary-main.md"
        main = _run(record, tmp_path, {**base, "GITHUB_STEP_SUMMARY": str(summary)})
        assert main.returncode == 0, main.stderr
        assert "| Car | 3d | 0.70 |" in summary.read_text()  # the AP table, as --format markdown writes it

        summary = tmp_path / "summary-pr.md"
        base["KITTI_EVAL_TOKEN"] = reader
        pr = _run(gate, tmp_path, {**base, "GITHUB_STEP_SUMMARY": str(summary), "GITHUB_HEAD_REF": "feature"})
        assert pr.returncode == 0, pr.stdout + pr.stderr
        assert "gate: PASSED" in pr.stdout and "passed" in summary.read_text()
        assert "not stored: the token is read-only" in pr.stderr
        assert ET.parse(tmp_path / "gate.xml").getroot().get("failures") == "0"

        worse = tmp_path / "worse.pkl"
        _without_pedestrians(worse)
        summary = tmp_path / "summary-worse.md"
        failed = _run(
            _worse(gate, worse), tmp_path, {**base, "GITHUB_STEP_SUMMARY": str(summary), "GITHUB_HEAD_REF": "lost"}
        )
        assert failed.returncode == 3, failed.stdout + failed.stderr
        assert "gate: FAILED" in failed.stdout
        assert "| ❌ | `Pedestrian/3d/moderate/R40/strict drop <= 0.5` |" in summary.read_text()
        with server.client() as c:
            history = _ok(c.get("/v1/evaluations", headers={"Authorization": f"Bearer {token}"}))["items"]
        assert [e["evaluation"]["labels"]["branch"] for e in history] == ["main"]  # the gates stored nothing
    finally:
        server.stop()


def test_the_gitlab_ci_recipe_records_main_and_gates_a_merge_request(tmp_path: Path) -> None:
    pipeline = _yaml_block(GITLAB_RECIPE, "variables:")
    common = pipeline[".kitti-eval"]["before_script"]
    assert common[0].startswith("pip install")

    def job(name: str) -> str:
        return "\n".join([*common[1:], *pipeline[name]["script"]])

    server, token, reader = _ci_service(tmp_path)
    try:
        assert pipeline["variables"]["KITTI_EVAL_SERVICE"] == _CI_URL
        base = {"KITTI_EVAL_SERVICE": server.url, "KITTI_EVAL_TOKEN": token, "CI_COMMIT_SHA": "0123abc"}
        base["KITTI_EVAL_GATE_TOKEN"] = reader  # the merge request's gate reads it
        main = _run(job("kitti-record-main"), tmp_path, {**base, "CI_COMMIT_REF_NAME": "main"})
        assert main.returncode == 0, main.stderr
        assert "Car" in (tmp_path / "result.md").read_text()
        mr = _run(job("kitti-gate"), tmp_path, {**base, "CI_COMMIT_REF_NAME": "feature"})
        assert mr.returncode == 0, mr.stdout + mr.stderr
        assert "passed" in (tmp_path / "gate.md").read_text()
        assert ET.parse(tmp_path / "gate.xml").getroot().get("failures") == "0"
        assert pipeline["kitti-gate"]["artifacts"]["reports"]["junit"] == "gate.xml"
        assert "not stored: the token is read-only" in mr.stderr
        with server.client() as c:
            history = _ok(c.get("/v1/evaluations", headers={"Authorization": f"Bearer {token}"}))["items"]
        assert [e["evaluation"]["labels"]["branch"] for e in history] == ["main"]
    finally:
        server.stop()
