"""The idempotency keys of submissions sent and not yet shown scored, so that a run of ``kitti-eval submit``
again (the first killed after its file reached the service: ``kill -9``, a closed laptop, a cancelled CI job)
sends the key the first run sent and is answered with the submission it made, counted once.

A key is saved, before the file is sent, under (the service, the benchmark, the phase, the file's sha256) in
``submissions.json`` of the client's folder; it is forgotten once its submission is shown scored (or failed,
or refused: nothing of it counts then). A key older than :data:`KEEP_DAYS` is forgotten (the service keeps a
key for a day by default, ``KITTI_EVAL_IDEMPOTENCY_KEY_HOURS``)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from ..errors import ConfigError
from .files import write_private_json

__all__ = ["PendingKeys", "Held", "sha256_of", "KEEP_DAYS", "FILE_NAME"]

FILE_NAME = "submissions.json"
#: how long a saved key is kept at most
KEEP_DAYS = 7.0


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
        entries = self._read()
        entries[_entry_name(service, benchmark, phase, sha256)] = {"key": key, "saved_at": time.time()}
        write_private_json(self.path, entries)

    def forget(self, key: str) -> None:
        """Forgets ``key`` (its submission was shown scored, failed, or was refused)."""
        entries = self._read()
        kept = {k: v for k, v in entries.items() if v["key"] != key}
        if len(kept) != len(entries):
            write_private_json(self.path, kept)

    @contextlib.contextmanager
    def held(self, service: str, benchmark: str, phase: str | None, sha256: str, *, new: bool) -> Iterator[Held]:
        """The key to send (the saved one, else a new one saved first; ``new``: a new one whatever was saved),
        forgotten when the block ends without an error (unless the block set ``keep``: its submission is not
        shown scored yet), or with a refusal that recorded nothing or a job that failed."""
        from ..client import new_key
        from ..errors import QuotaExceeded, ServiceError, ServiceUnreachable, SubmissionRefused

        key = None if new else self.get(service, benchmark, phase, sha256)
        reused = key is not None
        if key is None:
            key = new_key()
            self.save(service, benchmark, phase, sha256, key)
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
