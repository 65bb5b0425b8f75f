"""``kitti-eval admin backup DIR`` and ``restore DIR``: a consistent copy of a running service, and the service
again from it in an empty data folder.

What a service keeps is its database (every record and every file: registered ground truths, kept predictions,
the inputs of queued jobs) and, in its data folder, the admin token it generated (``admin-token``). The rest of
the data folder is made again at start (the unpacked ground truths, from the database; the scratch space).

* **SQLite**: the database is copied with SQLite's online backup API (``sqlite3.Connection.backup``), in one
  step under a read transaction: a copy of the database as it was at one moment, taken while the service
  writes (WAL mode: readers do not stop writers, nor writers the copy).
* **PostgreSQL**: ``pg_dump --format=custom`` (a snapshot of one transaction, the documented way), restored by
  ``pg_restore`` into an empty database.

``DIR`` gets ``manifest.json`` (what was copied, the schema's revision, each file's sha256 and size), the
database (``kitti-eval.db`` or ``database.dump``) and the data folder's files. Restoring checks the sha256s,
refuses a data folder or a database that holds one already, and says when the copy's schema is older than this
release's (``kitti-eval admin db upgrade`` then).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.engine import make_url

from kitti_eval import __version__

from .settings import Settings
from .store import Store

__all__ = ["BackupError", "Backup", "backup", "restore"]

MANIFEST = "manifest.json"
SQLITE_FILE = "kitti-eval.db"
PG_DUMP_FILE = "database.dump"
#: the data folder's own files a backup carries (the rest is made again at start)
DATA_FILES = ("admin-token",)
FORMAT = 1


class BackupError(Exception):
    """A backup or a restore that cannot be done; the message says why and what to do."""


@dataclass(frozen=True)
class Backup:
    folder: Path
    backend: str
    revision: str | None
    files: dict[str, dict[str, object]]
    seconds: float


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _libpq_url(settings: Settings) -> str:
    """The database's URL as libpq (pg_dump, pg_restore) reads it: no SQLAlchemy driver name."""
    url = make_url(settings.resolved_database_url).set(drivername="postgresql")
    return url.render_as_string(hide_password=False)


def _tool(name: str) -> str:
    found = shutil.which(name)
    if found is None:
        raise BackupError(f"{name} is not on PATH: install PostgreSQL's client programs (Debian: postgresql-client)")
    return found


def _run(argv: list[str], what: str) -> None:
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        reason = (done.stderr.strip() or f"exit {done.returncode}").splitlines()[-1]
        raise BackupError(f"{what} failed: {reason}")


def _empty_target(folder: Path) -> None:
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise BackupError(f"{folder} is not an empty folder: a backup goes into a new or empty one")
    folder.mkdir(parents=True, exist_ok=True)


def backup(settings: Settings, folder: Path) -> Backup:
    """A consistent copy of the service's database and data files into ``folder`` (new or empty)."""
    started = time.monotonic()
    _empty_target(folder)
    store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
    try:
        state = store.schema_state()
        backend = store.dialect
    finally:
        store.dispose()
    if state.empty:
        raise BackupError(f"the database {settings.database_name} holds no kitti-eval tables: nothing to back up")
    if backend == "sqlite":
        source = Path(str(make_url(settings.resolved_database_url).database))
        target = folder / SQLITE_FILE
        src = sqlite3.connect(source, timeout=settings.database_busy_s)
        try:
            dst = sqlite3.connect(target)
            try:
                src.backup(dst)  # every page in one step: the database as it was at one moment
            finally:
                dst.close()
        finally:
            src.close()
    else:
        target = folder / PG_DUMP_FILE
        argv = [_tool("pg_dump"), "--format=custom", "--no-owner", "--no-privileges", f"--file={target}"]
        _run([*argv, _libpq_url(settings)], "pg_dump")
    copied = [target]
    for name in DATA_FILES:
        path = settings.data_dir / name
        if path.is_file():
            shutil.copy2(path, folder / name)
            copied.append(folder / name)
    files = {p.name: {"sha256": _sha256(p), "bytes": p.stat().st_size} for p in copied}
    manifest = {
        "format": FORMAT,
        "kitti_eval": __version__,
        "backend": backend,
        "schema_revision": state.revision,
        "created_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "files": files,
    }
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return Backup(folder, backend, state.revision, files, time.monotonic() - started)


def _manifest(folder: Path) -> dict[str, Any]:
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError) as e:
        raise BackupError(f"{folder / MANIFEST} cannot be read ({e}): not a kitti-eval backup") from None
    if (
        not isinstance(manifest, dict)
        or manifest.get("format") != FORMAT
        or not isinstance(manifest.get("files"), dict)
    ):
        raise BackupError(f"{folder / MANIFEST} is not a kitti-eval backup's manifest (format {FORMAT})")
    for name, entry in manifest["files"].items():
        path = folder / name
        if Path(name).name != name or not path.is_file():
            raise BackupError(f"{folder} lacks {name}, which its manifest lists")
        if _sha256(path) != entry.get("sha256"):
            raise BackupError(f"{path} is not the file the backup made (its sha256 differs): the copy is damaged")
    return manifest


def restore(settings: Settings, folder: Path) -> Backup:
    """The service's database and data files from the backup in ``folder``, into the settings' data folder (no
    database there yet) and database (SQLite in that folder, or an empty PostgreSQL database)."""
    started = time.monotonic()
    manifest = _manifest(folder)
    backend = str(manifest["backend"])
    store = Store(settings.resolved_database_url, busy_s=settings.database_busy_s)
    try:
        if store.dialect != backend:
            raise BackupError(
                f"{folder} is a backup of a {backend} database; the settings name a {store.dialect} one "
                f"({settings.database_name})"
            )
        if backend == "sqlite":
            target = Path(str(make_url(settings.resolved_database_url).database))
            if target.exists():
                raise BackupError(f"{target} exists: restore into a data folder without a database")
        elif not store.schema_state().empty:
            raise BackupError(
                f"the database {settings.database_name} holds kitti-eval tables: restore into an empty one"
            )
    finally:
        store.dispose()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    for name in DATA_FILES:
        if (settings.data_dir / name).exists() and name in manifest["files"]:
            raise BackupError(f"{settings.data_dir / name} exists: restore into a data folder without one")
    if backend == "sqlite":
        partial = target.with_name(target.name + ".restoring")
        shutil.copyfile(folder / SQLITE_FILE, partial)
        check = sqlite3.connect(partial)
        try:
            result = check.execute("PRAGMA integrity_check").fetchone()[0]
        finally:
            check.close()
        if result != "ok":
            partial.unlink()
            raise BackupError(f"{folder / SQLITE_FILE} fails SQLite's integrity check: {result}")
        os.replace(partial, target)
    else:
        argv = [_tool("pg_restore"), "--no-owner", "--no-privileges", "--exit-on-error", "--single-transaction"]
        _run([*argv, f"--dbname={_libpq_url(settings)}", str(folder / PG_DUMP_FILE)], "pg_restore")
    for name in DATA_FILES:
        if name in manifest["files"]:
            shutil.copyfile(folder / name, settings.data_dir / name)
            os.chmod(settings.data_dir / name, 0o600)
    revision = manifest.get("schema_revision")
    files: dict[str, dict[str, object]] = manifest["files"]
    return Backup(folder, backend, revision if isinstance(revision, str) else None, files, time.monotonic() - started)
