#!/usr/bin/env python3
"""Build the service's Docker image and check that a container of it works as a service must.

    python scripts/container_smoke.py                     # build, start, check, clean up
    python scripts/container_smoke.py --no-build --image kitti-eval:latest
    python scripts/container_smoke.py --build-network host --network host   # Docker without a bridge
    python scripts/container_smoke.py --build-arg BASE=kitti-base:bookworm  # another base image
    python scripts/container_smoke.py --database-url postgresql://user:pw@host:5432/empty_db
    python scripts/container_smoke.py --user 12345:0 --read-only     # as a cluster runs it (see below)
    python scripts/container_smoke.py --user 12345:12345 --read-only --no-home   # any uid, no HOME
    python scripts/container_smoke.py --compose           # compose.yaml: up -d --wait exits 0, down is quick
    python scripts/container_smoke.py --compose --compose-command docker-compose --compose-file override.yaml

It starts a container on a fresh volume, waits for ``/readyz``, uploads the bundled demo predictions
against the ``demo`` ground truth and checks the numbers against ``kitti-eval demo --format json`` (run in
the container, and on this machine too when kitti-eval is installed here), restarts the container and
reads the evaluation back by its id, checks that the service does not run as root, runs ``kitti-eval
demo`` in the container, and waits for Docker to report the image's HEALTHCHECK healthy (the first probe
runs 30 s after the start). Every check is printed; the exit status is 0 only if all passed.

``--user UID:GID`` runs the container as another user (Kubernetes' ``runAsUser``, OpenShift's random uids, which
belong to the root group: ``/data`` is writable by it), and ``--read-only`` on a read-only root filesystem with
a tmpfs on ``/tmp`` (``readOnlyRootFilesystem``), with every capability dropped and no privilege escalation: the
security settings of the Kubernetes example (docs/service/container.md). Either way the service must start,
compile nothing (no warning about numba's cache in its log) and pass every check.

``--user UID:GID`` with a group other than root's first starts the image on a fresh volume the uid may not
write, which must exit 2 with one line naming the folder and the uid (no traceback), then gives the volume to the
uid as Kubernetes' ``fsGroup`` would (a one-off ``chown`` as root) and runs every check, the volume mounted
``:nocopy`` (while a named volume is empty, Docker copies the image's ``/data``, its owner too, onto it at every
mount, which would undo the ``chown``). ``--no-home`` starts
the service (and ``kitti-eval demo``) with no HOME in its environment (``env -u HOME``), as ``env -i`` and some
init systems do.

The log is checked too: the service's worker processes started, every line JSON (uvicorn's own too), one line a
request and none for the probes (``/healthz``, ``/readyz``, ``/metrics``), and no kernel compiled for want of a
cache.

``--compose`` checks compose.yaml instead: ``docker compose up -d --wait`` (the image built, PostgreSQL, the
service and a worker) exits 0 once every service is healthy, and ``docker compose down`` ends within 20 s, each
container within 10 s of its stop signal (Docker's events say when each was signalled and when it exited).
It needs Compose v2 (``docker compose``) and says so when it is missing; ``--compose-command docker-compose``
runs Compose v1 (1.29) instead, which has no ``--wait``: ``up -d``, then every container's health polled until
all are healthy, which is what ``--wait`` does (v1 builds the image only when ``kitti-eval:local`` is not there
yet). ``--compose-file FILE`` (repeatable) is read after compose.yaml: an override for a test run, e.g. another
image for ``db`` where ``postgres:16`` cannot be pulled.

On ``--network host`` there is no port mapping, so the image's command (port 8000) is replaced by
``kitti-eval serve`` on the chosen port and its HEALTHCHECK (which probes port 8000) is not run.
It talks to the service on 127.0.0.1 only, and removes the container and volume it made (``--keep`` not).

Only the standard library and the ``docker`` command are needed.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEMO_PREDICTIONS = ROOT / "kitti_eval" / "data" / "demo" / "result.pkl.gz"
#: the parts of the JSON document that are the evaluation's numbers and what they were computed on
#: ``--read-only``: the flags of Kubernetes' readOnlyRootFilesystem (and an emptyDir on /tmp), capabilities
#: drop [ALL] and allowPrivilegeEscalation false (docs/service/container.md's manifests; the tests compare them)
READ_ONLY = ["--read-only", "--tmpfs", "/tmp", "--cap-drop", "ALL", "--security-opt", "no-new-privileges"]
COMPARED = ("protocol", "classes", "threshold_sets", "overlaps", "ap", "num_gt", "num_det", "frames", "coco")


class SmokeFailure(Exception):
    """A check that did not hold."""


def say(text: str) -> None:
    print(text, flush=True)


def check(condition: bool, what: str, detail: str = "") -> None:
    if not condition:
        raise SmokeFailure(what + (f": {detail}" if detail else ""))
    say(f"ok    {what}")


def docker(*args: str, timeout: float = 600, check_rc: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)
    if check_rc and proc.returncode != 0:
        raise SmokeFailure(f"docker {' '.join(args)} exited {proc.returncode}: {proc.stderr.strip()[-2000:]}")
    return proc


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def http(
    method: str, url: str, body: bytes | None = None, headers: dict[str, str] | None = None, timeout: float = 120
) -> tuple[int, bytes]:
    request = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as err:
        return err.code, err.read()


def multipart(fields: dict[str, str], files: dict[str, Path]) -> tuple[bytes, str]:
    """A multipart/form-data body (the standard library has no encoder) and its content type."""
    boundary = uuid.uuid4().hex
    parts = []
    for name, value in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode())
    for name, path in files.items():
        head = (
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{path.name}"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        )
        parts.append(head.encode() + path.read_bytes() + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def wait_ready(base: str, container: str, timeout: float) -> float:
    """Seconds until ``/readyz`` answers 200; fails if the container stops or time runs out."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        try:
            status, _ = http("GET", f"{base}/readyz", timeout=2)
            if status == 200:
                return time.monotonic() - start
        except (OSError, urllib.error.URLError):
            pass
        running = docker("inspect", "--format", "{{.State.Running}}", container).stdout.strip()
        if running != "true":
            raise SmokeFailure(f"the container stopped before it was ready (State.Running={running})")
        time.sleep(0.25)
    raise SmokeFailure(f"/readyz did not answer 200 within {timeout:.0f} s")


def wait_healthy(container: str, timeout: float) -> str:
    """Docker's health status once it is no longer "starting" (or when time runs out)."""
    start = time.monotonic()
    while True:
        status = docker("inspect", "--format", "{{.State.Health.Status}}", container).stdout.strip()
        if status != "starting" or time.monotonic() - start > timeout:
            return status
        time.sleep(1)


def check_log(log: str) -> None:
    """What the service's log must and must not say: its worker processes started, one JSON line a request
    (uvicorn's access lines are off), no kernel compiled for want of a writable cache."""
    lines = [line for line in log.splitlines() if line.strip()]
    records = []
    plain = []
    for line in lines:
        try:
            records.append(json.loads(line))
        except ValueError:
            plain.append(line)
    check(not plain, f"every log line is JSON ({len(records)} lines), uvicorn's own too", "; ".join(plain[:2]))
    started = [r for r in records if "worker processes of" in str(r.get("message", ""))]
    check(bool(started), "the service started its worker processes", "no 'started N worker processes' line")
    say(f"      {started[0]['message']}")
    requests = [r for r in records if r.get("logger") == "kitti_eval.server.access"]
    uvicorn_access = [line for line in lines if '"GET /readyz HTTP' in line or '"POST /v1/evaluations HTTP' in line]
    check(
        bool(requests) and not uvicorn_access,
        f"one JSON log line a request ({len(requests)} lines of the service's access log, none of uvicorn's)",
        "; ".join(uvicorn_access[:2]),
    )
    probes = [r for r in requests if r.get("route") in ("/healthz", "/readyz", "/metrics")]
    check(not probes, "the probes are not logged per request", json.dumps(probes[:1]))
    compiled = [line for line in lines if "NUMBA_CACHE_DIR" in line or "cannot cache function" in line]
    check(not compiled, "nothing compiled at start (the kernels came with the package)", "; ".join(compiled[:1]))


def same_numbers(got: dict[str, object], expected: dict[str, object], what: str) -> None:
    differing = [key for key in COMPARED if got.get(key) != expected.get(key)]
    check(not differing, what, f"these differ: {', '.join(differing)}")


def host_demo() -> dict[str, object] | None:
    """``kitti-eval demo --format json`` on this machine, if kitti-eval is installed here."""
    beside = Path(sys.executable).with_name("kitti-eval")
    cli = str(beside) if beside.exists() else shutil.which("kitti-eval")
    if cli is None:
        return None
    proc = subprocess.run([cli, "demo", "--format", "json", "--quiet"], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise SmokeFailure(f"kitti-eval demo on this machine exited {proc.returncode}: {proc.stderr[-2000:]}")
    return dict(json.loads(proc.stdout))


def smoke(args: argparse.Namespace) -> dict[str, str]:
    figures: dict[str, str] = {}
    if args.build:
        say(f"...   docker build -t {args.image} {ROOT}")
        start = time.monotonic()
        network = ["--network", args.build_network] if args.build_network else []
        build_args = [arg for value in args.build_arg for arg in ("--build-arg", value)]
        build = ["build", "-t", args.image, *network, *build_args, str(ROOT)]
        docker(*build, timeout=3600)
        figures["image build"] = f"{time.monotonic() - start:.1f} s"
        check(True, f"the image builds ({figures['image build']})")
    size = int(docker("image", "inspect", "--format", "{{.Size}}", args.image).stdout.strip())
    figures["image size"] = f"{size / 1e6:.0f} MB"

    port = args.port or free_port()
    base = f"http://127.0.0.1:{port}"
    name = f"kitti-eval-smoke-{uuid.uuid4().hex[:8]}"
    volume = name
    run = ["run", "-d", "--name", name, "-v", f"{volume}:/data"]
    if args.user:
        run += ["--user", args.user]
    if args.read_only:
        run += READ_ONLY
    if args.database_url:
        run += ["-e", f"KITTI_EVAL_DATABASE_URL={args.database_url}"]
    no_home = ["env", "-u", "HOME"] if args.no_home else []
    if args.network == "host":
        # no port mapping on the host's network: the service itself listens on 127.0.0.1 and the chosen port
        run += ["--network", "host", "--no-healthcheck", args.image]
        run += [*no_home, "kitti-eval", "serve", "--host", "127.0.0.1", "--port", str(port)]
    else:
        run += ["-p", f"127.0.0.1:{port}:8000"] + (["--network", args.network] if args.network else []) + [args.image]
        if no_home:
            run += [*no_home, "kitti-eval", "serve", "--host", "0.0.0.0", "--port", "8000"]
    docker("volume", "create", volume)
    if args.user and args.user.partition(":")[2] not in ("", "0"):
        refused_on_a_volume_it_may_not_write(args, volume)
        # as Kubernetes' fsGroup does: the volume given to the uid's group before the service starts on it
        owner = args.user if ":" in args.user else f"{args.user}:0"
        docker(
            "run", "--rm", "--user", "0:0", "-v", f"{volume}:/data", "--entrypoint", "chown", args.image, owner, "/data"
        )
        # and mounted without Docker's copy of the image's /data: while the volume is empty, Docker (20.10) copies
        # the image's folder, its owner too, onto it at every mount, which would undo the chown
        run[run.index(f"{volume}:/data")] = f"{volume}:/data:nocopy"
    try:
        start = time.monotonic()
        docker(*run)
        wait_ready(base, name, args.ready_timeout)
        figures["docker run to /readyz 200"] = f"{time.monotonic() - start:.1f} s"
        check(True, f"/readyz answers 200 {figures['docker run to /readyz 200']} after docker run")

        body, content_type = multipart({"gt": "demo", "model": "container-smoke"}, {"predictions": DEMO_PREDICTIONS})
        start = time.monotonic()  # the first upload once /readyz said 200: its worker processes are up
        status, raw = http("POST", f"{base}/v1/evaluations", body, {"Content-Type": content_type})
        figures["first upload"] = f"{time.monotonic() - start:.2f} s"
        check(
            status == 201,
            f"uploading the demo predictions answers 201 ({figures['first upload']})",
            raw[:500].decode(errors="replace"),
        )
        uploaded = json.loads(raw)
        evaluation_id = str(uploaded["id"])

        inside = docker("exec", name, *no_home, "kitti-eval", "demo", "--format", "json", "--quiet")
        in_container = json.loads(inside.stdout)
        same_numbers(
            uploaded, in_container, "the upload's numbers equal kitti-eval demo --format json's in the container"
        )
        car = in_container["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
        check(isinstance(car, float) and 0 < car < 100, f"Car 3D moderate R40 AP is a percentage ({car})")
        here = host_demo()
        if here is None:
            say("skip  kitti-eval is not installed on this machine: the numbers were compared in the container only")
        else:
            same_numbers(uploaded, here, "the upload's numbers equal kitti-eval demo --format json on this machine")

        store = " (in PostgreSQL)" if args.database_url else " (in SQLite on the volume)"
        start = time.monotonic()
        docker("restart", name, timeout=120)
        wait_ready(base, name, args.ready_timeout)
        figures["restart to /readyz 200"] = f"{time.monotonic() - start:.1f} s"
        check(True, f"after docker restart /readyz answers 200 again ({figures['restart to /readyz 200']})")
        status, raw = http("GET", f"{base}/v1/evaluations/{evaluation_id}")
        check(
            status == 200,
            f"the evaluation {evaluation_id} is still there after the restart{store}",
            raw[:500].decode(errors="replace"),
        )
        kept = json.loads(raw)
        check(kept["id"] == evaluation_id, "GET by id answers that evaluation")
        same_numbers(kept, uploaded, "its numbers are the ones the upload answered")

        uid = docker("exec", name, "id", "-u").stdout.strip()
        check(uid.isdigit() and int(uid) != 0, f"commands in the container run as a user other than root (uid {uid})")
        if args.user:
            wanted = args.user.split(":")[0]
            check(uid == wanted, f"the container runs as the uid it was given ({wanted})", f"id -u says {uid}")
        if args.read_only:
            probe = docker("exec", "--user", "0", name, "touch", "/opt/kitti-eval/probe", check_rc=False)
            check(
                probe.returncode != 0 and "Read-only file system" in probe.stderr,
                "the root filesystem is read-only (even root's touch in /opt/kitti-eval fails)",
                f"exit {probe.returncode}: {probe.stderr.strip()[-300:]}",
            )
        logged = docker("logs", name)
        check_log(logged.stdout + logged.stderr)
        status_lines = docker("exec", name, "cat", "/proc/1/status").stdout.splitlines()
        uids = next((line.split()[1:] for line in status_lines if line.startswith("Uid:")), [])
        check(
            bool(uids) and "0" not in uids,
            f"the service's process (pid 1) is not root (real, effective, saved, fs uids {' '.join(uids)})",
        )
        if args.network != "host":
            start = time.monotonic()
            health = wait_healthy(name, timeout=args.ready_timeout)
            check(
                health == "healthy",
                f"Docker reports the image's HEALTHCHECK {health} ({time.monotonic() - start:.0f} s)",
            )
        else:
            say("skip  the image's HEALTHCHECK: it probes port 8000, which --network host does not map")
        table = docker("exec", name, *no_home, "kitti-eval", "demo", check_rc=False)
        check(
            table.returncode == 0 and "Car AP_R40@0.70, 0.70, 0.70:" in table.stdout,
            "kitti-eval demo runs in the container and prints the table",
            f"exit {table.returncode}: {table.stdout[-500:]}{table.stderr[-1500:]}",
        )
    except Exception:
        logs = docker("logs", "--tail", "40", name, check_rc=False)
        say("----- the container's last log lines -----\n" + logs.stdout + logs.stderr)
        raise
    finally:
        if not args.keep:
            docker("rm", "-f", name, check_rc=False)
            docker("volume", "rm", "-f", volume, check_rc=False)
        else:
            say(f"kept  container {name} and volume {volume} ({base})")
    return figures


def refused_on_a_volume_it_may_not_write(args: argparse.Namespace, volume: str) -> None:
    """The image as ``args.user`` on ``volume`` as created (the image's /data: uid 10001, the root group): the
    service must exit 2 with one line naming the folder, the uid and the fix, not a PermissionError."""
    uid, _, gid = args.user.partition(":")
    run = ["run", "--rm", "--user", args.user, "-v", f"{volume}:/data", *(READ_ONLY if args.read_only else [])]
    done = docker(*run, "-e", "KITTI_EVAL_WARMUP=false", args.image, check_rc=False, timeout=300)
    out = done.stdout + done.stderr
    lines = [line for line in out.splitlines() if "cannot be written by uid" in line]
    check(
        done.returncode == 2 and len(lines) == 1 and "Traceback" not in out,
        f"on a volume uid {uid} may not write the service exits 2 with one line naming it (gid {gid or 0})",
        f"exit {done.returncode}: {out[-1500:]}",
    )
    say(f"      {json.loads(lines[0])['message'] if lines[0].startswith('{') else lines[0]}")


def compose_command(args: argparse.Namespace) -> tuple[list[str], bool]:
    """The compose command (``--compose-command``, default ``docker compose``) and whether it is v2 (it has
    ``up --wait``); fails with what to do when it is not there."""
    command = shlex.split(args.compose_command)
    try:
        version = subprocess.run([*command, "version"], capture_output=True, text=True, timeout=60)
    except OSError as e:
        version = subprocess.CompletedProcess(command, 127, "", str(e))
    if version.returncode != 0:
        raise SmokeFailure(
            f"{args.compose_command} is not there ({(version.stderr or version.stdout).strip()[-300:]}): install "
            "Docker Compose v2 (the docker-compose-plugin package), or give --compose-command docker-compose "
            "(v1, which has no --wait: the script then polls every container's health as --wait does)"
        )
    first = version.stdout.strip().splitlines()[0] if version.stdout.strip() else ""
    v1 = first.startswith("docker-compose version 1.")
    say(f"...   {args.compose_command}: {first}" + (" (v1: up -d, then the health polled as --wait does)" * v1))
    return command, not v1


def project_containers(project: str) -> list[dict[str, Any]]:
    """``docker inspect`` of every container of the compose project (by compose's label: v1 and v2 set it)."""
    ids = docker("ps", "-a", "-q", "--filter", f"label=com.docker.compose.project={project}").stdout.split()
    return list(json.loads(docker("inspect", *ids).stdout)) if ids else []


def health_of(containers: list[dict[str, Any]]) -> dict[str, str]:
    """Each container's name and its health (or its state when it has no healthcheck or stopped)."""
    states = {}
    for c in containers:
        state = c["State"]
        health = (state.get("Health") or {}).get("Status")
        states[c["Name"].lstrip("/")] = health if state.get("Running") and health else f"{state.get('Status')}"
    return states


def wait_all_healthy(project: str, timeout: float) -> dict[str, str]:
    """What ``up --wait`` does: until every container of the project is healthy, or one is unhealthy or not
    running, or time runs out; the last states."""
    deadline = time.monotonic() + timeout
    while True:
        states = health_of(project_containers(project))
        settled = states and all(s != "starting" for s in states.values())
        if settled or time.monotonic() > deadline:
            return states
        time.sleep(1)


def stop_times(project: str, since: float, until: float) -> dict[str, float]:
    """Seconds from Docker's first signal to each container of the project (its stop signal, or the SIGKILL
    at the end of its grace period) to its exit, from Docker's events between ``since`` and ``until``."""
    events = docker(
        "events",
        "--since",
        f"{since:.3f}",
        "--until",
        f"{until + 1:.3f}",
        "--format",
        "{{json .}}",
        "--filter",
        "type=container",
        "--filter",
        f"label=com.docker.compose.project={project}",
        "--filter",
        "event=kill",
        "--filter",
        "event=die",
        timeout=60,
    ).stdout
    signalled: dict[str, float] = {}
    stopped: dict[str, float] = {}
    for line in events.splitlines():
        event = json.loads(line)
        name = str(event["Actor"]["Attributes"].get("com.docker.compose.service", event["Actor"]["ID"][:12]))
        at = int(event["timeNano"]) / 1e9
        if event["Action"] == "kill":
            signalled.setdefault(name, at)
        elif event["Action"] == "die":
            stopped.setdefault(name, at)
    return {name: stopped[name] - signalled.get(name, stopped[name]) for name in sorted(stopped)}


def compose_smoke(args: argparse.Namespace) -> dict[str, str]:
    """compose.yaml as an operator scripts it: ``up -d --wait`` exits 0 with every service healthy (the worker's
    healthcheck too), and ``down`` is quick with nothing running."""
    figures: dict[str, str] = {}
    command, v2 = compose_command(args)
    project = f"kitti-eval-smoke-{uuid.uuid4().hex[:8]}"
    env = {**os.environ, "POSTGRES_PASSWORD": uuid.uuid4().hex, "KITTI_EVAL_PORT": str(args.port or free_port())}
    files = [arg for f in [ROOT / "compose.yaml", *args.compose_file] for arg in ("-f", str(f))]
    compose = [*command, "--project-directory", str(ROOT), *files, "-p", project]

    def run(*more: str, timeout: float) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*compose, *more], env=env, capture_output=True, text=True, timeout=timeout)

    wait_s = args.ready_timeout + 120
    try:
        start = time.monotonic()
        if v2:
            up = run("up", "-d", "--wait", "--wait-timeout", str(int(wait_s)), timeout=3600)
            what = "docker compose up -d --wait exits 0 with every service healthy"
        else:
            up = run("up", "-d", timeout=3600)
            if up.returncode == 0:
                states = wait_all_healthy(project, wait_s)
                if any(s != "healthy" for s in states.values()):
                    up = subprocess.CompletedProcess(up.args, 1, up.stdout, f"not healthy: {states}")
            what = f"{args.compose_command} up -d, then every container healthy (as --wait)"
        figures["compose up, all healthy"] = f"{time.monotonic() - start:.1f} s"
        check(
            up.returncode == 0,
            f"{what} ({figures['compose up, all healthy']})",
            f"exit {up.returncode}: {up.stderr[-1500:]}",
        )
        states = health_of(project_containers(project))
        unhealthy = [f"{name}: {state}" for name, state in states.items() if state != "healthy"]
        services = ", ".join(sorted(states))
        check(len(states) >= 3 and not unhealthy, f"every service reports healthy ({services})", "; ".join(unhealthy))
    finally:
        since = time.time()
        start = time.monotonic()
        down = run("down", "-v", timeout=300)
        down_s = time.monotonic() - start
        figures["compose down"] = f"{down_s:.1f} s"
        stops = stop_times(project, since, time.time())
        if stops:
            figures["each container, signal to exit"] = ", ".join(f"{n} {s:.1f} s" for n, s in stops.items())
    slow = [f"{name} {took:.1f} s" for name, took in stops.items() if took >= 10]
    check(
        bool(stops) and not slow,
        f"every container ends within 10 s of its stop signal ({figures.get('each container, signal to exit')})",
        f"{', '.join(slow) or 'no stop events'} (compose waits for each, dependents first, up to its "
        "stop_grace_period)",
    )
    check(
        down.returncode == 0 and down_s < 20,
        f"{args.compose_command} down ends within 20 s ({figures['compose down']}; "
        f"{figures.get('each container, signal to exit', 'no stop events')})",
        down.stderr[-800:],
    )
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image", default="kitti-eval:smoke", help="the image's tag (default kitti-eval:smoke)")
    parser.add_argument("--no-build", dest="build", action="store_false", help="use --image as it is")
    parser.add_argument("--port", type=int, default=0, help="the port on 127.0.0.1 (default: a free one)")
    parser.add_argument(
        "--network",
        default=os.environ.get("KITTI_EVAL_SMOKE_NETWORK", ""),
        help="docker run's --network (default $KITTI_EVAL_SMOKE_NETWORK, else Docker's default bridge)",
    )
    parser.add_argument("--build-network", default="", help="docker build's --network, e.g. host")
    parser.add_argument(
        "--build-arg",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="docker build's --build-arg, e.g. BASE=kitti-base:bookworm (the image both stages start from); repeatable",
    )
    parser.add_argument(
        "--database-url",
        default="",
        help="KITTI_EVAL_DATABASE_URL for the container (default: its SQLite database in the volume); "
        "an empty PostgreSQL database, as the container reaches it",
    )
    parser.add_argument("--user", default="", help="docker run's --user, e.g. 12345:0 (default: the image's)")
    parser.add_argument(
        "--read-only",
        action="store_true",
        help="a read-only root filesystem with a tmpfs on /tmp, no capabilities, no privilege escalation",
    )
    parser.add_argument(
        "--no-home", action="store_true", help="start the service and kitti-eval demo with no HOME (env -u HOME)"
    )
    parser.add_argument(
        "--compose", action="store_true", help="check compose.yaml instead: up -d --wait exits 0, down is quick"
    )
    parser.add_argument(
        "--compose-command",
        default="docker compose",
        help="with --compose: the compose command (default 'docker compose', v2); 'docker-compose' (v1) has no "
        "--wait, so the script runs up -d and polls every container's health as --wait does",
    )
    parser.add_argument(
        "--compose-file",
        action="append",
        default=[],
        type=Path,
        metavar="FILE",
        help="with --compose: a file read after compose.yaml (an override, e.g. another image for db); repeatable",
    )
    parser.add_argument("--ready-timeout", type=float, default=180, help="seconds to wait for /readyz")
    parser.add_argument("--keep", action="store_true", help="leave the container and its volume")
    args = parser.parse_args(argv)
    if shutil.which("docker") is None:
        say("FAIL  no docker command")
        return 2
    try:
        figures = compose_smoke(args) if args.compose else smoke(args)
    except (SmokeFailure, subprocess.TimeoutExpired, OSError, ValueError, KeyError) as err:
        say(f"FAIL  {err}")
        return 1
    say("all checks passed; " + ", ".join(f"{k}: {v}" for k, v in figures.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
