"""The outcome of an evaluation: an immutable record with a versioned JSON form."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .ap import Curve
from .protocol import ALL_METRICS, DEFAULT_OSET, DEFAULT_RECALL, Difficulty, Metric

__all__ = ["EvalResult", "SCHEMA_VERSION"]

#: Version of the JSON layout written by :meth:`EvalResult.to_dict`; bumped on any incompatible change.
SCHEMA_VERSION = 1

# ap[threshold_set][recall][class][metric][difficulty] -> percent, or None where not evaluated
APTable = Mapping[str, Mapping[str, Mapping[str, Mapping[str, Mapping[str, float | None]]]]]


@dataclass(frozen=True)
class EvalResult:
    """Average precision for every threshold set x recall mode x class x metric x difficulty.

    ``ap[oset][recall][cls][metric][difficulty]`` is a percentage, or ``None`` where the protocol does not
    evaluate that value (official protocol: AOS when an alpha is -10, a class no detection can be
    scored on). ``curves`` (optional) holds the 41-point curves behind each value, keyed
    ``[oset][cls][metric][difficulty]``.
    """

    protocol: str
    classes: tuple[str, ...]
    threshold_sets: tuple[str, ...]
    overlaps: Mapping[str, Mapping[str, Mapping[str, float]]]
    ap: APTable
    num_gt: Mapping[str, Mapping[str, int]]
    num_det: Mapping[str, int]
    frames: int
    frames_without_predictions: tuple[str, ...]
    aos_evaluated: bool
    warnings: tuple[str, ...] = ()
    curves: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Curve]]]] | None = field(default=None, repr=False)
    #: seconds spent per stage (align, overlaps, matching, ap); not part of the JSON document
    timings: Mapping[str, float] = field(default_factory=dict, repr=False, compare=False)
    #: per distance range asked for: {"label", "min", "max" (metres; inf for open), "ap" (same layout as
    #: ``ap``), "num_gt" (valid ground truth in the range per class and difficulty)}
    ranges: tuple[Mapping[str, Any], ...] = ()
    #: COCO-style AP when asked for: ``coco[recall][class][metric][difficulty]``, the mean over the class's
    #: ten IoU thresholds (:func:`kitti_eval.core.protocol.coco_thresholds`); None otherwise
    coco: Mapping[str, Any] | None = None

    def get(
        self,
        cls: str,
        metric: str | Metric,
        difficulty: str | Difficulty,
        recall: str = DEFAULT_RECALL,
        oset: str = DEFAULT_OSET,
    ) -> float | None:
        """One value, e.g. ``result.get("Car", "3d", "moderate")`` (R40, strict thresholds)."""
        m = Metric(metric).value
        d = difficulty.label if isinstance(difficulty, Difficulty) else str(difficulty)
        return self.ap[oset][recall][cls][m][d]

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> EvalResult:
        """Back from :meth:`to_dict` (curves and timings are not kept), e.g. to render a stored result."""
        if doc.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"expected schema_version {SCHEMA_VERSION}, got {doc.get('schema_version')!r}")
        return cls(
            protocol=doc["protocol"],
            classes=tuple(doc["classes"]),
            threshold_sets=tuple(doc["threshold_sets"]),
            overlaps=copy.deepcopy(doc["overlaps"]),
            ap=copy.deepcopy(doc["ap"]),
            num_gt=copy.deepcopy(doc["num_gt"]),
            num_det=dict(doc["num_det"]),
            frames=int(doc["frames"]),
            frames_without_predictions=tuple(doc["frames_without_predictions"]),
            aos_evaluated=bool(doc["aos_evaluated"]),
            warnings=tuple(doc["warnings"]),
            ranges=tuple({**r, "max": math.inf if r["max"] is None else r["max"]} for r in doc.get("ranges", [])),
            coco=copy.deepcopy(doc.get("coco")),
        )

    def to_dict(self, *, include_curves: bool = False) -> dict[str, Any]:
        """The JSON form (schema version :data:`SCHEMA_VERSION`); every key is always present."""
        out: dict[str, Any] = {
            "schema_version": SCHEMA_VERSION,
            "protocol": self.protocol,
            "classes": list(self.classes),
            "threshold_sets": list(self.threshold_sets),
            "metrics": [m.value for m in ALL_METRICS],
            "difficulties": [d.label for d in Difficulty],
            "overlaps": copy.deepcopy(_plain(self.overlaps)),
            "ap": copy.deepcopy(_plain(self.ap)),
            "num_gt": copy.deepcopy(_plain(self.num_gt)),
            "num_det": dict(self.num_det),
            "frames": self.frames,
            "frames_without_predictions": list(self.frames_without_predictions),
            "aos_evaluated": self.aos_evaluated,
            "warnings": list(self.warnings),
            "ranges": [
                {
                    "label": r["label"],
                    "min": r["min"],
                    "max": None if math.isinf(r["max"]) else r["max"],
                    "ap": copy.deepcopy(_plain(r["ap"])),
                    "num_gt": copy.deepcopy(_plain(r["num_gt"])),
                }
                for r in self.ranges
            ],
            "coco": copy.deepcopy(_plain(self.coco)) if self.coco is not None else None,
        }
        if include_curves and self.curves is not None:
            out["curves"] = {
                oset: {
                    cls: {
                        m: {
                            d: {
                                "precision": [float(v) for v in (c.orientation if m == "aos" else c.precision)],
                                "recall": [float(v) for v in c.recall],
                                "thresholds": [float(v) for v in c.thresholds],
                                "num_valid_gt": c.num_valid_gt,
                            }
                            for d, c in by_d.items()
                        }
                        for m, by_d in by_m.items()
                    }
                    for cls, by_m in by_cls.items()
                }
                for oset, by_cls in self.curves.items()
            }
        return out


def _plain(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {k: _plain(v) for k, v in obj.items()}
    return obj
