"""Scratch folders: what a killed process left is removed when the next one starts, and nothing else is."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from server_helpers import ADMIN_TOKEN, ROOT, app_client

from kitti_eval_server import Settings
from kitti_eval_server.service import Service

HOURS_AGO = time.time() - 2 * 3600

#: a service process that opens a scratch folder (as an upload being unpacked does), says where, and waits
_HOLD_SCRATCH = """
import sys, time
from pathlib import Path
from kitti_eval_server import Settings
from kitti_eval_server.service import Service

service = Service(Settings(data_dir=Path(sys.argv[1]), admin_token="t", register_demo=False, warmup=False))
service.start()
with service.scratch() as folder:
    (folder / "pred").mkdir()
    (folder / "pred" / "000000.txt").write_text("Car 0 0 0 1 2 3 4 1 1 1 1 1 1 0 0.9\\n")
    print(folder, flush=True)
    time.sleep(120)
"""


def _settings(data_dir: Path) -> Settings:
    return Settings(data_dir=data_dir, admin_token=ADMIN_TOKEN, register_demo=False, warmup=False)


def test_scratch_of_a_killed_process_is_removed_at_the_next_start(tmp_path) -> None:
    data_dir = tmp_path / "data"
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLD_SCRATCH, str(data_dir)], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        left = Path(proc.stdout.readline().strip())
        assert (left / "pred" / "000000.txt").is_file()
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    assert left.is_dir()  # kill -9: no clean-up ran
    with app_client(data_dir, register_demo=False, warmup=False):
        assert not left.exists()  # gone at start-up, not an hour later
        assert list((data_dir / "tmp").iterdir()) == []


def test_start_up_leaves_a_live_process_scratch_and_what_is_not_its_own(tmp_path) -> None:
    data_dir = tmp_path / "data"
    other = Service(_settings(data_dir))  # another worker on the same data folder, busy unpacking
    other.start()
    try:
        with other.scratch() as busy:
            (busy / "000000.txt").write_text("x")
            os.utime(busy, (HOURS_AGO, HOURS_AGO))  # however old it is
            tmp = data_dir / "tmp"
            foreign = [tmp / "notes.txt", tmp / "someone-else", tmp / "kitti-eval-not-ours"]
            foreign[0].write_text("not the service's")
            foreign[1].mkdir()
            foreign[2].mkdir()
            for path in foreign:
                os.utime(path, (HOURS_AGO, HOURS_AGO))
            with app_client(data_dir, register_demo=False, warmup=False) as c:
                service = c.app.state.service
                assert (busy / "000000.txt").read_text() == "x"
                assert all(path.exists() for path in foreign)
                with service.scratch() as mine:  # and the new one's own folders are its own
                    assert mine.parent == tmp and mine.name != busy.name
                assert not mine.exists()
            assert busy.is_dir()
    finally:
        other.stop()
    assert not busy.exists()
    leftovers = sorted(p.name for p in (data_dir / "tmp").iterdir())
    assert leftovers == sorted(p.name for p in foreign)


def test_folders_of_the_older_layout_go_after_an_hour(tmp_path) -> None:
    """Before the owner was part of the name, scratch folders were bare ids; their owner cannot be told,
    so they go by age, as they did."""
    tmp = tmp_path / "data" / "tmp"
    tmp.mkdir(parents=True)
    old, recent = tmp / ("a" * 32), tmp / ("b" * 32)
    for folder in (old, recent):
        folder.mkdir()
        (folder / "000000.txt").write_text("x")
    os.utime(old, (HOURS_AGO, HOURS_AGO))
    service = Service(_settings(tmp_path / "data"))
    service.start()
    try:
        assert not old.exists() and recent.is_dir()
    finally:
        service.stop()
