"""``kitti-eval worker --check``: a worker container's healthcheck. A worker process records itself on the
database (its row in ``job_workers``) once its kernels are warm and it polls for jobs, and beats the row every
15 s while it runs; the check is healthy when a process of this host beat within the last three beats: it is
connected and polling. It opens the database only (no kernels, no worker), so it answers in about a second."""

from __future__ import annotations

import socket
import sys
from datetime import timedelta
from pathlib import Path
from typing import Any

import sqlalchemy.exc

from ..settings import Settings, settings_error
from ..store import Store
from .queue import now_utc
from .workers import Workers

__all__ = ["CHECK_WITHIN_S", "check_workers"]

#: three beats of a worker process (Workers' beat_s)
CHECK_WITHIN_S = 3 * Workers.BEAT_S


def _say(msg: str) -> None:
    print(f"kitti-eval worker: {msg}", file=sys.stderr)  # noqa: T201


def check_workers(*, data_dir: Path | None, database_url: str | None, within_s: float = CHECK_WITHIN_S) -> int:
    """0 with one line saying how many worker processes of this host are connected and polling, else 1 with one
    line saying why not (none seen lately, or the database not reached); 2 when the settings are refused."""
    overrides: dict[str, Any] = {k: v for k, v in (("data_dir", data_dir), ("database_url", database_url)) if v}
    try:
        settings = Settings(**overrides)
    except ValueError as e:
        _say(settings_error(e))
        return 2
    host = socket.gethostname()
    store = Store(settings.resolved_database_url)
    try:
        since = now_utc() - timedelta(seconds=within_s)
        seen = [w for w in store.worker_store.workers_seen(since) if w.host == host]
    except sqlalchemy.exc.SQLAlchemyError as e:
        reason = (str(getattr(e, "orig", None) or e).strip() or type(e).__name__).splitlines()[0]
        _say(f"unhealthy: cannot read the database {settings.database_name}: {reason}")
        return 1
    finally:
        store.dispose()
    if not seen:
        _say(
            f"unhealthy: no worker process of {host} seen on the database {settings.database_name} in the last "
            f"{within_s:g} s (starting: warming its kernels; or not connected)"
        )
        return 1
    threads = sum(w.threads for w in seen)
    _say(
        f"healthy: connected and polling: {len(seen)} worker process{'es' * (len(seen) != 1)} of {host} "
        f"({threads} thread{'s' * (threads != 1)}) seen on the database {settings.database_name} in the last "
        f"{within_s:g} s"
    )
    return 0
