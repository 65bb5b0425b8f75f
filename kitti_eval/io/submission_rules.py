"""The rules of a benchmark submission and their checks, on predictions already read (a pickle's) or on a folder
of result txt files; :mod:`kitti_eval.io.submission` reads a file and checks it, and says what is checked.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..core.frames import Annotations, normalize_frame_id
from ..core.protocol import KITTI_CLASSES
from ..errors import InputError
from .formats.kitti_txt import parse_kitti_txt, read_bytes, txt_files

__all__ = [
    "KITTI_RESULT_CLASSES",
    "SubmissionRules",
    "Validation",
    "validate_annotations",
    "validate_txt_folder",
]

#: the classes a result may name (compared case-insensitively): KITTI's object classes
KITTI_RESULT_CLASSES = KITTI_CLASSES
#: frames named in one sentence before "and N more"
_SHOWN_FRAMES = 20


@dataclass(frozen=True)
class SubmissionRules:
    """What a submission must satisfy besides being readable."""

    #: the test frame ids (normalised: ``"15"`` and ``"000015"`` are one frame)
    frames: tuple[str, ...]
    #: class names accepted in a result (compared case-insensitively)
    classes: tuple[str, ...] = KITTI_RESULT_CLASSES
    #: boxes a frame may hold (KITTI val averages about 40 detections a frame before score thresholds)
    max_boxes_per_frame: int = 1000
    #: problems listed; past it one last sentence says how many more there were
    max_problems: int = 100
    #: what the frames are called: ``"test"`` (a sealed test set) or ``"validation"`` (a set on open labels)
    labels: str = "test"

    def __post_init__(self) -> None:
        if not self.frames:
            raise ValueError("a test set has at least one frame")
        if self.labels not in ("test", "validation"):
            raise ValueError("labels is 'test' or 'validation'")
        if self.max_boxes_per_frame < 1 or self.max_problems < 1:
            raise ValueError("max_boxes_per_frame and max_problems must be >= 1")


@dataclass
class Validation:
    """The outcome: ``problems`` (sentences, in the order found) is empty when the submission is valid."""

    problems: list[str] = field(default_factory=list)
    frames: int = 0
    boxes: int = 0
    #: problems found beyond ``max_problems`` (not listed)
    more: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self) -> list[str]:
        """The problems as they are shown, one a line, with the count of those left out."""
        tail = [f"... and {self.more} more problems"] if self.more else []
        return [*self.problems, *tail]


class _Collector:
    def __init__(self, rules: SubmissionRules) -> None:
        self.rules = rules
        self.out = Validation()
        self.known = {c.lower() for c in rules.classes}

    def problem(self, text: str) -> None:
        if len(self.out.problems) < self.rules.max_problems:
            self.out.problems.append(text)
        else:
            self.out.more += 1

    def frame(self, where: str, names: Sequence[str], values: Sequence[float] | None, width: int) -> None:
        """One frame's boxes: class names, box count, finite numbers (``values``: ``width`` a box)."""
        self.out.frames += 1
        self.out.boxes += len(names)
        if len(names) > self.rules.max_boxes_per_frame:
            self.problem(f"{where}: {len(names)} boxes; a frame may hold at most {self.rules.max_boxes_per_frame}")
        for k, name in enumerate(names):
            if str(name).lower() not in self.known:
                shown = str(name)[:40]
                self.problem(
                    f"{where}, box {k + 1}: unknown class {shown!r}; a result names one of "
                    f"{', '.join(self.rules.classes)}"
                )
                break  # one a frame: a model that writes another name writes it everywhere
        if values is not None:
            for k, v in enumerate(values):
                if not math.isfinite(v):
                    self.problem(f"{where}, box {k // width + 1}: a number that is not finite ({v})")
                    break

    def frame_set(self, seen: Collection[str]) -> None:
        wanted = set(self.rules.frames)
        missing = [f for f in self.rules.frames if f not in seen]
        extra = sorted(f for f in seen if f not in wanted)
        if missing:
            self.problem(f"{len(missing)} {self.rules.labels} frames are missing: {_shown(missing)}")
        if extra:
            self.problem(f"{len(extra)} frames are not in the {self.rules.labels} set: {_shown(extra)}")


def _shown(frames: Sequence[str]) -> str:
    more = len(frames) - _SHOWN_FRAMES
    return ", ".join(frames[:_SHOWN_FRAMES]) + (f" and {more} more" if more > 0 else "")


def validate_annotations(annos: Annotations, rules: SubmissionRules, collector: _Collector | None = None) -> Validation:
    """The checks of :func:`kitti_eval.io.submission.validate_submission` on predictions already loaded (a pickle's)."""
    c = collector or _Collector(rules)
    c.frame_set(set(annos.frame_ids))
    for i, fid in enumerate(annos.frame_ids):
        lo, hi = int(annos.offsets[i]), int(annos.offsets[i + 1])
        c.frame(f"frame {fid}", annos.name[lo:hi].tolist(), None, 1)
    return c.out


def validate_txt_folder(folder: Path, rules: SubmissionRules, *, shown_as: str | None = None) -> Validation:
    """The checks of :func:`kitti_eval.io.submission.validate_submission` on a folder of result txt files (an
    archive unpacked into it: ``shown_as`` names the archive)."""
    c = _Collector(rules)
    files: dict[str, Path] = {}
    for path in sorted(txt_files(folder), key=lambda q: q.name):
        try:
            fid = normalize_frame_id(path.stem)
        except (TypeError, ValueError):
            c.problem(f"{path.name}: not a frame's file (a result file is named <frame>.txt, e.g. 000042.txt)")
            continue
        if fid in files:
            c.problem(f"{path.name}: frame {fid} is also in {files[fid].name}")
            continue
        files[fid] = path
    if not files and shown_as is not None:
        c.problem(f"{shown_as}: no result txt files")
    c.frame_set(files)
    wanted = set(rules.frames)
    for fid, path in files.items():
        if fid not in wanted:
            continue  # named above; what it holds does not matter
        try:
            names, values = parse_kitti_txt(read_bytes(path), "detections", frame=fid, source=path.name)
        except InputError as e:
            c.out.frames += 1
            c.problem(f"{path.name}: {e.message}")
            continue
        c.frame(path.name, names, values, 15)
    return c.out
