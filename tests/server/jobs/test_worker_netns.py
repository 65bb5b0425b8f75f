"""A worker on another machine, as near as one machine gets: ``kitti-eval worker`` in a network namespace of its
own (its own interfaces, reaching the database over a veth pair as over a network), given only the database's
URL: no data folder, no service's address. It evaluates the jobs the service accepts. Needs root (network
namespaces), iproute2 and PostgreSQL; skipped otherwise."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest
from server_helpers import LiveServer, golden_bytes, register, upload
from server_postgres import PostgresCluster, why_no_postgres

pytestmark = pytest.mark.slow

HOST_IP, WORKER_IP = "10.213.7.1", "10.213.7.2"


def _why_not() -> str | None:
    if why_no_postgres() is not None:
        return why_no_postgres()
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return "needs root and iproute2 (ip netns) for a network namespace"
    probe = f"ke-probe-{os.getpid()}"
    if subprocess.run(["ip", "netns", "add", probe], capture_output=True).returncode != 0:
        return "network namespaces cannot be made here (no CAP_SYS_ADMIN / CAP_NET_ADMIN)"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


@pytest.fixture()
def namespace():
    """A network namespace whose only way out is a veth pair to this machine (HOST_IP <-> WORKER_IP)."""
    why = _why_not()
    if why is not None:
        pytest.skip(why)
    name = f"ke-{uuid.uuid4().hex[:8]}"
    host_end, ns_end = f"veh{name[3:]}", f"ven{name[3:]}"
    _ip("netns", "add", name)
    try:
        _ip("link", "add", host_end, "type", "veth", "peer", "name", ns_end)
        _ip("link", "set", ns_end, "netns", name)
        _ip("addr", "add", f"{HOST_IP}/30", "dev", host_end)
        _ip("link", "set", host_end, "up")
        _ip("netns", "exec", name, "ip", "addr", "add", f"{WORKER_IP}/30", "dev", ns_end)
        _ip("netns", "exec", name, "ip", "link", "set", ns_end, "up")
        _ip("netns", "exec", name, "ip", "link", "set", "lo", "up")
        yield name
    finally:
        subprocess.run(["ip", "link", "del", host_end], capture_output=True)
        subprocess.run(["ip", "netns", "del", name], capture_output=True)


def test_a_worker_in_another_network_namespace_without_the_data_folder_evaluates_jobs(namespace, tmp_path) -> None:
    pg = PostgresCluster()
    pg.listen = f"127.0.0.1,{HOST_IP}"
    pg.trusted = [f"{WORKER_IP}/32"]
    pg.start()
    worker: subprocess.Popen[bytes] | None = None
    server: LiveServer | None = None
    try:
        remote_url = f"postgresql://postgres@{HOST_IP}:{pg.port}/postgres"
        # the worker's namespace cannot reach this machine's loopback: only the database, over the veth pair
        probe = subprocess.run(
            [
                "ip",
                "netns",
                "exec",
                namespace,
                sys.executable,
                "-c",
                f"import socket; socket.create_connection(('127.0.0.1', {pg.port}), 2)",
            ],
            capture_output=True,
            timeout=30,
        )
        assert probe.returncode != 0
        workdir = Path(tempfile.mkdtemp(prefix="kitti-eval-remote-worker-"))
        env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
        env["KITTI_EVAL_DATA_DIR"] = str(workdir / "nowhere")  # no data folder: it is never made
        log = open(tmp_path / "worker.log", "wb")  # noqa: SIM115 - closed below
        worker = subprocess.Popen(
            [
                "ip",
                "netns",
                "exec",
                namespace,
                sys.executable,
                "-m",
                "kitti_eval.cli",
                "worker",
                "--database-url",
                remote_url,
                "--processes",
                "1",
                "--work-dir",
                str(workdir / "work"),
            ],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        server = LiveServer(tmp_path / "data", database_url=pg.url, job_threads=0).start(timeout=300)
        with server.client() as c:
            assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
            jobs = [
                upload(c, golden_bytes("result.pkl"), gt="small", params={"wait": "0"}).json()["id"] for _ in range(3)
            ]
            deadline = time.monotonic() + 300
            states = {}
            while time.monotonic() < deadline:
                states = {j: c.get(f"/v1/jobs/{j}").json() for j in jobs}
                if all(s["state"] in ("done", "failed") for s in states.values()):
                    break
                time.sleep(0.5)
            assert [s["state"] for s in states.values()] == ["done"] * 3, (
                states,
                (tmp_path / "worker.log").read_text()[-3000:],
            )
            docs = [c.get(s["result_location"]).json() for s in states.values()]
            direct = upload(c, golden_bytes("result.pkl"), gt="small").json()  # the same file, evaluated again
            assert all(d["ap"] == direct["ap"] for d in docs) and docs[0]["ap"]
        assert not (workdir / "nowhere").exists()
    finally:
        if worker is not None:
            worker.send_signal(signal.SIGTERM)
            try:
                worker.wait(60)
            except subprocess.TimeoutExpired:
                worker.kill()
        if server is not None:
            server.stop()
        pg.stop()
