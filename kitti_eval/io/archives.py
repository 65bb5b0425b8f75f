"""Safe extraction of the KITTI txt files of a zip or a tar (plain, gz, bz2, xz): the one extractor.

Archives are checked member by member before and while anything is written: no absolute paths, no
``..``, no links, devices, fifos or sparse files, at most ``max_members`` members and ``max_unpacked_bytes``
unpacked (counting what is actually written, not only what headers claim; a zip's central directory is
sized up before :mod:`zipfile` reads it). Only ``.txt`` files are written, flat, under validated basenames,
into one numbered subfolder of ``dest`` per archive folder; nothing is ever extracted with ``extractall``.
When several folders hold txt files, the one named ``label_2`` (or else ``data``) is taken.

Every refusal is an :class:`~kitti_eval.errors.InputError` whose source is the caller's name for the
archive; messages name archive members, never the paths written to.
"""

from __future__ import annotations

import bz2
import errno
import gzip
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
from typing import IO, Literal

from ..errors import InputError, UnknownFormatError

__all__ = [
    "ArchiveLimits",
    "ArchiveKind",
    "InputKind",
    "MAX_TXT_FILE_BYTES",
    "sniff_archive",
    "sniff_input",
    "extract_txt_folder",
    "too_large_txt",
]

ArchiveKind = Literal["zip", "tar"]
InputKind = Literal["pickle", "zip", "tar"]

_CHUNK = 1 << 20
_GZIP_MAGIC = b"\x1f\x8b"
_ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")
_BZ2_MAGIC = b"BZh"
_XZ_MAGIC = b"\xfd7zXZ\x00"
_MAX_NAME = 1024
#: the most one KITTI txt file (one frame) may hold, in an archive or a folder: a frame of 10,000 boxes is
#: about 1 MB; the parser holds a file's tokens in memory at once
MAX_TXT_FILE_BYTES = 16 << 20
_DRIVE = re.compile(r"^[A-Za-z]:")
#: when txt files sit in several folders, the first of these names that exactly one of them has wins
_PREFERRED_FOLDERS = ("label_2", "data")


@dataclass(frozen=True)
class ArchiveLimits:
    """Caps on one archive. ``members_setting`` / ``bytes_setting`` optionally name what raises each cap
    (e.g. an environment variable), appended to the refusal message."""

    max_members: int = 100_000
    max_unpacked_bytes: int = 2 << 30
    members_setting: str | None = None
    bytes_setting: str | None = None

    def _members_message(self) -> str:
        hint = f" ({self.members_setting})" if self.members_setting else ""
        return f"more than {self.max_members} members{hint}"

    def _bytes_message(self, what: str) -> str:
        hint = f" ({self.bytes_setting})" if self.bytes_setting else ""
        return f"unpacks to more than {self.max_unpacked_bytes >> 20} MB{hint}; a {what} bomb?"


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


def sniff_archive(file: IO[bytes]) -> ArchiveKind | None:
    """``"zip"`` or ``"tar"`` (plain, or a gzip holding a tar, or any bz2/xz stream) from the first bytes of
    a seekable file, else None; the file is rewound."""
    file.seek(0)
    head = file.read(4096)
    file.seek(0)
    if head[:4] in _ZIP_MAGICS:
        return "zip"
    if head[:2] == _GZIP_MAGIC:
        try:
            inner = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, 1024)
        except zlib.error:
            return None
        return "tar" if _looks_like_tar(inner) else None
    if head[:3] == _BZ2_MAGIC or head[:6] == _XZ_MAGIC or _looks_like_tar(head):
        return "tar"
    return None


def _looks_like_kitti_line(head: bytes) -> bool:
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as e:
        text = head[: e.start].decode("utf-8")
    for line in text.splitlines():
        fields = line.split()
        if fields:
            return len(fields) in (15, 16) and fields[0][:1].isalpha()
    return False


def sniff_input(file: IO[bytes], source: str) -> InputKind:
    """What a file is, from its first bytes, never from its name: ``"zip"`` or ``"tar"`` (of KITTI txt
    files; a ``torch.save`` zip is one, and its extraction says what to export instead), or ``"pickle"``
    (plain or gzipped; also a numpy ``.npy``, which the pickle loader refuses saying what to export instead).
    The file (seekable) is rewound.

    Raises
    ------
    UnknownFormatError : a single KITTI txt file, or anything else
    InputError : an empty file
    """
    file.seek(0)
    head = file.read(4096)
    file.seek(0)
    if not head:
        raise InputError("the file is empty", source=source)
    archive = sniff_archive(file)
    if archive is not None:
        return archive
    if head[:2] == _GZIP_MAGIC or head[0] == 0x80 or head[:6] == b"\x93NUMPY":  # gzip without a tar, protocol 2+
        return "pickle"
    if _looks_like_kitti_line(head):  # before the protocol-0 check: a class name may start with 'c'
        raise UnknownFormatError(
            "this is a single KITTI txt file; pass the folder of txt files (or a zip or tar of it)", source=source
        )
    if head[0] in b"(]}c":  # how a protocol 0/1 pickle of a list or dict starts: MARK, EMPTY_LIST, EMPTY_DICT, GLOBAL
        return "pickle"
    raise UnknownFormatError(
        f"unknown format (starts with {head[:8]!r}); expected a pickle (.pkl, .pkl.gz), a "
        "zip or tar of KITTI txt files, or a folder of them",
        source=source,
    )


# ------------------------------------------------------------------------------------------ checking


class _Budget:
    """Unpacked bytes and member count left; raises InputError when either runs out."""

    def __init__(self, limits: ArchiveLimits, source: str) -> None:
        self.bytes_left = limits.max_unpacked_bytes
        self.members_left = limits.max_members
        self.limits = limits
        self.source = source

    def member(self) -> None:
        self.members_left -= 1
        if self.members_left < 0:
            raise InputError(self.limits._members_message(), source=self.source)

    def spend(self, n: int) -> None:
        self.bytes_left -= n
        if self.bytes_left < 0:
            raise InputError(self.limits._bytes_message("zip"), source=self.source)


def too_large_txt(name: str, source: str) -> InputError:
    return InputError(
        f"{name} is larger than {MAX_TXT_FILE_BYTES >> 20} MB; a KITTI txt file holds one frame (a few KB)",
        source=source,
        frame=PurePosixPath(name).stem,
    )


def _member_name(raw: str, source: str) -> str:
    """The member's path, normalised to 'a/b/c', or InputError for anything that could escape."""
    if len(raw) > _MAX_NAME:
        raise InputError(f"a member name is longer than {_MAX_NAME} characters", source=source)
    if any(not c.isprintable() for c in raw):
        raise InputError(f"member {raw!r} has control characters in its name", source=source)
    name = raw.replace("\\", "/")
    if name.startswith("/") or _DRIVE.match(name):
        raise InputError(f"member {raw!r} has an absolute path", source=source)
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise InputError(f"member {raw!r} points outside the archive ('..')", source=source)
    return "/".join(parts)


def _wanted(name: str) -> bool:
    """A KITTI txt file: ``.txt``, not hidden, not macOS resource-fork clutter."""
    parts = name.split("/")
    base = parts[-1]
    return base.lower().endswith(".txt") and not base.startswith(".") and "__MACOSX" not in parts


#: errno values of a full disk or an exhausted quota: the machine's fault, not the archive's, so they pass through
#: unchanged instead of becoming an InputError
_NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT})


def _out_of_space(e: BaseException) -> bool:
    return isinstance(e, OSError) and e.errno in _NO_SPACE


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

    def write(self, name: str, read: Callable[[int], bytes], *, charged: bool = False) -> None:
        """Write one member; its bytes are charged to the budget as they come unless ``charged`` (the
        caller charged its exact size already)."""
        parent = str(PurePosixPath(name).parent)
        base = PurePosixPath(name).name
        folder = self.folders.get(parent)
        if folder is None:
            folder = self.folders[parent] = self.dest / str(len(self.folders))
            folder.mkdir(parents=True)
        target = folder / base
        if str(target) in self.names:
            raise InputError(f"member {name!r} is listed twice", source=self.source)
        self.names[str(target)] = name
        size = 0
        with open(target, "xb") as out:
            while chunk := read(_CHUNK):
                size += len(chunk)
                if size > MAX_TXT_FILE_BYTES:
                    raise too_large_txt(name, self.source)
                if not charged:
                    self.budget.spend(len(chunk))
                out.write(chunk)

    def folder(self) -> Path:
        if not self.folders:
            hint = (
                " This looks like a torch.save() file: export predictions as plain numpy arrays and "
                "pickle the list of per-frame dicts."
                if self.torch_like
                else ""
            )
            raise InputError(
                f"no .txt files in the archive (expected a folder of KITTI txt files, one per frame).{hint}",
                source=self.source,
            )
        parent = self._pick()
        folder = self.folders[parent]
        self.names[str(folder)] = parent
        return folder

    def _pick(self) -> str:
        if len(self.folders) == 1:
            return next(iter(self.folders))
        for preferred in _PREFERRED_FOLDERS:
            hits = [p for p in self.folders if PurePosixPath(p).name == preferred]
            if len(hits) == 1:
                return hits[0]
        shown = ", ".join(sorted((p + "/") if p != "." else "./" for p in self.folders)[:5])
        raise InputError(
            f"txt files in several folders ({shown}); pack one folder (or one named label_2/ or data/)",
            source=self.source,
        )


# ----------------------------------------------------------------------------------------------- zip

#: bytes of central directory allowed per permitted member (KITTI's "pred/000123.txt" takes about 100)
_CD_BYTES_PER_MEMBER = 300


def _check_zip_directory(file: IO[bytes], limits: ArchiveLimits, source: str) -> None:
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
    entries, cd_size = struct.unpack("<HI", tail[at + 10 : at + 16])
    z64 = tail.rfind(b"PK\x06\x06", 0, at)
    if (entries == 0xFFFF or cd_size == 0xFFFFFFFF) and z64 >= 0 and len(tail) >= z64 + 56:
        entries, cd_size = struct.unpack("<QQ", tail[z64 + 32 : z64 + 48])
    if entries > limits.max_members or cd_size > limits.max_members * _CD_BYTES_PER_MEMBER:
        raise InputError(limits._members_message(), source=source)


def _zip_members(file: IO[bytes], writer: _Writer, budget: _Budget, source: str) -> None:
    _check_zip_directory(file, budget.limits, source)
    try:
        zf = zipfile.ZipFile(file)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as e:
        raise InputError(f"not a readable zip archive ({e})", source=source) from None
    with zf:
        infos = zf.infolist()
        wanted = []
        for info in infos:
            budget.member()
            name = _member_name(info.filename, source)
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise InputError(f"member {info.filename!r} is a symbolic link; links are not accepted", source=source)
            if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise InputError(f"member {info.filename!r} is not a regular file or folder", source=source)
            writer.saw(name)
            if info.is_dir() or not name:
                continue
            if info.flag_bits & 0x1:
                raise InputError(f"member {info.filename!r} is encrypted", source=source)
            budget.spend(info.file_size)  # what the headers claim, all of it, before writing anything
            if _wanted(name):
                if info.file_size > MAX_TXT_FILE_BYTES:
                    raise too_large_txt(name, source)
                wanted.append((name, info))
        budget.bytes_left = budget.limits.max_unpacked_bytes  # now count what is really written
        for name, info in wanted:
            try:
                with zf.open(info) as src:
                    writer.write(name, src.read)
            except (
                zipfile.BadZipFile,
                zlib.error,
                NotImplementedError,
                EOFError,
                OSError,
                RuntimeError,
                ValueError,
            ) as e:
                if _out_of_space(e):
                    raise
                raise InputError(f"member {info.filename!r} cannot be unpacked ({e})", source=source) from None


# ----------------------------------------------------------------------------------------------- tar


class _CappedReader:
    """A read-only view of a decompressing stream that stops at the unpacked-size budget."""

    def __init__(self, inner: IO[bytes], limit: int, source: str, limits: ArchiveLimits) -> None:
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
            raise InputError(self.limits._bytes_message("tar"), source=self.source)
        return data


def _decompressed(file: IO[bytes]) -> IO[bytes]:
    file.seek(0)
    head = file.read(6)
    file.seek(0)
    if head[:2] == _GZIP_MAGIC:
        return gzip.GzipFile(fileobj=file, mode="rb")  # type: ignore[return-value]
    if head[:3] == _BZ2_MAGIC:
        return bz2.BZ2File(file)
    if head[:6] == _XZ_MAGIC:
        return lzma.LZMAFile(file)
    return file


def _tar_members(file: IO[bytes], writer: _Writer, budget: _Budget, source: str, limits: ArchiveLimits) -> None:
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
                    raise InputError(f"member {member.name!r} is a link; links are not accepted", source=source)
                if member.isdev():
                    raise InputError(f"member {member.name!r} is a device or fifo, not a file", source=source)
                if member.size < 0:
                    raise InputError(f"member {member.name!r} has a negative size", source=source)
                if member.issparse() or not member.isreg():
                    raise InputError(f"member {member.name!r} is not a regular file", source=source)
                budget.spend(member.size)  # a tar member holds exactly its header's size: charged before reading
                if not name or not _wanted(name):
                    continue
                if member.size > MAX_TXT_FILE_BYTES:
                    raise too_large_txt(name, source)
                src = tf.extractfile(member)
                if src is None:  # pragma: no cover - isreg() members always have data
                    continue
                writer.write(name, src.read, charged=True)
    except InputError:
        raise
    except (tarfile.TarError, OSError, EOFError, zlib.error, lzma.LZMAError, ValueError) as e:
        if _out_of_space(e):
            raise
        raise InputError(
            f"not a readable tar archive, or a truncated one ({e or type(e).__name__})", source=source
        ) from None


# ------------------------------------------------------------------------------------------ public


def extract_txt_folder(
    file: IO[bytes], kind: ArchiveKind, dest: Path, limits: ArchiveLimits, source: str
) -> tuple[Path, dict[str, str]]:
    """Unpack the txt files of a seekable zip or tar ``file`` into (a subfolder of) ``dest``.

    Returns the folder holding the chosen txt files and ``{written path: member name}`` (the folder itself
    maps to its member folder), so that errors about written files can be reported by member name.
    ``source`` names the archive in every error.
    """
    budget = _Budget(limits, source)
    writer = _Writer(Path(dest), budget, source)
    file.seek(0)
    if kind == "zip":
        _zip_members(file, writer, budget, source)
    elif kind == "tar":
        _tar_members(file, writer, budget, source, limits)
    else:
        raise ValueError(f"not an archive kind: {kind!r}")
    folder = writer.folder()
    return folder, writer.names
