"""The container's files without Docker: the smoke script's upload and checks against the real service, its
failure exit, and compose.yaml's wiring of the service to PostgreSQL."""

from __future__ import annotations

import importlib.util
import json
import re
import stat
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from doc_examples import take

from kitti_eval.cli import main as cli_main
from kitti_eval.demo import demo_paths

ROOT = Path(__file__).resolve().parents[2]

#: the docs' Kubernetes manifests (taken when the module is collected: the docs-examples test sees them run)
(KUBERNETES,) = take("docs/service/container.md", "## Kubernetes", lang="yaml")


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


def test_the_compose_check_says_what_to_do_without_compose_v2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """Docker without its compose plugin answers ``docker compose`` with "unknown command": the check fails with
    one line naming v2's package and v1's path (``--compose-command docker-compose``), not a compose traceback."""
    fake = tmp_path / "docker"
    fake.write_text('#!/bin/sh\necho "docker: unknown command: docker $1" >&2\nexit 1\n')
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert smoke.main(["--compose"]) == 1
    out = capsys.readouterr().out
    assert out.startswith("FAIL  docker compose is not there (docker: unknown command: docker compose)")
    assert "--compose-command docker-compose" in out and out.count("\n") == 1


def _compose() -> dict[str, Any]:
    yaml = pytest.importorskip("yaml")
    return dict(yaml.safe_load((ROOT / "compose.yaml").read_text()))


def test_compose_runs_the_service_and_its_workers_on_a_healthy_postgresql() -> None:
    compose = _compose()
    db, service, worker = (compose["services"][name] for name in ("db", "kitti-eval", "worker"))
    assert db["image"] == "postgres:16"
    assert db["healthcheck"]["test"][:2] == ["CMD", "pg_isready"]
    assert service["depends_on"] == {"db": {"condition": "service_healthy"}}
    assert worker["depends_on"]["db"] == {"condition": "service_healthy"}
    assert "http://127.0.0.1:8000/readyz" in service["healthcheck"]["test"][-1]
    # the image is built here, never pulled: the workers run the one the service builds
    assert service["build"] == "." and service["pull_policy"] == "build"
    assert worker["image"] == service["image"] and worker["pull_policy"] == "never" and "build" not in worker
    assert worker["command"] == ["kitti-eval", "worker"]
    assert "ports" not in worker and "deploy" not in worker  # `--scale worker=N` decides how many
    assert service["ports"] == ["127.0.0.1:${KITTI_EVAL_PORT:-8000}:8000"]  # published on the loopback only
    # the evaluations run in the workers only: the service is ready once one is seen on the database
    assert service["environment"]["KITTI_EVAL_WORKER_PROCESSES"] == "0"
    assert service["environment"]["KITTI_EVAL_JOB_THREADS"] == "0"
    user, db_name = db["environment"]["POSTGRES_USER"], db["environment"]["POSTGRES_DB"]
    for env in (service["environment"], worker["environment"]):
        # the password never inside the URL (any character works): libpq reads PGPASSWORD
        assert env["KITTI_EVAL_DATABASE_URL"] == f"postgresql://{user}@db:5432/{db_name}"
        assert env["PGPASSWORD"] == db["environment"]["POSTGRES_PASSWORD"] == "${POSTGRES_PASSWORD:-}"
    assert service["environment"]["KITTI_EVAL_ADMIN_TOKEN"] == "${KITTI_EVAL_ADMIN_TOKEN:-}"  # from .env, no default
    for s in (service, worker):
        assert s["read_only"] is True and s["tmpfs"] == ["/tmp"]
    named = {volume.split(":")[0] for s in (db, service) for volume in s["volumes"]}
    assert named == set(compose["volumes"]) == {"pgdata", "kitti-eval-data"}
    assert [v.split(":")[1] for v in service["volumes"]] == ["/data"]  # the image's VOLUME


def test_every_compose_service_has_a_healthcheck_and_stops_on_its_signal() -> None:
    """``docker compose up -d --wait`` exits 1 when a service has no healthcheck ("has no healthcheck
    configured"), even with everything up; the worker's says a worker process of its own is connected and
    polling (``kitti-eval worker --check``, tests/server/jobs/test_worker_check.py)."""
    services = _compose()["services"]
    for name, service in services.items():
        check = service.get("healthcheck", {})
        assert check.get("test") and not check.get("disable"), name
    assert services["worker"]["healthcheck"]["test"] == ["CMD", "kitti-eval", "worker", "--check"]
    # the service's processes are not PID 1: Docker's init hands SIGTERM on (the drain) and reaps
    for name in ("kitti-eval", "worker"):
        assert services[name]["init"] is True and services[name]["stop_signal"] == "SIGTERM", name
    assert services["db"]["stop_signal"] == "SIGINT"  # PostgreSQL's fast shutdown


def test_every_compose_command_works_without_a_variable_in_the_shell() -> None:
    """No ``${VAR:?...}``: compose interpolates the whole file for every command (ps, logs, down), so a required
    variable missing from the shell and .env would make each of them fail."""
    text = (ROOT / "compose.yaml").read_text()
    assert re.findall(r"\$\{\w+:?\?", text) == []
    assert re.findall(r"\$\{\w+\}", text) == []  # unset, compose would warn on every command
    assert "${POSTGRES_PASSWORD:-}" in text  # what the compose commands read from .env


def test_the_kubernetes_example_is_what_the_smoke_script_runs() -> None:
    """The manifests' security settings are the ones ``container_smoke.py --user UID:GID --read-only`` gives
    ``docker run``: the same uid and group, a read-only root with a writable /tmp, no capability, no privilege
    escalation; and every container runs the image as it is checked (its command, or the worker's)."""
    yaml = pytest.importorskip("yaml")
    documents = list(yaml.safe_load_all(KUBERNETES.code))
    deployments = [d for d in documents if d["kind"] == "Deployment"]
    assert {d["metadata"]["name"] for d in deployments} == {"kitti-eval-web", "kitti-eval-worker"}
    read_only = smoke.READ_ONLY
    for deployment in deployments:
        pod = deployment["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        uid, gid = pod["securityContext"]["runAsUser"], pod["securityContext"]["runAsGroup"]
        assert uid not in (0, 10001) and gid == 0  # another uid than the image's, of the root group (OpenShift)
        (container,) = pod["containers"]
        security = container["securityContext"]
        assert security["readOnlyRootFilesystem"] is True and "--read-only" in read_only
        assert security["capabilities"] == {"drop": ["ALL"]} and read_only[read_only.index("--cap-drop") + 1] == "ALL"
        assert security["allowPrivilegeEscalation"] is False
        assert read_only[read_only.index("--security-opt") + 1] == "no-new-privileges"
        mounts = {m["mountPath"]: m["name"] for m in container["volumeMounts"]}
        volumes = {v["name"]: v for v in pod["volumes"]}
        assert volumes[mounts["/tmp"]] == {"name": mounts["/tmp"], "emptyDir": {}}
        assert read_only[read_only.index("--tmpfs") + 1] == "/tmp"
        assert container["resources"]["limits"]["cpu"]  # sizes its worker processes
        env = {e["name"]: e.get("value") for e in container["env"]}
        assert env["KITTI_EVAL_DATABASE_URL"].startswith("postgresql://kitti@")  # the password from the Secret
        assert container.get("command") in (None, ["kitti-eval", "worker"])
    web = next(d for d in deployments if d["metadata"]["name"] == "kitti-eval-web")
    probes = web["spec"]["template"]["spec"]["containers"][0]
    assert probes["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert probes["livenessProbe"]["httpGet"]["path"] == "/healthz"
    smoke_doc = (ROOT / "docs" / "service" / "container.md").read_text()
    assert f"--user {web['spec']['template']['spec']['securityContext']['runAsUser']}:0 --read-only" in smoke_doc


def test_the_cpus_are_those_of_the_containers_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``docker run --cpus``, a Kubernetes CPU limit: a quota of the cgroup, not fewer CPUs to run on. The
    worker processes of ``kitti-eval serve`` (one a CPU) and the matching threads follow it, rounded up."""
    from kitti_eval.core import cpus as cpu_count

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("150000 100000\n")
    assert cpu_count.cgroup_cpu_quota(str(v2)) == 1.5
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cpu_count.cgroup_cpu_quota(str(v2)) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert cpu_count.cgroup_cpu_quota(str(v1)) == 3.0
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cpu_count.cgroup_cpu_quota(str(v1)) is None
    assert cpu_count.cgroup_cpu_quota(str(tmp_path / "none")) is None

    monkeypatch.setattr(cpu_count.os, "sched_getaffinity", lambda pid: set(range(8)))
    for quota, cpus in [(None, 8), (1.5, 2), (0.25, 1), (3.0, 3), (16.0, 8)]:
        monkeypatch.setattr(cpu_count, "cgroup_cpu_quota", lambda quota=quota: quota)
        assert cpu_count.available_cpus() == cpus, quota


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
