"""Reading one input, or a pair, whatever its format: the options of one read (:class:`LoadOptions`) and what
it returns (:class:`Loaded`: the annotations and the warnings about the input).

Every route ends in :meth:`Annotations.from_frames`, which validates shapes, dtypes, finiteness and
duplicate frames; the formats (:mod:`kitti_eval.io.formats`) only find the frames, their ids and their field
dicts, and report structural problems (wrong top-level type, entries without a frame id, txt lines with the
wrong number of fields) with the entry, frame and line where they happen. A folder is read as KITTI txt
files, a zip or tar as an archived txt folder, any other file as a pickle (only through the restricted
unpickler's scan, :func:`kitti_eval.io.safe_pickle.check_pickle`, gzip or not). OpenPCDet's result.pkl and
infos in their usual layout skip the objects: :mod:`kitti_eval.io.pickle_columns` takes them from the checked
bytes into the same columns, with the same checks (:meth:`Annotations.from_columns`), and leaves anything
else, refusals included, to the route above. Detections that carry only ``boxes_lidar`` are
converted to the camera frame with each frame's calibration from the ground-truth infos
(:mod:`kitti_eval.io.camera`; see :func:`read_pair`).
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO, Any

from ..core.frames import Annotations, Kind, normalize_frame_id
from ..errors import InputError
from . import limits
from .camera import calibs_from_object, camera_fields
from .formats import FORMATS, REGISTRY, check_layout, detect_format
from .formats._common import check_kind
from .formats.kitti_txt import input_kind, load_kitti_txt_dir, load_txt_archive, read_text
from .pickle_columns import read_detections, read_ground_truth
from .safe_pickle import CheckedPickle, check_pickle, check_pickles

__all__ = [
    "LoadOptions",
    "Loaded",
    "LoadedPair",
    "read_annotations",
    "read_object",
    "read_pickle",
    "read_ground_truth_and_calibs",
    "read_pair",
    "read_split",
    "apply_split",
]

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class LoadOptions:
    """How one input is read.

    ``fmt``: a name of :data:`kitti_eval.io.formats.FORMATS`, instead of detecting the layout.
    ``max_bytes``, ``max_frames``: see :func:`kitti_eval.io.limits.input_limits` (None: its values); ``box_limits``:
    :func:`kitti_eval.io.limits.box_limits` (None: its values).
    ``calibs`` ({frame id: :class:`kitti_eval.io.calib.Calib`}) converts LiDAR-only detections and checks
    detections that carry both. ``keep_lidar`` keeps the ``boxes_lidar`` of detections as written, for display
    (:attr:`Annotations.boxes_lidar`). ``known_frames`` (the ground truth's frame ids): a frame of detections
    outside them is refused as soon as it is read. ``calibs`` and ``keep_lidar`` apply to detections only.
    """

    fmt: str | None = None
    max_bytes: int | None = None
    max_frames: int | None = None
    calibs: Mapping[str, Any] | None = None
    keep_lidar: bool = False
    known_frames: Collection[str] | None = None
    #: the boxes one frame and the whole input may hold (None: :func:`kitti_eval.io.limits.box_limits`)
    box_limits: limits.BoxLimits | None = None

    def __post_init__(self) -> None:
        if self.fmt is not None and self.fmt not in FORMATS:
            raise InputError(f"unknown format {self.fmt!r}; known: {', '.join(FORMATS)}")

    def with_limits(self) -> LoadOptions:
        """These options with the limits left at None filled in from the environment."""
        max_bytes, max_frames = limits.resolve(self.max_bytes, self.max_frames)
        return replace(self, max_bytes=max_bytes, max_frames=max_frames)


DEFAULT = LoadOptions()


@dataclass(frozen=True)
class Loaded:
    """What one read gives: the annotations, and warnings about the input (for the caller to show)."""

    annotations: Annotations
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class LoadedPair:
    """Ground truth and predictions read together, and the warnings of both reads (in that order)."""

    gt: Annotations
    dt: Annotations
    warnings: tuple[str, ...] = ()


def _missing(kind: Kind, source: str) -> InputError:
    what = "ground truth" if kind == "ground_truth" else "detections"
    return InputError(
        f"no such file or directory (expected {what} as a KITTI txt folder, a zip/tar of one, or a pickle)",
        source=source,
    )


def read_annotations(path: PathLike, kind: Kind, options: LoadOptions = DEFAULT) -> Loaded:
    """A folder is read as KITTI txt files, a zip/tar as an archived txt folder, a file as a pickle."""
    check_kind(kind)
    options = options.with_limits()
    assert options.max_bytes is not None and options.max_frames is not None
    fmt = options.fmt
    p = Path(path)
    source = str(path)
    if p.is_dir():
        if fmt not in (None, "kitti_txt"):
            raise InputError(f"a folder is read as KITTI txt files, not as {fmt!r}", source=source)
        return Loaded(
            load_kitti_txt_dir(
                p, kind, max_frames=options.max_frames, known_frames=options.known_frames, bounds=options.box_limits
            )
        )
    if not p.exists():
        raise _missing(kind, source)
    if p.suffix.lower() == ".txt":
        raise InputError(
            "this is a single txt file; pass the folder that holds one KITTI txt file per frame", source=source
        )
    if fmt == "kitti_txt" or (fmt is None and input_kind(p, source) != "pickle"):
        annos = load_txt_archive(
            p, kind, source, options.max_bytes, options.max_frames, options.known_frames, options.box_limits
        )
        return Loaded(annos)
    return read_pickle(p, kind, source, options)


def read_pickle(
    path_or_fileobj: PathLike | IO[bytes], kind: Kind, source: str, options: LoadOptions = DEFAULT
) -> Loaded:
    """Annotations from a pickle (a path or a binary file object, gzip or not), read only through the restricted
    unpickler's scan: a result.pkl of the usual layout straight from its bytes into the columns
    (:mod:`kitti_eval.io.pickle_columns`), anything else built and read as :func:`read_object` reads it. The
    limits of ``options`` (None: the environment's) apply; ``options.fmt`` forces a pickle layout."""
    check_kind(kind)
    options = options.with_limits()
    checked = check_pickle(path_or_fileobj, source=source, max_bytes=options.max_bytes, max_entries=options.max_frames)
    return _read_checked(checked, kind, options)


def _read_checked(checked: CheckedPickle, kind: Kind, options: LoadOptions) -> Loaded:
    """Annotations of a checked pickle: from its bytes where :mod:`kitti_eval.io.pickle_columns` takes it, else
    from its objects (whose reading makes every refusal, as ever)."""
    if kind == "ground_truth":
        return _read_checked_ground_truth(checked, options)[0]
    if options.fmt in (None, "annos_list"):
        warnings: list[str] = []
        annos = read_detections(
            checked,
            max_frames=limits.resolve(None, options.max_frames)[1],
            keep_lidar=options.keep_lidar,
            known_frames=options.known_frames,
            calibs=options.calibs,
            warnings=warnings,
        )
        if annos is not None:
            return Loaded(_bounded(annos, options), tuple(warnings))
    return read_object(checked.load(), kind, checked.source, options)


def _read_checked_ground_truth(checked: CheckedPickle, options: LoadOptions) -> tuple[Loaded, Mapping[str, Any]]:
    """Ground truth of a checked pickle and its calibration per frame: from its bytes where
    :mod:`kitti_eval.io.pickle_columns` takes it (OpenPCDet infos), else from its objects."""
    if options.fmt in (None, "openpcdet_infos"):
        max_frames = limits.resolve(None, options.max_frames)[1]
        fast = read_ground_truth(checked, max_frames=max_frames, known_frames=options.known_frames)
        if fast is not None:
            return Loaded(_bounded(fast[0], options)), fast[1]
    obj = checked.load()
    return read_object(obj, "ground_truth", checked.source, options), calibs_from_object(obj)


def _bounded(annos: Annotations, options: LoadOptions) -> Annotations:
    """Annotations a pickle's columns were read into straight from its bytes (compact, and capped by its bytes),
    held to the box limits every other read checks as it goes (``options.box_limits``, else
    :func:`kitti_eval.io.limits.box_limits`)."""
    (options.box_limits or limits.box_limits()).check_counts(annos.counts, annos.frame_ids, source=annos.source)
    return annos


def read_object(obj: object, kind: Kind, source: str, options: LoadOptions = DEFAULT) -> Loaded:
    """Annotations from an already unpickled object (e.g. an upload passed through ``load_pickle``);
    ``options.fmt`` forces a pickle layout."""
    check_kind(kind)
    fmt = options.fmt
    if fmt == "kitti_txt":
        raise InputError("this is a pickle, not KITTI txt files", source=source)
    if fmt is None:
        fmt = detect_format(obj, kind, source=source)
    else:
        check_layout(obj, fmt, source)
    reader = REGISTRY[fmt].reader
    assert reader is not None
    warnings: list[str] = []
    frames = reader(obj, kind, source, warnings)
    if kind == "detections":
        frames = camera_fields(frames, options.calibs, source, warnings)
    annos = Annotations.from_frames(
        kind,
        source,
        frames,
        keep_lidar=options.keep_lidar and kind == "detections",
        max_frames=limits.resolve(None, options.max_frames)[1],
        known_frames=options.known_frames,
        box_limits=options.box_limits or limits.box_limits(),
    )
    return Loaded(annos, tuple(warnings))


def read_split(path: PathLike) -> list[str]:
    """Frame ids of a KITTI ``ImageSets/<split>.txt`` (one a line; blank lines skipped), normalised."""

    text = read_text(Path(path))
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


def read_ground_truth_and_calibs(path: PathLike, options: LoadOptions = DEFAULT) -> tuple[Loaded, Mapping[str, Any]]:
    """Ground truth and, from an infos pickle, its calibration per frame (read once; empty for txt)."""
    options = options.with_limits()
    p = Path(path)
    if _is_pickle_file(p, options.fmt):
        checked = check_pickle(p, source=str(path), max_bytes=options.max_bytes, max_entries=options.max_frames)
        return _read_checked_ground_truth(checked, LoadOptions(fmt=options.fmt, max_frames=options.max_frames))
    gt_options = LoadOptions(fmt=options.fmt, max_bytes=options.max_bytes, max_frames=options.max_frames)
    return read_annotations(path, "ground_truth", gt_options), {}


def read_pair(
    gt_path: PathLike,
    pred_path: PathLike,
    *,
    gt_format: str | None = None,
    options: LoadOptions = DEFAULT,
    split: PathLike | None = None,
) -> LoadedPair:
    """Ground truth and predictions, the pickle of ground truth read once (its calibration converts LiDAR-only
    predictions); with ``split``, only the listed frames (dropped prediction frames are reported in the
    warnings); otherwise a prediction frame that is not in the ground truth is refused as soon as it is read.

    ``options`` are the predictions' (their ``fmt``, ``keep_lidar``); their limits apply to both files; the
    ground truth's layout is ``gt_format`` (None: detected). Their ``calibs`` and ``known_frames`` come from
    the ground truth.
    """
    options = options.with_limits()
    gt_options = LoadOptions(fmt=gt_format, max_bytes=options.max_bytes, max_frames=options.max_frames)
    if _is_pickle_file(Path(gt_path), gt_format) and _is_pickle_file(Path(pred_path), options.fmt):
        # the predictions are read and checked in a helper thread while the ground truth is converted
        checked = check_pickles(
            [gt_path, pred_path],
            sources=[str(gt_path), str(pred_path)],
            max_bytes=options.max_bytes,
            max_entries=options.max_frames,
        )
        gt, calibs = _read_checked_ground_truth(next(checked), gt_options)
        pred_options = replace(
            options, calibs=calibs, known_frames=None if split is not None else gt.annotations.frame_index()
        )
        dt = _read_checked(next(checked), "detections", pred_options)
    else:
        gt, calibs = read_ground_truth_and_calibs(gt_path, gt_options)
        pred_options = replace(
            options, calibs=calibs, known_frames=None if split is not None else gt.annotations.frame_index()
        )
        dt = read_annotations(pred_path, "detections", pred_options)
    warnings = [*gt.warnings, *dt.warnings]
    gt_annos, dt_annos = gt.annotations, dt.annotations
    if split is not None:
        gt_annos, dt_annos, dropped = apply_split(gt_annos, dt_annos, read_split(split))
        if dropped:
            warnings.append(f"{pred_path}: predictions for {dropped} frames outside the split {split} were dropped")
    return LoadedPair(gt_annos, dt_annos, tuple(warnings))
