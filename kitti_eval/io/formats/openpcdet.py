"""OpenPCDet's pickles: ``kitti_infos_*.pkl`` (a list of info dicts: ground truth) and ``result.pkl`` (a list
of annos dicts that carry ``frame_id``; for ground truth, plain annos dicts with ``frame_id``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ...core.frames import Kind, shown_frame_id
from ...errors import InputError
from ._common import KIND_WORD, Format, Frames, frame_id, type_name

__all__ = ["INFOS", "ANNOS_LIST", "entry_frame_id"]

#: keys of an info dict (one of them, and no ``name``, makes a list of infos)
INFO_KEYS = frozenset({"annos", "image", "point_cloud", "calib"})


def entry_frame_id(entry: Mapping[str, Any], i: int, source: str, fallbacks: list[int] | None = None) -> object:
    """An infos entry's frame id: ``image.image_idx``, else ``point_cloud.lidar_idx`` (the entry's index is then
    added to ``fallbacks``), else ``frame_id``."""
    for parent, key in (("image", "image_idx"), ("point_cloud", "lidar_idx")):
        sub = entry.get(parent)
        if sub is None:
            continue
        if type(sub) is not dict and not isinstance(sub, Mapping):  # a dict, first: the Mapping check is slower
            raise InputError(
                f"infos entry #{i}: '{parent}' is {type_name(sub)}, expected a dict",
                source=source,
                frame=f"#{i}",
                field=parent,
            )
        if sub.get(key) is not None:
            if parent == "point_cloud" and fallbacks is not None:
                fallbacks.append(i)
            return frame_id(sub[key], f"infos entry #{i}: {parent}.{key}", source, f"#{i}")
    if entry.get("frame_id") is not None:
        return frame_id(entry["frame_id"], f"infos entry #{i}: frame_id", source, f"#{i}")
    raise InputError(
        f"infos entry #{i} has no frame id (image.image_idx, point_cloud.lidar_idx or frame_id)",
        source=source,
        frame=f"#{i}",
    )


def _claims_infos(first: Mapping[str, Any], kind: Kind, source: str) -> bool:
    if not (INFO_KEYS & first.keys() and "name" not in first):
        return False
    if kind == "detections":
        raise InputError(
            "this is an OpenPCDet infos file (ground-truth labels), not detections; "
            "pass it as the ground truth and the result.pkl as the predictions",
            source=source,
        )
    return True


def _read_infos(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    fallbacks: list[int] = []
    first = None
    for i, info in enumerate(obj):
        fid = entry_frame_id(info, i, source, fallbacks)
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
        if type(annos) is not dict and not isinstance(annos, Mapping):
            raise InputError(
                f"infos entry #{i}: 'annos' is {type_name(annos)}, expected a dict",
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


def _claims_annos_list(first: Mapping[str, Any], kind: Kind, source: str) -> bool:
    return "name" in first or "frame_id" in first


def _read_annos_list(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
    for i, entry in enumerate(obj):
        fid = entry.get("frame_id")
        if fid is None:
            raise InputError(
                f"{KIND_WORD[kind]} entry #{i} has no frame_id (frames are matched by id, never by position)",
                source=source,
                frame=f"#{i}",
                field="frame_id",
            )
        yield frame_id(fid, f"{KIND_WORD[kind]} entry #{i}: frame_id", source, f"#{i}"), entry


#: ``openpcdet_infos``: a list of OpenPCDet info dicts (``image``/``point_cloud``/``annos``): ground truth
INFOS = Format("openpcdet_infos", "list", _read_infos, _claims_infos)
#: ``annos_list``: a list of annos dicts that carry ``frame_id`` (OpenPCDet's ``result.pkl``); the generic list
ANNOS_LIST = Format("annos_list", "list", _read_annos_list, _claims_annos_list, generic=True)
