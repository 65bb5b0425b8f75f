"""Uploaded files as the service keeps them, unread: their bytes, counted and hashed once, and the client's name
for them (for messages and records only, never a path). Reading one (what it is, unpacking, loading, the
submission's checks) is the library's one call, :func:`kitti_eval.io.upload.read_upload`.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from typing import IO

__all__ = [
    "FileIn",
    "Upload",
    "Received",
    "receive_content",
    "receive_upload",
    "stored_upload",
    "clean_filename",
]

_CHUNK = 1 << 20


@dataclass(frozen=True)
class FileIn:
    """An uploaded file as the routes hand it over: its spooled bytes and the client's name."""

    file: IO[bytes]
    filename: str | None


@dataclass(frozen=True)
class Upload:
    """An uploaded file: its (seekable) bytes, the client's name for it, its sha256 and size."""

    file: IO[bytes]
    filename: str
    sha256: str
    size: int


def clean_filename(name: str | None, default: str) -> str:
    """The client's file name, for messages and records only (never used as a path)."""
    text = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    text = "".join(c for c in text if c.isprintable()).strip()[:200]
    return text or default


@dataclass(frozen=True)
class Received:
    """An upload kept as it is, unread (a job's input): the client's name for it, its bytes and their sha256."""

    filename: str
    sha256: str
    content: bytes

    @property
    def size(self) -> int:
        return len(self.content)


def receive_content(file: IO[bytes], filename: str | None, default_name: str) -> Received:
    """An already spooled upload's bytes, read once, and their sha256."""
    content = _whole(file)
    return Received(clean_filename(filename, default_name), hashlib.sha256(content).hexdigest(), content)


def _whole(file: IO[bytes]) -> bytes:
    """All of a spooled upload's bytes. One held in memory (a ``BytesIO``, or the form parser's
    ``SpooledTemporaryFile`` that has not rolled over to disk, whose ``BytesIO`` it keeps as ``_file``) hands over
    its buffer itself rather than a copy: reading a val-sized file in memory copied 22 MB, 25-70 ms of the web
    process's CPU an upload on a loaded machine. Nothing is written to the file afterwards."""
    held = getattr(file, "_file", file)
    if isinstance(held, io.BytesIO):
        return held.getvalue()
    file.seek(0)
    return file.read()


def stored_upload(content: bytes, filename: str, sha256: str) -> Upload:
    """A file the service keeps (a job's input, kept predictions, a ground truth's file), as an upload: its name
    and sha256 are the ones recorded when it was received, so it is not hashed again."""
    return Upload(file=io.BytesIO(content), filename=filename, sha256=sha256, size=len(content))


def receive_upload(file: IO[bytes], filename: str | None, default_name: str) -> Upload:
    """Hash an already spooled upload (in chunks) and rewind it."""
    file.seek(0)
    digest = hashlib.sha256()
    size = 0
    while chunk := file.read(_CHUNK):
        digest.update(chunk)
        size += len(chunk)
    file.seek(0)
    return Upload(file=file, filename=clean_filename(filename, default_name), sha256=digest.hexdigest(), size=size)
