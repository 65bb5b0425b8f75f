"""Uploaded files, hostile until proven otherwise: identify them by content, unpack archives safely, load.

An upload is one of

* a pickle, plain or gzipped (OpenPCDet ``result.pkl`` / ``kitti_infos_val.pkl``): read only through
  :func:`kitti_eval.io.loaders.annotations_from_pickle` (the restricted unpickler), with the decompressed size
  capped;
* a zip or a tar (plain, gz, bz2, xz) of KITTI txt files (a ``label_2`` or result folder), unpacked by
  :func:`kitti_eval.io.archives.extract_txt_folder` (the library's one safe extractor: no absolute paths, no
  ``..``, no links, devices, fifos or sparse files, at most ``max_members`` members and
  ``max_unpacked_bytes`` unpacked, only the ``.txt`` files of one folder written, flat, into a scratch
  folder the service owns; nothing is ever extracted with ``extractall``). Its refusals are reported as
  :class:`~kitti_eval_server.errors.ArchiveError`.
"""

from __future__ import annotations

import enum
import hashlib
import io
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from kitti_eval.core.frames import Annotations, Kind
from kitti_eval.errors import InputError, UnsafePickleError
from kitti_eval.io import archives
from kitti_eval.io.archives import ArchiveKind, ArchiveLimits, sniff_input
from kitti_eval.io.loaders import annotations_from_pickle, input_limits, load_kitti_txt_dir

from ..errors import ArchiveError

__all__ = [
    "FileIn",
    "InputFormat",
    "Limits",
    "Upload",
    "Loaded",
    "Received",
    "receive_content",
    "receive_upload",
    "stored_upload",
    "sniff",
    "extract_txt_folder",
    "load_upload",
    "load_txt_folder",
    "clean_filename",
]

_CHUNK = 1 << 20


class InputFormat(str, enum.Enum):
    PICKLE = "pickle"
    ZIP = "zip"
    TAR = "tar"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class FileIn:
    """An uploaded file as the routes hand it over: its spooled bytes and the client's name."""

    file: IO[bytes]
    filename: str | None


@dataclass(frozen=True)
class Limits:
    """Upload limits: ``max_unpacked_bytes`` also caps a decompressed pickle; the archive caps are built from
    these (with the settings that raise them named in the messages)."""

    max_unpacked_bytes: int
    max_members: int
    #: frames one upload may hold; None: the library's (KITTI_EVAL_MAX_FRAMES, else 200,000)
    max_frames: int | None = None

    @property
    def frames(self) -> int:
        return self.max_frames if self.max_frames is not None else input_limits()[1]

    @property
    def archive(self) -> ArchiveLimits:
        return ArchiveLimits(
            max_members=self.max_members,
            max_unpacked_bytes=self.max_unpacked_bytes,
            members_setting="KITTI_EVAL_MAX_ARCHIVE_MEMBERS",
            bytes_setting="KITTI_EVAL_MAX_UNPACKED_MB",
        )


@dataclass(frozen=True)
class Upload:
    """An uploaded file: its (seekable) bytes, the client's name for it, its sha256 and size."""

    file: IO[bytes]
    filename: str
    sha256: str
    size: int


@dataclass(frozen=True)
class Loaded:
    format: InputFormat
    annotations: Annotations
    #: the txt folder an archive was unpacked to (None for pickles)
    folder: Path | None


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
    file.seek(0)
    content = file.read()
    return Received(clean_filename(filename, default_name), hashlib.sha256(content).hexdigest(), content)


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


# ------------------------------------------------------------------------------------------- sniffing


def sniff(file: IO[bytes], source: str) -> InputFormat:
    """What an upload is, from its content: the library's test (:func:`kitti_eval.io.archives.sniff_input`), so a
    file loads the same way here and through the CLI."""
    return InputFormat(sniff_input(file, source))


# ------------------------------------------------------------------------------------------ archives


def extract_txt_folder(
    file: IO[bytes], fmt: InputFormat, dest: Path, limits: Limits, source: str
) -> tuple[Path, dict[str, str]]:
    """Unpack the txt files of an archive into ``dest``; returns their folder and {path: member name}.

    :func:`kitti_eval.io.archives.extract_txt_folder` does the work; its refusals become ArchiveError (same
    message: it names the upload and archive members only, never a server path).
    """
    if fmt is InputFormat.ZIP:
        kind: ArchiveKind = "zip"
    elif fmt is InputFormat.TAR:
        kind = "tar"
    else:  # pragma: no cover - callers pass archives only
        raise ValueError(f"not an archive format: {fmt}")
    try:
        return archives.extract_txt_folder(file, kind, dest, limits.archive, source)
    except InputError as e:
        raise ArchiveError(str(e)) from None


# -------------------------------------------------------------------------------------------- loading


def _relabel(e: InputError, names: dict[str, str], source: str) -> InputError:
    """The same error with the scratch path replaced by 'upload:member' (no server paths reach clients)."""
    where = source
    if e.source in names:
        member = names[e.source]
        where = source if member in (".", "") else f"{source}:{member}"
    cls = UnsafePickleError if isinstance(e, UnsafePickleError) else InputError
    return cls(e.message, source=where, frame=e.frame, field=e.field)


def load_upload(
    upload: Upload,
    kind: Kind,
    scratch: Path,
    limits: Limits,
    *,
    keep_lidar: bool = False,
    known_frames: Collection[str] | None = None,
) -> Loaded:
    """Identify, unpack and load one upload as ground truth or detections (``keep_lidar``, ``known_frames``:
    see :func:`kitti_eval.io.loaders.load_detections`). A pickle of more frames than the limit is refused
    before it is built.

    Raises InputError / UnsafePickleError (from the library), ArchiveError or UnknownFormatError; every
    message names the upload by the client's file name.
    """
    fmt = sniff(upload.file, upload.filename)
    if fmt is InputFormat.PICKLE:
        annotations = annotations_from_pickle(
            upload.file,
            kind,
            source=upload.filename,
            max_bytes=limits.max_unpacked_bytes,
            max_frames=limits.frames,
            keep_lidar=keep_lidar,
            known_frames=known_frames,
        )
        return Loaded(fmt, annotations, None)
    folder, names = extract_txt_folder(upload.file, fmt, scratch, limits, upload.filename)
    annotations = load_txt_folder(folder, names, upload.filename, limits, kind, known_frames=known_frames)
    return Loaded(fmt, annotations, folder)


def load_txt_folder(
    folder: Path,
    names: dict[str, str],
    source: str,
    limits: Limits,
    kind: Kind = "detections",
    *,
    known_frames: Collection[str] | None = None,
) -> Annotations:
    """The txt files of an unpacked upload (:func:`extract_txt_folder`'s folder and names), loaded; errors name
    the upload and its members, never the folder."""
    try:
        return load_kitti_txt_dir(folder, kind, max_frames=limits.frames, known_frames=known_frames)
    except InputError as e:
        raise _relabel(e, names, source) from None
