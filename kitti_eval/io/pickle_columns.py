"""Ground truth and detections straight from a checked pickle's bytes into the evaluator's columns, without
building an object.

The scan (:mod:`kitti_eval.io._pickle_scan`) has checked every byte of the pickle before this module looks
at it, and it records what it saw: every item put into a list or dict, in order, and for every numpy array
the state it was given (shape, dtype and where its data lie in the bytes). For the layouts almost every
file has, :func:`read_detections` (OpenPCDet's result.pkl: a list of plain dicts, one a frame, each with
``frame_id`` and the fields as numpy arrays of numbers, the names as a 1-D str array) and
:func:`read_ground_truth` (OpenPCDet's infos: the same fields in each entry's ``annos``, the frame id in its
``image``, its calibration's matrices in ``calib``) take each field of all frames from those bytes at once
(one join of the frames' data and one conversion to float64 per field and dtype) and run the checks over
whole columns (:meth:`Annotations.from_columns`). Nothing is unpickled, called or imported.

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

from ..core.frames import NUMERIC_FIELDS, REQUIRED_FIELDS, Annotations, Kind, normalize_frame_id
from ..errors import InputError
from . import _pickle_scan as _ps
from .calib import calib_from_info
from .camera import _LazyCalibs, check_agreement
from .safe_pickle import CheckedPickle

__all__ = ["read_detections", "read_ground_truth"]

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
            and all((c >> 8, c & 255) in _NUMBER_TYPES for c in set(codes.tolist()))
            and set(self.kind[~b].tolist()) <= {ord("f"), ord("i"), ord("u")}
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
    distinct = sorted(set(codes.tolist()))
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


class _Record:
    """What the scan recorded of a checked pickle, and the walks over it."""

    def __init__(self, checked: CheckedPickle) -> None:
        self.nodes, self.ch, self.root, self.items = checked.scan[5], checked.scan[6], checked.scan[7], checked.scan[8]
        self.kinds = self.nodes[:, _ps.W] & _ps.KIND_MASK
        self.data = memoryview(checked.data).cast("B")
        self.source = checked.source

    def frames(self) -> np.ndarray | None:
        """The items of the top-level list when each is a distinct plain dict (the frames), else None."""
        if self.kinds[self.root] != _ps.K_LIST:
            return None
        frames = self.items[self.items[:, 0] == self.root, 1]
        if not len(frames) or np.any(self.kinds[frames] != _ps.K_DICT) or len(np.unique(frames)) != len(frames):
            return None
        return frames

    def table(self, dicts: np.ndarray, names: tuple[str, ...], *, others: bool) -> np.ndarray | None:
        """(len(dicts), len(names)) the value of each key of ``names`` in each of the plain dicts ``dicts`` (-1
        where a dict lacks it); None when one is not a plain dict, a dict is there twice, a key is there twice,
        a key is not a str of plain ASCII text, or a key is not one of ``names`` and ``others`` is False.

        A key is compared as the dict pickle builds compares it: a ``numpy.str_`` (or a str written with escapes)
        equals its text, and the last of two equal keys gives the value. Only a plain ASCII str is read here, each
        at most once a dict; any other key sends the file to the objects, whose dict has settled which value won.
        """
        if np.any(self.kinds[dicts] != _ps.K_DICT) or len(np.unique(dicts)) != len(dicts):
            return None
        count, width = len(dicts), len(names)
        position = np.full(len(self.nodes), -1, np.int64)
        position[dicts] = np.arange(count)
        entries = self.items[self.items[:, 2] >= 0]
        owner = position[entries[:, 0]]
        entries, owner = entries[owner >= 0], owner[owner >= 0]
        keys, which = np.unique(entries[:, 1], return_inverse=True)
        index = {f: i for i, f in enumerate(names)}
        field_of = []
        for key in keys.tolist():  # a few str nodes: the memo shares them between frames
            text = _text(self.data, self.nodes, key)
            if text is None:  # a numpy.str_, escaped text, or another kind: equal to a name or not, pickle decides
                return None
            i = index.get(text, -1)
            if i < 0 and not others:
                return None
            field_of.append(i)
        field = np.asarray(field_of, np.int64)[which.reshape(-1)]
        mine = field >= 0
        slot = owner[mine] * width + field[mine]
        if np.any(np.bincount(slot, minlength=1) > 1):  # a key twice in one dict
            return None
        flat = np.full(count * width, -1, np.int64)
        flat[slot] = entries[mine, 2]
        return flat.reshape(count, width)

    def arrays_of_numbers(self, values: np.ndarray, ndim: int) -> list[tuple[str, int, tuple[int, ...]]] | None:
        """How to make each of the nodes ``values`` into the array it is, (dtype, where its data start, shape),
        when each is a numpy array of numbers of ``ndim`` dimensions (C order, little-endian); else None."""
        arrays = _Arrays(self.nodes, self.ch, values)
        if not arrays.ok:
            return None
        codes = arrays.kind * 256 + arrays.itemsize
        if not (
            np.all((arrays.ndim == ndim) & arrays.c_order & arrays.raw_ok & ~arrays.big)
            and np.all(arrays.nbytes == arrays.size * arrays.itemsize)
            and all((c >> 8, c & 255) in _NUMBER_TYPES for c in set(codes.tolist()))
        ):
            return None
        dims = zip(arrays.d0.tolist(), arrays.d1.tolist())
        return [
            (f"<{chr(c >> 8)}{c & 255}", start, (d0, d1)[:ndim])
            for c, start, (d0, d1) in zip(codes.tolist(), arrays.start.tolist(), dims)
        ]

    def array(self, spec: tuple[str, int, tuple[int, ...]]) -> np.ndarray:
        """The array :meth:`arrays_of_numbers` said how to make, as the unpickler builds it (a fresh copy)."""
        dtype, start, shape = spec
        return np.frombuffer(self.data, dtype, int(np.prod(shape)), start).reshape(shape).copy()


def _annotations(
    record: _Record,
    kind: Kind,
    ids: tuple[str, ...],
    table: np.ndarray,
    names: tuple[str, ...],
    *,
    keep_lidar: bool,
    calibs: Mapping[str, Any] | None,
    warnings: list[str],
) -> Annotations | None:
    """The columns of the frames' field dicts (``table``: their values, by ``names``), checked over whole
    columns; None where :meth:`Annotations.from_frames` would not take them as they are."""
    present = table >= 0
    given = [bool(present[:, f].all()) for f in range(len(names))]
    if given != [bool(present[:, f].any()) for f in range(len(names))]:  # a field in some frames only
        return None
    at = {f: i for i, f in enumerate(names)}
    if not all(given[at[f]] for f in REQUIRED_FIELDS[kind]):
        return None
    nodes, ch, data = record.nodes, record.ch, record.data
    names_ = _Arrays(nodes, ch, table[:, at["name"]])
    if not names_.ok:
        return None
    boxed = names_.size > 0
    if not np.all((names_.ndim[boxed] == 1) & (names_.kind[boxed] == _U) & ~names_.big[boxed] & names_.raw_ok[boxed]):
        return None
    if np.any(names_.nbytes[boxed] != names_.size[boxed] * names_.itemsize[boxed]):
        return None
    if np.any(names_.itemsize[boxed] <= 0):
        return None
    count = len(table)
    counts = np.where(boxed, names_.d0, 0)
    offsets = np.zeros(count + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    width = int(names_.itemsize[boxed].max()) // 4 if boxed.any() else 1
    if not boxed.all():  # as from_frames, where a frame without boxes adds an empty <U1 array (dtypes join)
        width = max(width, 1)
    name = _gather(
        data,
        names_,
        boxed,
        names_.itemsize[boxed],
        counts,
        (int(offsets[-1]),),
        lambda size: f"<U{size // 4}",
        f"<U{width}",
    )
    columns: dict[str, np.ndarray] = {}
    for field, trailing in _TRAILING.items():
        if field not in at or not given[at[field]]:
            continue
        arrays = _Arrays(nodes, ch, table[:, at[field]])
        column = arrays.column(data, boxed, counts, trailing) if arrays.ok else None
        if column is None:
            return None
        columns[field] = column
    lidar = columns.pop("boxes_lidar", None)
    said: list[str] = []
    if lidar is not None:
        check_agreement(columns["location"], columns["rotation_y"], lidar, offsets, ids, calibs, record.source, said)
    if keep_lidar and lidar is None:
        lidar = np.full((int(offsets[-1]), 7), np.nan)
    try:
        annotations = Annotations.from_columns(
            kind, record.source, ids, offsets, name, columns, lidar=lidar if keep_lidar else None
        )
    except InputError:
        return None  # refused: the objects' route says so, in its own words
    warnings.extend(said)
    return annotations


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
    record = _Record(checked)
    frames = record.frames()
    table = None if frames is None else record.table(frames, _FIELDS, others=False)
    if table is None or np.any(table[:, 0] < 0):
        return None
    ids = _frame_ids(record.data, record.nodes, record.ch, table[:, 0], max_frames, known_frames)
    if ids is None:
        return None
    return _annotations(
        record, "detections", ids, table[:, 1:], _FIELDS[1:], keep_lidar=keep_lidar, calibs=calibs, warnings=warnings
    )


#: an OpenPCDet infos entry's keys (another key is read as before), and those of its parts read here
_INFO = ("point_cloud", "image", "calib", "annos")
_IMAGE = ("image_idx", "image_shape")
_CALIB = ("P2", "R0_rect", "Tr_velo_to_cam")
_ANNOS = ("name", *NUMERIC_FIELDS)


def read_ground_truth(
    checked: CheckedPickle, *, max_frames: int, known_frames: Collection[str] | None = None
) -> tuple[Annotations, Mapping[str, Any]] | None:
    """Ground truth of a checked pickle in OpenPCDet's infos layout (``openpcdet_infos``: every entry with
    ``image.image_idx``, ``annos`` and, where it has one, a ``calib`` of three matrices), read from its bytes,
    and each frame's calibration (built when first asked for, as :func:`kitti_eval.io.camera.calibs_from_object`
    builds it); None for anything else (see the module)."""
    record = _Record(checked)
    entries = record.frames()
    infos = None if entries is None else record.table(entries, _INFO, others=False)
    if infos is None or np.any(infos[:, 1] < 0) or np.any(infos[:, 3] < 0):
        return None
    image = record.table(infos[:, 1], _IMAGE, others=True)
    if image is None or np.any(image[:, 0] < 0):
        return None
    ids = _frame_ids(record.data, record.nodes, record.ch, image[:, 0], max_frames, known_frames)
    annos = record.table(infos[:, 3], _ANNOS, others=True)
    if ids is None or annos is None:
        return None
    with_calib = np.flatnonzero(infos[:, 2] >= 0)
    calib = record.table(infos[with_calib, 2], _CALIB, others=True)
    if calib is None or np.any(calib < 0):
        return None
    shapes = image[with_calib, 1]
    p2s, r0s, trs = (record.arrays_of_numbers(column, 2) for column in calib.T)
    shape_specs = record.arrays_of_numbers(shapes[shapes >= 0], 1)
    if p2s is None or r0s is None or trs is None or shape_specs is None:
        return None  # read from the objects, where a calibration may be anything calib_from_info reads
    shape_of = iter(shape_specs)
    parts = {
        ids[i]: (record, p2, r0, tr, next(shape_of) if shape >= 0 else None)
        for i, p2, r0, tr, shape in zip(with_calib.tolist(), p2s, r0s, trs, shapes.tolist())
    }
    annotations = _annotations(record, "ground_truth", ids, annos, _ANNOS, keep_lidar=False, calibs=None, warnings=[])
    if annotations is None:
        return None
    return annotations, _LazyCalibs(parts, _calib_of)


def _calib_of(part: tuple[Any, ...]) -> Any:
    """A frame's calibration from the arrays (already checked) of its infos entry, as calib_from_info reads them."""
    record, p2, r0, tr, shape = part
    image = {} if shape is None else {"image_shape": record.array(shape)}
    matrices = {"P2": record.array(p2), "R0_rect": record.array(r0), "Tr_velo_to_cam": record.array(tr)}
    return calib_from_info({"calib": matrices, "image": image})
