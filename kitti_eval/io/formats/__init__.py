"""The input formats, one module each (detection and reading side by side), in one registry.

==================  ====================================================================================
``openpcdet_infos``  list of OpenPCDet info dicts (``image``/``point_cloud``/``annos``): ground truth
``annos_list``       list of annos dicts that carry ``frame_id`` (OpenPCDet ``result.pkl``; for ground
                     truth, plain annos dicts with ``frame_id``)
``annos_by_frame``   dict ``{frame id: annos dict}`` (PointPillars style; for ground truth the values may
                     also be info dicts holding ``annos``)
``mmdet3d_infos``    mmdetection3d 1.x info dict ``{'metainfo', 'data_list'}``: ground truth
``mmdet3d_results``  list of mmdetection3d KITTI-format result dicts (``sample_idx``)
``kitti_txt``        a folder of KITTI txt files (or a zip/tar of one)
==================  ====================================================================================

A new format is a module here that makes a :class:`Format` (its ``claims`` test and its ``reader``), and
one entry in :data:`REGISTRY`.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from ...core.frames import Kind
from ...errors import InputError
from . import annos_by_frame, kitti_txt, mmdet3d, openpcdet
from ._common import KIND_WORD, Format, Reader, describe_format, expected_layouts, type_name

__all__ = ["Format", "REGISTRY", "FORMATS", "PICKLE_FORMATS", "detect_format", "check_layout", "describe_format"]

#: every format by name, in the order options and messages list them
REGISTRY: Mapping[str, Format] = MappingProxyType(
    {
        f.name: f
        for f in (
            openpcdet.INFOS,
            openpcdet.ANNOS_LIST,
            annos_by_frame.ANNOS_BY_FRAME,
            mmdet3d.INFOS,
            mmdet3d.RESULTS,
            kitti_txt.KITTI_TXT,
        )
    }
)
#: every format name ``--gt-format`` / ``--pred-format`` accept
FORMATS: tuple[str, ...] = tuple(REGISTRY)
#: pickle format name -> its reader of (frame id, fields) for :meth:`Annotations.from_frames`
PICKLE_FORMATS: Mapping[str, Reader] = MappingProxyType(
    {name: f.reader for name, f in REGISTRY.items() if f.reader is not None}
)


def _in_detection_order(layout: str) -> list[Format]:
    """The pickle formats of ``layout``: the specific ones first, then the generic one."""
    mine = [f for f in REGISTRY.values() if f.layout == layout and f.claims is not None]
    return sorted(mine, key=lambda f: f.generic)


def detect_format(obj: object, kind: Kind, *, source: str) -> str:
    """The name of the pickle layout of ``obj`` (a key of :data:`PICKLE_FORMATS`), or InputError."""
    expected = expected_layouts(kind)
    if isinstance(obj, (list, tuple)):
        for i, entry in enumerate(obj):
            if not isinstance(entry, Mapping):
                raise InputError(
                    f"{KIND_WORD[kind]} entry #{i} is {type_name(entry)}, expected a dict; "
                    f"the file should hold {expected}",
                    source=source,
                    frame=f"#{i}",
                )
        if not obj:
            raise InputError(f"the pickle holds an empty {type(obj).__name__}: no frames", source=source)
        for fmt in _in_detection_order("list"):
            if fmt.claims is not None and fmt.claims(obj[0], kind, source):
                return fmt.name
        raise InputError(
            f"entry #0 has none of the expected keys: found {describe_format(obj)}; expected {expected}",
            source=source,
            frame="#0",
        )
    if isinstance(obj, Mapping):
        for fmt in _in_detection_order("dict"):
            if fmt.claims is not None and fmt.claims(obj, kind, source):
                return fmt.name
    raise InputError(f"expected {expected}; found {describe_format(obj)}", source=source)


def check_layout(obj: Any, fmt: str, source: str) -> None:
    """A forced format must at least have the right top-level type."""
    if REGISTRY[fmt].layout == "dict":
        if not isinstance(obj, Mapping):
            raise InputError(f"format {fmt!r} expects a dict; found {describe_format(obj)}", source=source)
        return
    if not isinstance(obj, (list, tuple)):
        raise InputError(f"format {fmt!r} expects a list; found {describe_format(obj)}", source=source)
    for i, entry in enumerate(obj):
        if not isinstance(entry, Mapping):
            raise InputError(f"entry #{i} is {type_name(entry)}, expected a dict", source=source, frame=f"#{i}")
