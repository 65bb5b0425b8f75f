"""mmdetection3d 1.x: the v2 infos (``{'metainfo', 'data_list'}``: ground truth; names from
``metainfo['categories']``, ``bbox_label`` -1 is DontCare, ``bbox_3d`` = x y z l h w ry in the camera frame,
bottom centre; frame ids from ``sample_idx``) and its KITTI-format result dicts (OpenPCDet's fields plus
``sample_idx``, an int or an array repeating it per box; entries with no boxes and no id are skipped)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ...core.frames import Kind, shown_frame_id
from ...errors import InputError
from ..calib import Calib
from ._common import KIND_WORD, Format, Frames, frame_id, type_name

__all__ = ["INFOS", "RESULTS", "calib"]


def _claims_infos(obj: Mapping[Any, Any], kind: Kind, source: str) -> bool:
    if not ("data_list" in obj and "metainfo" in obj):
        return False
    if kind == "detections":
        raise InputError(
            "this is an mmdetection3d 1.x info file (metainfo/data_list: ground-truth "
            "labels), not detections; pass it as the ground truth",
            source=source,
        )
    return True


def _read_infos(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
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
                f"data_list entry #{i} is {type_name(entry)}, expected a dict", source=source, frame=f"#{i}"
            )
        if entry.get("sample_idx") is None:
            raise InputError(
                f"data_list entry #{i} has no sample_idx", source=source, frame=f"#{i}", field="sample_idx"
            )
        fid = frame_id(entry["sample_idx"], f"data_list entry #{i}: sample_idx", source, f"#{i}")
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
                f"'instances' is {type_name(instances)}, expected a list",
                source=source,
                frame=shown,
                field="instances",
            )
        yield fid, _instances(instances, label2cat, source, shown)


def _instances(instances: Sequence[Any], label2cat: Mapping[int, str], source: str, frame: str) -> dict[str, Any]:
    n = len(instances)
    names: list[str] = []
    cols: dict[str, list[Any]] = {k: [] for k in ("bbox", "bbox_3d", "truncated", "occluded", "alpha")}
    for j, inst in enumerate(instances):
        if not isinstance(inst, Mapping):
            raise InputError(f"instance #{j} is {type_name(inst)}, expected a dict", source=source, frame=frame)
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


def _claims_results(first: Mapping[str, Any], kind: Kind, source: str) -> bool:
    return "sample_idx" in first and "frame_id" not in first and "name" in first


def _read_results(obj: Any, kind: Kind, source: str, warnings: list[str]) -> Frames:
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
                    f"{KIND_WORD[kind]} entry #{i} has boxes but an empty sample_idx",
                    source=source,
                    frame=f"#{i}",
                    field="sample_idx",
                )
            if len(uniq) > 1:
                raise InputError(
                    f"{KIND_WORD[kind]} entry #{i}: sample_idx holds several frames {uniq[:4].tolist()}",
                    source=source,
                    frame=f"#{i}",
                    field="sample_idx",
                )
            raw = uniq[0]
        if raw is None:
            raise InputError(
                f"{KIND_WORD[kind]} entry #{i} has no sample_idx (frames are matched by id, never by position)",
                source=source,
                frame=f"#{i}",
                field="sample_idx",
            )
        yield frame_id(raw, f"{KIND_WORD[kind]} entry #{i}: sample_idx", source, f"#{i}"), entry


def calib(entry: Mapping[str, Any]) -> Calib:
    """The calibration of a ``data_list`` entry (``images.CAM2``: ``lidar2cam``, ``cam2img``, its size)."""
    cam = entry["images"]["CAM2"]
    p2 = np.asarray(cam["cam2img"], dtype=np.float64)
    p2 = np.pad(p2, ((0, 3 - p2.shape[0]), (0, 4 - p2.shape[1]))) if p2.shape != (4, 4) else p2[:3]
    shape = (int(cam["height"]), int(cam["width"])) if "height" in cam else None
    return Calib(np.asarray(cam["lidar2cam"], dtype=np.float64).reshape(4, 4), p2, shape)


#: ``mmdet3d_infos``
INFOS = Format("mmdet3d_infos", "dict", _read_infos, _claims_infos)
#: ``mmdet3d_results``
RESULTS = Format("mmdet3d_results", "list", _read_results, _claims_results)
