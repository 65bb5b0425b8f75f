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
* Pickles (read only through :func:`kitti_eval.safe_pickle.load_pickle`, gzip or not), by detected format:

  ==================  ====================================================================================
  ``openpcdet_infos``  list of OpenPCDet info dicts (``image``/``point_cloud``/``annos``): ground truth
  ``annos_list``       list of annos dicts that carry ``frame_id`` (OpenPCDet ``result.pkl``; for ground
                       truth, plain annos dicts with ``frame_id``)
  ``annos_by_frame``   dict ``{frame id: annos dict}`` (PointPillars style; for ground truth the values may
                       also be info dicts holding ``annos``)
  ==================  ====================================================================================

  New formats are added to :data:`PICKLE_FORMATS` with a detector in :func:`detect_format`.
"""

from __future__ import annotations

import os
from array import array
from collections.abc import Callable, Iterator, Mapping
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .frames import Annotations, Kind
from .safe_pickle import load_pickle

__all__ = [
    "load_ground_truth", "load_detections", "load_annotations", "load_kitti_txt_dir", "parse_kitti_txt",
    "annotations_from_object", "detect_format", "describe_format", "PICKLE_FORMATS", "KITTI_TXT_FIELDS",
]

#: the fields of a KITTI label line, in file order (``score`` only in detections)
KITTI_TXT_FIELDS = ("type", "truncated", "occluded", "alpha", "x1", "y1", "x2", "y2", "h", "w", "l",
                    "x", "y", "z", "ry", "score")
_N_FIELDS = {"ground_truth": 15, "detections": 16}
_KIND_WORD = {"ground_truth": "ground-truth", "detections": "result"}

PathLike = str | os.PathLike[str]
Frames = Iterator[tuple[object, Mapping[str, Any]]]


# ----------------------------------------------------------------------------------------- public API

def load_ground_truth(path: PathLike, *, max_bytes: int | None = None) -> Annotations:
    """Ground truth from a KITTI ``label_2``-style txt folder or an infos/annos pickle (see module doc)."""
    return load_annotations(path, "ground_truth", max_bytes=max_bytes)


def load_detections(path: PathLike, *, max_bytes: int | None = None) -> Annotations:
    """Detections from a KITTI txt folder (16 fields) or a ``result.pkl``-style pickle (see module doc)."""
    return load_annotations(path, "detections", max_bytes=max_bytes)


def load_annotations(path: PathLike, kind: Kind, *, max_bytes: int | None = None) -> Annotations:
    """A folder is read as KITTI txt files, a file as a (possibly gzipped) pickle."""
    _check_kind(kind)
    p = Path(path)
    source = str(path)
    if p.is_dir():
        return load_kitti_txt_dir(p, kind)
    if not p.exists():
        what = "ground truth" if kind == "ground_truth" else "detections"
        raise InputError(f"no such file or directory (expected {what} as a KITTI txt folder or a pickle)",
                         source=source)
    if p.suffix.lower() == ".txt":
        raise InputError("this is a single txt file; pass the folder that holds one KITTI txt file per "
                         "frame", source=source)
    obj = load_pickle(p, source=source, max_bytes=max_bytes)
    return annotations_from_object(obj, kind, source=source)


def annotations_from_object(obj: object, kind: Kind, *, source: str) -> Annotations:
    """Annotations from an already unpickled object (e.g. an upload passed through ``load_pickle``)."""
    _check_kind(kind)
    fmt = detect_format(obj, kind, source=source)
    return Annotations.from_frames(kind, source, PICKLE_FORMATS[fmt](obj, kind, source))


# ---------------------------------------------------------------------------------------- KITTI txt

def _txt_files(directory: Path) -> list[Path]:
    try:
        entries = list(os.scandir(directory))
    except OSError as e:
        raise InputError(f"cannot list the folder: {e.strerror or e}", source=str(directory)) from None
    return [Path(e.path) for e in entries
            if e.name.lower().endswith(".txt") and not e.name.startswith(".") and e.is_file()]


def load_kitti_txt_dir(directory: PathLike, kind: Kind) -> Annotations:
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
        hint = (f"; it has subfolders {', '.join(subdirs[:5])}: pass the one holding the txt files"
                if subdirs else "")
        raise InputError(f"no .txt files in the folder{hint}", source=str(root))
    files.sort(key=lambda f: f.name)

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
        "truncated": table[:, 0], "occluded": table[:, 1], "alpha": table[:, 2], "bbox": table[:, 3:7],
        "dimensions": table[:, [9, 7, 8]],  # h w l -> l h w
        "location": table[:, 10:13], "rotation_y": table[:, 13],
    }
    if kind == "detections":
        columns["score"] = table[:, 14]

    def frames() -> Frames:
        for fid, lo, n in spans:
            fields: dict[str, Any] = {k: v[lo:lo + n] for k, v in columns.items()}
            fields["name"] = name_arr[lo:lo + n]
            yield fid, fields

    return Annotations.from_frames(kind, str(root), frames())


def _read_text(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as e:
        raise InputError(f"cannot read: {e.strerror or e}", source=str(path), frame=path.stem) from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"not a text file (byte {e.start} is not UTF-8)", source=str(path),
                         frame=path.stem) from None


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
        del tokens[n_keep - 1::width - 1]
    return lines, names, tokens


def _raise_bad_line(lines: list[str], kind: Kind, accepted: set[int], frame: str, source: str) -> None:
    first_width = None
    for lineno, line in enumerate(lines, 1):
        n = len(line.split())
        if n == 0:
            continue
        if n not in accepted:
            if kind == "ground_truth":
                expected = ("15 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry; a 16th, "
                            "score, is also accepted)")
            else:
                expected = "16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score)"
            raise InputError(f"line {lineno}: expected {expected}, got {n}", source=source, frame=frame)
        if first_width is None:
            first_width = n
        elif n != first_width:
            raise InputError(f"line {lineno}: {n} fields, but earlier lines have {first_width}; use one "
                             "layout per file", source=source, frame=frame)
    raise InputError("inconsistent field counts", source=source, frame=frame)  # pragma: no cover


def _raise_bad_number(lines: list[str], n_fields: int, frame: str, source: str) -> None:
    for lineno, line in enumerate(lines, 1):
        parts = line.split()
        for k, tok in enumerate(parts[1:n_fields], 1):
            try:
                float(tok)
            except ValueError:
                field = KITTI_TXT_FIELDS[k]
                raise InputError(f"line {lineno}: {field} is not a number: {tok!r}", source=source,
                                 frame=frame, field=field) from None
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
        keys = list(obj.keys())
        shown = ", ".join(repr(k) for k in keys[:6]) + (", ..." if len(keys) > 6 else "")
        return f"a dict with {len(keys)} keys [{shown}]"
    return _type_name(obj)


_INFO_KEYS = frozenset({"annos", "image", "point_cloud", "calib"})
_ANNOS_KEYS = frozenset({"name", "bbox", "dimensions", "location", "rotation_y"})


def detect_format(obj: object, kind: Kind, *, source: str) -> str:
    """The name of the pickle layout of ``obj`` (a key of :data:`PICKLE_FORMATS`), or InputError."""
    expected = ("a list of per-frame dicts (OpenPCDet kitti_infos_*.pkl, or annos dicts with frame_id)"
                if kind == "ground_truth" else "a list of per-frame dicts (OpenPCDet result.pkl)")
    expected += ", or a dict {frame id: annos dict}"
    if isinstance(obj, (list, tuple)):
        for i, entry in enumerate(obj):
            if not isinstance(entry, Mapping):
                raise InputError(f"{_KIND_WORD[kind]} entry #{i} is {_type_name(entry)}, expected a dict; "
                                 f"the file should hold {expected}", source=source, frame=f"#{i}")
        if not obj:
            raise InputError(f"the pickle holds an empty {type(obj).__name__}: no frames", source=source)
        first = obj[0]
        if _INFO_KEYS & first.keys() and "name" not in first:
            if kind == "detections":
                raise InputError("this is an OpenPCDet infos file (ground-truth labels), not detections; "
                                 "pass it as the ground truth and the result.pkl as the predictions",
                                 source=source)
            return "openpcdet_infos"
        if "name" in first or "frame_id" in first:
            return "annos_list"
        raise InputError(f"entry #0 has none of the expected keys: found {describe_format(obj)}; expected "
                         f"{expected}", source=source, frame="#0")
    if isinstance(obj, Mapping):
        if "data_list" in obj and "metainfo" in obj:
            raise InputError("this is an mmdetection3d 1.x info file (metainfo/data_list), which is not "
                             "supported yet; use OpenPCDet infos or KITTI txt files", source=source)
        if _ANNOS_KEYS & obj.keys():
            raise InputError(f"this is a single frame's annos dict ({describe_format(obj)}); expected one "
                             f"per frame: {expected}", source=source)
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
        raise InputError(f"{what} is {_type_name(value)}, expected a string or an integer", source=source,
                         frame=frame, field="frame_id")
    return value


def _entry_frame_id(entry: Mapping[str, Any], i: int, source: str) -> object:
    for parent, key in (("image", "image_idx"), ("point_cloud", "lidar_idx")):
        sub = entry.get(parent)
        if sub is None:
            continue
        if not isinstance(sub, Mapping):
            raise InputError(f"infos entry #{i}: '{parent}' is {_type_name(sub)}, expected a dict",
                             source=source, frame=f"#{i}", field=parent)
        if sub.get(key) is not None:
            return _frame_id(sub[key], f"infos entry #{i}: {parent}.{key}", source, f"#{i}")
    if entry.get("frame_id") is not None:
        return _frame_id(entry["frame_id"], f"infos entry #{i}: frame_id", source, f"#{i}")
    raise InputError(f"infos entry #{i} has no frame id (image.image_idx, point_cloud.lidar_idx or frame_id)",
                     source=source, frame=f"#{i}")


def _frames_openpcdet_infos(obj: Any, kind: Kind, source: str) -> Frames:
    for i, info in enumerate(obj):
        fid = _entry_frame_id(info, i, source)
        if "annos" not in info:
            raise InputError(f"the infos have no labels ('annos' missing in entry #{i}): a test split? "
                             "Ground truth needs the train/val infos or the label_2 folder", source=source,
                             frame=str(fid))
        annos = info["annos"]
        if not isinstance(annos, Mapping):
            raise InputError(f"infos entry #{i}: 'annos' is {_type_name(annos)}, expected a dict",
                             source=source, frame=str(fid), field="annos")
        yield fid, annos


def _frames_annos_list(obj: Any, kind: Kind, source: str) -> Frames:
    for i, entry in enumerate(obj):
        fid = entry.get("frame_id")
        if fid is None:
            raise InputError(f"{_KIND_WORD[kind]} entry #{i} has no frame_id (frames are matched by id, "
                             "never by position)", source=source, frame=f"#{i}", field="frame_id")
        yield _frame_id(fid, f"{_KIND_WORD[kind]} entry #{i}: frame_id", source, f"#{i}"), entry


def _frames_annos_by_frame(obj: Any, kind: Kind, source: str) -> Frames:
    for pos, (key, value) in enumerate(obj.items()):
        key = _frame_id(key, f"key #{pos} of the dict", source, f"#{pos}")
        if kind == "ground_truth" and isinstance(value, Mapping) and "annos" in value and "name" not in value:
            value = value["annos"]  # an info dict keyed by frame (PointPillars kitti_infos_*.pkl)
        yield key, value


#: pickle layout name -> generator of (frame id, fields) for :meth:`Annotations.from_frames`
PICKLE_FORMATS: dict[str, Callable[[Any, Kind, str], Frames]] = {
    "openpcdet_infos": _frames_openpcdet_infos,
    "annos_list": _frames_annos_list,
    "annos_by_frame": _frames_annos_by_frame,
}
