"""``kitti-eval worker --check``: a worker container's healthcheck says whether a worker process of this host is
connected to the database and polling for jobs (its beat, recorded once its kernels are warm)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from server_helpers import app_client

from kitti_eval.cli import main


def test_the_check_is_unhealthy_until_a_worker_of_this_host_beats(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir, job_threads=0, ready=False, warmup=False):
        pass  # the tables, and no worker
    assert main(["worker", "--check", "--data-dir", str(data_dir)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"kitti-eval worker: unhealthy: no worker process of {socket.gethostname()} seen")
    assert err.count("\n") == 1
    with app_client(data_dir, job_threads=1, warmup=False):  # its worker threads beat the process's row
        assert main(["worker", "--check", "--data-dir", str(data_dir)]) == 0
    err = capsys.readouterr().err
    assert err.startswith("kitti-eval worker: healthy: connected and polling: 1 worker process of ")
    assert "(1 thread)" in err
    # stopped: its row is removed, and the check says so again
    assert main(["worker", "--check", "--data-dir", str(data_dir)]) == 1


def test_the_check_without_a_database_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = f"sqlite:///{tmp_path / 'missing' / 'kitti-eval.db'}"
    assert main(["worker", "--check", "--database-url", url]) == 1
    err = capsys.readouterr().err
    assert err.startswith("kitti-eval worker: unhealthy: cannot read the database") and err.count("\n") == 1
