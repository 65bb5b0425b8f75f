"""KITTI txt folders: one ``<frame>.txt`` per frame, 15 fields per line for ground truth (a 16th, the score, is
accepted and ignored) and exactly 16 for detections; dimensions are written h, w, l and are reordered to the
l, h, w of :class:`~kitti_eval.core.frames.Annotations`. Files are read as bytes, as the official devkit's
``fscanf`` reads them, and refused where it would read them otherwise (the rules:
:mod:`~kitti_eval.io.formats.txt_grammar`). A folder without ``.txt`` files but with a ``data/``
subfolder that has them (OpenPCDet's ``final_result/data``) is read from there. Zip and tar archives of such
a folder are unpacked safely (:func:`extract_txt_archive`, over :mod:`kitti_eval.io.archives`)."""

from __future__ import annotations

import dataclasses
import os
import tempfile
from array import array
from collections.abc import Collection, Sequence
from itertools import chain
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from ...core.budget import setting_name
from ...core.frames import Annotations, Kind, normalize_frame_id
from ...errors import InputError
from ..archives import (
    MAX_TXT_FILE_BYTES,
    ArchiveLimits,
    InputKind,
    extract_txt_folder,
    sniff_archive,
    sniff_input,
    too_large_txt,
)
from ..limits import MAX_FRAMES_ENV, MAX_INPUT_ENV, BoxLimits, box_limits, resolve
from ._common import Format, Frames, check_kind
from .txt_grammar import (
    KITTI_TXT_FIELDS,
    check_names,
    check_number_bytes,
    check_start,
    explain_numbers,
    foreign_separator,
    not_a_separator,
    table_problem,
    values_problem,
)

__all__ = [
    "KITTI_TXT",
    "KITTI_TXT_FIELDS",
    "load_kitti_txt_dir",
    "parse_kitti_txt",
    "read_bytes",
    "read_text",
    "txt_files",
    "input_kind",
    "is_archive",
    "extract_txt_archive",
    "load_txt_archive",
]

PathLike = str | os.PathLike[str]

_N_FIELDS = {"ground_truth": 15, "detections": 16}


def txt_files(directory: Path) -> list[Path]:
    try:
        entries = list(os.scandir(directory))
    except OSError as e:
        raise InputError(f"cannot list the folder: {e.strerror or e}", source=str(directory)) from None
    return [
        Path(e.path) for e in entries if e.name.lower().endswith(".txt") and not e.name.startswith(".") and e.is_file()
    ]


def load_kitti_txt_dir(
    directory: PathLike,
    kind: Kind,
    *,
    max_frames: int | None = None,
    known_frames: Collection[str] | None = None,
    bounds: BoxLimits | None = None,
) -> Annotations:
    """One KITTI txt file per frame; the frame id is the file stem (``000015.txt`` -> ``"000015"``).

    Files are read in name order; files not ending in ``.txt`` (and hidden files) are ignored; an empty
    file is a frame without boxes.
    """
    check_kind(kind)
    root = Path(directory)
    files = txt_files(root)
    if not files and (root / "data").is_dir():
        files = txt_files(root / "data")  # OpenPCDet --save_to_file: final_result/data/*.txt
    if not files:
        subdirs = sorted(e.name for e in os.scandir(root) if e.is_dir())
        hint = f"; it has subfolders {', '.join(subdirs[:5])}: pass the one holding the txt files" if subdirs else ""
        raise InputError(f"no .txt files in the folder{hint}", source=str(root))
    files.sort(key=lambda f: f.name)
    max_frames = resolve(None, max_frames)[1]
    if len(files) > max_frames:
        raise InputError(
            f"{len(files)} txt files, more than the limit of {max_frames} frames ({setting_name(MAX_FRAMES_ENV)})",
            source=str(root),
        )

    _refuse_one_frame_twice(files, str(root))
    n_values = _N_FIELDS[kind] - 1  # numbers per line that are kept (score dropped for ground truth)
    names: list[str] = []
    values = array("d")  # plain float() parsing, straight into one buffer
    spans: list[tuple[str, int, int]] = []  # (frame id, first row, row count)
    bounds = bounds or box_limits()  # boxes per frame and in all, checked file by file, before the next is read
    for f in files:
        lines, width, frame_names, tokens = _split_frame(read_bytes(f), kind, f.stem, str(f))
        bounds.check_frame(len(frame_names), len(names) + len(frame_names), source=str(f), frame=f.stem)
        try:
            values.extend(map(float, tokens))
        except ValueError:
            _raise_bad_number(lines, width, kind, f.stem, str(f))
        spans.append((f.stem, len(names), len(frame_names)))
        names.extend(frame_names)

    table = np.frombuffer(values, dtype=np.float64).reshape(len(names), n_values)
    problem = table_problem(table, kind)
    if problem is not None:
        row, field, message = problem
        k = next(k for k, (_, lo, n) in enumerate(spans) if lo <= row < lo + n)
        _raise_at_record(read_bytes(files[k]), row - spans[k][1], field, message, spans[k][0], str(files[k]))
    name_arr = np.array(names) if names else np.zeros(0, dtype="<U1")
    # columns after the type: trunc occ alpha x1 y1 x2 y2 h w l x y z ry [score]
    columns = {
        "truncated": table[:, 0],
        "occluded": table[:, 1],
        "alpha": table[:, 2],
        "bbox": table[:, 3:7],
        "dimensions": table[:, [9, 7, 8]],  # h w l -> l h w
        "location": table[:, 10:13],
        "rotation_y": table[:, 13],
    }
    if kind == "detections":
        columns["score"] = table[:, 14]

    def frames() -> Frames:
        for fid, lo, n in spans:
            fields: dict[str, Any] = {k: v[lo : lo + n] for k, v in columns.items()}
            fields["name"] = name_arr[lo : lo + n]
            yield fid, fields

    return Annotations.from_frames(kind, str(root), frames(), max_frames=max_frames, known_frames=known_frames)


def _refuse_one_frame_twice(files: Sequence[Path], source: str) -> None:
    """Two files of one frame (``0.txt`` and ``000000.txt``: ids are compared zero-padded to six digits) are
    refused naming both, before any is read; an id that is no id is left to the frames' own refusal."""
    first: dict[str, Path] = {}
    for f in files:
        try:
            key = normalize_frame_id(f.stem)
        except (TypeError, ValueError):
            continue
        if key in first:
            raise InputError(
                f"two files of frame {key}: {first[key].name} and {f.name} (frame ids are compared zero-padded to "
                "six digits); keep one",
                source=source,
                frame=key,
            )
        first[key] = f


def read_bytes(path: Path) -> bytes:
    """A txt file's bytes, as the devkit reads them (refused past :data:`MAX_TXT_FILE_BYTES`)."""
    try:
        with open(path, "rb") as fh:
            if os.fstat(fh.fileno()).st_size > MAX_TXT_FILE_BYTES:
                raise too_large_txt(path.name, str(path))
            raw = fh.read(MAX_TXT_FILE_BYTES + 1)
            if len(raw) > MAX_TXT_FILE_BYTES:  # a file that grew, or a pipe
                raise too_large_txt(path.name, str(path))
    except OSError as e:
        raise InputError(f"cannot read: {e.strerror or e}", source=str(path), frame=path.stem) from None
    return raw


def read_text(path: Path) -> str:
    """A text file that is not a KITTI label file (a split's frame list), as text: a byte order mark is
    dropped, bytes that are not UTF-8 become U+FFFD."""
    return read_bytes(path).decode("utf-8-sig", "replace")


def parse_kitti_txt(text: bytes | str, kind: Kind, *, frame: str, source: str) -> tuple[list[str], list[float]]:
    """Parse one frame's KITTI lines (the file's bytes; text is taken as UTF-8): the class names, and the
    numbers after the type, flat.

    Returns ``(names, values)`` with ``len(values) == 14 * len(names)`` for ground truth (truncated ..
    ry; a 16th field is ignored) and ``15 * len(names)`` for detections (.. ry, score). Blank lines are
    skipped. Raises :class:`InputError` naming the frame, the 1-based line and the field, for anything
    the devkit would read otherwise (:mod:`~kitti_eval.io.formats.txt_grammar`).
    """
    raw = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text
    lines, width, names, tokens = _split_frame(raw, kind, frame, source)
    try:
        values = list(map(float, tokens))
    except ValueError:
        _raise_bad_number(lines, width, kind, frame, source)
    problem = values_problem(values, kind)
    if problem is not None:
        _raise_at_record(raw, problem[0], problem[1], problem[2], frame, source)
    return names, values


def _split_frame(raw: bytes, kind: Kind, frame: str, source: str) -> tuple[list[bytes], int, list[str], list[bytes]]:
    """(lines, fields a line, names, number tokens) of one file: the layout and every field's spelling
    checked against the devkit's grammar (:mod:`~kitti_eval.io.formats.txt_grammar`), the numbers not yet
    converted.

    Works on the whole file at once (all tokens in one list, names every ``width`` tokens) once every
    non-blank line is known to have the same accepted number of fields: 3769 files x 40 lines in ~0.1 s.
    """
    check_start(raw, frame, source)
    n_keep = _N_FIELDS[kind]  # fields kept per line, the type included
    accepted = {15, 16} if kind == "ground_truth" else {16}
    lines = raw.splitlines()  # at LF, CR and CRLF; VT and FF separate fields, as any C whitespace
    rows = list(map(bytes.split, lines))  # at the six C whitespace bytes only, as fscanf
    counts = set(map(len, rows))
    counts.discard(0)  # blank lines
    if not counts <= accepted or len(counts) > 1:
        _raise_bad_line(lines, kind, accepted, frame, source)
    width = counts.pop() if counts else n_keep
    tokens = list(chain.from_iterable(rows))
    names = tokens[0::width]
    del tokens[0::width]  # now width - 1 numbers per line
    check_names(raw, lines, names, width, kind, frame, source)
    if width > n_keep:  # a 16th field (score) in ground truth: dropped
        del tokens[n_keep - 1 :: width - 1]
    if not check_number_bytes(raw, names, tokens, n_keep - 1, kind):
        explain_numbers(lines, width, kind, frame, source)
    # "\n" is in no name and in no character a bad byte is replaced with: one decode for the whole file
    text_names = b"\n".join(names).decode("utf-8", "replace").split("\n") if names else []
    return lines, width, text_names, tokens


def _raise_bad_line(lines: list[bytes], kind: Kind, accepted: set[int], frame: str, source: str) -> None:
    first_width = None
    for lineno, line in enumerate(lines, 1):
        n = len(line.split())
        if n == 0:
            continue
        if n not in accepted:
            if kind == "ground_truth":
                expected = (
                    "15 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry; a 16th, "
                    "score, is also accepted)"
                )
            else:
                expected = "16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score)"
            sep = foreign_separator(line)
            hint = f"; {not_a_separator(sep)}, and reads the characters around it as one field" if sep else ""
            raise InputError(f"line {lineno}: expected {expected}, got {n}{hint}", source=source, frame=frame)
        if first_width is None:
            first_width = n
        elif n != first_width:
            raise InputError(
                f"line {lineno}: {n} fields, but earlier lines have {first_width}; use one layout per file",
                source=source,
                frame=frame,
            )
    raise InputError("inconsistent field counts", source=source, frame=frame)  # pragma: no cover


def _raise_bad_number(lines: list[bytes], width: int, kind: Kind, frame: str, source: str) -> NoReturn:
    explain_numbers(lines, width, kind, frame, source)
    raise InputError("unparsable number", source=source, frame=frame)  # pragma: no cover


def _raise_at_record(raw: bytes, record: int, field: str, message: str, frame: str, source: str) -> NoReturn:
    """Raise ``message`` for the ``record``-th (0-based) non-blank line of the file ``raw``."""
    lines = raw.splitlines()
    lineno = [i for i, line in enumerate(lines, 1) if line.split()][record]
    raise InputError(f"line {lineno}: {message}", source=source, frame=frame, field=field)


_DEFAULT_LIMITS = ArchiveLimits()


def input_kind(path: PathLike, source: str | None = None) -> InputKind:
    """What a file holds, from its content (the same test the service makes of an upload):
    :func:`kitti_eval.io.archives.sniff_input`. Raises InputError (UnknownFormatError for other content)."""
    try:
        with open(path, "rb") as fh:
            return sniff_input(fh, str(path) if source is None else source)
    except OSError as e:
        raise InputError(f"cannot read {path}: {e.strerror or e}", source=source) from None


def is_archive(path: PathLike) -> bool:
    """A zip or tar of txt files by its content (False for anything else, or a file that cannot be read)."""
    try:
        return input_kind(path) != "pickle"
    except InputError:
        return False


def extract_txt_archive(path: PathLike, dest: PathLike, *, limits: ArchiveLimits = _DEFAULT_LIMITS) -> Path:
    """Unpack the ``.txt`` files of one folder of a zip or tar into a subfolder of ``dest``; returns it.

    A thin wrapper over :func:`kitti_eval.io.archives.extract_txt_folder` (which see for the checks and for
    which folder is taken when several hold txt files); anything that is not a zip is read as a tar.
    """
    source = str(path)
    try:
        fh = open(path, "rb")
    except OSError as e:
        raise InputError(f"cannot read the archive ({e.strerror or type(e).__name__})", source=source) from None
    with fh:
        folder, _ = extract_txt_folder(fh, sniff_archive(fh) or "tar", Path(dest), limits, source)
    return folder


def load_txt_archive(
    p: Path,
    kind: Kind,
    source: str,
    max_bytes: int,
    max_frames: int,
    known_frames: Collection[str] | None,
    bounds: BoxLimits | None = None,
) -> Annotations:
    """The KITTI txt folder in the zip or tar ``p``, unpacked to a temporary folder (at most ``max_bytes``)."""
    archive_limits = ArchiveLimits(max_unpacked_bytes=max_bytes, bytes_setting=MAX_INPUT_ENV)
    with tempfile.TemporaryDirectory(prefix="kitti-eval-") as tmp:
        folder = extract_txt_archive(p, tmp, limits=archive_limits)
        try:
            annos = load_kitti_txt_dir(folder, kind, max_frames=max_frames, known_frames=known_frames, bounds=bounds)
        except InputError as e:
            raise type(e)(e.message, source=source, frame=e.frame, field=e.field) from None
    return dataclasses.replace(annos, source=source)


#: ``kitti_txt``: a folder of KITTI txt files, or a zip or tar of one
KITTI_TXT = Format("kitti_txt", "folder")
