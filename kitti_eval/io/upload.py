"""One file as a user sends it, read in one call: what it is (from its content, never its name), unpacked
safely when it is an archive, loaded, and, for a benchmark submission, checked as ``kitti-eval validate``
checks it. ``kitti-eval validate``, the service's uploads (evaluations, ground truths, a board's entries) and
its submissions all read through :func:`read_upload`, so a file is read, refused or accepted the same way
everywhere.

A file is

* a pickle, plain or gzipped (OpenPCDet ``result.pkl`` / ``kitti_infos_val.pkl``): read only through
  :func:`kitti_eval.io.reading.read_pickle` (the restricted unpickler's scan; a result.pkl of the usual
  layout straight from its bytes into the columns), its decompressed size and its frames capped before it is
  built;
* a zip or a tar (plain, gz, bz2, xz) of KITTI txt files (a ``label_2`` or result folder), unpacked by
  :func:`kitti_eval.io.archives.extract_txt_folder` (the one safe extractor: no absolute paths, no ``..``, no
  links, devices, fifos or sparse files, at most ``max_members`` members and ``max_bytes`` unpacked, only the
  ``.txt`` files of one folder written, flat, into the caller's scratch folder).

Errors are the library's one tree: :class:`~kitti_eval.errors.UnknownFormatError` (neither),
:class:`~kitti_eval.errors.UnsafePickleError`, :class:`~kitti_eval.errors.ArchiveError` (an archive refused:
unreadable, or past a limit), :class:`~kitti_eval.errors.InputError` (what was read is malformed) and, when
``rules`` are given, :class:`~kitti_eval.errors.InvalidSubmissionError` (readable, but it breaks the rules: its
``problems`` are the validator's sentences). Every message names the file by ``source`` (and an archive's
member), never a path of the scratch folder.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from ..core.frames import Annotations, Kind
from ..errors import ArchiveError, InputError, InvalidSubmissionError, UnknownFormatError, UnsafePickleError
from .archives import ArchiveLimits, InputKind, extract_txt_folder, sniff_input
from .formats.kitti_txt import load_kitti_txt_dir
from .limits import MAX_INPUT_ENV, BoxLimits, box_limits, resolve
from .reading import DEFAULT, LoadOptions, read_pickle
from .submission_rules import SubmissionRules, Validation, validate_annotations, validate_txt_folder

__all__ = ["UploadLimits", "LoadedUpload", "read_upload"]


@dataclass(frozen=True)
class UploadLimits:
    """The caps on one file. ``max_bytes``: a pickle after decompression, an archive's unpacked txt files;
    ``max_frames``: the frames it may hold (None: :func:`kitti_eval.io.limits.input_limits`, from the
    environment); ``max_members``: an archive's members; ``boxes``: the boxes of a frame and of the file (None:
    :func:`kitti_eval.io.limits.box_limits`, from the environment). ``bytes_setting`` / ``members_setting`` name
    what raises a cap, in the refusal."""

    max_bytes: int | None = None
    max_frames: int | None = None
    max_members: int = ArchiveLimits.max_members
    bytes_setting: str | None = MAX_INPUT_ENV
    members_setting: str | None = None
    boxes: BoxLimits | None = None

    def resolved(self) -> tuple[int, int]:
        """``(max_bytes, max_frames)``, the ones left at None read from the environment."""
        return resolve(self.max_bytes, self.max_frames)

    @property
    def archive(self) -> ArchiveLimits:
        """The caps of an archive's unpacking."""
        return ArchiveLimits(
            max_members=self.max_members,
            max_unpacked_bytes=self.resolved()[0],
            members_setting=self.members_setting,
            bytes_setting=self.bytes_setting,
        )


@dataclass(frozen=True)
class LoadedUpload:
    """What reading a file gave: what it was, the annotations and the warnings of the read; ``folder``, the txt
    folder an archive was unpacked into (None for a pickle); ``validation``, the checks' outcome when rules were
    given (valid: a refusal raises)."""

    kind: InputKind
    annotations: Annotations
    warnings: tuple[str, ...] = ()
    folder: Path | None = None
    validation: Validation | None = None


def read_upload(
    file: IO[bytes],
    kind: Kind,
    *,
    source: str,
    scratch: Path,
    limits: UploadLimits = UploadLimits(),
    options: LoadOptions = DEFAULT,
    rules: SubmissionRules | None = None,
) -> LoadedUpload:
    """Identify, unpack, load and (with ``rules``, as detections) check the file ``file`` (seekable bytes), named
    ``source`` in every message; an archive is unpacked into ``scratch`` (the caller's folder, left for it to
    remove). ``options``: the read's layout and what it keeps (:class:`~kitti_eval.io.reading.LoadOptions`; its
    limits are ``limits``'). See the module for the errors it raises."""
    max_bytes, max_frames = limits.resolved()
    bounds = limits.boxes or box_limits()
    options = dataclasses.replace(options, max_bytes=max_bytes, max_frames=max_frames, box_limits=bounds)
    what = sniff_input(file, source)
    if what == "pickle":
        return _pickle(file, kind, source, options, rules)
    try:
        folder, names = extract_txt_folder(file, what, scratch, limits.archive, source)
    except InputError as e:  # the extractor's refusals: the archive, not what it holds
        raise ArchiveError(e.message, source=e.source, frame=e.frame, field=e.field) from None
    validation = None
    if rules is not None:
        validation = validate_txt_folder(folder, rules, shown_as=source)
        if not validation.ok:
            raise InvalidSubmissionError(validation.problems, validation.more)
    try:
        annotations = load_kitti_txt_dir(
            folder, kind, max_frames=max_frames, known_frames=options.known_frames, bounds=bounds
        )
    except InputError as e:
        raise _named(e, names, source) from None
    return LoadedUpload(what, dataclasses.replace(annotations, source=source), (), folder, validation)


def _pickle(
    file: IO[bytes], kind: Kind, source: str, options: LoadOptions, rules: SubmissionRules | None
) -> LoadedUpload:
    try:
        loaded = read_pickle(file, kind, source, options)
    except (UnsafePickleError, UnknownFormatError):  # not a submission at all
        raise
    except InputError as e:  # a pickle, but not a result that can be read: one of the submission's problems
        if rules is None:
            raise
        raise InvalidSubmissionError([str(e)]) from None
    if rules is None:
        return LoadedUpload("pickle", loaded.annotations, loaded.warnings)
    validation = validate_annotations(loaded.annotations, rules)
    if not validation.ok:
        raise InvalidSubmissionError(validation.problems, validation.more)
    return LoadedUpload("pickle", loaded.annotations, loaded.warnings, None, validation)


def _named(e: InputError, names: dict[str, str], source: str) -> InputError:
    """The same error naming ``source`` (and the archive's member) instead of the scratch folder's path."""
    where = source
    if e.source in names:
        member = names[e.source]
        where = source if member in (".", "") else f"{source}:{member}"
    return type(e)(e.message, source=where, frame=e.frame, field=e.field)
