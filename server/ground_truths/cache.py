"""Named ground-truth sets: registered once (validated), kept in the database, loaded into a bounded cache.

The registered file itself is stored in the database (one row per sha256), so every server on the same
database can use it. Each server unpacks it once into its data folder (``<data_dir>/ground-truths``: a pickle
as ``<sha256>.pkl``, an archive as the folder of txt files it holds, ``<sha256>/``), and loads it from there
into memory on first use. Deleting a name deletes the file when no other name uses the same content.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import logging
import os
import re
import shutil
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import AbstractContextManager
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from kitti_eval.core.frames import Annotations
from kitti_eval.errors import KittiEvalError
from kitti_eval.io.archives import extract_txt_folder
from kitti_eval.io.loaders import load_ground_truth
from kitti_eval.io.upload import UploadLimits, read_upload

from ..errors import ApiError, BadRequest, Conflict, NotFound, echo
from ..scoring.uploads import Upload, receive_upload
from ..store import BenchmarkStore, GroundTruthRecord, GroundTruthStore

__all__ = ["GroundTruths", "GroundTruthCache", "NAME_PATTERN", "annotations_nbytes", "display_name"]

log = logging.getLogger("kitti_eval.server")

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
_NAME = re.compile(NAME_PATTERN)


class GroundTruthUnavailable(ApiError):
    status_code = 500
    code = "ground_truth_unavailable"


def display_name(name: str) -> str:
    """How messages name a registered ground truth (its ``source``)."""
    return f"the ground truth {name!r}"


def annotations_nbytes(annotations: Annotations) -> int:
    """Memory held by the arrays of an Annotations (what the cache bound counts)."""
    total = 0
    for f in dataclasses.fields(annotations):
        value = getattr(annotations, f.name)
        if isinstance(value, np.ndarray):
            total += value.nbytes
    return total


class GroundTruthCache:
    """Loaded sets (ground truth, or kept predictions) by sha256, least recently used dropped first; each set
    is loaded once."""

    def __init__(
        self, max_entries: int, max_bytes: int, *, what: str = "ground truth", setting: str = "KITTI_EVAL_GT_CACHE_MB"
    ) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.what = what
        self.setting = setting
        self._entries: OrderedDict[str, tuple[Annotations, int]] = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[str, threading.Lock] = {}
        #: told of every :meth:`get_or_load`: True when the set was in memory (the metrics count them)
        self.on_lookup: Callable[[bool], None] | None = None

    def get(self, key: str) -> Annotations | None:
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key: str, annotations: Annotations) -> None:
        size = annotations_nbytes(annotations)
        if size > self.max_bytes:
            log.warning(
                "%s %s (%d MB) is larger than the cache (%s); not cached", self.what, key[:12], size >> 20, self.setting
            )
            return
        with self._lock:
            self._entries[key] = (annotations, size)
            self._entries.move_to_end(key)
            while len(self._entries) > self.max_entries or self.nbytes > self.max_bytes:
                self._entries.popitem(last=False)

    def get_or_load(self, key: str, load: Callable[[], Annotations]) -> Annotations:
        found = self.get(key)
        if found is not None:
            if self.on_lookup is not None:
                self.on_lookup(True)
            return found
        with self._lock:
            key_lock = self._loading.setdefault(key, threading.Lock())
        with key_lock:  # one loader per set; the others wait for it and then hit the cache
            found = self.get(key)
            if self.on_lookup is not None:
                self.on_lookup(found is not None)
            if found is None:
                found = load()
                self.put(key, found)
        with self._lock:
            self._loading.pop(key, None)
        return found

    def evict(self, key: str) -> None:
        with self._lock:
            self._entries.pop(key, None)

    @property
    def nbytes(self) -> int:
        return sum(size for _, size in self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)


class GroundTruths:
    """Register, look up, load and delete named ground-truth sets."""

    def __init__(
        self,
        ground_truth_store: GroundTruthStore,
        benchmark_store: BenchmarkStore,
        root: Path,
        cache: GroundTruthCache,
        limits: UploadLimits,
        scratch: Callable[[], AbstractContextManager[Path]],
    ) -> None:
        self.ground_truth_store = ground_truth_store
        self.benchmark_store = benchmark_store  # a ground truth a benchmark uses is not deleted
        self.root = root
        self.cache = cache
        self.limits = limits
        self.scratch = scratch

    @staticmethod
    def check_name(name: str) -> str:
        if not _NAME.fullmatch(name):
            raise BadRequest(
                f"ground-truth name {echo(name)} is not valid: 1-64 letters, digits, '.', '_' or '-', "
                "starting with a letter or digit"
            )
        return name

    def register_bundled(self, name: str, path: Path, scratch: Path) -> None:
        """Register the file at ``path`` (one this package ships: the demo's) as ``name`` unless one is registered
        under that name (by this process before, or by another meanwhile)."""
        if self.ground_truth_store.get_ground_truth(name) is not None:
            return
        with open(path, "rb") as fh:
            try:
                self.register(name, receive_upload(fh, path.name, path.name), scratch)
            except Exception as e:  # noqa: BLE001 - another worker may have registered it meanwhile
                if self.ground_truth_store.get_ground_truth(name) is None:
                    raise
                log.debug("%s registered concurrently: %s", name, e)
        log.info("registered the bundled ground truth %s as %r", path.name, name)

    def register(
        self, name: str, upload: Upload, scratch: Path, *, project: str | None = None, sealed: bool = False
    ) -> GroundTruthRecord:
        """Validate ``upload`` as ground truth (by loading it), keep it, and record it under ``name``."""
        self.check_name(name)
        if self.ground_truth_store.get_ground_truth(name) is not None:
            raise Conflict(f"a ground truth named {name!r} exists; delete it first or pick another name")
        if not sealed:
            self._check_not_a_test_set(name)
        loaded = read_upload(upload.file, "ground_truth", source=upload.filename, scratch=scratch, limits=self.limits)
        upload.file.seek(0)
        content = upload.file.read()
        record = GroundTruthRecord(
            name=name,
            sha256=upload.sha256,
            format=loaded.kind,
            filename=upload.filename,
            storage=self._relative(upload.sha256, loaded.kind),
            size_bytes=upload.size,
            frames=loaded.annotations.num_frames,
            boxes=loaded.annotations.num_boxes,
            created_at=datetime.now(timezone.utc),
            project=project,
            sealed=sealed,
        )
        if not self.ground_truth_store.add_ground_truth(record, content):
            raise Conflict(f"a ground truth named {name!r} exists; delete it first or pick another name")
        try:
            self._keep_local(record, content, loaded.folder)
        except OSError as e:  # the registration is committed (file and all) and stands: the copy is made later
            if e.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            log.warning("no room for the local copy of ground truth %r (%s); it is written when next needed", name, e)
        self.cache.put(upload.sha256, loaded.annotations)
        return record

    def _check_not_a_test_set(self, name: str) -> None:
        """A benchmark's test set stays sealed: its name is registered again (a corrected set) sealed only."""
        users = self.benchmark_store.benchmarks_using(name)
        if users:
            named = ", ".join(repr(b.name) for b in users)
            raise Conflict(
                f"{name!r} is the test set of benchmark {named}: register it with sealed=true, or pick another name"
            )

    @staticmethod
    def _relative(sha256: str, fmt: str) -> str:
        return f"ground-truths/{sha256}.pkl" if fmt == "pickle" else f"ground-truths/{sha256}"

    def _keep_local(self, record: GroundTruthRecord, content: bytes, folder: Path | None) -> Path:
        """Put the file (or, for an archive, its unpacked txt folder) under the data folder; its path."""
        self.root.mkdir(parents=True, exist_ok=True)
        target = self.root.parent / record.storage
        if record.format == "pickle":
            tmp = target.with_name(f".{target.name}.{os.getpid()}.{threading.get_ident()}")
            try:
                with open(tmp, "wb") as out:
                    out.write(content)
                os.replace(tmp, target)
            except BaseException:
                tmp.unlink(missing_ok=True)  # no partial copy left behind
                raise
        elif not target.is_dir():
            assert folder is not None
            try:
                os.replace(folder, target)  # scratch and storage share the data folder: a rename
            except OSError:
                if not target.is_dir():
                    raise
        return target

    def _materialise(self, record: GroundTruthRecord) -> Path:
        """The local copy of a registered file, written from the database when this server lacks it."""
        target = self.root.parent / record.storage
        if target.exists():
            return target
        content = self.ground_truth_store.ground_truth_content(record.sha256)
        if content is None:
            raise GroundTruthUnavailable(
                f"ground truth {record.name!r} has no stored file; an admin should register it again"
            )
        with self.scratch() as scratch:
            folder = None
            if record.format != "pickle":  # a zip or tar, unpacked as it was at its registration
                folder, _ = extract_txt_folder(
                    io.BytesIO(content),
                    "zip" if record.format == "zip" else "tar",
                    scratch,
                    self.limits.archive,
                    record.filename,
                )
            return self._keep_local(record, content, folder)

    def record(self, name: str) -> GroundTruthRecord:
        record = self.ground_truth_store.get_ground_truth(name)
        if record is None:
            raise NotFound(f"no ground truth named {echo(name)}; GET /v1/ground-truths lists them")
        return record

    def load(self, record: GroundTruthRecord) -> Annotations:
        """The loaded set (from the cache, or from storage once), its ``source`` the ground truth's name: every
        message and warning made of it says "the ground truth 'NAME'", never the path of the server's copy
        (nor the file name it was registered from, which is what a set cached at registration would say)."""

        def from_storage() -> Annotations:
            path = self._materialise(record)
            try:
                return load_ground_truth(path)
            except KittiEvalError as e:
                log.error("registered ground truth %r cannot be loaded from %s: %s", record.name, path, e)
                raise GroundTruthUnavailable(
                    f"ground truth {record.name!r} cannot be loaded from the server's "
                    "storage; an admin should register it again"
                ) from None

        loaded = self.cache.get_or_load(record.sha256, from_storage)
        return dataclasses.replace(loaded, source=display_name(record.name))

    def delete(self, name: str) -> GroundTruthRecord:
        record, shared = self.ground_truth_store.delete_ground_truth(name)
        if record is None:
            raise NotFound(f"no ground truth named {echo(name)}")
        if not shared:
            self.cache.evict(record.sha256)
            path = self.root.parent / record.storage
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        return record
