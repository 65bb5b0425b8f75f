"""A dict ``{frame id: annos dict}`` (PointPillars style); for ground truth the values may also be info dicts
holding ``annos``. The generic dict: a dict that no other format claims is read as this one."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ...core.frames import Kind
from ...errors import InputError
from ._common import Format, Frames, describe_format, expected_layouts, frame_id

__all__ = ["ANNOS_BY_FRAME"]

#: keys of one frame's annos dict: a dict holding them is one frame, not a dict of frames
_ANNOS_KEYS = frozenset({"name", "bbox", "dimensions", "location", "rotation_y"})


def _claims(obj: Mapping[Any, Any], kind: Kind, source: str) -> bool:
    if _ANNOS_KEYS & obj.keys():
        raise InputError(
            f"this is a single frame's annos dict ({describe_format(obj)}); expected one per frame: "
            f"{expected_layouts(kind)}",
            source=source,
        )
    if not obj:
        raise InputError("the pickle holds an empty dict: no frames", source=source)
    return True


def _read(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    for pos, (key, value) in enumerate(obj.items()):
        key = frame_id(key, f"key #{pos} of the dict", source, f"#{pos}")
        if kind == "ground_truth" and isinstance(value, Mapping) and "annos" in value and "name" not in value:
            value = value["annos"]  # an info dict keyed by frame (PointPillars kitti_infos_*.pkl)
        yield key, value


#: ``annos_by_frame``
ANNOS_BY_FRAME = Format("annos_by_frame", "dict", _read, _claims, generic=True)
