"""Detections straight from a checked pickle's bytes into the evaluator's columns, without building an object.

The scan (:mod:`kitti_eval.io._pickle_scan`) has checked every byte of the pickle before this module looks
at it, and it records what it saw: every item put into a list or dict, in order, and for every numpy array
the state it was given (shape, dtype and where its data lie in the bytes). For the layout almost every
result.pkl has (a list of plain dicts, one a frame, each with ``frame_id`` and the fields as numpy arrays of
numbers, the names as a 1-D str array) :func:`read_detections` takes each field of all frames from those bytes
at once (one join of the frames' data and one conversion to float64 per field and dtype) and runs the checks
over whole columns (:meth:`Annotations.from_columns`). Nothing is unpickled, called or imported.

Anything else returns None, and the caller reads the pickle as before (the C unpickler, then the format's
reader and :meth:`Annotations.from_frames`): another layout or kind of value, a frame id that is refused
(repeated, past the limit, not in the ground truth), a value a check refuses. Every refusal, and its
message, is therefore the one the objects get; this module only ever accepts what that route accepts, with
the same numbers, arrays of the same dtypes and the same warnings.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import numpy as np

from ..core.frames import NUMERIC_FIELDS, REQUIRED_FIELDS, Annotations, normalize_frame_id
from ..errors import InputError
from . import _pickle_scan as _ps
from .camera import check_agreement
from .safe_pickle import CheckedPickle

__all__ = ["read_detections"]

#: the keys a frame of detections may have here (another key, e.g. mmdetection3d's sample_idx, is read as before)
_FIELDS = ("frame_id", "name", *NUMERIC_FIELDS, "boxes_lidar")
_INDEX = {f: i for i, f in enumerate(_FIELDS)}
_TRAILING: dict[str, tuple[int, ...]] = {**NUMERIC_FIELDS, "boxes_lidar": (7,)}
#: array dtypes (kind letter, itemsize) taken as numbers: those numpy converts to float64 as concatenate does
_NUMBER_TYPES = frozenset([(ord("f"), s) for s in (2, 4, 8)] + [(ord(k), s) for k in "iu" for s in (1, 2, 4, 8)])
_U = ord("U")
_STR_CONTENT = _ps.K_STR | _ps.F_CONTENT
_BYTES_CONTENT = _ps.K_BYTES | _ps.F_CONTENT


class _Arrays:
    """What the scan recorded of one array a frame (``values``: their nodes): shape, dtype, data."""

    def __init__(self, nodes: np.ndarray, ch: np.ndarray, values: np.ndarray) -> None:
        w = nodes[values, _ps.W]
        #: every value a numpy array with its state set (the state's node is then the array's A)
        self.ok = bool(np.all((w & (_ps.KIND_MASK | _ps.F_BUILT)) == (_ps.K_SHELL | _ps.F_BUILT)))
        if not self.ok:
            return
        state = ch[nodes[nodes[values, _ps.A], _ps.A] + np.arange(5)[:, None]]  # (1, shape, dtype, fortran, data)
        shape, dtype, fortran, raw = state[1], state[2], state[3], state[4]
        self.ndim = nodes[shape, _ps.B]
        self.ok = bool(np.all(self.ndim <= 2))
        first = nodes[shape, _ps.A]
        last = max(len(ch) - 1, 0)
        self.d0 = np.where(self.ndim >= 1, nodes[ch[np.minimum(first, last)], _ps.V], 1)
        self.d1 = np.where(self.ndim >= 2, nodes[ch[np.minimum(first + 1, last)], _ps.V], 1)
        self.size = np.where(self.ndim == 0, 1, self.d0 * np.where(self.ndim == 2, self.d1, 1))
        self.kind = nodes[dtype, _ps.A]
        self.itemsize = nodes[dtype, _ps.V]
        self.big = (nodes[dtype, _ps.W] & _ps.F_BIG != 0) & (self.itemsize > 1)
        self.c_order = (nodes[fortran, _ps.V] == 0) | (self.ndim < 2)  # the flag is True or False (the scan)
        self.raw_ok = (nodes[raw, _ps.W] & (_ps.KIND_MASK | _ps.F_CONTENT)) == _BYTES_CONTENT
        self.start = nodes[raw, _ps.A]
        self.nbytes = nodes[raw, _ps.V]

    def column(
        self, data: memoryview, boxed: np.ndarray, counts: np.ndarray, trailing: tuple[int, ...]
    ) -> np.ndarray | None:
        """The frames' values as one fresh float64 array (N, *trailing), or None unless every frame's value
        is a C-ordered array of numbers of shape (n, *trailing) (anything empty where a frame has no boxes)."""
        if np.any(self.size[~boxed] != 0):
            return None
        ndim = 1 + len(trailing)
        width = trailing[0] if trailing else 1
        b = boxed
        codes = self.kind[b] * 256 + self.itemsize[b]
        if not (
            np.all(self.ndim[b] == ndim)
            and np.all(self.d0[b] == counts[b])
            and np.all(self.d1[b] == width)
            and np.all(self.c_order[b] & self.raw_ok[b] & ~self.big[b])
            and np.all(self.nbytes[b] == self.size[b] * self.itemsize[b])
            and all((c >> 8, c & 255) in _NUMBER_TYPES for c in np.unique(codes).tolist())
            and all(int(k) in (ord("f"), ord("i"), ord("u")) for k in np.unique(self.kind[~b]).tolist())
        ):
            return None
        n = int(counts.sum())
        return _gather(data, self, b, codes, counts, (n, *trailing), lambda code: f"<{chr(code >> 8)}{code & 255}")


def _gather(
    data: memoryview,
    arrays: _Arrays,
    boxed: np.ndarray,
    codes: np.ndarray,
    counts: np.ndarray,
    shape: tuple[int, ...],
    dtype_of: Any,
    out_dtype: Any = np.float64,
) -> np.ndarray:
    """The boxed frames' data, joined per dtype and converted: one fresh array of ``shape``."""
    starts, ends = arrays.start[boxed], arrays.start[boxed] + arrays.nbytes[boxed]
    distinct = np.unique(codes).tolist()
    if len(distinct) == 1:
        joined = b"".join([data[a:e] for a, e in zip(starts.tolist(), ends.tolist())])
        return np.frombuffer(joined, dtype_of(distinct[0])).astype(out_dtype).reshape(shape)
    out = np.empty(shape, out_dtype)
    boxed_counts = counts[boxed]
    for code in distinct:
        mine = codes == code
        joined = b"".join([data[a:e] for a, e in zip(starts[mine].tolist(), ends[mine].tolist())])
        rows = np.repeat(mine, boxed_counts)
        out[rows] = np.frombuffer(joined, dtype_of(code)).reshape(-1, *shape[1:])
    return out


def _text(data: memoryview, nodes: np.ndarray, node: int) -> str | None:
    """The text of a str node whose raw bytes are its ASCII text, else None."""
    if nodes[node, _ps.W] & (_ps.KIND_MASK | _ps.F_CONTENT) != _STR_CONTENT:
        return None
    a, b = int(nodes[node, _ps.A]), int(nodes[node, _ps.B])
    return bytes(data[a : a + b]).decode("ascii")


def _id_value(data: memoryview, nodes: np.ndarray, ch: np.ndarray, node: int, kind: int) -> object:
    """A frame id that is an int, a ``numpy.str_`` or a numpy int (OpenPCDet's collate gives ``numpy.str_``)
    as the value it is; None for anything else."""
    if kind == _ps.K_INT:
        return int(nodes[node, _ps.V])
    if kind & _ps.KIND_MASK != _ps.K_SCALAR:
        return None
    args = int(nodes[node, _ps.A])
    dtype, raw = (int(c) for c in ch[nodes[args, _ps.A] : nodes[args, _ps.A] + 2])
    if nodes[raw, _ps.W] & (_ps.KIND_MASK | _ps.F_CONTENT) != _BYTES_CONTENT or nodes[dtype, _ps.W] & _ps.F_BIG:
        return None
    a, b = int(nodes[raw, _ps.A]), int(nodes[raw, _ps.V])
    letter = chr(int(nodes[dtype, _ps.A]))
    if letter == "U":  # numpy.str_: UTF-32 without its trailing NULs; a code point past U+10FFFF is refused later
        try:
            return str(data[a : a + b], "utf-32-le").rstrip("\0")
        except UnicodeDecodeError:
            return None
    if letter in "iu" and b in (1, 2, 4, 8):
        return int.from_bytes(data[a : a + b], "little", signed=letter == "i")
    return None


def _frame_ids(
    data: memoryview,
    nodes: np.ndarray,
    ch: np.ndarray,
    values: np.ndarray,
    max_frames: int,
    known: Collection[str] | None,
) -> tuple[str, ...] | None:
    """The frames' ids, normalised, when each is an ASCII str, an int or a numpy str or int scalar, and none would
    be refused (the objects' route then says why)."""
    kinds = nodes[values, _ps.W] & (_ps.KIND_MASK | _ps.F_CONTENT | _ps.F_BOOL)
    texts = kinds == _STR_CONTENT
    raw: list[object]
    if texts.all():  # what result.pkl holds
        starts = nodes[values, _ps.A]
        ends = starts + nodes[values, _ps.B]
        raw = [str(data[a:e], "ascii") for a, e in zip(starts.tolist(), ends.tolist())]
    else:
        raw = []
        for node, kind in zip(values.tolist(), kinds.tolist()):
            value = _text(data, nodes, node) if kind == _STR_CONTENT else _id_value(data, nodes, ch, node, kind)
            if value is None:
                return None
            raw.append(value)
    try:
        ids = tuple(map(normalize_frame_id, raw))
    except (TypeError, ValueError):
        return None
    if len(set(ids)) != len(ids) or len(ids) > max_frames:
        return None
    if known is not None and not all(fid in known for fid in ids):
        return None
    return ids


def read_detections(
    checked: CheckedPickle,
    *,
    max_frames: int,
    keep_lidar: bool = False,
    known_frames: Collection[str] | None = None,
    calibs: Mapping[str, Any] | None = None,
    warnings: list[str],
) -> Annotations | None:
    """Detections of a checked pickle in OpenPCDet's result.pkl layout (``annos_list``), read from its bytes; None
    for anything else (see the module). The options are :class:`kitti_eval.io.reading.LoadOptions`'; the
    agreement of camera fields and ``boxes_lidar`` is checked as :func:`kitti_eval.io.camera.camera_fields`
    checks it, its warning appended to ``warnings``."""
    nodes, ch, root, items = checked.scan[5], checked.scan[6], checked.scan[7], checked.scan[8]
    kinds = nodes[:, _ps.W] & _ps.KIND_MASK
    if kinds[root] != _ps.K_LIST:
        return None
    frames = items[items[:, 0] == root, 1]
    count = len(frames)
    if not count or np.any(kinds[frames] != _ps.K_DICT) or len(np.unique(frames)) != count:
        return None
    position = np.full(len(nodes), -1, np.int64)
    position[frames] = np.arange(count)
    entries = items[items[:, 2] >= 0]
    frame_of = position[entries[:, 0]]
    entries, frame_of = entries[frame_of >= 0], frame_of[frame_of >= 0]
    data = memoryview(checked.data).cast("B")
    keys, which = np.unique(entries[:, 1], return_inverse=True)
    field_of = []
    for key in keys.tolist():  # a few str nodes: the memo shares them between frames
        index = _INDEX.get(_text(data, nodes, key) or "")
        if index is None:
            return None
        field_of.append(index)
    slot = frame_of * len(_FIELDS) + np.asarray(field_of, np.int64)[which.reshape(-1)]
    if np.any(np.bincount(slot, minlength=1) > 1):  # a field twice in one dict
        return None
    flat = np.full(count * len(_FIELDS), -1, np.int64)
    flat[slot] = entries[:, 2]
    table = flat.reshape(count, len(_FIELDS))
    present = table >= 0
    given = [bool(present[:, f].all()) for f in range(len(_FIELDS))]
    if given != [bool(present[:, f].any()) for f in range(len(_FIELDS))]:  # a field in some frames only
        return None
    if not all(given[_INDEX[f]] for f in ("frame_id", *REQUIRED_FIELDS["detections"])):
        return None
    ids = _frame_ids(data, nodes, ch, table[:, 0], max_frames, known_frames)
    if ids is None:
        return None

    names = _Arrays(nodes, ch, table[:, _INDEX["name"]])
    if not names.ok:
        return None
    boxed = names.size > 0
    if not np.all((names.ndim[boxed] == 1) & (names.kind[boxed] == _U) & ~names.big[boxed] & names.raw_ok[boxed]):
        return None
    if np.any(names.nbytes[boxed] != names.size[boxed] * names.itemsize[boxed]):
        return None
    if np.any(names.itemsize[boxed] <= 0):
        return None
    counts = np.where(boxed, names.d0, 0)
    offsets = np.zeros(count + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    width = int(names.itemsize[boxed].max()) // 4 if boxed.any() else 1
    if not boxed.all():  # as from_frames, where a frame without boxes adds an empty <U1 array (dtypes join)
        width = max(width, 1)
    name = _gather(
        data,
        names,
        boxed,
        names.itemsize[boxed],
        counts,
        (int(offsets[-1]),),
        lambda size: f"<U{size // 4}",
        f"<U{width}",
    )

    columns: dict[str, np.ndarray] = {}
    for field, trailing in _TRAILING.items():
        if not given[_INDEX[field]]:
            continue
        arrays = _Arrays(nodes, ch, table[:, _INDEX[field]])
        column = arrays.column(data, boxed, counts, trailing) if arrays.ok else None
        if column is None:
            return None
        columns[field] = column
    lidar = columns.pop("boxes_lidar", None)
    said: list[str] = []
    if lidar is not None:
        check_agreement(columns["location"], columns["rotation_y"], lidar, offsets, ids, calibs, checked.source, said)
    if keep_lidar and lidar is None:
        lidar = np.full((int(offsets[-1]), 7), np.nan)
    try:
        annotations = Annotations.from_columns(
            "detections", checked.source, ids, offsets, name, columns, lidar=lidar if keep_lidar else None
        )
    except InputError:
        return None  # refused: the objects' route says so, in its own words
    warnings.extend(said)
    return annotations
