"""What every input format shares: the :class:`Format` record the registry holds, the frames a reader yields,
frame ids and the words of messages."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ...core.frames import Kind
from ...errors import InputError

__all__ = [
    "Format",
    "Frames",
    "Reader",
    "Claim",
    "KIND_WORD",
    "check_kind",
    "type_name",
    "describe_format",
    "expected_layouts",
    "frame_id",
]

#: (frame id, fields) pairs, as :meth:`kitti_eval.core.frames.Annotations.from_frames` takes them
Frames = Iterator[tuple[object, Mapping[str, Any]]]
#: a pickle format's reader: ``(obj, kind, source, warnings) -> frames``; it appends what it has to say about
#: the input to ``warnings`` (the list of the read that called it, returned with the read's result)
Reader = Callable[[Any, Kind, str, list[str]], Frames]
#: a pickle format's test of an object whose top level is of its layout (for "list": the first entry, every
#: entry known to be a dict): True when it is this format; InputError when it is this format, but cannot
#: hold ``kind`` (ground-truth infos given as detections)
Claim = Callable[[Any, Kind, str], bool]

#: how messages call an entry of each kind
KIND_WORD = {"ground_truth": "ground-truth", "detections": "result"}


@dataclass(frozen=True)
class Format:
    """One input format, as the registry (:mod:`kitti_eval.io.formats`) holds it.

    ``layout`` is what the file holds at its top level: a list of per-frame dicts, a dict, or (KITTI txt)
    a folder of files. A pickle format has a ``reader``, and a ``claims`` test by which detection knows it;
    a ``generic`` format is tried after the specific ones of its layout (it claims what they leave).
    """

    name: str
    layout: Literal["list", "dict", "folder"]
    reader: Reader | None = None
    claims: Claim | None = None
    generic: bool = False


def expected_layouts(kind: Kind) -> str:
    """What a pickle of ``kind`` should hold, for messages."""
    expected = (
        "a list of per-frame dicts (OpenPCDet kitti_infos_*.pkl, or annos dicts with frame_id)"
        if kind == "ground_truth"
        else "a list of per-frame dicts (OpenPCDet result.pkl)"
    )
    return expected + ", or a dict {frame id: annos dict}"


def check_kind(kind: str) -> None:
    if kind not in KIND_WORD:
        raise ValueError(f"kind must be 'ground_truth' or 'detections', got {kind!r}")


def type_name(obj: object) -> str:
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
        return f"a {kind} of {len(obj)} entries, the first {type_name(first)}"
    if isinstance(obj, Mapping):
        names = list(obj.keys())
        shown = ", ".join(repr(k) for k in names[:6]) + (", ..." if len(names) > 6 else "")
        return f"a dict with {len(names)} keys [{shown}]"
    return type_name(obj)


_ID_TYPES = (str, int, bytes, np.str_, np.integer)


def frame_id(value: object, what: str, source: str, frame: str) -> object:
    """A raw frame id of an accepted type (0-d arrays unwrapped); the rest is from_frames' job."""
    if type(value) is str:  # what most files hold, first
        return value
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if not isinstance(value, _ID_TYPES) or isinstance(value, (bool, np.bool_)):
        raise InputError(
            f"{what} is {type_name(value)}, expected a string or an integer",
            source=source,
            frame=frame,
            field="frame_id",
        )
    return value
