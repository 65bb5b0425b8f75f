"""The outcome of an evaluation: an immutable record with a versioned JSON form."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import ConfigError, InputError
from .ap import Curve
from .protocol import (
    ALL_METRICS,
    DEFAULT_OSET,
    DEFAULT_RECALL,
    DIFFICULTIES,
    METRICS,
    RECALL_MODES,
    THRESHOLD_SETS,
    Difficulty,
    Metric,
)

__all__ = ["EvalResult", "SCHEMA_VERSION", "ValueKey", "ERROR_TYPES", "AOS_TYPES"]

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


#: the error types of AP (bbox, bev, 3d), in the order they are shown (kitti_eval.analysis.decomposition counts them)
ERROR_TYPES: tuple[str, ...] = ("classification", "localization", "both", "duplicate", "background", "missed")
#: AOS adds orientation
AOS_TYPES: tuple[str, ...] = (*ERROR_TYPES, "orientation")


@dataclass(frozen=True, order=True)
class ValueKey:
    """One value of the result: class, metric, difficulty, recall mode, threshold set."""

    cls: str
    metric: str
    difficulty: str
    recall: str = DEFAULT_RECALL
    oset: str = DEFAULT_OSET
    #: an error type of the decomposition ("" for the AP itself)
    error: str = ""

    @classmethod
    def parse(cls, text: str) -> ValueKey:
        parts = [p.strip() for p in text.strip().split("/")]
        if not 3 <= len(parts) <= 5 or not all(parts):
            raise ConfigError(
                f"expected Class/metric/difficulty[/R40|R11[/strict|loose]] or Class/metric/difficulty/"
                f"<error type>[/R40|R11], got {text!r}"
            )
        if len(parts) >= 4 and parts[3] in AOS_TYPES:
            if len(parts) == 5 and parts[4] not in RECALL_MODES:
                raise ConfigError(f"unknown recall mode {parts[4]!r} in {text!r}; expected R40 or R11")
            if parts[3] == "orientation" and parts[1] != "aos":
                raise ConfigError(f"orientation errors are an AOS type: write {parts[0]}/aos/{parts[2]}/orientation")
            key = cls(parts[0], parts[1], parts[2], parts[4] if len(parts) == 5 else "R40", "strict", parts[3])
        else:
            key = cls(*parts)
        if key.metric not in METRICS:
            raise ConfigError(f"unknown metric {key.metric!r} in {text!r}; expected one of {', '.join(METRICS)}")
        if key.difficulty not in DIFFICULTIES:
            raise ConfigError(
                f"unknown difficulty {key.difficulty!r} in {text!r}; expected one of {', '.join(DIFFICULTIES)}"
            )
        if key.recall not in RECALL_MODES:
            raise ConfigError(f"unknown recall mode {key.recall!r} in {text!r}; expected R40 or R11")
        if key.oset not in THRESHOLD_SETS:
            raise ConfigError(f"unknown threshold set {key.oset!r} in {text!r}; expected strict or loose")
        return key

    def __str__(self) -> str:
        if self.error:
            return f"{self.cls}/{self.metric}/{self.difficulty}/{self.error}/{self.recall}"
        return f"{self.cls}/{self.metric}/{self.difficulty}/{self.recall}/{self.oset}"

    def read(self, doc: Mapping[str, Any]) -> float | None:
        """The value in a result document; a class or key the document lacks is an error."""
        if self.error:
            return self._read_error(doc)
        try:
            by_cls = doc["ap"][self.oset][self.recall]
        except (KeyError, TypeError):
            raise InputError(f"the result has no AP table for {self.recall}/{self.oset}") from None
        if self.cls not in by_cls:
            raise InputError(f"the result has no class {self.cls!r} (it has {', '.join(by_cls) or 'none'})")
        value = by_cls[self.cls][self.metric][self.difficulty]
        return None if value is None else float(value)

    def find(self, doc: Mapping[str, Any]) -> float | None:
        """The value in a result document, None where the document has none (no such class, table or key)."""
        try:
            return self.read(doc)
        except (InputError, KeyError, TypeError, AttributeError):
            return None

    def _read_error(self, doc: Mapping[str, Any]) -> float | None:
        table = doc.get("errors" if self.recall == "R40" else "errors_r11")
        if not isinstance(table, Mapping):
            raise InputError(
                f"the result has no error decomposition for {self}: evaluate with --errors (or gate --gt/--pred)"
            )
        if self.cls not in table:
            raise InputError(f"the error decomposition has no class {self.cls!r} (it has {', '.join(table)})")
        types = table[self.cls][self.metric][self.difficulty]
        value = None if types is None else types.get(self.error)
        return None if value is None else float(value)
