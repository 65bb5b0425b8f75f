"""Shared by the server tests: an in-process client, a real uvicorn in a subprocess, archive builders."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import signal
import socket
import subprocess
import sys
import tarfile
import time
import warnings
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

with warnings.catch_warnings():  # newer starlette prefers httpx2 and says so on import
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from kitti_eval_server import Settings, create_app

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden" / "small"
ADMIN_TOKEN = "test-admin-token"
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
READY_TIMEOUT_S = 120.0  # a cold numba cache compiles the kernels during the warm-up


def golden_bytes(name: str) -> bytes:
    return (GOLDEN / name).read_bytes()


# ------------------------------------------------------------------------------------------ in-process


@contextlib.contextmanager
def app_client(data_dir: Path, *, ready: bool = True, **settings: Any) -> Iterator[TestClient]:
    """A TestClient on a fresh app (lifespan run), waiting until /readyz says ready (unless ``ready`` is False:
    a service without a worker of its own is never ready until a worker process is seen)."""
    settings.setdefault("admin_token", ADMIN_TOKEN)
    app = create_app(Settings(data_dir=data_dir, **settings))
    with TestClient(app, raise_server_exceptions=False) as client:
        if ready:
            wait_ready(client.get)
        yield client


def wait_ready(get: Any, timeout: float = READY_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            if get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline:
            raise TimeoutError(f"not ready after {timeout} s")
        time.sleep(0.05)


def upload(
    client: Any,
    data: bytes,
    filename: str = "result.pkl",
    *,
    gt: str | None = "demo",
    fields: dict[str, Any] | None = None,
    params: dict[str, str] | None = None,
    gt_file: tuple[str, bytes] | None = None,
    headers: dict[str, str] | None = None,
) -> httpx.Response:
    form = dict(fields or {})
    if gt is not None:
        form["gt"] = gt
    files: dict[str, Any] = {"predictions": (filename, data, "application/octet-stream")}
    if gt_file is not None:
        files["gt_file"] = (gt_file[0], gt_file[1], "application/octet-stream")
    return client.post("/v1/evaluations", data=form, files=files, params=params or {}, headers=headers)


def register(
    client: Any, name: str, data: bytes, filename: str, headers: dict[str, str] | None = None
) -> httpx.Response:
    return client.post(
        "/v1/ground-truths",
        data={"name": name},
        files={"file": (filename, data)},
        headers=ADMIN if headers is None else headers,
    )


def assert_error(response: httpx.Response, status: int | tuple[int, ...], *needles: str) -> dict[str, Any]:
    """The one error shape, the expected status, the expected words, and never a traceback."""
    statuses = (status,) if isinstance(status, int) else status
    assert response.status_code in statuses, (response.status_code, response.text)
    body = response.json()
    assert set(body) == {"error"}, body
    err = body["error"]
    assert isinstance(err["code"], str) and isinstance(err["message"], str) and err["message"], body
    assert "Traceback" not in response.text and 'File "' not in response.text
    for needle in needles:
        assert needle.lower() in err["message"].lower(), (needle, err["message"])
    return err


# ------------------------------------------------------------------------------------------ archives


def tar_of(files: dict[str, bytes], compression: str = "gz") -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=f"w:{compression}" if compression else "w") as tf:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def zip_of(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def golden_txt(archive: str) -> dict[str, bytes]:
    """{member name: bytes} of one of the golden txt archives (label_2.tar.gz, pred.tar.gz)."""
    out = {}
    with tarfile.open(GOLDEN / archive) as tf:
        for member in tf:
            if member.isfile():
                out[member.name] = tf.extractfile(member).read()  # type: ignore[union-attr]
    return out


# ------------------------------------------------------------------------------------------ real server


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    """``uvicorn kitti_eval_server.main:app`` in a subprocess on 127.0.0.1 and a free port, configured by
    environment."""

    def __init__(
        self,
        data_dir: Path,
        *,
        via_serve: bool = False,
        python: Path | None = None,
        environ: dict[str, str] | None = None,
        ready_path: str = "/readyz",
        **settings: Any,
    ) -> None:
        self.data_dir = data_dir
        self.via_serve = via_serve  # ``kitti-eval serve`` (its graceful shutdown) instead of plain uvicorn
        # another installation's interpreter (then run outside the checkout), and variables of its own
        self.python = python
        self.environ = environ or {}
        #: what says the server is up: /readyz, or /healthz for one that is never ready (no worker of its own)
        self.ready_path = ready_path
        self.settings = {"admin_token": ADMIN_TOKEN, **settings}
        self.port = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = data_dir.parent / f"{data_dir.name}-uvicorn.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = READY_TIMEOUT_S, *, port: int | None = None) -> LiveServer:
        """Starts it on ``port`` (default: a free one) and waits until it says it is up."""
        self.port = port or free_port()
        env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
        env.update(self.environ)
        env["KITTI_EVAL_DATA_DIR"] = str(self.data_dir)
        env.update({f"KITTI_EVAL_{k.upper()}": str(v) for k, v in self.settings.items()})
        log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
        self._log = log
        if self.via_serve:
            args = ["--port", str(self.port), "--log-level", "info"]
            command = ["-c", f"import sys; from kitti_eval_server.main import serve; sys.exit(serve({args!r}))"]
        else:
            command = ["-m", "uvicorn", "kitti_eval_server.main:app", "--host", "127.0.0.1", "--port", str(self.port)]
            command += ["--log-level", "warning"]
        self.proc = subprocess.Popen(
            [str(self.python or sys.executable), *command],
            cwd=ROOT if self.python is None else self.data_dir.parent,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + timeout
        with httpx.Client(base_url=self.url, timeout=5) as client:
            while True:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"uvicorn exited with {self.proc.returncode}:\n{self.log()}")
                try:
                    if client.get(self.ready_path).status_code == 200:
                        return self
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline:
                    self.stop()
                    raise TimeoutError(f"uvicorn not ready after {timeout} s:\n{self.log()}")
                time.sleep(0.1)

    def client(self, **kw: Any) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=kw.pop("timeout", 60), **kw)

    def kill(self) -> None:
        """SIGKILL: no shutdown handlers, no flushing."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill()
        if getattr(self, "_log", None) is not None:
            self._log.close()
            self._log = None

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class LogRecords(logging.Handler):
    """Keeps the records a logger emits, for a test to read (with the service's formatters)."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
