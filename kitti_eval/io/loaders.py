"""Read ground truth and detections from KITTI txt folders and OpenPCDet-style pickles.

Every route ends in :meth:`Annotations.from_frames`, which validates shapes, dtypes, finiteness and
duplicate frames; the loaders here only find the frames, their ids and their field dicts, and report
structural problems (wrong top-level type, entries without a frame id, txt lines with the wrong number
of fields) with the entry, frame and line where they happen.

Formats
-------
* KITTI txt folder: one ``<frame>.txt`` per frame, 15 fields per line for ground truth (a 16th, the
  score, is accepted and ignored) and exactly 16 for detections; dimensions are written h, w, l and are
  reordered to the l, h, w of :class:`Annotations`. A folder without ``.txt`` files but with a ``data/``
  subfolder that has them (OpenPCDet's ``final_result/data``) is read from there.
* Pickles (read only through :func:`kitti_eval.io.safe_pickle.load_pickle`, gzip or not), by detected format:

  ==================  ====================================================================================
  ``openpcdet_infos``  list of OpenPCDet info dicts (``image``/``point_cloud``/``annos``): ground truth
  ``annos_list``       list of annos dicts that carry ``frame_id`` (OpenPCDet ``result.pkl``; for ground
                       truth, plain annos dicts with ``frame_id``)
  ``annos_by_frame``   dict ``{frame id: annos dict}`` (PointPillars style; for ground truth the values may
                       also be info dicts holding ``annos``)
  ``mmdet3d_infos``    mmdetection3d 1.x info dict ``{'metainfo', 'data_list'}``: ground truth; names from
                       ``metainfo['categories']``, ``bbox_label`` -1 is DontCare, ``bbox_3d`` = x y z l h w ry
                       (camera, bottom centre); frame ids from ``sample_idx``
  ``mmdet3d_results``  list of mmdetection3d KITTI-format result dicts (OpenPCDet's fields plus ``sample_idx``,
                       an int or an array repeating it per box; entries with no boxes and no id are skipped)
  ==================  ====================================================================================

  Detections that carry only ``boxes_lidar`` (OpenPCDet LiDAR convention) are converted to the camera frame
  with each frame's calibration (:mod:`kitti_eval.io.calib`), taken from the ground-truth infos; see
  :func:`load_pair`. Zip and tar archives of a KITTI txt folder are unpacked safely (:func:`extract_txt_archive`,
  over :mod:`kitti_eval.io.archives`).

  New formats are added to :data:`PICKLE_FORMATS` with a detector in :func:`detect_format`.
"""

from __future__ import annotations

import os
from array import array
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np

from ..core.frames import Annotations, Kind, normalize_frame_id, shown_frame_id
from ..errors import ConfigError, InputError
from .archives import (
    MAX_TXT_FILE_BYTES,
    ArchiveLimits,
    InputKind,
    extract_txt_folder,
    sniff_archive,
    sniff_input,
    too_large_txt,
)
from .safe_pickle import load_pickle, load_pickles

__all__ = [
    "load_ground_truth",
    "load_detections",
    "load_annotations",
    "load_kitti_txt_dir",
    "parse_kitti_txt",
    "annotations_from_object",
    "detect_format",
    "describe_format",
    "PICKLE_FORMATS",
    "KITTI_TXT_FIELDS",
    "FORMATS",
    "load_pair",
    "load_ground_truth_and_calibs",
    "read_split",
    "apply_split",
    "calibs_from_object",
    "extract_txt_archive",
    "is_archive",
    "ArchiveLimits",
]

#: the fields of a KITTI label line, in file order (``score`` only in detections)
KITTI_TXT_FIELDS = (
    "type",
    "truncated",
    "occluded",
    "alpha",
    "x1",
    "y1",
    "x2",
    "y2",
    "h",
    "w",
    "l",
    "x",
    "y",
    "z",
    "ry",
    "score",
)
_N_FIELDS = {"ground_truth": 15, "detections": 16}
_KIND_WORD = {"ground_truth": "ground-truth", "detections": "result"}

PathLike = str | os.PathLike[str]
Frames = Iterator[tuple[object, Mapping[str, Any]]]


# ------------------------------------------------------------------------------------------ limits

#: the environment variables that set the limits on one input (the service reads the same ones)
MAX_INPUT_ENV = "KITTI_EVAL_MAX_UNPACKED_MB"
MAX_FRAMES_ENV = "KITTI_EVAL_MAX_FRAMES"
DEFAULT_MAX_INPUT_MB = 512
DEFAULT_MAX_FRAMES = 200_000


def input_limits() -> tuple[int, int]:
    """``(max_bytes, max_frames)`` for one input, from :data:`MAX_INPUT_ENV` / :data:`MAX_FRAMES_ENV` or the
    defaults (512 MB, 200,000 frames; KITTI val is 22 MB and 3,769 frames).

    ``max_bytes`` caps a pickle after decompression and the unpacked txt files of an archive; ``max_frames``
    caps the frames of one input (a pickle's top-level list is refused before it is built, other layouts
    before a frame beyond the cap is converted). Every loader uses these unless given its own.
    """
    out = []
    for env, default, unit in ((MAX_INPUT_ENV, DEFAULT_MAX_INPUT_MB, 1 << 20), (MAX_FRAMES_ENV, DEFAULT_MAX_FRAMES, 1)):
        raw = os.environ.get(env, "").strip()
        try:
            value = float(raw) if raw else default
        except ValueError:
            value = -1
        if not value > 0 or value == float("inf"):
            raise ConfigError(f"{env}={raw!r}: expected a number > 0")
        out.append(int(value * unit))
    return out[0], out[1]


def _limits(max_bytes: int | None, max_frames: int | None) -> tuple[int, int]:
    if max_bytes is not None and max_frames is not None:
        return max_bytes, max_frames
    env_bytes, env_frames = input_limits()
    return (env_bytes if max_bytes is None else max_bytes), (env_frames if max_frames is None else max_frames)


# ------------------------------------------------------------------------------------------ public API


def load_ground_truth(
    path: PathLike, *, max_bytes: int | None = None, fmt: str | None = None, max_frames: int | None = None
) -> Annotations:
    """Ground truth from a KITTI ``label_2``-style txt folder (or a zip/tar of one) or an infos/annos pickle."""
    return load_annotations(path, "ground_truth", max_bytes=max_bytes, fmt=fmt, max_frames=max_frames)


def load_detections(
    path: PathLike,
    *,
    max_bytes: int | None = None,
    fmt: str | None = None,
    calibs: Mapping[str, Any] | None = None,
    warnings: list[str] | None = None,
    keep_lidar: bool = False,
    max_frames: int | None = None,
    known_frames: Collection[str] | None = None,
) -> Annotations:
    """Detections from a KITTI txt folder (16 fields; or a zip/tar of one) or a ``result.pkl``-style pickle.

    ``calibs`` ({frame id: :class:`kitti_eval.io.calib.Calib`}) converts LiDAR-only boxes and checks boxes that
    carry both; messages about the check are appended to ``warnings``. ``keep_lidar`` keeps the
    ``boxes_lidar`` as written, for display (:attr:`Annotations.boxes_lidar`). ``known_frames`` (the ground
    truth's frame ids): a frame outside them is refused as soon as it is read. ``max_bytes``, ``max_frames``:
    see :func:`input_limits` (None: its values).
    """
    return load_annotations(
        path,
        "detections",
        max_bytes=max_bytes,
        fmt=fmt,
        calibs=calibs,
        warnings=warnings,
        keep_lidar=keep_lidar,
        max_frames=max_frames,
        known_frames=known_frames,
    )


def _check_fmt(fmt: str | None) -> None:
    if fmt is not None and fmt not in FORMATS:
        raise InputError(f"unknown format {fmt!r}; known: {', '.join(FORMATS)}")


def _missing(p: Path, kind: Kind, source: str) -> InputError:
    what = "ground truth" if kind == "ground_truth" else "detections"
    return InputError(
        f"no such file or directory (expected {what} as a KITTI txt folder, a zip/tar of one, or a pickle)",
        source=source,
    )


def load_annotations(
    path: PathLike,
    kind: Kind,
    *,
    max_bytes: int | None = None,
    fmt: str | None = None,
    calibs: Mapping[str, Any] | None = None,
    warnings: list[str] | None = None,
    keep_lidar: bool = False,
    max_frames: int | None = None,
    known_frames: Collection[str] | None = None,
) -> Annotations:
    """A folder is read as KITTI txt files, a zip/tar as an archived txt folder, a file as a pickle.

    ``fmt`` (a name of :data:`FORMATS`) skips the detection of the layout; the rest: see
    :func:`load_detections`.
    """
    _check_kind(kind)
    _check_fmt(fmt)
    max_bytes, max_frames = _limits(max_bytes, max_frames)
    p = Path(path)
    source = str(path)
    if p.is_dir():
        if fmt not in (None, "kitti_txt"):
            raise InputError(f"a folder is read as KITTI txt files, not as {fmt!r}", source=source)
        return load_kitti_txt_dir(p, kind, max_frames=max_frames, known_frames=known_frames)
    if not p.exists():
        raise _missing(p, kind, source)
    if p.suffix.lower() == ".txt":
        raise InputError(
            "this is a single txt file; pass the folder that holds one KITTI txt file per frame", source=source
        )
    if fmt == "kitti_txt" or (fmt is None and input_kind(p, source) != "pickle"):
        return _load_txt_archive(p, kind, source, max_bytes, max_frames, known_frames)
    obj = load_pickle(p, source=source, max_bytes=max_bytes, max_entries=max_frames)
    return annotations_from_object(
        obj,
        kind,
        source=source,
        fmt=fmt,
        calibs=calibs,
        warnings=warnings,
        keep_lidar=keep_lidar,
        max_frames=max_frames,
        known_frames=known_frames,
    )


def annotations_from_object(
    obj: object,
    kind: Kind,
    *,
    source: str,
    fmt: str | None = None,
    calibs: Mapping[str, Any] | None = None,
    warnings: list[str] | None = None,
    keep_lidar: bool = False,
    max_frames: int | None = None,
    known_frames: Collection[str] | None = None,
) -> Annotations:
    """Annotations from an already unpickled object (e.g. an upload passed through ``load_pickle``).

    ``fmt`` forces a layout of :data:`PICKLE_FORMATS`; the rest: see :func:`load_detections`.
    """
    _check_kind(kind)
    _check_fmt(fmt)
    if fmt == "kitti_txt":
        raise InputError("this is a pickle, not KITTI txt files", source=source)
    if fmt is None:
        fmt = detect_format(obj, kind, source=source)
    else:
        _check_layout(obj, fmt, source)
    frames = PICKLE_FORMATS[fmt](obj, kind, source, warnings if warnings is not None else [])
    if kind == "detections":
        frames = _camera_fields(frames, calibs, source, warnings)
    return Annotations.from_frames(
        kind,
        source,
        frames,
        keep_lidar=keep_lidar and kind == "detections",
        max_frames=_limits(None, max_frames)[1],
        known_frames=known_frames,
    )


# ---------------------------------------------------------------------------------------- KITTI txt


def _txt_files(directory: Path) -> list[Path]:
    try:
        entries = list(os.scandir(directory))
    except OSError as e:
        raise InputError(f"cannot list the folder: {e.strerror or e}", source=str(directory)) from None
    return [
        Path(e.path) for e in entries if e.name.lower().endswith(".txt") and not e.name.startswith(".") and e.is_file()
    ]


def load_kitti_txt_dir(
    directory: PathLike, kind: Kind, *, max_frames: int | None = None, known_frames: Collection[str] | None = None
) -> Annotations:
    """One KITTI txt file per frame; the frame id is the file stem (``000015.txt`` -> ``"000015"``).

    Files are read in name order; files not ending in ``.txt`` (and hidden files) are ignored; an empty
    file is a frame without boxes.
    """
    _check_kind(kind)
    root = Path(directory)
    files = _txt_files(root)
    if not files and (root / "data").is_dir():
        files = _txt_files(root / "data")  # OpenPCDet --save_to_file: final_result/data/*.txt
    if not files:
        subdirs = sorted(e.name for e in os.scandir(root) if e.is_dir())
        hint = f"; it has subfolders {', '.join(subdirs[:5])}: pass the one holding the txt files" if subdirs else ""
        raise InputError(f"no .txt files in the folder{hint}", source=str(root))
    files.sort(key=lambda f: f.name)
    max_frames = _limits(None, max_frames)[1]
    if len(files) > max_frames:
        raise InputError(
            f"{len(files)} txt files, more than the limit of {max_frames} frames ({MAX_FRAMES_ENV})", source=str(root)
        )

    n_values = _N_FIELDS[kind] - 1  # numbers per line that are kept (score dropped for ground truth)
    names: list[str] = []
    values = array("d")  # plain float() parsing, straight into one buffer
    spans: list[tuple[str, int, int]] = []  # (frame id, first row, row count)
    for f in files:
        lines, frame_names, tokens = _split_frame(_read_text(f), kind, f.stem, str(f))
        try:
            values.extend(map(float, tokens))
        except ValueError:
            _raise_bad_number(lines, _N_FIELDS[kind], f.stem, str(f))
        spans.append((f.stem, len(names), len(frame_names)))
        names.extend(frame_names)

    table = np.frombuffer(values, dtype=np.float64).reshape(len(names), n_values)
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


def _read_text(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            if os.fstat(fh.fileno()).st_size > MAX_TXT_FILE_BYTES:
                raise too_large_txt(path.name, str(path))
            raw = fh.read(MAX_TXT_FILE_BYTES + 1)
            if len(raw) > MAX_TXT_FILE_BYTES:  # a file that grew, or a pipe
                raise too_large_txt(path.name, str(path))
    except OSError as e:
        raise InputError(f"cannot read: {e.strerror or e}", source=str(path), frame=path.stem) from None
    # the devkit reads the fields as bytes: a byte that is not UTF-8 (U+FFFD here) can only be part of a class
    # name, which then is no class's, as with any unknown name; in a number it fails to parse, naming the line
    return raw.decode("utf-8-sig", "replace")


def parse_kitti_txt(text: str, kind: Kind, *, frame: str, source: str) -> tuple[list[str], list[float]]:
    """Parse one frame's KITTI lines: the class names, and the numbers after the type, flat.

    Returns ``(names, values)`` with ``len(values) == 14 * len(names)`` for ground truth (truncated ..
    ry; a 16th field is ignored) and ``15 * len(names)`` for detections (.. ry, score). Blank lines are
    skipped. Raises :class:`InputError` naming the frame, the 1-based line and the field.
    """
    lines, names, tokens = _split_frame(text, kind, frame, source)
    try:
        values = list(map(float, tokens))
    except ValueError:
        _raise_bad_number(lines, _N_FIELDS[kind], frame, source)
        raise  # pragma: no cover - _raise_bad_number always raises
    return names, values


def _split_frame(text: str, kind: Kind, frame: str, source: str) -> tuple[list[str], list[str], list[str]]:
    """(lines, names, number tokens): field counts checked per line, tokens not yet converted.

    Works on the whole file at once (all tokens in one list, names every ``width`` tokens) once every
    non-blank line is known to have the same accepted number of fields: 3769 files x 40 lines in ~0.1 s.
    """
    n_keep = _N_FIELDS[kind]  # fields kept per line, the type included
    accepted = {15, 16} if kind == "ground_truth" else {16}
    lines = text.splitlines()
    rows = list(map(str.split, lines))
    counts = set(map(len, rows))
    counts.discard(0)  # blank lines
    if not counts <= accepted or len(counts) > 1:
        _raise_bad_line(lines, kind, accepted, frame, source)
    width = counts.pop() if counts else n_keep
    tokens = list(chain.from_iterable(rows))
    names = tokens[0::width]
    del tokens[0::width]  # now width - 1 numbers per line
    if width > n_keep:  # a 16th field (score) in ground truth: dropped
        del tokens[n_keep - 1 :: width - 1]
    return lines, names, tokens


def _raise_bad_line(lines: list[str], kind: Kind, accepted: set[int], frame: str, source: str) -> None:
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
            raise InputError(f"line {lineno}: expected {expected}, got {n}", source=source, frame=frame)
        if first_width is None:
            first_width = n
        elif n != first_width:
            raise InputError(
                f"line {lineno}: {n} fields, but earlier lines have {first_width}; use one layout per file",
                source=source,
                frame=frame,
            )
    raise InputError("inconsistent field counts", source=source, frame=frame)  # pragma: no cover


def _raise_bad_number(lines: list[str], n_fields: int, frame: str, source: str) -> None:
    for lineno, line in enumerate(lines, 1):
        parts = line.split()
        for k, tok in enumerate(parts[1:n_fields], 1):
            try:
                float(tok)
            except ValueError:
                field = KITTI_TXT_FIELDS[k]
                raise InputError(
                    f"line {lineno}: {field} is not a number: {tok!r}", source=source, frame=frame, field=field
                ) from None
    raise InputError("unparsable number", source=source, frame=frame)  # pragma: no cover


# ------------------------------------------------------------------------------------------ pickles


def _check_kind(kind: str) -> None:
    if kind not in _N_FIELDS:
        raise ValueError(f"kind must be 'ground_truth' or 'detections', got {kind!r}")


def _type_name(obj: object) -> str:
    if isinstance(obj, np.ndarray):
        return f"a numpy array of shape {obj.shape} and dtype {obj.dtype}"
    return type(obj).__name__


def describe_format(obj: object) -> str:
    """A short description of an unpickled object's shape, for messages."""
    if isinstance(obj, (list, tuple)):
        kind = type(obj).__name__
        if not obj:
            return f"an empty {kind}"
        first = obj[0]
        if isinstance(first, Mapping):
            keys = ", ".join(sorted(map(str, first.keys()))[:12])
            return f"a {kind} of {len(obj)} entries, the first a dict with keys [{keys}]"
        return f"a {kind} of {len(obj)} entries, the first {_type_name(first)}"
    if isinstance(obj, Mapping):
        names = list(obj.keys())
        shown = ", ".join(repr(k) for k in names[:6]) + (", ..." if len(names) > 6 else "")
        return f"a dict with {len(names)} keys [{shown}]"
    return _type_name(obj)


_INFO_KEYS = frozenset({"annos", "image", "point_cloud", "calib"})
_ANNOS_KEYS = frozenset({"name", "bbox", "dimensions", "location", "rotation_y"})


def detect_format(obj: object, kind: Kind, *, source: str) -> str:
    """The name of the pickle layout of ``obj`` (a key of :data:`PICKLE_FORMATS`), or InputError."""
    expected = (
        "a list of per-frame dicts (OpenPCDet kitti_infos_*.pkl, or annos dicts with frame_id)"
        if kind == "ground_truth"
        else "a list of per-frame dicts (OpenPCDet result.pkl)"
    )
    expected += ", or a dict {frame id: annos dict}"
    if isinstance(obj, (list, tuple)):
        for i, entry in enumerate(obj):
            if not isinstance(entry, Mapping):
                raise InputError(
                    f"{_KIND_WORD[kind]} entry #{i} is {_type_name(entry)}, expected a dict; "
                    f"the file should hold {expected}",
                    source=source,
                    frame=f"#{i}",
                )
        if not obj:
            raise InputError(f"the pickle holds an empty {type(obj).__name__}: no frames", source=source)
        first = obj[0]
        if "sample_idx" in first and "frame_id" not in first and "name" in first:
            return "mmdet3d_results"
        if _INFO_KEYS & first.keys() and "name" not in first:
            if kind == "detections":
                raise InputError(
                    "this is an OpenPCDet infos file (ground-truth labels), not detections; "
                    "pass it as the ground truth and the result.pkl as the predictions",
                    source=source,
                )
            return "openpcdet_infos"
        if "name" in first or "frame_id" in first:
            return "annos_list"
        raise InputError(
            f"entry #0 has none of the expected keys: found {describe_format(obj)}; expected {expected}",
            source=source,
            frame="#0",
        )
    if isinstance(obj, Mapping):
        if "data_list" in obj and "metainfo" in obj:
            if kind == "detections":
                raise InputError(
                    "this is an mmdetection3d 1.x info file (metainfo/data_list: ground-truth "
                    "labels), not detections; pass it as the ground truth",
                    source=source,
                )
            return "mmdet3d_infos"
        if _ANNOS_KEYS & obj.keys():
            raise InputError(
                f"this is a single frame's annos dict ({describe_format(obj)}); expected one per frame: {expected}",
                source=source,
            )
        if not obj:
            raise InputError("the pickle holds an empty dict: no frames", source=source)
        return "annos_by_frame"
    raise InputError(f"expected {expected}; found {describe_format(obj)}", source=source)


_ID_TYPES = (str, int, bytes, np.str_, np.integer)


def _frame_id(value: object, what: str, source: str, frame: str) -> object:
    """A raw frame id of an accepted type (0-d arrays unwrapped); the rest is from_frames' job."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if not isinstance(value, _ID_TYPES) or isinstance(value, (bool, np.bool_)):
        raise InputError(
            f"{what} is {_type_name(value)}, expected a string or an integer",
            source=source,
            frame=frame,
            field="frame_id",
        )
    return value


def _entry_frame_id(entry: Mapping[str, Any], i: int, source: str, fallbacks: list[int] | None = None) -> object:
    """An infos entry's frame id: ``image.image_idx``, else ``point_cloud.lidar_idx`` (the entry's index is then
    added to ``fallbacks``), else ``frame_id``."""
    for parent, key in (("image", "image_idx"), ("point_cloud", "lidar_idx")):
        sub = entry.get(parent)
        if sub is None:
            continue
        if not isinstance(sub, Mapping):
            raise InputError(
                f"infos entry #{i}: '{parent}' is {_type_name(sub)}, expected a dict",
                source=source,
                frame=f"#{i}",
                field=parent,
            )
        if sub.get(key) is not None:
            if parent == "point_cloud" and fallbacks is not None:
                fallbacks.append(i)
            return _frame_id(sub[key], f"infos entry #{i}: {parent}.{key}", source, f"#{i}")
    if entry.get("frame_id") is not None:
        return _frame_id(entry["frame_id"], f"infos entry #{i}: frame_id", source, f"#{i}")
    raise InputError(
        f"infos entry #{i} has no frame id (image.image_idx, point_cloud.lidar_idx or frame_id)",
        source=source,
        frame=f"#{i}",
    )


def _frames_openpcdet_infos(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    fallbacks: list[int] = []
    first = None
    for i, info in enumerate(obj):
        fid = _entry_frame_id(info, i, source, fallbacks)
        if fallbacks and first is None:
            first = fid
        if "annos" not in info:
            raise InputError(
                f"the infos have no labels ('annos' missing in entry #{i}): a test split? "
                "Ground truth needs the train/val infos or the label_2 folder",
                source=source,
                frame=shown_frame_id(fid),
            )
        annos = info["annos"]
        if not isinstance(annos, Mapping):
            raise InputError(
                f"infos entry #{i}: 'annos' is {_type_name(annos)}, expected a dict",
                source=source,
                frame=shown_frame_id(fid),
                field="annos",
            )
        yield fid, annos
    if fallbacks:
        warnings.append(
            f"{source}: {len(fallbacks)} entries have no image.image_idx; their point_cloud.lidar_idx is used as the "
            f"frame id (the first: entry #{fallbacks[0]}, frame {shown_frame_id(first)})"
        )


def _frames_annos_list(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    for i, entry in enumerate(obj):
        fid = entry.get("frame_id")
        if fid is None:
            raise InputError(
                f"{_KIND_WORD[kind]} entry #{i} has no frame_id (frames are matched by id, never by position)",
                source=source,
                frame=f"#{i}",
                field="frame_id",
            )
        yield _frame_id(fid, f"{_KIND_WORD[kind]} entry #{i}: frame_id", source, f"#{i}"), entry


def _frames_annos_by_frame(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    for pos, (key, value) in enumerate(obj.items()):
        key = _frame_id(key, f"key #{pos} of the dict", source, f"#{pos}")
        if kind == "ground_truth" and isinstance(value, Mapping) and "annos" in value and "name" not in value:
            value = value["annos"]  # an info dict keyed by frame (PointPillars kitti_infos_*.pkl)
        yield key, value


#: pickle layout name -> generator of (frame id, fields) for :meth:`Annotations.from_frames`
PICKLE_FORMATS: dict[str, Callable[[Any, Kind, str, list[str]], Frames]] = {
    "openpcdet_infos": _frames_openpcdet_infos,
    "annos_list": _frames_annos_list,
    "annos_by_frame": _frames_annos_by_frame,
}


# ------------------------------------------------------------------------------------ mmdetection3d 1.x


def _frames_mmdet3d_infos(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    meta = obj.get("metainfo")
    data_list = obj.get("data_list")
    if not isinstance(meta, Mapping) or not isinstance(data_list, (list, tuple)):
        raise InputError("an mmdetection3d 1.x info file needs a 'metainfo' dict and a 'data_list' list", source=source)
    if not data_list:
        raise InputError("an mmdetection3d 1.x info file with an empty data_list: no frames", source=source)
    cats = meta.get("categories")
    if not isinstance(cats, Mapping):
        raise InputError(
            "mmdetection3d 1.x info file without metainfo['categories'] (class name -> label)",
            source=source,
            field="metainfo",
        )
    label2cat: dict[int, str] = {}
    for name, label in cats.items():
        try:
            label2cat[int(label)] = str(name)
        except (TypeError, ValueError):
            raise InputError(
                f"metainfo['categories'][{name!r}] is {label!r}, expected an integer label",
                source=source,
                field="metainfo",
            ) from None
    label2cat.setdefault(-1, "DontCare")
    for i, entry in enumerate(data_list):
        if not isinstance(entry, Mapping):
            raise InputError(
                f"data_list entry #{i} is {_type_name(entry)}, expected a dict", source=source, frame=f"#{i}"
            )
        if entry.get("sample_idx") is None:
            raise InputError(
                f"data_list entry #{i} has no sample_idx", source=source, frame=f"#{i}", field="sample_idx"
            )
        fid = _frame_id(entry["sample_idx"], f"data_list entry #{i}: sample_idx", source, f"#{i}")
        shown = shown_frame_id(fid)
        instances = entry.get("instances")
        if instances is None:
            raise InputError(
                f"data_list entry #{i} has no 'instances' (a test split?)",
                source=source,
                frame=shown,
                field="instances",
            )
        if not isinstance(instances, (list, tuple)):
            raise InputError(
                f"'instances' is {_type_name(instances)}, expected a list",
                source=source,
                frame=shown,
                field="instances",
            )
        yield fid, _mmdet3d_instances(instances, label2cat, source, shown)


def _mmdet3d_instances(
    instances: Sequence[Any], label2cat: Mapping[int, str], source: str, frame: str
) -> dict[str, Any]:
    n = len(instances)
    names: list[str] = []
    cols: dict[str, list[Any]] = {k: [] for k in ("bbox", "bbox_3d", "truncated", "occluded", "alpha")}
    for j, inst in enumerate(instances):
        if not isinstance(inst, Mapping):
            raise InputError(f"instance #{j} is {_type_name(inst)}, expected a dict", source=source, frame=frame)
        for key in ("bbox_label", *cols):
            if key not in inst:
                raise InputError(f"instance #{j} has no '{key}'", source=source, frame=frame, field=key)
        label = inst["bbox_label"]
        try:
            names.append(label2cat[int(label)])
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"instance #{j}: bbox_label {label!r} is not in metainfo['categories']",
                source=source,
                frame=frame,
                field="bbox_label",
            ) from None
        for key, col in cols.items():
            col.append(inst[key])
    fields: dict[str, Any] = {"name": np.array(names) if n else np.zeros(0, dtype="<U1")}
    try:
        box3d = np.asarray(cols["bbox_3d"], dtype=np.float64).reshape(n, 7) if n else np.zeros((0, 7))
        fields["bbox"] = np.asarray(cols["bbox"], dtype=np.float64).reshape(n, 4) if n else np.zeros((0, 4))
        for key in ("truncated", "occluded", "alpha"):
            fields[key] = np.asarray(cols[key], dtype=np.float64).reshape(n)
    except (TypeError, ValueError) as e:
        raise InputError(
            f"instances: bbox must be 4 numbers, bbox_3d 7, truncated/occluded/alpha one ({e})",
            source=source,
            frame=frame,
        ) from None
    fields["location"] = box3d[:, 0:3]
    fields["dimensions"] = box3d[:, 3:6]
    fields["rotation_y"] = box3d[:, 6]
    return fields


def _frames_mmdet3d_results(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    for i, entry in enumerate(obj):
        raw = entry.get("sample_idx")
        if isinstance(raw, (list, tuple)):
            raw = np.asarray(raw)
        if isinstance(raw, np.ndarray) and raw.ndim == 1:
            uniq = np.unique(raw)
            if len(uniq) == 0:
                if np.size(entry.get("score", ())) == 0:
                    continue  # mmdet3d writes an empty sample_idx for a frame without boxes: nothing to add
                raise InputError(
                    f"{_KIND_WORD[kind]} entry #{i} has boxes but an empty sample_idx",
                    source=source,
                    frame=f"#{i}",
                    field="sample_idx",
                )
            if len(uniq) > 1:
                raise InputError(
                    f"{_KIND_WORD[kind]} entry #{i}: sample_idx holds several frames {uniq[:4].tolist()}",
                    source=source,
                    frame=f"#{i}",
                    field="sample_idx",
                )
            raw = uniq[0]
        if raw is None:
            raise InputError(
                f"{_KIND_WORD[kind]} entry #{i} has no sample_idx (frames are matched by id, never by position)",
                source=source,
                frame=f"#{i}",
                field="sample_idx",
            )
        yield _frame_id(raw, f"{_KIND_WORD[kind]} entry #{i}: sample_idx", source, f"#{i}"), entry


def _check_layout(obj: object, fmt: str, source: str) -> None:
    """A forced format must at least have the right top-level type."""
    want = {"mmdet3d_infos": Mapping, "annos_by_frame": Mapping}.get(fmt, (list, tuple))
    if not isinstance(obj, want):
        raise InputError(
            f"format {fmt!r} expects a {'dict' if want is Mapping else 'list'}; found {describe_format(obj)}",
            source=source,
        )
    if want is not Mapping:
        for i, entry in enumerate(obj):
            if not isinstance(entry, Mapping):
                raise InputError(f"entry #{i} is {_type_name(entry)}, expected a dict", source=source, frame=f"#{i}")


PICKLE_FORMATS["mmdet3d_infos"] = _frames_mmdet3d_infos
PICKLE_FORMATS["mmdet3d_results"] = _frames_mmdet3d_results

#: every format name ``--gt-format`` / ``--pred-format`` accept
FORMATS: tuple[str, ...] = (*PICKLE_FORMATS, "kitti_txt")


# -------------------------------------------------------------------------- LiDAR boxes and calibration

_CAMERA_FIELDS = ("location", "dimensions", "rotation_y")


class _LazyCalibs(Mapping[str, Any]):
    """{frame id: :class:`kitti_eval.io.calib.Calib`}, each worked out from its entry when first asked for (the
    loader asks for a few frames: those with LiDAR boxes only, and every tenth one to compare both); a
    frame whose calibration cannot be read is missing."""

    def __init__(self, entries: dict[str, Any], build: Callable[[Any], Any]) -> None:
        self._entries, self._build, self._done = entries, build, dict[str, Any]()

    def __getitem__(self, frame_id: str) -> Any:
        if frame_id not in self._done:
            try:
                self._done[frame_id] = self._build(self._entries[frame_id])
            except (TypeError, ValueError, IndexError, AttributeError, InputError) as e:
                raise KeyError(frame_id) from e
        return self._done[frame_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


def _mmdet3d_calib(entry: Mapping[str, Any]) -> Any:
    from .calib import Calib

    cam = entry["images"]["CAM2"]
    p2 = np.asarray(cam["cam2img"], dtype=np.float64)
    p2 = np.pad(p2, ((0, 3 - p2.shape[0]), (0, 4 - p2.shape[1]))) if p2.shape != (4, 4) else p2[:3]
    shape = (int(cam["height"]), int(cam["width"])) if "height" in cam else None
    return Calib(np.asarray(cam["lidar2cam"], dtype=np.float64).reshape(4, 4), p2, shape)


def calibs_from_object(obj: object) -> Mapping[str, Any]:
    """{frame id: :class:`kitti_eval.io.calib.Calib`} from ground-truth infos (OpenPCDet list, PointPillars
    dict, mmdetection3d 1.x), each read when first used; empty when the object has no calibration. Never
    raises (a frame whose calibration cannot be read is missing)."""
    from .calib import calib_from_info

    entries: dict[str, Any] = {}
    try:
        if isinstance(obj, Mapping) and "data_list" in obj:
            for entry in obj["data_list"]:
                if isinstance(entry, Mapping) and "images" in entry:
                    entries[normalize_frame_id(entry["sample_idx"])] = entry
            return _LazyCalibs(entries, _mmdet3d_calib)
        items = (
            obj.items()
            if isinstance(obj, Mapping)
            else ((None, e) for e in obj)
            if isinstance(obj, (list, tuple))
            else ()
        )
        for i, (key, info) in enumerate(items):
            if isinstance(info, Mapping) and "calib" in info:
                entries[normalize_frame_id(key if key is not None else _entry_frame_id(info, i, ""))] = info
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, InputError):
        return {}
    return _LazyCalibs(entries, calib_from_info)


#: camera/LiDAR agreement is checked on every so many frames that carry both
_CHECK_EVERY = 10


def _numeric_boxes(lidar: Any, location: Any, rotation_y: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(location, rotation_y, boxes_lidar) as float64 when they are numbers of the shapes (N, 3), (N,) and
    (N, 7) with N > 0; None otherwise (from_frames then names what is wrong)."""
    arrays = [np.asarray(v) for v in (location, rotation_y, lidar)]
    if any(a.dtype.kind not in "iuf" for a in arrays):
        return None
    loc, ry, box = arrays
    n = len(box) if box.ndim else 0
    if n == 0 or loc.shape != (n, 3) or ry.shape != (n,) or box.shape != (n, 7):
        return None
    return loc.astype(np.float64), ry.astype(np.float64), box.astype(np.float64)


def _camera_fields(frames: Frames, calibs: Mapping[str, Any] | None, source: str, warnings: list[str] | None) -> Frames:
    """Detections: LiDAR-only frames converted to camera fields; frames with both checked for agreement."""
    from .calib import disagreeing_boxes, lidar_to_camera

    # frames with both camera fields and LiDAR boxes: every CHECK_EVERY-th is collected, then checked in
    # one vectorised call (a broken conversion shows in any sample; checking all costs ~0.1 s on KITTI val)
    both: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    seen_both = 0
    for fid, fields in frames:
        if not isinstance(fields, Mapping) or "boxes_lidar" not in fields:
            yield fid, fields
            continue
        has_camera = all(k in fields for k in _CAMERA_FIELDS)
        if has_camera:
            seen_both += 1
        calib = None
        if calibs and (not has_camera or (seen_both - 1) % _CHECK_EVERY == 0):  # only where it is used
            try:
                calib = calibs.get(normalize_frame_id(fid))
            except (TypeError, ValueError):
                calib = None
        lidar = fields["boxes_lidar"]
        if has_camera:
            if calib is not None:
                sample = _numeric_boxes(lidar, fields["location"], fields["rotation_y"])
                if sample is not None:
                    both.append((*sample, calib.velo_to_rect))
            yield fid, fields
            continue
        if any(k in fields for k in _CAMERA_FIELDS):
            yield fid, fields  # partial camera fields: from_frames names what is missing
            continue
        arr = np.asarray(lidar)
        if arr.dtype.kind not in "iuf" and arr.size:
            raise InputError(
                f"expected numbers, got dtype {arr.dtype}",
                source=source,
                frame=shown_frame_id(fid),
                field="boxes_lidar",
            )
        if arr.size == 0:
            arr = np.zeros((0, 7))
        if arr.ndim != 2 or arr.shape[1] != 7:
            raise InputError(
                f"expected shape (N, 7), got {arr.shape}", source=source, frame=shown_frame_id(fid), field="boxes_lidar"
            )
        if calib is None:
            raise InputError(
                "LiDAR-only boxes (boxes_lidar without location/dimensions/rotation_y) need the "
                "frame's calibration: pass OpenPCDet (or mmdetection3d) infos as the ground truth",
                source=source,
                frame=shown_frame_id(fid),
                field="boxes_lidar",
            )
        out = dict(fields)
        conv = lidar_to_camera(arr, calib)
        out.update(conv)
        if "alpha" in fields and np.size(fields["alpha"]) == len(arr):
            out["alpha"] = fields["alpha"]
        yield fid, out
    if warnings is None or not both:
        return
    counts = [len(b[2]) for b in both]
    flags = disagreeing_boxes(
        np.concatenate([b[0] for b in both]),
        np.concatenate([b[1] for b in both]),
        np.concatenate([b[2] for b in both]),
        np.repeat(np.stack([b[3] for b in both]), counts, axis=0),
    )
    checked, bad = len(flags), int(np.count_nonzero(flags))
    bad_frames = int(np.count_nonzero(np.add.reduceat(flags, np.cumsum([0, *counts[:-1]])))) if checked else 0
    if bad > 0.01 * checked:
        warnings.append(
            f"{source}: camera fields and boxes_lidar disagree (location > 0.1 m or yaw > 0.1 rad) "
            f"for {bad} of {checked} boxes checked (every {_CHECK_EVERY}th frame) in {bad_frames} "
            "frames; the camera fields are evaluated"
        )


# ---------------------------------------------------------------------------------------- archives

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


def _load_txt_archive(
    p: Path, kind: Kind, source: str, max_bytes: int, max_frames: int, known_frames: Collection[str] | None
) -> Annotations:
    import dataclasses
    import tempfile

    limits = ArchiveLimits(max_unpacked_bytes=max_bytes, bytes_setting=MAX_INPUT_ENV)
    with tempfile.TemporaryDirectory(prefix="kitti-eval-") as tmp:
        folder = extract_txt_archive(p, tmp, limits=limits)
        try:
            annos = load_kitti_txt_dir(folder, kind, max_frames=max_frames, known_frames=known_frames)
        except InputError as e:
            raise InputError(e.message, source=source, frame=e.frame, field=e.field) from None
    return dataclasses.replace(annos, source=source)


# ------------------------------------------------------------------------------ pairs and split files


def read_split(path: PathLike) -> list[str]:
    """Frame ids of a KITTI ``ImageSets/<split>.txt`` (one a line; blank lines skipped), normalised."""

    text = _read_text(Path(path))
    ids: list[str] = []
    seen: set[str] = set()
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            fid = normalize_frame_id(line.strip())
        except (TypeError, ValueError) as e:
            raise InputError(f"line {lineno}: {e}", source=str(path)) from None
        if fid not in seen:
            seen.add(fid)
            ids.append(fid)
    if not ids:
        raise InputError("the split file lists no frames", source=str(path))
    return ids


def apply_split(gt: Annotations, dt: Annotations, frame_ids: Sequence[str]) -> tuple[Annotations, Annotations, int]:
    """Ground truth subset to ``frame_ids`` (each must be there), predictions of other frames dropped.

    Returns ``(gt, dt, dropped)`` with the number of prediction frames dropped.
    """
    gt = gt.subset(list(frame_ids))
    wanted = set(frame_ids)
    keep = [fid for fid in dt.frame_ids if fid in wanted]
    dropped = dt.num_frames - len(keep)
    if dropped:
        dt = dt.subset(keep)
    return gt, dt, dropped


def _is_pickle_file(p: Path, fmt: str | None) -> bool:
    """``p`` is read as a pickle: a file that is neither a txt file nor an archive (unless ``fmt`` says)."""
    if not p.is_file() or fmt == "kitti_txt" or p.suffix.lower() == ".txt":
        return False
    return fmt is not None or input_kind(p) == "pickle"


def load_ground_truth_and_calibs(
    gt_path: PathLike,
    *,
    fmt: str | None = None,
    max_bytes: int | None = None,
    warnings: list[str] | None = None,
    max_frames: int | None = None,
) -> tuple[Annotations, Mapping[str, Any]]:
    """Ground truth and, from an infos pickle, its calibration per frame (read once; empty for txt)."""
    _check_fmt(fmt)
    max_bytes, max_frames = _limits(max_bytes, max_frames)
    gp = Path(gt_path)
    if _is_pickle_file(gp, fmt):
        obj = load_pickle(gp, source=str(gt_path), max_bytes=max_bytes, max_entries=max_frames)
        gt = annotations_from_object(
            obj, "ground_truth", source=str(gt_path), fmt=fmt, warnings=warnings, max_frames=max_frames
        )
        return gt, calibs_from_object(obj)
    return load_ground_truth(gt_path, fmt=fmt, max_bytes=max_bytes, max_frames=max_frames), {}


def load_pair(
    gt_path: PathLike,
    pred_path: PathLike,
    *,
    gt_format: str | None = None,
    pred_format: str | None = None,
    split: PathLike | None = None,
    warnings: list[str] | None = None,
    max_bytes: int | None = None,
    keep_lidar: bool = False,
    max_frames: int | None = None,
) -> tuple[Annotations, Annotations]:
    """Ground truth and predictions, the pickle of ground truth read once (its calibration converts
    LiDAR-only predictions); with ``split``, only the listed frames (dropped prediction frames are
    reported in ``warnings``); otherwise a prediction frame that is not in the ground truth is refused as
    soon as it is read. ``keep_lidar``, ``max_bytes``, ``max_frames``: see :func:`load_detections`."""
    _check_fmt(pred_format)
    _check_fmt(gt_format)
    max_bytes, max_frames = _limits(max_bytes, max_frames)
    if _is_pickle_file(Path(gt_path), gt_format) and _is_pickle_file(Path(pred_path), pred_format):
        # the predictions are read and checked in a helper thread while the ground truth is converted
        objects = load_pickles(
            [gt_path, pred_path], sources=[str(gt_path), str(pred_path)], max_bytes=max_bytes, max_entries=max_frames
        )
        gt_obj = next(objects)
        gt = annotations_from_object(
            gt_obj, "ground_truth", source=str(gt_path), fmt=gt_format, warnings=warnings, max_frames=max_frames
        )
        calibs = calibs_from_object(gt_obj)
        del gt_obj
        dt = annotations_from_object(
            next(objects),
            "detections",
            source=str(pred_path),
            fmt=pred_format,
            calibs=calibs,
            warnings=warnings,
            keep_lidar=keep_lidar,
            max_frames=max_frames,
            known_frames=None if split is not None else gt.frame_index(),
        )
    else:
        gt, calibs = load_ground_truth_and_calibs(
            gt_path, fmt=gt_format, max_bytes=max_bytes, warnings=warnings, max_frames=max_frames
        )
        dt = load_detections(
            pred_path,
            fmt=pred_format,
            calibs=calibs,
            warnings=warnings,
            max_bytes=max_bytes,
            keep_lidar=keep_lidar,
            max_frames=max_frames,
            known_frames=None if split is not None else gt.frame_index(),
        )
    if split is not None:
        gt, dt, dropped = apply_split(gt, dt, read_split(split))
        if dropped and warnings is not None:
            warnings.append(f"{pred_path}: predictions for {dropped} frames outside the split {split} were dropped")
    return gt, dt
