"""A worker process warms its kernels at the priority it was started with and lowers it (``worker_nice``) only
before it takes a job: accepting comes before evaluating, but a start, which accepts nothing yet, is not slowed."""

from __future__ import annotations

import os
import subprocess
import sys

from server_helpers import ROOT

#: a worker's start (Service.run_jobs), the priority it warmed its kernels at and the one it takes jobs at
_START = """
import os, sys
from pathlib import Path
import kitti_eval_server.service as service_module
from kitti_eval_server import Settings
from kitti_eval_server.service import Service

warmed_at = []
real = service_module.warm_up

def warm_up(**kw):
    warmed_at.append(os.nice(0))
    real(**kw)

service_module.warm_up = warm_up
service = Service(Settings(data_dir=Path(sys.argv[1]), job_threads=1, register_demo=False, warmup=False))
started_at = os.nice(0)
service.run_jobs(nice=7)
print(started_at, warmed_at[0], os.nice(0), flush=True)
service.stop(grace_s=0)
"""


def test_a_worker_warms_up_at_its_own_priority_and_takes_jobs_at_the_lower_one(tmp_path) -> None:
    env = {**os.environ, "KITTI_EVAL_DATABASE_URL": f"sqlite:///{tmp_path / 'kitti-eval.db'}"}
    out = subprocess.run(
        [sys.executable, "-c", _START, str(tmp_path / "work")], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    started, warmed, taking_jobs = (int(x) for x in out.stdout.split())
    assert warmed == started
    assert taking_jobs == min(19, started + 7)
