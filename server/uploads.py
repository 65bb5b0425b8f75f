"""Uploaded files, hostile until proven otherwise: identify them by content, unpack archives safely, load.

An upload is one of

* a pickle, plain or gzipped (OpenPCDet ``result.pkl`` / ``kitti_infos_val.pkl``): read only through
  :func:`kitti_eval.safe_pickle.load_pickle`, with the decompressed size capped;
* a zip or a tar (plain, gz, bz2, xz) of KITTI txt files (a ``label_2`` or result folder).

Archives are checked member by member before and while anything is written: no absolute paths, no
``..``, no links, devices, fifos or sparse files, at most ``max_members`` members and ``max_unpacked_bytes``
unpacked (counting what is actually written, not only what headers claim). Only the ``.txt`` files of one
folder are written, flat, under names that are validated basenames, into a scratch folder the service
owns; nothing is ever extracted with ``extractall``.
"""

from __future__ import annotations

import bz2
import enum
import hashlib
import lzma
import re
import stat
import struct
import tarfile
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from kitti_eval.errors import InputError, UnsafePickleError
from kitti_eval.frames import Annotations, Kind
from kitti_eval.loaders import annotations_from_object, load_kitti_txt_dir
from kitti_eval.safe_pickle import load_pickle

from .errors import ArchiveError, UnknownFormat

__all__ = ["InputFormat", "Limits", "Upload", "Loaded", "receive_upload", "sniff", "extract_txt_folder",
           "load_upload", "clean_filename"]

_CHUNK = 1 << 20
_GZIP_MAGIC = b"\x1f\x8b"
_ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")
_BZ2_MAGIC = b"BZh"
_XZ_MAGIC = b"\xfd7zXZ\x00"
_NPY_MAGIC = b"\x93NUMPY"
#: how a protocol 0/1 pickle of a list or dict starts: MARK, EMPTY_LIST, EMPTY_DICT, GLOBAL
_OLD_PICKLE_STARTS = b"(]}c"
_MAX_NAME = 1024
_DRIVE = re.compile(r"^[A-Za-z]:")


class InputFormat(str, enum.Enum):
    PICKLE = "pickle"
    ZIP = "zip"
    TAR = "tar"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class Limits:
    max_unpacked_bytes: int
    max_members: int


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

def _looks_like_tar(block: bytes) -> bool:
    if len(block) < 512:
        return False
    if block[257:262] == b"ustar":
        return True
    try:
        tarfile.TarInfo.frombuf(block[:512], "utf-8", "surrogateescape")
    except (tarfile.HeaderError, ValueError):
        return False
    return True


def _looks_like_kitti_line(head: bytes) -> bool:
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as e:
        text = head[:e.start].decode("utf-8")
    for line in text.splitlines():
        fields = line.split()
        if fields:
            return len(fields) in (15, 16) and fields[0][:1].isalpha()
    return False


def sniff(file: IO[bytes], source: str) -> InputFormat:
    """What an upload is, from its first bytes (never from its name)."""
    file.seek(0)
    head = file.read(4096)
    file.seek(0)
    if not head:
        raise InputError("the file is empty", source=source)
    if head[:4] in _ZIP_MAGICS:
        return InputFormat.ZIP
    if head[:2] == _GZIP_MAGIC:
        try:
            inner = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, 1024)
        except zlib.error:
            return InputFormat.PICKLE  # load_pickle reports the broken gzip
        return InputFormat.TAR if _looks_like_tar(inner) else InputFormat.PICKLE
    if head[:3] == _BZ2_MAGIC or head[:6] == _XZ_MAGIC or _looks_like_tar(head):
        return InputFormat.TAR
    if head[0] == 0x80 or head[:6] == _NPY_MAGIC:
        return InputFormat.PICKLE  # .npy: load_pickle explains what to upload instead
    if _looks_like_kitti_line(head):  # before the protocol-0 check: a class name may start with 'c'
        raise UnknownFormat(f"{source}: this is a single KITTI txt file; upload the folder of txt files as a "
                            "zip or tar")
    if head[0] in _OLD_PICKLE_STARTS:
        return InputFormat.PICKLE
    raise UnknownFormat(f"{source}: unknown format (starts with {head[:8]!r}); expected a pickle (.pkl, "
                        ".pkl.gz) or a zip/tar of KITTI txt files")


# ------------------------------------------------------------------------------------------ archives

class _Budget:
    """Unpacked bytes and member count left; raises ArchiveError when either runs out."""

    def __init__(self, limits: Limits, source: str) -> None:
        self.bytes_left = limits.max_unpacked_bytes
        self.members_left = limits.max_members
        self.limits = limits
        self.source = source

    def member(self) -> None:
        self.members_left -= 1
        if self.members_left < 0:
            raise ArchiveError(f"{self.source}: more than {self.limits.max_members} members "
                               "(KITTI_EVAL_MAX_ARCHIVE_MEMBERS)")

    def spend(self, n: int) -> None:
        self.bytes_left -= n
        if self.bytes_left < 0:
            raise ArchiveError(f"{self.source}: unpacks to more than {self.limits.max_unpacked_bytes >> 20} MB "
                               "(KITTI_EVAL_MAX_UNPACKED_MB); a zip bomb?")


def _member_name(raw: str, source: str) -> str:
    """The member's path, normalised to 'a/b/c', or ArchiveError for anything that could escape."""
    if len(raw) > _MAX_NAME:
        raise ArchiveError(f"{source}: a member name is longer than {_MAX_NAME} characters")
    if any(not c.isprintable() for c in raw):
        raise ArchiveError(f"{source}: member {raw!r} has control characters in its name")
    name = raw.replace("\\", "/")
    if name.startswith("/") or _DRIVE.match(name):
        raise ArchiveError(f"{source}: member {raw!r} has an absolute path")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise ArchiveError(f"{source}: member {raw!r} points outside the archive ('..')")
    return "/".join(parts)


def _wanted(name: str) -> bool:
    """A KITTI txt file: ``.txt``, not hidden, not macOS resource-fork clutter."""
    parts = name.split("/")
    base = parts[-1]
    return base.lower().endswith(".txt") and not base.startswith(".") and "__MACOSX" not in parts


class _Writer:
    """Writes wanted members flat into one numbered subfolder per archive folder."""

    def __init__(self, dest: Path, budget: _Budget, source: str) -> None:
        self.dest = dest
        self.budget = budget
        self.source = source
        self.folders: dict[str, Path] = {}
        self.names: dict[str, str] = {}  # written path -> member name, for messages
        self.torch_like = False  # a member named data.pkl: what torch.save() zips hold

    def saw(self, name: str) -> None:
        if PurePosixPath(name).name == "data.pkl":
            self.torch_like = True

    def write(self, name: str, read: Callable[[int], bytes]) -> None:
        parent = str(PurePosixPath(name).parent)
        base = PurePosixPath(name).name
        folder = self.folders.get(parent)
        if folder is None:
            folder = self.folders[parent] = self.dest / str(len(self.folders))
            folder.mkdir(parents=True)
        target = folder / base
        if str(target) in self.names:
            raise ArchiveError(f"{self.source}: member {name!r} is listed twice")
        self.names[str(target)] = name
        with open(target, "xb") as out:
            while chunk := read(_CHUNK):
                self.budget.spend(len(chunk))
                out.write(chunk)

    def folder(self) -> Path:
        if not self.folders:
            hint = (" This looks like a torch.save() file: export predictions as plain numpy arrays and "
                    "pickle the list of per-frame dicts." if self.torch_like else "")
            raise ArchiveError(f"{self.source}: no .txt files in the archive (expected a folder of KITTI txt "
                               f"files, one per frame).{hint}")
        if len(self.folders) > 1:
            shown = ", ".join(sorted((p + "/") if p != "." else "./" for p in self.folders)[:5])
            raise ArchiveError(f"{self.source}: txt files in several folders ({shown}); upload one folder")
        ((parent, folder),) = self.folders.items()
        self.names[str(folder)] = parent
        return folder


#: bytes of central directory allowed per permitted member (KITTI's "pred/000123.txt" takes about 100)
_CD_BYTES_PER_MEMBER = 300


def _check_zip_directory(file: IO[bytes], limits: Limits, source: str) -> None:
    """Refuse a zip whose central directory is too big before zipfile reads it all into memory."""
    file.seek(0, 2)
    size = file.tell()
    tail_len = min(size, (1 << 16) + 22 + 20 + 56)  # the longest comment, EOCD, zip64 locator and record
    file.seek(size - tail_len)
    tail = file.read(tail_len)
    file.seek(0)
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or len(tail) < at + 22:
        return  # zipfile reports the broken archive
    entries, cd_size = struct.unpack("<HI", tail[at + 10:at + 16])
    z64 = tail.rfind(b"PK\x06\x06", 0, at)
    if (entries == 0xFFFF or cd_size == 0xFFFFFFFF) and z64 >= 0 and len(tail) >= z64 + 56:
        entries, cd_size = struct.unpack("<QQ", tail[z64 + 32:z64 + 48])
    if entries > limits.max_members or cd_size > limits.max_members * _CD_BYTES_PER_MEMBER:
        raise ArchiveError(f"{source}: more than {limits.max_members} members (KITTI_EVAL_MAX_ARCHIVE_MEMBERS)")


def _zip_members(file: IO[bytes], writer: _Writer, budget: _Budget, source: str) -> None:
    _check_zip_directory(file, budget.limits, source)
    try:
        zf = zipfile.ZipFile(file)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as e:
        raise ArchiveError(f"{source}: not a readable zip archive ({e})") from None
    with zf:
        infos = zf.infolist()
        wanted = []
        for info in infos:
            budget.member()
            name = _member_name(info.filename, source)
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise ArchiveError(f"{source}: member {info.filename!r} is a symbolic link; links are not accepted")
            if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise ArchiveError(f"{source}: member {info.filename!r} is not a regular file or folder")
            writer.saw(name)
            if info.is_dir() or not name:
                continue
            if info.flag_bits & 0x1:
                raise ArchiveError(f"{source}: member {info.filename!r} is encrypted")
            budget.spend(info.file_size)  # what the headers claim, all of it, before writing anything
            if _wanted(name):
                wanted.append((name, info))
        budget.bytes_left = budget.limits.max_unpacked_bytes  # now count what is really written
        for name, info in wanted:
            try:
                with zf.open(info) as src:
                    writer.write(name, src.read)
            except (zipfile.BadZipFile, zlib.error, NotImplementedError, EOFError, OSError, RuntimeError,
                    ValueError) as e:
                raise ArchiveError(f"{source}: member {info.filename!r} cannot be unpacked ({e})") from None


class _CappedReader:
    """A read-only view of a decompressing stream that stops at the unpacked-size budget."""

    def __init__(self, inner: IO[bytes], limit: int, source: str, limits: Limits) -> None:
        self.inner = inner
        self.left = limit
        self.source = source
        self.limits = limits

    def read(self, n: int = -1) -> bytes:
        if n is None or n < 0:
            n = _CHUNK
        data = self.inner.read(min(n, self.left + 1))
        self.left -= len(data)
        if self.left < 0:
            raise ArchiveError(f"{self.source}: unpacks to more than {self.limits.max_unpacked_bytes >> 20} MB "
                               "(KITTI_EVAL_MAX_UNPACKED_MB); a tar bomb?")
        return data


def _decompressed(file: IO[bytes]) -> IO[bytes]:
    file.seek(0)
    head = file.read(6)
    file.seek(0)
    if head[:2] == _GZIP_MAGIC:
        import gzip

        return gzip.GzipFile(fileobj=file, mode="rb")  # type: ignore[return-value]
    if head[:3] == _BZ2_MAGIC:
        return bz2.BZ2File(file)
    if head[:6] == _XZ_MAGIC:
        return lzma.LZMAFile(file)
    return file


def _tar_members(file: IO[bytes], writer: _Writer, budget: _Budget, source: str, limits: Limits) -> None:
    # decompress ourselves, capped: tarfile reads pax and long-name headers whole, whatever their size
    stream = _CappedReader(_decompressed(file), limits.max_unpacked_bytes + (1 << 20), source, limits)
    try:
        with tarfile.open(fileobj=stream, mode="r|") as tf:  # type: ignore[call-overload]
            for member in tf:
                budget.member()
                name = _member_name(member.name, source)
                writer.saw(name)
                if member.isdir():
                    continue
                if member.issym() or member.islnk():
                    raise ArchiveError(f"{source}: member {member.name!r} is a link; links are not accepted")
                if member.isdev():
                    raise ArchiveError(f"{source}: member {member.name!r} is a device or fifo, not a file")
                if member.size < 0:
                    raise ArchiveError(f"{source}: member {member.name!r} has a negative size")
                if member.issparse() or not member.isreg():
                    raise ArchiveError(f"{source}: member {member.name!r} is not a regular file")
                if not name or not _wanted(name):
                    budget.spend(member.size)
                    continue
                src = tf.extractfile(member)
                if src is None:  # pragma: no cover - isreg() members always have data
                    continue
                writer.write(name, src.read)
    except ArchiveError:
        raise
    except (tarfile.TarError, OSError, EOFError, zlib.error, lzma.LZMAError, ValueError) as e:
        raise ArchiveError(f"{source}: not a readable tar archive, or a truncated one ({e or type(e).__name__})") \
            from None


def extract_txt_folder(file: IO[bytes], fmt: InputFormat, dest: Path, limits: Limits,
                       source: str) -> tuple[Path, dict[str, str]]:
    """Unpack the txt files of an archive into ``dest``; returns their folder and {path: member name}."""
    budget = _Budget(limits, source)
    writer = _Writer(dest, budget, source)
    file.seek(0)
    if fmt is InputFormat.ZIP:
        _zip_members(file, writer, budget, source)
    elif fmt is InputFormat.TAR:
        _tar_members(file, writer, budget, source, limits)
    else:  # pragma: no cover - callers pass archives only
        raise ValueError(f"not an archive format: {fmt}")
    folder = writer.folder()
    return folder, writer.names


# -------------------------------------------------------------------------------------------- loading

def _relabel(e: InputError, names: dict[str, str], source: str) -> InputError:
    """The same error with the scratch path replaced by 'upload:member' (no server paths reach clients)."""
    where = source
    if e.source in names:
        member = names[e.source]
        where = source if member in (".", "") else f"{source}:{member}"
    cls = UnsafePickleError if isinstance(e, UnsafePickleError) else InputError
    return cls(e.message, source=where, frame=e.frame, field=e.field)


def load_upload(upload: Upload, kind: Kind, scratch: Path, limits: Limits) -> Loaded:
    """Identify, unpack and load one upload as ground truth or detections.

    Raises InputError / UnsafePickleError (from the library), ArchiveError or UnknownFormat; every
    message names the upload by the client's file name.
    """
    fmt = sniff(upload.file, upload.filename)
    if fmt is InputFormat.PICKLE:
        obj = load_pickle(upload.file, source=upload.filename, max_bytes=limits.max_unpacked_bytes)
        return Loaded(fmt, annotations_from_object(obj, kind, source=upload.filename), None)
    folder, names = extract_txt_folder(upload.file, fmt, scratch, limits, upload.filename)
    try:
        annotations = load_kitti_txt_dir(folder, kind)
    except InputError as e:
        raise _relabel(e, names, upload.filename) from None
    return Loaded(fmt, annotations, folder)
