"""The container's files without Docker: the smoke script's upload and checks against the real service, its
failure exit, and compose.yaml's wiring of the service to PostgreSQL."""

from __future__ import annotations

import importlib.util
import json
import stat
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from kitti_eval.cli import main as cli_main
from kitti_eval.demo import demo_paths

ROOT = Path(__file__).resolve().parents[2]


def _smoke() -> ModuleType:
    spec = importlib.util.spec_from_file_location("container_smoke", ROOT / "scripts" / "container_smoke.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


smoke = _smoke()


def test_the_smoke_upload_is_taken_and_its_numbers_are_the_demos(client: Any, tmp_path: Path) -> None:
    body, content_type = smoke.multipart({"gt": "demo", "model": "container-smoke"}, {"predictions": demo_paths()[1]})
    response = client.post("/v1/evaluations", content=body, headers={"Content-Type": content_type})
    assert response.status_code == 201, response.text
    uploaded = response.json()
    assert uploaded["evaluation"]["labels"]["model"] == "container-smoke"
    out = tmp_path / "demo.json"
    assert cli_main(["demo", "--format", "json", "--quiet", "--output", str(out)]) == 0
    demo = json.loads(out.read_text())
    assert demo["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] == pytest.approx(60.33954716517563, abs=1e-9)
    smoke.same_numbers(uploaded, demo, "the upload's numbers are the demo's")  # does not raise
    demo["num_det"]["Car"] += 1
    with pytest.raises(smoke.SmokeFailure, match="these differ: num_det"):
        smoke.same_numbers(uploaded, demo, "a changed count is noticed")


def test_the_smoke_script_fails_when_docker_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    fake = tmp_path / "docker"
    fake.write_text("#!/bin/sh\necho 'no such image' >&2\nexit 1\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert smoke.main(["--no-build", "--image", "missing:tag"]) == 1
    out = capsys.readouterr().out
    assert out.startswith("FAIL  docker image inspect") and "no such image" in out
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert smoke.main(["--no-build"]) == 2
    assert capsys.readouterr().out == "FAIL  no docker command\n"


def test_compose_runs_the_service_on_a_healthy_postgresql() -> None:
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((ROOT / "compose.yaml").read_text())
    db, service = compose["services"]["db"], compose["services"]["kitti-eval"]
    assert db["image"] == "postgres:16"
    assert db["healthcheck"]["test"][:2] == ["CMD", "pg_isready"]
    assert service["depends_on"] == {"db": {"condition": "service_healthy"}}
    assert "http://127.0.0.1:8000/readyz" in service["healthcheck"]["test"][-1]
    assert service["build"] == "."
    assert service["ports"] == ["127.0.0.1:${KITTI_EVAL_PORT:-8000}:8000"]  # published on the loopback only
    env = dict(item.split("=", 1) if "=" in item else (item, None) for item in service["environment"])
    user, db_name = db["environment"]["POSTGRES_USER"], db["environment"]["POSTGRES_DB"]
    assert env["KITTI_EVAL_DATABASE_URL"].startswith(f"postgresql://{user}:${{POSTGRES_PASSWORD")
    assert env["KITTI_EVAL_DATABASE_URL"].endswith(f"@db:5432/{db_name}")
    assert env["KITTI_EVAL_ADMIN_TOKEN"] is None  # passed on from the shell, never a default in the file
    named = {volume.split(":")[0] for s in (db, service) for volume in s["volumes"]}
    assert named == set(compose["volumes"]) == {"pgdata", "kitti-eval-data"}
    assert [v.split(":")[1] for v in service["volumes"]] == ["/data"]  # the image's VOLUME


def test_the_cpus_are_those_of_the_containers_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``docker run --cpus``, a Kubernetes CPU limit: a quota of the cgroup, not fewer CPUs to run on. The
    worker processes of ``kitti-eval serve`` (one a CPU) and the matching threads follow it, rounded up."""
    from kitti_eval.core import matching

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("150000 100000\n")
    assert matching.cgroup_cpu_quota(str(v2)) == 1.5
    (v2 / "cpu.max").write_text("max 100000\n")
    assert matching.cgroup_cpu_quota(str(v2)) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert matching.cgroup_cpu_quota(str(v1)) == 3.0
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert matching.cgroup_cpu_quota(str(v1)) is None
    assert matching.cgroup_cpu_quota(str(tmp_path / "none")) is None

    monkeypatch.setattr(matching.os, "sched_getaffinity", lambda pid: set(range(8)))
    for quota, cpus in [(None, 8), (1.5, 2), (0.25, 1), (3.0, 3), (16.0, 8)]:
        monkeypatch.setattr(matching, "cgroup_cpu_quota", lambda quota=quota: quota)
        assert matching.available_cpus() == cpus, quota


def test_serve_leaves_the_access_log_and_the_forwarded_headers_to_the_service(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One log line a request (the service's), and X-Forwarded-For believed only as KITTI_EVAL_TRUSTED_PROXIES
    says: uvicorn's own access log and proxy headers (which trust 127.0.0.1 by default) are off."""
    uvicorn = pytest.importorskip("uvicorn")
    from kitti_eval_server import main as server_main

    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: calls.append(kw))
    monkeypatch.delenv("KITTI_EVAL_WORKER_PROCESSES", raising=False)
    monkeypatch.delenv("KITTI_EVAL_JOB_THREADS", raising=False)
    assert server_main.serve(["--data-dir", str(tmp_path), "--host", "0.0.0.0"]) == 0
    (kw,) = calls
    assert kw["access_log"] is False and kw["proxy_headers"] is False and kw["host"] == "0.0.0.0"
