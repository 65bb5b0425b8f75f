"""The CLI and the service run as a user who may write nowhere but their data folder.

This is how clusters run the image (another uid, a read-only root filesystem) and how a shared installation
is used from compute nodes: no ``NUMBA_CACHE_DIR``, an installation the user cannot write (numba's in-tree
``__pycache__``), no writable home (numba's user-wide cache). numba alone refuses to decorate a kernel then;
:mod:`kitti_eval.core.kernel_cache` compiles it in memory with one warning. Here the package is copied into a
folder owned by root, the process runs as uid 12345, which /etc/passwd does not know, in an environment with no
HOME at all (``env -i``: no home to be found, by the variable or by the uid), and ``kitti-eval demo`` and
``kitti-eval serve`` (its worker processes too, with an upload) must work and give the numbers they give here;
a data folder that uid may not write is refused in one line (exit 2). Needs root to switch users (CI runs as
root): skipped elsewhere.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from server_helpers import free_port

import kitti_eval
from kitti_eval.core.cpus import available_cpus
from kitti_eval.demo import demo_paths

pytestmark = pytest.mark.slow

UID = GID = 12345  # no entry in /etc/passwd: no home by the uid either
PACKAGE = Path(kitti_eval.__file__).resolve().parent
SERVER = PACKAGE.parent / "server"
WARNING = "set NUMBA_CACHE_DIR to a writable folder to keep them"


def _as_nobody(argv: list[str], env: dict[str, str], cwd: Path, **kwargs: object) -> subprocess.Popen[str]:
    return subprocess.Popen(  # type: ignore[call-overload, no-any-return]
        argv, env=env, cwd=cwd, user=UID, group=GID, extra_groups=[], text=True, **kwargs
    )


def _interpreter(env: dict[str, str], cwd: Path) -> str | None:
    """A Python of this version that uid 12345 can run, and that can start itself again (the worker processes
    do): this one, or where it leads (a virtual environment's interpreter may sit in a folder only root reads)."""
    version = f"{sys.version_info[0]}.{sys.version_info[1]}"
    check = (
        "import subprocess, sys; "
        "subprocess.run([sys.executable, '-c', ''], check=True); "
        "print(f'{sys.version_info[0]}.{sys.version_info[1]}')"
    )
    candidates = [sys.executable, os.path.realpath(sys.executable), getattr(sys, "_base_executable", "")]
    candidates.append(shutil.which(f"python{version}", path=env["PATH"]) or "")
    for python in dict.fromkeys(c for c in candidates if c):
        try:
            proc = _as_nobody([python, "-c", check], env, cwd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            out, _ = proc.communicate(timeout=60)
        except OSError:
            continue
        if proc.returncode == 0 and out.strip() == version:
            return python
    return None


@pytest.fixture(scope="module")
def read_only_install() -> Iterator[tuple[str, dict[str, str], Path]]:
    """(interpreter, environment, folder): the package and the service copied into a folder of root's, which
    uid 12345 may read and not write, first on the path; the dependencies from this installation's
    site-packages (root's as well)."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("switching to uid 12345 needs root")
    folder = Path(tempfile.mkdtemp(prefix="kitti-eval-ro-"))
    try:
        skip = shutil.ignore_patterns("__pycache__", "*.py[cod]", "*.nbi", "*.nbc")
        shutil.copytree(PACKAGE, folder / "kitti_eval", ignore=skip)
        shutil.copytree(SERVER, folder / "kitti_eval_server", ignore=skip)
        for path in [folder, *folder.rglob("*")]:
            path.chmod(0o755 if path.is_dir() else 0o644)
        env = {
            "PATH": "/usr/local/bin:/usr/bin:/bin",
            "LANG": "C.UTF-8",
            "PYTHONPATH": os.pathsep.join([str(folder), *site.getsitepackages()]),
        }
        python = _interpreter(env, folder)
        if python is None:
            pytest.skip(f"no Python {sys.version_info[0]}.{sys.version_info[1]} that uid {UID} can run")
        deps = _as_nobody([python, "-c", "import numba, numpy, fastapi"], env, folder, stderr=subprocess.PIPE)
        _, why = deps.communicate(timeout=120)
        if deps.returncode != 0:  # this installation's site-packages lie in a folder that uid 12345 cannot read
            pytest.skip(f"uid {UID} cannot import this installation's dependencies: {why.strip()[-300:]}")
        yield python, env, folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _nothing_written(folder: Path) -> None:
    assert not any(folder.rglob("__pycache__")), "something was written into the installation"
    assert not (folder / "~").exists(), "a home taken literally (~) was made in the working folder"


def test_demo_as_another_user_with_nowhere_to_cache(read_only_install: tuple[str, dict[str, str], Path]) -> None:
    python, env, folder = read_only_install
    assert "HOME" not in env
    here = subprocess.run(
        [sys.executable, "-m", "kitti_eval.cli", "demo"], capture_output=True, text=True, timeout=600, check=True
    )
    proc = _as_nobody(
        [python, "-m", "kitti_eval.cli", "demo"], env, folder, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    assert out == here.stdout and "Car AP@0.70, 0.70, 0.70" in out
    # one line: the kernels are compiled in memory, and how to keep them; not numba's "cannot cache" crash
    assert err.count(WARNING) == 1 and err.startswith("kitti-eval: warning: numba's cache has no writable place"), err
    assert "Traceback" not in err
    _nothing_written(folder)


def test_serve_and_an_upload_as_another_user_with_nowhere_to_cache(
    read_only_install: tuple[str, dict[str, str], Path],
) -> None:
    python, env, folder = read_only_install
    data = Path(tempfile.mkdtemp(prefix="kitti-eval-data-"))
    os.chown(data, UID, GID)
    port = free_port()
    log_path = data.parent / f"{data.name}.log"
    gt_path, pred_path = demo_paths()
    expected = json.loads(
        subprocess.run(
            [sys.executable, "-m", "kitti_eval.cli", "demo", "--format", "json"],
            capture_output=True,
            text=True,
            timeout=600,
            check=True,
        ).stdout
    )["ap"]
    argv = [python, "-m", "kitti_eval.cli", "serve", "--port", str(port), "--data-dir", str(data)]
    with open(log_path, "w") as log:
        proc = _as_nobody(argv, {**env, "KITTI_EVAL_LOG_FORMAT": "json"}, folder, stdout=log, stderr=subprocess.STDOUT)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as client:
            deadline = time.monotonic() + 600  # every process compiles its kernels: minutes on a busy machine
            while True:
                assert proc.poll() is None, log_path.read_text()[-4000:]
                try:
                    if client.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline, log_path.read_text()[-4000:]
                time.sleep(0.2)
            r = client.post(
                "/v1/evaluations",
                data={"gt": "demo"},
                files={"predictions": (pred_path.name, pred_path.read_bytes())},
            )
        assert r.status_code == 201, r.text
        assert r.json()["ap"] == expected
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        text = log_path.read_text()
        shutil.rmtree(data, ignore_errors=True)
        log_path.unlink()
    assert proc.returncode in (0, -15), text[-4000:]  # uvicorn ends by SIGTERM again once it has shut down
    assert "Application shutdown complete" in text
    lines = [json.loads(line) for line in text.splitlines() if line.startswith("{")]
    warned = [line for line in lines if WARNING in line.get("message", "")]
    # the web process and each worker process (one a CPU) say it once, in the service's log
    assert len(warned) == 1 + available_cpus() and all(w["level"] == "warning" for w in warned), warned
    assert "Traceback" not in text and "cannot cache function" not in text
    assert gt_path.exists()
    _nothing_written(folder)


def test_serve_on_a_data_folder_the_uid_may_not_write_is_one_line(
    read_only_install: tuple[str, dict[str, str], Path],
) -> None:
    python, env, folder = read_only_install
    data = Path(tempfile.mkdtemp(prefix="kitti-eval-data-"))  # root's, 0700: uid 12345 may not write it
    try:
        argv = [python, "-m", "kitti_eval.cli", "serve", "--port", str(free_port()), "--data-dir", str(data / "d")]
        run_env = {**env, "KITTI_EVAL_LOG_FORMAT": "json", "KITTI_EVAL_WARMUP": "false"}
        proc = _as_nobody(argv, run_env, folder, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        out, _ = proc.communicate(timeout=300)
    finally:
        shutil.rmtree(data, ignore_errors=True)
    assert proc.returncode == 2, out[-3000:]
    assert "Traceback" not in out and "PermissionError" not in out
    (line,) = [line for line in out.splitlines() if "cannot be written" in line]
    message = json.loads(line)["message"]
    assert message.startswith(f"the data folder {data / 'd'} cannot be written by uid {UID} (gid {GID})"), message
    assert "fsGroup" in message
