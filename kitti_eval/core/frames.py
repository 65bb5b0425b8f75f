"""Annotations of many frames in one columnar, validated container.

Every loader ends here: it hands :meth:`Annotations.from_frames` a list of ``(frame_id, fields)`` pairs,
and gets back flat float64 arrays with frame offsets (CSR layout), or an :class:`InputError` that names
the frame and the field. Nothing downstream re-checks the data. The frames readers usually give (plain dicts
of numpy arrays) are taken as whole columns, one concatenation per field and every check over all frames at
once; anything else is checked frame by frame, and a refusal is always the one the first bad frame gets.

Coordinate frame: KITTI rectified camera (x right, y down, z forward). ``location`` is the bottom centre
of the box (the box spans ``y - h`` .. ``y``); ``dimensions`` are **(l, h, w)** in metres, the order all
pickle formats use (the txt files write h, w, l; the txt loader reorders); ``rotation_y`` is the yaw about
the camera y axis; ``bbox`` is the 2D image box (x1, y1, x2, y2) in pixels.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from ..errors import InputError, WorkLimitError
from .budget import setting_name
from .protocol import DONTCARE

__all__ = [
    "Annotations",
    "BoxLimits",
    "normalize_frame_id",
    "shown_frame_id",
    "dimension_order_warnings",
    "UnsizedBoxes",
    "unsized_boxes",
    "size_warnings",
]

Kind = Literal["ground_truth", "detections"]

#: field -> trailing shape of one box
_NUMERIC_FIELDS: Mapping[str, tuple[int, ...]] = {
    "truncated": (),
    "occluded": (),
    "alpha": (),
    "bbox": (4,),
    "dimensions": (3,),
    "location": (3,),
    "rotation_y": (),
    "score": (),
}
_REQUIRED = {
    "ground_truth": ("name", "dimensions", "location", "rotation_y"),
    "detections": ("name", "dimensions", "location", "rotation_y", "score"),
}
#: the numeric fields (field -> trailing shape of one box) and the fields each kind needs, for readers that
#: build the columns themselves (:meth:`Annotations.from_columns`)
NUMERIC_FIELDS = _NUMERIC_FIELDS
REQUIRED_FIELDS: Mapping[str, tuple[str, ...]] = _REQUIRED
#: fields that come from the image; a LiDAR-only set may lack them (filled with these values, and listed in
#: ``Annotations.missing_fields`` so that an image-based evaluation refuses them)
IMAGE_FIELDS: Mapping[Kind, Mapping[str, float]] = {
    "ground_truth": {"bbox": 0.0, "alpha": -10.0, "truncated": 0.0, "occluded": 0.0},
    "detections": {"bbox": 0.0, "alpha": -10.0},
}


@dataclass(frozen=True)
class UnsizedBoxes:
    """The boxes of a set whose size is not positive (:func:`unsized_boxes`): how many, and the first one."""

    count: int = 0
    #: (frame id, box index in the frame, class, (l, h, w)) of the first such box
    first: tuple[str, int, str, tuple[float, float, float]] | None = None

    def merged(self, later: UnsizedBoxes) -> UnsizedBoxes:
        """This part's count and the count of a part that comes after it, as one set's."""
        return UnsizedBoxes(self.count + later.count, self.first or later.first)


def unsized_boxes(annos: Annotations) -> UnsizedBoxes:
    """The size rule: every box is read as written, as the KITTI devkit, OpenPCDet and mmdetection3d read it.

    None of the references refuses a box whose l, h or w is zero or negative, and real data has them: KITTI
    result files write -1 for "not given" (a BEV-only result has h = -1, a 2D-only one l = h = w = -1 at
    -1000), mmdetection3d's own test data has ground-truth Cars of size -1 -1 -1, and its monocular results
    write 2D-only detections with sizes of 0. So they are evaluated, from the box as written
    (:mod:`kitti_eval.core.geometry`): in BEV a box is the rectangle of sides ``|l|`` and ``|w|`` (-1 -1 -1 is
    a 1 x 1 m square), in 3D it spans ``[y - h, y]`` (empty when ``h <= 0``), and a box with ``l = 0`` or
    ``w = 0`` overlaps nothing in BEV and 3D (the devkit crashes on such ground truth). Whether a class is
    scored in BEV or 3D at all depends on its detections' sizes
    (:func:`kitti_eval.core.evaluation.scored_metrics`).

    A size that is not positive is still worth saying (a converter that wrote zeros by mistake loses every
    BEV and 3D match silently otherwise): this counts such boxes, DontCare regions aside (they always carry
    -1), for one warning per input (:func:`size_warnings`).
    """
    rows = np.flatnonzero((annos.dimensions <= 0).any(axis=1))
    if len(rows):
        rows = rows[np.char.lower(annos.name[rows]) != DONTCARE.lower()]
    if not len(rows):
        return UnsizedBoxes()
    row = int(rows[0])
    frame = int(np.searchsorted(annos.offsets, row, side="right")) - 1
    ell, h, w = (float(v) for v in annos.dimensions[row])
    first = (annos.frame_ids[frame], row - int(annos.offsets[frame]), str(annos.name[row]), (ell, h, w))
    return UnsizedBoxes(len(rows), first)


def size_warnings(annos: Annotations, *, unsized: UnsizedBoxes | None = None) -> list[str]:
    """One warning for an input with boxes whose size is not positive (:func:`unsized_boxes`); ``unsized``: the
    whole set's count when ``annos`` names a set given in parts (its kind and source are used)."""
    found = unsized_boxes(annos) if unsized is None else unsized
    if not found.count or found.first is None:
        return []
    frame, box, cls, dims = found.first
    kind = "predicted" if annos.kind == "detections" else "ground-truth"
    return [
        f"{annos.source}: {found.count} {kind} box{'es' if found.count > 1 else ''} (DontCare aside) "
        f"{'have' if found.count > 1 else 'has'} a size that is not positive (the first: frame {frame}, box {box} "
        f"({cls}), (l, h, w) = {dims}); evaluated as the KITTI devkit reads them: -1 is 'not given', and a box "
        "without length or width overlaps nothing in BEV and 3D"
    ]


@dataclass(frozen=True)
class BoxLimits:
    """The work-limit rule for boxes: at most ``per_frame`` boxes in one frame and ``per_input`` in one input
    (ground truth or predictions, DontCare rows included); None: no limit. The settings and their defaults are
    :func:`kitti_eval.io.limits.box_limits`' (the names in ``*_setting``, for the refusal). Checked as frames
    are read (:meth:`check_frame`) and over whole columns (:meth:`check_counts`), on the path every format takes
    (:meth:`Annotations.from_frames`, :meth:`Annotations.from_columns`), before any work that grows with them.
    """

    per_frame: int | None = None
    per_input: int | None = None
    per_frame_setting: str = "KITTI_EVAL_MAX_BOXES_PER_FRAME"
    per_input_setting: str = "KITTI_EVAL_MAX_BOXES"

    def check_frame(self, count: int, total: int, *, source: str, frame: str) -> None:
        """Refuse a frame of ``count`` boxes, or one that brings the input to ``total`` boxes, past a limit."""
        if self.per_frame is not None and count > self.per_frame:
            raise WorkLimitError(
                f"{count} boxes in one frame, more than the limit of {self.per_frame} ({self.per_frame_setting})",
                source=source,
                frame=frame,
            )
        if self.per_input is not None and total > self.per_input:
            raise WorkLimitError(
                f"{total} boxes up to this frame, more than the limit of {self.per_input} in one input "
                f"({self.per_input_setting})",
                source=source,
                frame=frame,
            )

    def check_counts(self, counts: np.ndarray, ids: Sequence[str], *, source: str) -> None:
        """:meth:`check_frame` over the (F,) box counts of frames ``ids``: the first frame past a limit."""
        if not len(counts):
            return
        over = np.zeros(len(counts), dtype=np.bool_)
        if self.per_frame is not None:
            over |= counts > self.per_frame
        if self.per_input is not None:
            over |= np.cumsum(counts) > self.per_input
        if over.any():
            f = int(np.argmax(over))
            self.check_frame(int(counts[f]), int(counts[: f + 1].sum()), source=source, frame=ids[f])


_MAX_CODE_POINT = 0x10FFFF


def _is_text(arr: np.ndarray) -> bool:
    """A numpy str array holds only code points Python can represent. numpy builds ``U`` arrays and scalars
    from raw bytes without checking; a code point above U+10FFFF makes every use of the str raise
    SystemError."""
    if arr.dtype.kind != "U" or arr.size == 0 or arr.dtype.itemsize == 0:
        return True
    return int(_code_points(arr).max()) <= _MAX_CODE_POINT


def _code_points(arr: np.ndarray) -> np.ndarray:
    """The code points of a non-empty numpy str array, as it holds them: (len, characters) unsigned ints."""
    return np.ascontiguousarray(arr).view(np.dtype(arr.dtype.byteorder + "u4")).reshape(len(arr), -1)


def _is_text_scalar(value: np.str_) -> bool:
    """:func:`_is_text` of one numpy str scalar (a scalar holds its code points in native order), without
    making an array of it: frame ids are checked once a frame."""
    raw = value.tobytes()
    return not raw or max(memoryview(raw).cast("I")) <= _MAX_CODE_POINT


def shown_frame_id(value: object) -> str:
    """A frame id for messages: normalised where it can be, else a safe description."""
    try:
        return normalize_frame_id(value)
    except (TypeError, ValueError):
        return "<not text>" if isinstance(value, np.str_) else repr(value)[:80]


def normalize_frame_id(value: object) -> str:
    """A frame's key: digits are zero-padded to six (``15``, ``'15'`` and ``'000015'`` are one frame)."""
    if type(value) is str:  # the common cases, first
        return _frame_key(value)
    if type(value) is int and value >= 0:
        return f"{value:06d}"
    if isinstance(value, np.str_) and not _is_text_scalar(value):
        raise ValueError("it is not text (a code point above U+10FFFF)")
    if isinstance(value, (bool, np.bool_)):
        raise TypeError("a frame id cannot be a boolean")
    if isinstance(value, (int, np.integer)):
        if value < 0:
            raise ValueError(f"negative frame id {value}")
        return f"{int(value):06d}"
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, (str, np.str_)):
        return _frame_key(str(value))
    raise TypeError(f"a frame id must be a string or an integer, got {type(value).__name__}")


def _frame_key(text: str) -> str:
    text = text.strip()
    if not text:
        raise ValueError("empty frame id")
    return text.zfill(6) if text.isdigit() else text


def _names(value: Any, source: str, frame: str) -> npt.NDArray[np.str_]:
    """One frame's class names as a numpy str array. A ``U`` array is returned as it is: whether its code
    points are text is checked once for all frames (:func:`_names_are_text`)."""
    arr = np.asarray(value) if not isinstance(value, np.ndarray) else value
    if arr.size == 0:
        return np.zeros(0, dtype="<U1")
    if arr.dtype.kind == "U" and arr.ndim == 1:
        return arr
    where = {"source": source, "frame": frame, "field": "name"}
    if arr.ndim != 1:
        raise InputError(f"expected a 1-D array of class names, got shape {arr.shape}", **where)
    if arr.dtype.kind == "S":
        # bytes are names as the references read them: a byte that is not UTF-8 makes a name no class has
        # (U+FFFD in its place), as any unknown name is; the devkit reads names as raw bytes too
        return np.char.decode(arr, "utf-8", "replace")
    if arr.dtype.kind == "O" and all(isinstance(v, (str, np.str_)) for v in arr):
        return arr.astype("U")
    raise InputError(f"expected class names as strings, got dtype {arr.dtype}", **where)


def _names_are_text(names: np.ndarray, offsets: np.ndarray, ids: Sequence[str], source: str) -> None:
    """Refuse the class names of all frames (concatenated, frame after frame) if one holds a code point
    above U+10FFFF, naming the first frame that does."""
    if _is_text(names):
        return
    row = int(np.argmax((_code_points(names) > _MAX_CODE_POINT).any(axis=1)))
    frame = int(np.searchsorted(offsets, row, side="right")) - 1
    text = "class names must be text; a name holds a code point above U+10FFFF"
    raise InputError(text, source=source, frame=ids[frame], field="name")


def _numeric(value: Any, trailing: tuple[int, ...], n: int, source: str, frame: str, name: str) -> np.ndarray:
    """Check dtype and shape of one frame's field ``name``; returned as is (copied later, when concatenated)."""
    arr = value if isinstance(value, np.ndarray) else np.asarray(value)
    if arr.dtype.kind not in "iuf":
        if arr.size == 0 and arr.dtype.kind in "bOU":
            arr = np.zeros(0)
        else:
            raise InputError(f"expected numbers, got dtype {arr.dtype}", source=source, frame=frame, field=name)
    if arr.size == 0 and n == 0:
        return np.zeros((0, *trailing), dtype=np.float64)
    if arr.shape != (n, *trailing):
        raise InputError(f"expected shape {(n, *trailing)}, got {arr.shape}", source=source, frame=frame, field=name)
    return arr


def _replay(frames: list[tuple[object, Mapping[str, Any]]], error: BaseException | None) -> Iterator[Any]:
    """The frames already taken from a reader, then the error the reader raised after them (if it did)."""
    yield from frames
    if error is not None:
        raise error


_NUMBERS = frozenset("iuf")
_size = operator.attrgetter("size")
_dtype = operator.attrgetter("dtype")
_ndim = operator.attrgetter("ndim")


def _sizes(col: list[Any]) -> np.ndarray:
    return np.fromiter(map(_size, col), np.int64, len(col))


def _numeric_column(col: list[Any], counts: np.ndarray, trailing: tuple[int, ...]) -> np.ndarray | None:
    """One field of all frames as one fresh float64 array, when every frame's value is what the frame-by-frame
    check (:func:`_numeric`) takes as it is: a numeric array of shape ``(n, *trailing)`` (anything empty in a
    frame without boxes). None when it is not (that check then names the frame and the field)."""
    if not col:
        return np.zeros((0, *trailing), dtype=np.float64)
    if set(map(type, col)) != {np.ndarray} or any(dt.kind not in _NUMBERS for dt in set(map(_dtype, col))):
        return None
    boxed = counts > 0
    flags = boxed.tolist()
    if any(a.size for a in itertools.compress(col, [not b for b in flags])):
        return None  # boxes in a frame without names
    parts = list(itertools.compress(col, flags))
    if not parts:
        return np.zeros((0, *trailing), dtype=np.float64)
    try:
        lengths = np.fromiter(map(len, parts), np.int64, len(parts))
        if not np.array_equal(lengths, counts[boxed]):
            return None
        # a fresh float64 array: inputs are never aliased or mutated
        arr = np.concatenate(parts, dtype=np.float64)
    except (TypeError, ValueError):  # a 0-d value, or values of different dimensions
        return None
    return arr if arr.shape == (int(lengths.sum()), *trailing) else None


def _filled(kind: Kind, f: str, n: int, ids: Sequence[str], absent: dict[str, str]) -> np.ndarray:
    """The column of a numeric field no frame has (an image field is then noted in ``absent``)."""
    if f in IMAGE_FIELDS[kind] and ids:
        absent[f] = ids[0]
    return np.full((n, *_NUMERIC_FIELDS[f]), -1.0 if f == "score" else IMAGE_FIELDS[kind].get(f, 0.0))


@dataclass(frozen=True)
class _Columns:
    """The frames' fields concatenated (before the checks over whole columns)."""

    ids: tuple[str, ...]
    offsets: npt.NDArray[np.int64]
    name: np.ndarray
    numeric: dict[str, np.ndarray]
    absent: dict[str, str]
    lidar: np.ndarray | None

    @classmethod
    def of(
        cls,
        kind: Kind,
        frames: list[tuple[object, Mapping[str, Any]]],
        ids: tuple[str, ...],
        *,
        keep_lidar: bool,
    ) -> _Columns | None:
        """The columns of frames (with their ids, normalised and checked) that hold what readers usually give
        (plain dicts of numpy arrays, names as 1-D str arrays, every optional field in all frames or in none),
        one concatenation per field; None for anything else, and for anything :meth:`frame_by_frame` would
        refuse (which then says why)."""
        fields = [d for _, d in frames]
        if set(map(type, fields)) - {dict}:
            return None
        try:
            names = [d["name"] for d in fields]
        except KeyError:
            return None
        if set(map(type, names)) - {np.ndarray}:
            return None
        counts = _sizes(names)
        boxed = counts > 0
        named = list(itertools.compress(names, boxed.tolist()))
        if set(map(_ndim, named)) - {1} or any(dt.kind != "U" or not dt.isnative for dt in set(map(_dtype, named))):
            return None
        offsets = np.zeros(len(fields) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        numeric: dict[str, np.ndarray] = {}
        absent: dict[str, str] = {}
        n = int(offsets[-1])
        for f, trailing in _NUMERIC_FIELDS.items():
            try:
                col = [d[f] for d in fields]
            except KeyError:
                if f in _REQUIRED[kind] or any(f in d for d in fields):
                    return None  # missing, or in some frames only: filled frame by frame
                numeric[f] = _filled(kind, f, n, ids, absent)
                continue
            arr = _numeric_column(col, counts, trailing)
            if arr is None:
                return None
            numeric[f] = arr
        lidar = None
        if keep_lidar:
            boxes = [d.get("boxes_lidar") for d in fields]
            given = sum(b is not None for b in boxes)
            if given == len(boxes):
                lidar = _numeric_column(boxes, counts, (7,))
                if lidar is None:
                    return None
            elif given:
                return None
            else:
                lidar = np.full((n, 7), np.nan)
        if not boxed.all():  # as frame by frame, where a frame without boxes adds an empty <U1 array (dtypes join)
            named.append(np.zeros(0, dtype="<U1"))
        name = np.concatenate(named) if named else np.zeros(0, dtype="<U1")
        return cls(ids, offsets, name, numeric, absent, lidar)

    @classmethod
    def frame_by_frame(
        cls,
        kind: Kind,
        source: str,
        frames: Iterable[tuple[object, Mapping[str, Any]]],
        keep_lidar: bool,
        max_frames: int | None,
        known_frames: Collection[str] | None,
        box_limits: BoxLimits | None = None,
    ) -> _Columns:
        """The columns of any frames :meth:`Annotations.from_frames` takes, each frame checked as it comes."""
        ids: list[str] = []
        seen: dict[str, int] = {}
        cols: dict[str, list[np.ndarray]] = {f: [] for f in ("name", *_NUMERIC_FIELDS)}
        counts: list[int] = []
        absent: dict[str, str] = {}
        lidar: list[np.ndarray] = []
        total = 0
        for pos, (raw_id, fields) in enumerate(frames):
            try:
                fid = normalize_frame_id(raw_id)
            except (TypeError, ValueError) as e:
                raise InputError(
                    f"bad frame id {shown_frame_id(raw_id)}: {e}", source=source, frame=f"#{pos}", field="frame_id"
                ) from None
            if fid in seen:
                raise InputError(f"frame appears twice (entries #{seen[fid]} and #{pos})", source=source, frame=fid)
            if max_frames is not None and pos >= max_frames:
                raise InputError(
                    f"more than the limit of {max_frames} frames ({setting_name('KITTI_EVAL_MAX_FRAMES')})",
                    source=source,
                    frame=fid,
                )
            if known_frames is not None and fid not in known_frames:
                raise InputError("predictions for a frame that is not in the ground truth", source=source, frame=fid)
            seen[fid] = pos
            if not isinstance(fields, Mapping):
                raise InputError(f"expected a dict of arrays, got {type(fields).__name__}", source=source, frame=fid)
            missing = [f for f in _REQUIRED[kind] if f not in fields]
            if missing:
                raise InputError(f"missing field(s) {', '.join(missing)}", source=source, frame=fid, field=missing[0])
            names = _names(fields["name"], source, fid)
            n = len(names)
            total += n
            if box_limits is not None:
                box_limits.check_frame(n, total, source=source, frame=fid)
            cols["name"].append(names)
            for f, trailing in _NUMERIC_FIELDS.items():
                if f in fields:
                    cols[f].append(_numeric(fields[f], trailing, n, source, fid, f))
                elif f == "score":
                    cols[f].append(np.full(n, -1.0))
                else:
                    cols[f].append(np.full((n, *trailing), IMAGE_FIELDS[kind].get(f, 0.0)))
                    if f in IMAGE_FIELDS[kind]:
                        absent.setdefault(f, fid)
            if keep_lidar:
                if fields.get("boxes_lidar") is not None:
                    lidar.append(_numeric(fields["boxes_lidar"], (7,), n, source, fid, "boxes_lidar"))
                else:
                    lidar.append(np.full((n, 7), np.nan))
            ids.append(fid)
            counts.append(n)
        offsets = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        name = np.concatenate(cols["name"]) if cols["name"] else np.zeros(0, dtype="<U1")
        # fresh float64 arrays: inputs are never aliased or mutated
        numeric = {
            f: np.concatenate(cols[f], dtype=np.float64) if cols[f] else np.zeros((0, *trailing), dtype=np.float64)
            for f, trailing in _NUMERIC_FIELDS.items()
        }
        kept = None
        if keep_lidar:
            kept = np.concatenate(lidar, dtype=np.float64) if lidar else np.zeros((0, 7), dtype=np.float64)
        return cls(tuple(ids), offsets, name, numeric, absent, kept)


@dataclass(frozen=True, eq=False)
class Annotations:
    """Boxes of ``F`` frames, concatenated frame after frame (``N`` boxes in all).

    Attributes
    ----------
    kind : "ground_truth" or "detections"
    source : where the boxes came from (a path), for messages
    frame_ids : (F,) normalised frame ids, unique
    offsets : (F + 1,) int64; frame ``f`` owns rows ``offsets[f]:offsets[f + 1]``
    name : (N,) str, class names as written (ground truth keeps its DontCare rows)
    truncated, occluded, alpha, rotation_y, score : (N,) float64 (score is -1 for ground truth)
    bbox : (N, 4) float64 image box x1, y1, x2, y2 (pixels)
    dimensions : (N, 3) float64 l, h, w (metres)
    location : (N, 3) float64 x, y, z of the bottom centre, camera frame (metres)
    """

    kind: Kind
    source: str
    frame_ids: tuple[str, ...]
    offsets: npt.NDArray[np.int64]
    name: npt.NDArray[np.str_]
    truncated: npt.NDArray[np.float64]
    occluded: npt.NDArray[np.float64]
    alpha: npt.NDArray[np.float64]
    bbox: npt.NDArray[np.float64]
    dimensions: npt.NDArray[np.float64]
    location: npt.NDArray[np.float64]
    rotation_y: npt.NDArray[np.float64]
    score: npt.NDArray[np.float64]
    #: image fields (see :data:`IMAGE_FIELDS`) some frame lacked: field -> the first such frame
    missing_fields: Mapping[str, str] = field(default_factory=dict)
    #: (N, 7) ``boxes_lidar`` as the input wrote them (NaN rows where a frame had none), only when asked for
    #: with ``keep_lidar``: they are shown, never evaluated (the camera fields are)
    boxes_lidar: npt.NDArray[np.float64] | None = None

    @property
    def num_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def num_boxes(self) -> int:
        return int(self.offsets[-1])

    @property
    def counts(self) -> npt.NDArray[np.int64]:
        """(F,) boxes per frame."""
        return np.diff(self.offsets)

    @cached_property
    def boxes_camera(self) -> npt.NDArray[np.float64]:
        """(N, 7) x, y, z, l, h, w, ry in the camera frame: the layout of :mod:`kitti_eval.core.geometry`."""
        return np.concatenate([self.location, self.dimensions, self.rotation_y[:, None]], axis=1)

    @cached_property
    def ground_distance(self) -> npt.NDArray[np.float64]:
        """(N,) distance from the camera in the ground plane, ``sqrt(x**2 + z**2)`` of the location (metres)."""
        return np.hypot(self.location[:, 0], self.location[:, 2])

    @cached_property
    def _name_vocabulary(self) -> tuple[npt.NDArray[np.intp], tuple[str, ...]]:
        """(N,) codes into the sorted distinct names, and those names lower-cased."""
        uniq, codes = np.unique(self.name, return_inverse=True)
        return codes.reshape(-1), tuple(str(u).lower() for u in uniq)

    def is_class(self, *names: str) -> npt.NDArray[np.bool_]:
        """(N,) bool: rows whose name is one of ``names``, compared case-insensitively (as the devkit does).

        Answers are remembered per set of names; treat the returned array as read-only.
        """
        wanted = frozenset(n.lower() for n in names)
        cache: dict[frozenset[str], npt.NDArray[np.bool_]] = self.__dict__.setdefault("_is_class_cache", {})
        hit = cache.get(wanted)
        if hit is None:
            codes, vocab = self._name_vocabulary
            member = np.array([v in wanted for v in vocab] or [False], dtype=np.bool_)
            hit = cache[wanted] = member[codes] if len(codes) else np.zeros(0, dtype=np.bool_)
            hit.flags.writeable = False
        return hit

    def frame_index(self) -> dict[str, int]:
        return {fid: i for i, fid in enumerate(self.frame_ids)}

    def frame(self, frame_id: str) -> dict[str, np.ndarray]:
        """The boxes of one frame as a dict of arrays (copies)."""
        idx = self.frame_index().get(normalize_frame_id(frame_id))
        if idx is None:
            raise InputError("no such frame", source=self.source, frame=str(frame_id))
        lo, hi = int(self.offsets[idx]), int(self.offsets[idx + 1])
        return {f: getattr(self, f)[lo:hi].copy() for f in ("name", *_NUMERIC_FIELDS)}

    @classmethod
    def from_frames(
        cls,
        kind: Kind,
        source: str,
        frames: Iterable[tuple[object, Mapping[str, Any]]],
        *,
        keep_lidar: bool = False,
        max_frames: int | None = None,
        known_frames: Collection[str] | None = None,
        box_limits: BoxLimits | None = None,
    ) -> Annotations:
        """Validate per-frame field dicts and concatenate them.

        Parameters
        ----------
        kind : "ground_truth" or "detections"
        source : a name for messages (usually the path)
        frames : pairs of (frame id, fields); fields hold ``name`` (N,), ``bbox`` (N, 4),
            ``dimensions`` (N, 3) as l, h, w, ``location`` (N, 3), ``rotation_y`` (N,), ``alpha`` (N,),
            and ``score`` (N,) for detections or ``truncated``/``occluded`` (N,) for ground truth.
            Empty frames may use any empty arrays (OpenPCDet writes float zeros for ``name``).
        keep_lidar : also keep each frame's ``boxes_lidar`` (N, 7) where present, for display
        max_frames : refuse more frames than this, before converting the first one past it
        known_frames : the frame ids there may be (those of the ground truth, for predictions); another is
            refused before it is converted
        box_limits : refuse a frame, or an input, of more boxes than these (None: no limit); the loaders pass
            :func:`kitti_eval.io.limits.box_limits`
        """
        if kind not in _REQUIRED:
            raise ValueError(f"kind must be 'ground_truth' or 'detections', got {kind!r}")
        # the frames, each frame id checked as it comes: a reader is never asked for the frame after one that
        # is refused by its id (a bad or repeated id, one past the limit, one the ground truth does not have)
        taken: list[tuple[object, Mapping[str, Any]]] = []
        ids: list[str] = []
        seen: set[str] = set()
        error: BaseException | None = None
        try:
            for pair in frames:
                taken.append(pair)
                fid = normalize_frame_id(pair[0])
                if fid in seen or (max_frames is not None and len(ids) >= max_frames):
                    break
                if known_frames is not None and fid not in known_frames:
                    break
                seen.add(fid)
                ids.append(fid)
        except Exception as e:  # noqa: BLE001 - raised again below, where the frame-by-frame reading meets it
            error = e
        if error is None and len(ids) == len(taken):
            whole = _Columns.of(kind, taken, tuple(ids), keep_lidar=keep_lidar)
            if whole is not None:
                return cls._checked(kind, source, whole, box_limits)
        # anything the columns do not take as they are: frame by frame, in the order the frames come (the same
        # refusal as ever for the same input, the reader's own included)
        rest = _replay(taken, error)
        return cls._checked(
            kind,
            source,
            _Columns.frame_by_frame(kind, source, rest, keep_lidar, max_frames, known_frames, box_limits),
            box_limits,
        )

    @classmethod
    def from_columns(
        cls,
        kind: Kind,
        source: str,
        frame_ids: tuple[str, ...],
        offsets: npt.NDArray[np.int64],
        name: npt.NDArray[np.str_],
        numeric: Mapping[str, np.ndarray],
        *,
        lidar: np.ndarray | None = None,
        box_limits: BoxLimits | None = None,
    ) -> Annotations:
        """Annotations from columns a reader built itself (:mod:`kitti_eval.io.pickle_columns`): fresh arrays,
        each field of all frames, frame after frame, as :meth:`from_frames` concatenates them; ``frame_ids``
        normalised and unique; ``numeric`` float64 of the shapes of :data:`NUMERIC_FIELDS`, a field no frame
        has left out (filled as :meth:`from_frames` fills it). The same checks over whole columns (names are
        text, numbers finite) as :meth:`from_frames`, with the same errors."""
        absent: dict[str, str] = {}
        n = int(offsets[-1])
        columns = {f: numeric[f] if f in numeric else _filled(kind, f, n, frame_ids, absent) for f in _NUMERIC_FIELDS}
        return cls._checked(kind, source, _Columns(frame_ids, offsets, name, columns, absent, lidar), box_limits)

    @classmethod
    def _checked(cls, kind: Kind, source: str, c: _Columns, box_limits: BoxLimits | None = None) -> Annotations:
        """The checks over whole columns (boxes within the limits, names are text, numbers finite), then the
        container."""
        if box_limits is not None:
            box_limits.check_counts(np.diff(c.offsets), c.ids, source=source)
        _names_are_text(c.name, c.offsets, c.ids, source)
        for f in _NUMERIC_FIELDS:
            arr = c.numeric[f]
            finite = np.isfinite(arr)
            if not finite.all():
                row = int(np.argwhere(~finite)[0][0])
                frame = int(np.searchsorted(c.offsets, row, side="right")) - 1
                raise InputError(
                    f"non-finite value {arr.reshape(len(arr), -1)[row].tolist()} in box {row - int(c.offsets[frame])}",
                    source=source,
                    frame=c.ids[frame],
                    field=f,
                )
        if c.lidar is not None:
            bad = np.isinf(c.lidar).any(axis=1)
            if bad.any():
                row = int(np.argmax(bad))
                frame = int(np.searchsorted(c.offsets, row, side="right")) - 1
                raise InputError(
                    f"non-finite value in box {row - int(c.offsets[frame])}",
                    source=source,
                    frame=c.ids[frame],
                    field="boxes_lidar",
                )
        return cls(
            kind=kind,
            source=source,
            frame_ids=c.ids,
            offsets=c.offsets,
            name=c.name,
            missing_fields=c.absent,
            boxes_lidar=c.lidar,
            **c.numeric,
        )

    def aligned_to(self, frame_ids: Sequence[str], *, reference: str = "ground truth") -> tuple[Annotations, list[str]]:
        """These boxes re-ordered to ``frame_ids`` (frames absent here become empty).

        Returns the aligned annotations and the ids of frames that had no entry here. A frame of ours
        that is not in ``frame_ids`` is an error: it cannot be scored, and it usually means the wrong
        ground truth.
        """
        mine = self.frame_index()
        wanted = set(frame_ids)
        unknown = [fid for fid in self.frame_ids if fid not in wanted]
        if unknown:
            more = f" and {len(unknown) - 1} more" if len(unknown) > 1 else ""
            raise InputError(
                f"predictions for a frame that is not in the {reference}{more}", source=self.source, frame=unknown[0]
            )
        missing = [fid for fid in frame_ids if fid not in mine]
        if not missing and tuple(frame_ids) == self.frame_ids:
            return self, []
        return self._take(frame_ids), missing

    def subset(self, frame_ids: Sequence[str]) -> Annotations:
        """Only the given frames, in that order (a frame not here is an error)."""
        mine = self.frame_index()
        absent = [fid for fid in frame_ids if fid not in mine]
        if absent:
            raise InputError(f"no such frame ({len(absent)} asked for are absent)", source=self.source, frame=absent[0])
        return self._take(frame_ids)

    def _take(self, frame_ids: Sequence[str]) -> Annotations:
        mine = self.frame_index()
        rows: list[np.ndarray] = []
        counts = np.zeros(len(frame_ids), dtype=np.int64)
        for k, fid in enumerate(frame_ids):
            idx = mine.get(fid)
            if idx is not None:
                lo, hi = int(self.offsets[idx]), int(self.offsets[idx + 1])
                rows.append(np.arange(lo, hi))
                counts[k] = hi - lo
        take = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        offsets = np.zeros(len(frame_ids) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        fields = {f: getattr(self, f)[take] for f in ("name", *_NUMERIC_FIELDS)}
        return Annotations(
            kind=self.kind,
            source=self.source,
            frame_ids=tuple(frame_ids),
            offsets=offsets,
            missing_fields=self.missing_fields,
            boxes_lidar=None if self.boxes_lidar is None else self.boxes_lidar[take],
            **fields,
        )


#: Typical (l, h, w) of KITTI classes, metres; used only to spot a swapped dimension order.
_TYPICAL_LHW: Mapping[str, tuple[float, float, float]] = {
    "car": (3.88, 1.53, 1.63),
    "pedestrian": (0.84, 1.76, 0.66),
    "cyclist": (1.76, 1.74, 0.60),
}
#: boxes per class the median is taken over (the first ones; plenty for a warning)
_MEDIAN_SAMPLE = 5000
_ORDERS = {"lhw": (0, 1, 2), "hwl": (1, 2, 0), "lwh": (0, 2, 1), "hlw": (1, 0, 2), "whl": (2, 1, 0), "wlh": (2, 0, 1)}


def dimension_samples(annos: Annotations) -> dict[str, tuple[int, np.ndarray]]:
    """Per class of :data:`_TYPICAL_LHW`: how many boxes, and the dimensions of the first 5000 (what
    :func:`dimension_order_warnings` looks at; samples of consecutive parts of a set combine with
    :func:`merge_dimension_samples`)."""
    out = {}
    for cls in _TYPICAL_LHW:
        rows = np.flatnonzero(annos.is_class(cls))
        out[cls] = (len(rows), annos.dimensions[rows[:_MEDIAN_SAMPLE]])
    return out


def merge_dimension_samples(parts: Iterable[dict[str, tuple[int, np.ndarray]]]) -> dict[str, tuple[int, np.ndarray]]:
    """The samples of consecutive parts of a set, in order, as those of the whole set."""
    out: dict[str, tuple[int, np.ndarray]] = {cls: (0, np.zeros((0, 3))) for cls in _TYPICAL_LHW}
    for part in parts:
        for cls, (n, rows) in part.items():
            total, kept = out[cls]
            out[cls] = (total + n, np.concatenate([kept, rows])[:_MEDIAN_SAMPLE])
    return out


def dimension_order_warnings(
    annos: Annotations, min_boxes: int = 5, *, samples: dict[str, tuple[int, np.ndarray]] | None = None
) -> list[str]:
    """Warn when a class's median dimensions fit another order than (l, h, w) much better.

    The column whose median is compared is the order as stored; a result written with (h, w, l)
    (the txt order) into a pickle shows Cars about 1.5 m long and 3.9 m wide. ``samples``: the whole set's
    (:func:`dimension_samples`) when ``annos`` names a set given in parts (its kind and source are used).
    """
    out: list[str] = []
    samples = dimension_samples(annos) if samples is None else samples
    for cls, typical in _TYPICAL_LHW.items():
        count, rows = samples[cls]
        if count < min_boxes:
            continue
        med = np.median(rows, axis=0)
        if not np.all(med > 0):
            continue
        errs = {}
        for order, perm in _ORDERS.items():
            # if the data were stored in `order`, column k holds dimension perm[k] of (l, h, w)
            expect = np.array([typical[p] for p in perm])
            errs[order] = float(np.sum(np.log(med / expect) ** 2))
        best = min(errs, key=errs.__getitem__)
        if best != "lhw" and errs[best] * 4 < errs["lhw"]:
            kind = "predictions" if annos.kind == "detections" else "ground truth"
            out.append(
                f"{annos.source}: {kind} of class {cls!r} have median dimensions "
                f"{tuple(round(float(v), 2) for v in med)} which look like ({', '.join(best)}) "
                f"rather than (l, h, w); pickles store dimensions as l, h, w (txt files as h, w, l)"
            )
    return out
