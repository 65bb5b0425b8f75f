"""Small hand-made scenes for protocol tests: boxes written out, nothing random."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kitti_eval.core.frames import Annotations


def box(
    name: str = "Car",
    *,
    x: float = 0.0,
    z: float = 20.0,
    y: float = 1.6,
    dims: Sequence[float] = (3.9, 1.5, 1.6),
    ry: float = 0.0,
    alpha: float = 0.0,
    x1: float = 100.0,
    y1: float = 150.0,
    width_px: float = 80.0,
    height_px: float = 60.0,
    truncated: float = 0.0,
    occluded: float = 0.0,
    score: float | None = None,
    bbox: Sequence[float] | None = None,
) -> dict[str, Any]:
    """One object; dims are (l, h, w); bbox defaults to (x1, y1, x1 + width_px, y1 + height_px)."""
    b = dict(
        name=name,
        truncated=truncated,
        occluded=occluded,
        alpha=alpha,
        bbox=list(bbox) if bbox is not None else [x1, y1, x1 + width_px, y1 + height_px],
        dimensions=list(dims),
        location=[x, y, z],
        rotation_y=ry,
    )
    if score is not None:
        b["score"] = score
    return b


def dontcare(
    bbox: Sequence[float],
    *,
    location: Sequence[float] = (-1000.0, -1000.0, -1000.0),
    dims: Sequence[float] = (-1.0, -1.0, -1.0),
) -> dict[str, Any]:
    """A KITTI DontCare line: a 2D region, with the -1000 / -1 placeholders for 3D unless given."""
    return dict(
        name="DontCare",
        truncated=-1.0,
        occluded=-1.0,
        alpha=-10.0,
        bbox=list(bbox),
        dimensions=list(dims),
        location=list(location),
        rotation_y=-10.0,
    )


def annotations(kind: str, frames: Sequence[Sequence[dict[str, Any]]], ids: Sequence[str] | None = None) -> Annotations:
    """Frames given as lists of :func:`box` dicts."""
    ids = list(ids) if ids is not None else [f"{i:06d}" for i in range(len(frames))]
    fields = ["name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y"]
    if kind == "detections":
        fields.append("score")
    out = []
    for fid, objs in zip(ids, frames):
        d: dict[str, Any] = {}
        for f in fields:
            vals = [o[f] for o in objs]
            if f == "name":
                d[f] = np.array(vals, dtype="<U20")
            elif f in ("bbox",):
                d[f] = np.array(vals, dtype=np.float64).reshape(-1, 4)
            elif f in ("dimensions", "location"):
                d[f] = np.array(vals, dtype=np.float64).reshape(-1, 3)
            else:
                d[f] = np.array(vals, dtype=np.float64)
        out.append((fid, d))
    return Annotations.from_frames(kind, f"<{kind}>", out)  # type: ignore[arg-type]


def one_car_per_frame(n: int, **kw: Any) -> list[list[dict[str, Any]]]:
    """``n`` frames with one Car each (same placement in every frame)."""
    return [[box("Car", **kw)] for _ in range(n)]


def hits(n: int, top: float = 0.99, step: float = 0.01, **kw: Any) -> list[list[dict[str, Any]]]:
    """Perfect detections of :func:`one_car_per_frame`, scores descending frame by frame."""
    return [[box("Car", score=round(top - i * step / 10, 6), **kw)] for i in range(n)]
