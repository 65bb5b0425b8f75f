"""A throwaway PostgreSQL cluster for the server tests: a temp folder, a free loopback port, torn down after.

PostgreSQL refuses to run as root, so as root the cluster runs as ``nobody`` through ``runuser`` (Debian's
util-linux); otherwise as the current user. The binaries are found on PATH (``pg_ctl``) or under
``/usr/lib/postgresql/<version>/bin`` (Debian's ``postgresql`` package).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from server_helpers import free_port

__all__ = ["PostgresCluster", "find_postgres_bin", "why_no_postgres"]


def find_postgres_bin() -> Path | None:
    """The folder holding initdb, pg_ctl and postgres, or None."""
    found = shutil.which("pg_ctl")
    if found:
        folder = Path(found).resolve().parent
        if (folder / "initdb").exists():
            return folder
    candidates = sorted(
        glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"),
        key=lambda p: [int(x) if x.isdigit() else 0 for x in Path(p).parts[-3].split(".")],
    )
    return Path(candidates[-1]).parent if candidates else None


def _as_nobody() -> bool:
    return os.geteuid() == 0


def why_no_postgres() -> str | None:
    """None when a cluster can be started here, else the reason to skip."""
    if find_postgres_bin() is None:
        return (
            "no PostgreSQL binaries (pg_ctl/initdb on PATH or /usr/lib/postgresql/*/bin); "
            "install Debian's 'postgresql' package to run this test"
        )
    if _as_nobody() and shutil.which("runuser") is None:
        return "running as root and 'runuser' is missing, so the cluster cannot run as an unprivileged user"
    return None


class PostgresCluster:
    """initdb + pg_ctl start in a temp folder; ``url`` is a SQLAlchemy URL for the ``postgres`` database."""

    def __init__(self) -> None:
        bindir = find_postgres_bin()
        assert bindir is not None
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="kitti-eval-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.started = False
        #: the addresses the server listens on (listen_addresses), and networks trusted besides loopback
        self.listen = "127.0.0.1"
        self.trusted: list[str] = []
        if _as_nobody():
            nobody = pwd.getpwnam("nobody")
            os.chown(self.root, nobody.pw_uid, nobody.pw_gid)
            os.chmod(self.root, 0o700)

    @property
    def url(self) -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/postgres"

    def _run(self, *args: str, timeout: float = 60) -> None:
        cmd = [args[0] if args[0] == "sh" else str(self.bindir / args[0]), *args[1:]]
        if _as_nobody():
            cmd = ["runuser", "-u", "nobody", "--", *cmd]
        proc = subprocess.run(cmd, cwd=self.root, capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(
                f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}\n{self.log()}"
            )

    def start(self) -> PostgresCluster:
        self._run(
            "initdb", "-D", str(self.data), "-U", "postgres", "--auth=trust", "-E", "UTF8", "--locale=C", "--no-sync"
        )
        return self.resume()

    def halt(self) -> None:
        """Stop the server (``pg_ctl stop -m fast``: sessions are ended, the data is kept), as an outage."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "30", "stop", timeout=60)
        self.started = False

    def resume(self) -> PostgresCluster:
        """Start the server on its data folder and port (the first start, or again after :meth:`halt`)."""
        options = f"-p {self.port} -k {self.root} -c listen_addresses={self.listen} -c max_connections=60"
        if self.trusted:
            hba = self.data / "pg_hba.conf"
            lines = "".join(f"host all all {network} trust\n" for network in self.trusted)
            self._run("sh", "-c", f"printf '%s' '{lines}' >> {hba}")
        self._run(
            "pg_ctl",
            "-D",
            str(self.data),
            "-o",
            options,
            "-l",
            str(self.root / "postgres.log"),
            "-w",
            "-t",
            "60",
            "start",
            timeout=90,
        )
        self.started = True
        self._wait_accepting()
        return self

    def _wait_accepting(self, timeout: float = 30) -> None:
        import psycopg

        deadline = time.monotonic() + timeout
        while True:
            try:
                with psycopg.connect(
                    host="127.0.0.1", port=self.port, user="postgres", dbname="postgres", connect_timeout=2
                ):
                    return
            except psycopg.OperationalError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    def stop(self) -> None:
        try:
            if self.started:
                self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "-t", "30", "stop", timeout=60)
                self.started = False
        finally:
            shutil.rmtree(self.root, ignore_errors=True)

    def log(self) -> str:
        try:
            return (self.root / "postgres.log").read_text(errors="replace")[-3000:]
        except OSError:
            return ""

    def __enter__(self) -> PostgresCluster:
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc: object) -> None:
        self.stop()
