"""Scratch folders for unpacking uploads, under ``<data_dir>/tmp``, named after the process that made them.

A process holds an exclusive lock on ``<data_dir>/run/<owner>.lock`` from :meth:`ScratchSpace.open` until
:meth:`ScratchSpace.close`, and names its folders ``<owner>.<id>``. The operating system drops the lock when
the process ends, however it ends, so a starting process can tell the folders of a process that is gone (a
``kill -9`` leaves them behind) from those of one still working on the same data folder (``uvicorn
--workers``, a second container on the volume): it removes the first at once and leaves the second. Entries
it did not name are never touched, except bare ids (the names before the owner was part of them) older than
an hour, as before.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import secrets
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["ScratchSpace", "OWNER_PREFIX"]

log = logging.getLogger("kitti_eval.server")

OWNER_PREFIX = "kitti-eval-"
_FOLDER = re.compile(rf"({re.escape(OWNER_PREFIX)}[0-9a-f]{{16}})\.[0-9a-f]{{32}}")
_LOCK = re.compile(rf"({re.escape(OWNER_PREFIX)}[0-9a-f]{{16}})\.lock")
_OLDER_LAYOUT = re.compile(r"[0-9a-f]{32}")
_OLDER_LAYOUT_STALE_S = 3600


class ScratchSpace:
    """This process's scratch folders, and the removal of those a dead process left."""

    def __init__(self, data_dir: Path) -> None:
        self.root = data_dir / "tmp"
        self.locks = data_dir / "run"
        self.owner = OWNER_PREFIX + secrets.token_hex(8)
        self._lock_fd: int | None = None

    def open(self) -> None:
        """Take this process's lock, then remove what dead processes left (called once, at start-up)."""
        self.root.mkdir(parents=True, exist_ok=True)
        self.locks.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.locks / f"{self.owner}.lock", os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._lock_fd = fd
        removed = self.clean()
        if removed:
            log.info("removed %d scratch folders left by stopped processes", removed)

    def close(self) -> None:
        """Give up the lock (the folders are gone by then: each is removed when its work ends)."""
        if self._lock_fd is None:
            return
        (self.locks / f"{self.owner}.lock").unlink(missing_ok=True)
        os.close(self._lock_fd)
        self._lock_fd = None

    @contextmanager
    def folder(self) -> Iterator[Path]:
        """A new empty folder of this process's, removed with its content on the way out."""
        assert self._lock_fd is not None, "open() the scratch space first"
        path = self.root / f"{self.owner}.{secrets.token_hex(16)}"
        path.mkdir()
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def clean(self) -> int:
        """Remove the scratch folders and lock files of processes that are gone; how many folders went."""
        alive: dict[str, bool] = {self.owner: True}
        removed = 0
        now = time.time()
        for entry in self.root.iterdir():
            match = _FOLDER.fullmatch(entry.name)
            try:
                if match is not None:
                    owner = match[1]
                    if owner not in alive:
                        alive[owner] = self._is_alive(owner)
                    stale = not alive[owner]
                else:
                    stale = bool(_OLDER_LAYOUT.fullmatch(entry.name)) and (
                        now - entry.stat().st_mtime > _OLDER_LAYOUT_STALE_S
                    )
                if stale and entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                    removed += 1
            except OSError:
                continue
        for lock in self.locks.iterdir():
            match = _LOCK.fullmatch(lock.name)
            if match is not None and match[1] not in alive:
                self._is_alive(match[1])  # removes the lock file of a process that is gone
        return removed

    def _is_alive(self, owner: str) -> bool:
        """Whether the process ``owner`` still holds its lock. The lock file of one that does not is removed."""
        path = self.locks / f"{owner}.lock"
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            return False  # stopped (a clean stop removes it), or cleaned by another process already
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            path.unlink(missing_ok=True)  # locked by us now: its owner is gone
            return False
        finally:
            os.close(fd)
