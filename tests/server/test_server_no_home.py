"""The service and its commands where there is no home: ``env -i``, an init system, a uid with no entry in
/etc/passwd. Nothing needs HOME once the settings name the folders; where a folder cannot be found or written
the command says so in one line (exit 2), never with a traceback."""

from __future__ import annotations

import json
import os
import pwd
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from server_helpers import free_port

from kitti_eval import _jit
from kitti_eval.core import kernel_cache
from kitti_eval.demo import demo_paths
from kitti_eval_server.data_folder import check_writable
from kitti_eval_server.errors import StartupRefused
from kitti_eval_server.main import serve
from kitti_eval_server.service import Service
from kitti_eval_server.settings import NoDataFolder, Settings, default_data_dir


@pytest.fixture
def no_home(monkeypatch: pytest.MonkeyPatch) -> None:
    """This process as a uid the user database does not know, started without HOME (``env -i``)."""

    def unknown(uid: int) -> Any:
        raise KeyError(f"getpwuid(): uid not found: {uid}")

    for name in ("HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME", "KITTI_EVAL_DATA_DIR", "NUMBA_CACHE_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(pwd, "getpwuid", unknown)
    with pytest.raises(RuntimeError):  # as pathlib finds it: no home at all
        Path.home()


def test_serve_help_without_a_home(no_home: None, capsys: pytest.CaptureFixture[str]) -> None:
    assert serve(["--help"]) == 0
    out = capsys.readouterr().out
    assert "KITTI_EVAL_DATA_DIR" in out and "no HOME" in out


def test_no_data_folder_and_no_home_is_one_sentence(no_home: None, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(NoDataFolder, match="set KITTI_EVAL_DATA_DIR"):
        default_data_dir()
    assert serve(["--port", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("kitti-eval serve: error: no data folder: KITTI_EVAL_DATA_DIR (or --data-dir) is unset")


def test_settings_naming_the_folder_need_no_home(no_home: None, tmp_path: Path) -> None:
    os.environ["KITTI_EVAL_DATA_DIR"] = str(tmp_path)
    try:
        assert Settings().data_dir == tmp_path
    finally:
        del os.environ["KITTI_EVAL_DATA_DIR"]


def test_the_kernel_cache_is_found_without_a_home(no_home: None) -> None:
    places = [place for place, _ in _jit._cache_places()]
    assert places and all(place.is_absolute() for place in places), places
    assert _jit.kernels_cached() in (True, False)  # answers, where Path.home() raised before


def test_numba_s_relative_user_cache_is_never_the_working_folder(no_home: None) -> None:
    """numba's user-wide cache is ``~/.cache/numba`` taken literally (relative) without a home: this package's
    kernels are then kept in their own ``__pycache__`` or in memory, never in ``./~`` of the working folder."""
    from kitti_eval.core import matching

    locator = kernel_cache.KernelLocator.from_function(matching._pass2.py_func, matching.__file__)
    assert locator is not None and os.path.isabs(locator.get_cache_path())


def test_an_unwritable_data_folder_is_one_sentence_naming_it_the_uid_and_the_fix(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    folder = blocker / "data"  # cannot be made, whoever runs the test (root too)
    with pytest.raises(StartupRefused) as e:
        check_writable(folder)
    message = e.value.message
    assert message.startswith(f"the data folder {folder} cannot be written by uid {os.getuid()} (gid {os.getgid()})")
    assert "fsGroup" in message and "KITTI_EVAL_DATA_DIR" in message and "\n" not in message
    # the folder could not be made: the one to give the uid is the nearest that exists (here a file in the way)
    assert f"(chown {os.getuid()}:{os.getgid()} {blocker}," in message
    service = Service(Settings(data_dir=folder, register_demo=False, warmup=False, job_threads=0))
    with pytest.raises(StartupRefused, match="cannot be written by uid"):
        service.start()
    service.stop()


def test_a_subfolder_the_service_cannot_write_is_named_too(tmp_path: Path) -> None:
    """A volume an earlier uid used may hold ``tmp/`` with that uid's permissions: named before anything fails on
    it (here a file where the folder should be, which fails whoever runs the test)."""
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "run").write_text("")
    with pytest.raises(StartupRefused) as e:
        check_writable(folder)
    assert e.value.message.startswith(f"{folder / 'run'} in the data folder cannot be written by uid {os.getuid()}")


def test_serve_on_an_unwritable_data_folder_exits_2(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    os.environ["KITTI_EVAL_WARMUP"] = "false"
    try:
        assert serve(["--port", "0", "--data-dir", str(blocker / "data")]) == 2
    finally:
        del os.environ["KITTI_EVAL_WARMUP"]
    assert "Traceback" not in capfd.readouterr().err
    (refusal,) = [r for r in caplog.records if r.name == "kitti_eval.server" and r.levelname == "ERROR"]
    assert "cannot be written by uid" in refusal.getMessage()


def test_env_i_serve_answers_an_upload_and_logs_only_json_lines(tmp_path: Path) -> None:
    """``env -i PATH=... KITTI_EVAL_DATA_DIR=... kitti-eval serve``: no HOME, no other variable. It starts,
    evaluates an upload, and every line it writes is JSON (uvicorn's own through the service's formatter); the
    probes are answered and counted, not logged."""
    pred = demo_paths()[1]
    port = free_port()
    env = {
        "PATH": os.environ["PATH"],
        "KITTI_EVAL_DATA_DIR": str(tmp_path / "data"),
        "KITTI_EVAL_WORKER_PROCESSES": "0",
        "KITTI_EVAL_JOB_THREADS": "1",
    }
    if "NUMBA_CACHE_DIR" in os.environ:  # the suite's kernels, where the suite keeps them
        env["NUMBA_CACHE_DIR"] = os.environ["NUMBA_CACHE_DIR"]
    argv = [sys.executable, "-m", "kitti_eval.cli", "serve", "--port", str(port)]
    log_path = tmp_path / "serve.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as client:
            deadline = time.monotonic() + 300
            while True:
                assert proc.poll() is None, log_path.read_text()[-4000:]
                try:
                    if client.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline, log_path.read_text()[-4000:]
                time.sleep(0.2)
            for _ in range(3):
                assert client.get("/healthz").status_code == 200
            r = client.post(
                "/v1/evaluations", data={"gt": "demo"}, files={"predictions": (pred.name, pred.read_bytes())}
            )
            assert r.status_code == 201, r.text
            metrics = client.get("/metrics").text
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    assert 'route="/healthz",status="200"} 3.0' in metrics
    text = log_path.read_text()
    lines = [json.loads(line) for line in text.splitlines()]  # every line JSON: this fails on any other
    assert {"Started server process", "Application startup complete."} <= {
        line["message"].partition(" [")[0] for line in lines if line["logger"] == "uvicorn.error"
    }
    routes = [line["route"] for line in lines if line["logger"] == "kitti_eval.server.access"]
    assert routes == ["/v1/evaluations"], routes
