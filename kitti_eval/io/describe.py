"""What a ground-truth or prediction file holds, before evaluating it (``kitti-eval describe FILE``).

Reports the detected format, whether it reads as ground truth or predictions, frames (and empty ones),
boxes per class, the dtypes of the stored fields, the dimension-order check, and for predictions that
carry both camera fields and ``boxes_lidar`` whether the two agree (yaw and dimensions always; locations
too when ``--gt`` names infos with calibration). Raises InputError when the file cannot be read safely.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..core.frames import Annotations, Kind, dimension_order_warnings
from ..errors import InputError

__all__ = ["describe", "KINDS"]

#: ``--kind`` values and what they read a file as
KINDS: dict[str, Kind] = {"gt": "ground_truth", "pred": "detections"}


def _first_frames(obj: object) -> list[Mapping[str, Any]]:
    """Per-frame field dicts of a pickle, for dtypes and the camera/LiDAR check (no validation)."""
    if isinstance(obj, Mapping) and "data_list" in obj:
        return []
    values = obj.values() if isinstance(obj, Mapping) else obj if isinstance(obj, (list, tuple)) else ()
    out = []
    for v in values:
        if isinstance(v, Mapping):
            out.append(v["annos"] if isinstance(v.get("annos"), Mapping) else v)
    return out


class _PseudoCalibs(dict):
    """Identity calibration for every frame: enough to count LiDAR-only boxes (not to evaluate them)."""

    def get(self, key, default=None):  # noqa: ANN001, ANN201
        from .calib import Calib

        return Calib(np.eye(4), np.eye(4)[:3], None)

    def __bool__(self) -> bool:
        return True


def _guess_kind(fmt: str, frames: Sequence[Mapping[str, Any]]) -> Kind:
    if fmt in ("openpcdet_infos", "mmdet3d_infos"):
        return "ground_truth"
    if fmt == "mmdet3d_results":
        return "detections"
    for f in frames:
        if "boxes_lidar" in f or "gt_boxes_lidar" in f:
            return "detections" if "boxes_lidar" in f else "ground_truth"
        score = np.asarray(f.get("score", ()))
        if score.size:
            return "ground_truth" if np.all(score == -1) else "detections"
    return "detections"


def _lidar_check(frames: Sequence[Mapping[str, Any]], calibs: Mapping[str, Any], lines: list[str]) -> None:
    from ..core.frames import normalize_frame_id
    from .calib import camera_lidar_disagreement, wrap_angle

    both = [f for f in frames if "boxes_lidar" in f and all(k in f for k in ("location", "dimensions", "rotation_y"))]
    lidar_only = [f for f in frames if "boxes_lidar" in f and "location" not in f]
    if lidar_only:
        lines.append(
            f"LiDAR-only frames: {len(lidar_only)} (boxes_lidar without camera fields; evaluating them "
            "needs infos with calibration as --gt)"
        )
    if not both:
        return
    total = bad = bad_frames = 0
    located = 0
    for f in both:
        lidar = np.asarray(f["boxes_lidar"], dtype=np.float64).reshape(-1, 7)
        ry = np.asarray(f["rotation_y"], dtype=np.float64).reshape(-1)
        dims = np.asarray(f["dimensions"], dtype=np.float64).reshape(-1, 3)
        if len(lidar) != len(ry) or len(dims) != len(ry):
            bad += len(ry)
            bad_frames += 1
            total += len(ry)
            continue
        wrong = (np.abs(wrap_angle(ry - wrap_angle(-lidar[:, 6] - np.pi / 2))) > 0.1) | (
            np.abs(dims - lidar[:, [3, 5, 4]]).max(axis=1, initial=0) > 0.1
        )
        n = int(wrong.sum())
        calib = None
        fid = f.get("frame_id", f.get("sample_idx"))
        if calibs and fid is not None:
            try:
                calib = calibs.get(normalize_frame_id(np.asarray(fid).reshape(-1)[0] if np.ndim(fid) else fid))
            except (TypeError, ValueError, IndexError):
                calib = None
        if calib is not None and len(lidar):
            located += 1
            n = max(n, camera_lidar_disagreement(f["location"], ry, lidar, calib))
        total += len(ry)
        bad += n
        bad_frames += n > 0
    what = "yaw, dimensions and location" if located else "yaw and dimensions (give --gt infos to check locations)"
    verdict = "DISAGREE" if total and bad > 0.01 * total else "agree"
    lines.append(
        f"camera vs LiDAR boxes ({what}): {verdict}: {bad} of {total} boxes differ by > 0.1 m or "
        f"> 0.1 rad, in {bad_frames} of {len(both)} frames"
    )


def describe(path: str | Path, kind: str | None = None, gt: str | Path | None = None) -> str:
    """The report for one file (raises InputError when it cannot be read)."""
    from .camera import calibs_from_object
    from .formats import detect_format
    from .formats.kitti_txt import is_archive
    from .reading import LoadOptions, read_annotations, read_object
    from .safe_pickle import load_pickle

    p = Path(path)
    if not p.exists():
        raise InputError("no such file or directory", source=str(path))
    lines = [f"file: {path}"]
    frames: list[Mapping[str, Any]] = []
    want: Kind | None = KINDS[kind] if kind else None
    if p.is_dir() or is_archive(p):
        fmt = "kitti_txt " + ("folder" if p.is_dir() else "archive")
        kinds: list[Kind] = [want] if want else ["detections", "ground_truth"]
        annos: Annotations | None = None
        for k in kinds:
            try:
                annos = read_annotations(p, k).annotations
                break
            except InputError:
                if k == kinds[-1]:
                    raise
        assert annos is not None
    else:
        obj = load_pickle(p, source=str(path))
        frames = _first_frames(obj)
        guess = want
        if guess is None:
            try:
                fmt0 = detect_format(obj, "ground_truth", source=str(path))
            except InputError:
                fmt0 = detect_format(obj, "detections", source=str(path))
            guess = _guess_kind(fmt0, frames)
        fmt = detect_format(obj, guess, source=str(path))
        calibs = calibs_from_object(obj) if guess == "ground_truth" else {}
        if gt is not None:
            calibs = calibs_from_object(load_pickle(Path(gt), source=str(gt)))
        if guess == "detections" and not calibs and any("boxes_lidar" in f and "location" not in f for f in frames):
            # LiDAR-only boxes cannot become camera boxes without calibration: count what is there
            annos = read_object(obj, guess, str(path), LoadOptions(calibs=_PseudoCalibs())).annotations
        else:
            annos = read_object(obj, guess, str(path), LoadOptions(calibs=calibs)).annotations
        if guess == "detections":
            _lidar_check(frames, calibs, lines)
        if frames:
            first = next((f for f in frames if np.size(f.get("name", ())) > 0), frames[0])
            dtypes = ", ".join(
                f"{k} {np.asarray(v).dtype}{list(np.shape(v))[1:] or ''}"
                for k, v in first.items()
                if isinstance(v, np.ndarray)
            )
            lines.append(f"fields (first non-empty frame): {dtypes}")
    lines.insert(1, f"format: {fmt}")
    lines.insert(2, f"kind: {'ground truth' if annos.kind == 'ground_truth' else 'predictions'}")
    empty = int(np.count_nonzero(annos.counts == 0))
    lines.insert(3, f"frames: {annos.num_frames} ({empty} empty); boxes: {annos.num_boxes}")
    names, counts = np.unique(annos.name, return_counts=True)
    per_class = ", ".join(f"{n} {c}" for n, c in zip(names.tolist(), counts.tolist())) or "none"
    lines.insert(4, f"boxes per class: {per_class}")
    if annos.kind == "detections" and annos.num_boxes:
        lines.insert(5, f"scores: {annos.score.min():.4g} .. {annos.score.max():.4g}")
    dim_warnings = dimension_order_warnings(annos)
    lines.append("dimension order: " + ("; ".join(dim_warnings) if dim_warnings else "looks like (l, h, w)"))
    return "\n".join(lines) + "\n"
