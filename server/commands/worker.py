"""``kitti-eval worker``: worker processes that run the service's accepted evaluations, on this machine or any
other that reaches the service's database (the server extra). Needs the database only.

Exit codes: 0 drained and stopped (SIGTERM or SIGINT), 1 no database, a process that did not stop cleanly or no
server extra, 2 usage. With ``--check`` (a healthcheck): 0 when a worker process of this host is seen on the
database, else 1.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from . import without_server_extra

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "worker",
        help="run the service's evaluations in worker processes (on any machine that reaches its database)",
        description="Run the jobs the service accepts (evaluations) in worker processes, each a Python process "
        "of its own, so that N processes use N cores. A worker needs only the database: the jobs' inputs and the "
        "ground truths' files are there. SIGTERM or SIGINT drains: no new job is taken, the running ones finish "
        "(or, after --grace seconds, go back to the queue), then the command exits 0. Reads the service's "
        "settings (KITTI_EVAL_DATABASE_URL, KITTI_EVAL_DATA_DIR, KITTI_EVAL_JOB_LEASE_S, ...); needs the server "
        "extra.",
    )
    p.add_argument("--database-url", help="KITTI_EVAL_DATABASE_URL of the service, e.g. postgresql://user:pw@host/db")
    p.add_argument("--data-dir", type=Path, help="KITTI_EVAL_DATA_DIR of the service: its SQLite database")
    p.add_argument(
        "--processes", type=int, metavar="N", help="worker processes (default: the cores this machine gives it)"
    )
    p.add_argument("--threads", type=int, default=1, metavar="N", help="workers in each process (default 1)")
    p.add_argument(
        "--grace",
        type=float,
        metavar="S",
        help="on SIGTERM or SIGINT, the seconds a running job has to finish before it goes back to the queue "
        "(default KITTI_EVAL_SHUTDOWN_GRACE_S, 30)",
    )
    p.add_argument(
        "--work-dir",
        type=Path,
        metavar="DIR",
        help="the workers' own folder: scratch space and unpacked ground truths (default: a temporary one, "
        "removed at the end)",
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="start nothing: exit 0 when a worker process of this host has recorded itself on the database lately "
        "(connected, kernels warm, polling for jobs), else 1; a container's healthcheck",
    )
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    if args.check:
        try:
            from ..jobs.check import check_workers
        except ImportError as e:
            return without_server_extra("worker", e)
        return check_workers(data_dir=args.data_dir, database_url=args.database_url)
    try:
        from .process import run_pool
    except ImportError as e:
        return without_server_extra("worker", e)
    return run_pool(
        data_dir=args.data_dir,
        database_url=args.database_url,
        processes=args.processes,
        threads=args.threads,
        grace_s=args.grace,
        work_dir=args.work_dir,
    )
