"""The client's own state in its folder (:func:`kitti_eval.client_config.config_dir`): files written readable by their
owner only, and the idempotency keys of submissions sent and not yet shown scored.

**Files.** A file is written whole or not at all, readable by its owner only, whatever was left or planted beside
it: to a temporary file that :func:`tempfile.mkstemp` makes (``O_CREAT | O_EXCL``, mode 0600: a name that exists,
a symlink included, is never opened), made 0600 again with ``fchmod`` before anything is written (a umask or an
ACL cannot widen it), flushed, then renamed over the file.

**Keys.** So that a run of ``kitti-eval submit`` again (the first killed after its file reached the service:
``kill -9``, a closed laptop, a cancelled CI job) sends the key the first run sent and is answered with the
submission it made, counted once: a key is saved, before the file is sent, under (the service, the benchmark,
the phase, the file's sha256) in ``submissions.json``; it is forgotten once its submission is shown scored (or
failed, or refused: nothing of it counts then). A key older than :data:`KEEP_DAYS` is forgotten (the service
keeps a key for a day by default, ``KITTI_EVAL_IDEMPOTENCY_KEY_HOURS``). The file is read and written again
under a lock (``submissions.json.lock``, the ``filelock`` package's: ``flock`` on POSIX, ``msvcrt.locking`` on
Windows), so runs that share the folder, in parallel, lose none of each other's keys; and two runs of the same
file to the same phase send one key (the second reads the key the first saved)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from .errors import ConfigError


def new_key() -> str:
    """A new idempotency key: a random UUID."""
    return str(uuid.uuid4())


__all__ = ["private_folder", "write_private_json", "PendingKeys", "Held", "sha256_of", "KEEP_DAYS", "FILE_NAME"]


def private_folder(folder: Path) -> Path:
    """``folder``, made when missing (readable by its owner only when made here)."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    return folder


def write_private_json(path: Path, data: Any) -> Path:
    """Writes ``data`` as JSON to ``path``, readable and writable by its owner only; returns ``path``."""
    private_folder(path.parent)
    fd, partial = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            if hasattr(os, "fchmod"):
                os.fchmod(out.fileno(), 0o600)
            json.dump(data, out, indent=2)
            out.flush()
            os.fsync(out.fileno())
        os.replace(partial, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise
    return path


FILE_NAME = "submissions.json"
#: how long a saved key is kept at most
KEEP_DAYS = 7.0
#: how long a run waits for another's hold of the keys' file (a read and a write: milliseconds)
LOCK_WAIT_S = 60.0


def sha256_of(raw: BinaryIO) -> str:
    """The sha256 of what ``raw`` holds from its start (the bytes the service fingerprints)."""
    digest = hashlib.sha256()
    raw.seek(0)
    while chunk := raw.read(1 << 20):
        digest.update(chunk)
    raw.seek(0)
    return digest.hexdigest()


def _entry_name(service: str, benchmark: str, phase: str | None, sha256: str) -> str:
    return json.dumps([service, benchmark, phase or "", sha256])


@dataclass
class Held:
    """A key held while its submission is sent: ``reused``, saved by an earlier run; ``keep``: set when the
    submission is not shown scored yet (accepted without waiting), so a run again is answered with it."""

    key: str
    reused: bool
    keep: bool = False


class PendingKeys:
    """The saved keys in the client's folder ``folder``."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / FILE_NAME

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The keys' file held by this run alone (a read then a write: no other run's write falls between)."""
        try:
            from filelock import FileLock, Timeout
        except ImportError:
            raise ConfigError("the client needs filelock: pip install 'kitti-eval[client]'") from None
        private_folder(self.path.parent)
        lock = FileLock(f"{self.path}.lock", timeout=LOCK_WAIT_S, mode=0o600)
        try:
            lock.acquire()
        except Timeout:
            raise ConfigError(
                f"{self.path}.lock: another kitti-eval held the submissions' keys for {LOCK_WAIT_S:.0f} s; "
                "try again when it has ended"
            ) from None
        try:
            yield
        finally:
            lock.release()

    def _read(self) -> dict[str, dict[str, Any]]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as e:
            raise ConfigError(f"{self.path}: not the submissions' keys kitti-eval saves: {e}") from None
        if not isinstance(data, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("key"), str) and isinstance(v.get("saved_at"), (int, float))
            for v in data.values()
        ):
            raise ConfigError(f"{self.path}: not the submissions' keys kitti-eval saves (delete it to start afresh)")
        horizon = time.time() - KEEP_DAYS * 86400
        return {k: v for k, v in data.items() if v["saved_at"] >= horizon}

    def get(self, service: str, benchmark: str, phase: str | None, sha256: str) -> str | None:
        """The key saved for this file sent to this phase, if one is."""
        entry = self._read().get(_entry_name(service, benchmark, phase, sha256))
        return None if entry is None else str(entry["key"])

    def save(self, service: str, benchmark: str, phase: str | None, sha256: str, key: str) -> None:
        """Saves ``key`` for this file sent to this phase (replacing one saved before)."""
        with self._locked():
            self._save(_entry_name(service, benchmark, phase, sha256), key)

    def _save(self, name: str, key: str) -> None:
        entries = self._read()
        entries[name] = {"key": key, "saved_at": time.time()}
        write_private_json(self.path, entries)

    def _take(self, service: str, benchmark: str, phase: str | None, sha256: str, *, new: bool) -> tuple[str, bool]:
        """The key to send and whether an earlier run saved it: the saved one (unless ``new``), else a new one
        saved first, looked up and saved under one hold of the file."""
        name = _entry_name(service, benchmark, phase, sha256)
        with self._locked():
            entry = None if new else self._read().get(name)
            if entry is not None:
                return str(entry["key"]), True
            key = new_key()
            self._save(name, key)
            return key, False

    def forget(self, key: str) -> None:
        """Forgets ``key`` (its submission was shown scored, failed, or was refused)."""
        with self._locked():
            entries = self._read()
            kept = {k: v for k, v in entries.items() if v["key"] != key}
            if len(kept) != len(entries):
                write_private_json(self.path, kept)

    @contextlib.contextmanager
    def held(self, service: str, benchmark: str, phase: str | None, sha256: str, *, new: bool) -> Iterator[Held]:
        """The key to send (the saved one, else a new one saved first; ``new``: a new one whatever was saved),
        forgotten when the block ends without an error (unless the block set ``keep``: its submission is not
        shown scored yet), or with a refusal that recorded nothing or a job that failed."""
        from .errors import QuotaExceeded, ServiceError, ServiceUnreachable, SubmissionRefused

        key, reused = self._take(service, benchmark, phase, sha256, new=new)
        held = Held(key, reused)
        try:
            yield held
        except (QuotaExceeded, SubmissionRefused):
            self.forget(key)  # refused before anything was recorded: nothing of it counts
            raise
        except ServiceUnreachable:
            raise
        except ServiceError as e:
            if e.code not in ("still_pending", "unexpected_answer"):
                self.forget(key)  # its job failed or was cancelled (not counted), or the request was refused
            raise
        else:
            if not held.keep:
                self.forget(key)
