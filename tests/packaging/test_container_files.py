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
