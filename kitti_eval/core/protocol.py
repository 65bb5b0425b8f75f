"""The KITTI evaluation protocol as data: every rule the evaluator applies is named here, once.

Two protocols share these tables and differ only in the flags of :class:`Protocol`:

* ``official``: what the KITTI devkit's C++ ``evaluate_object`` computes (DontCare regions suppress false
  positives in 2D, BEV and 3D; AOS is dropped when any detection has alpha = -10; a class, or one of its
  metrics, that no detection could be scored on is not evaluated: ``None``).
* ``openpcdet``: what OpenPCDet's ``get_official_eval_result`` prints (DontCare in 2D only; AOS decided by
  the first detection of the first non-empty frame; every requested class is reported, 0.0 when empty),
  but with exact float64 rotated IoU instead of its float32 GPU kernel.
"""

from __future__ import annotations

import difflib
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum, IntEnum
from types import MappingProxyType
from typing import Any, Literal

import numpy as np

from ..errors import ConfigError

__all__ = [
    "Metric",
    "Difficulty",
    "DifficultyLimits",
    "Protocol",
    "EvalConfig",
    "OVERLAP_METRICS",
    "OVERLAP_INDEX",
    "ALL_METRICS",
    "THRESHOLD_SETS",
    "METRICS",
    "OVERLAP_METRIC_NAMES",
    "DIFFICULTIES",
    "DEFAULT_METRIC",
    "DEFAULT_RECALL",
    "DEFAULT_OSET",
    "RECALL_MODES",
    "DEFAULT_CLASSES",
    "KNOWN_CLASSES",
    "KITTI_CLASSES",
    "CLASS_OVERLAPS",
    "NEIGHBOURS",
    "DONTCARE",
    "N_SAMPLE_PTS",
    "RECALL_SAMPLE_INDICES",
    "INVALID_ALPHA",
    "KITTI_DIFFICULTY",
    "OFFICIAL",
    "OPENPCDET",
    "PROTOCOLS",
    "get_protocol",
    "parse_iou_override",
    "overlaps_from_overrides",
    "DistanceRange",
    "parse_ranges",
    "COCO_IOU_RANGES",
    "COCO_STEPS",
    "coco_thresholds",
    "load_protocol_file",
    "NO_DIFFICULTY",
    "config_from_options",
]


class Metric(str, Enum):
    """What a detection is scored on."""

    BBOX = "bbox"  # 2D image box IoU
    BEV = "bev"  # bird's-eye-view rotated-rectangle IoU in the camera (x, z) plane
    THREE_D = "3d"  # 3D IoU: BEV intersection x overlap of [y - h, y]
    AOS = "aos"  # average orientation similarity, on the 2D matching

    def __str__(self) -> str:
        return self.value


#: Metrics that have their own overlap measure (AOS rides on the 2D matching).
OVERLAP_METRICS: tuple[Metric, ...] = (Metric.BBOX, Metric.BEV, Metric.THREE_D)
ALL_METRICS: tuple[Metric, ...] = (Metric.BBOX, Metric.BEV, Metric.THREE_D, Metric.AOS)
#: Where each overlap metric sits in per-metric triples (thresholds, overlap arrays): bbox 0, BEV 1, 3D 2.
OVERLAP_INDEX: Mapping[Metric, int] = MappingProxyType({m: i for i, m in enumerate(OVERLAP_METRICS)})


class Difficulty(IntEnum):
    """KITTI difficulty levels; cumulative (moderate includes easy, hard includes both)."""

    EASY = 0
    MODERATE = 1
    HARD = 2

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class DifficultyLimits:
    """Per-difficulty limits, indexed by :class:`Difficulty`.

    A ground-truth box is *ignored* (neither a hit nor a miss) when occlusion > max_occlusion, or
    truncation > max_truncation, or its 2D height ``y2 - y1`` (no abs) is **<=** min_height.
    A detection is *ignored* when its 2D height ``|y2 - y1|`` is **<** min_height.
    """

    min_height: tuple[float, float, float] = (40.0, 25.0, 25.0)
    max_occlusion: tuple[float, float, float] = (0.0, 1.0, 2.0)
    max_truncation: tuple[float, float, float] = (0.15, 0.30, 0.50)


KITTI_DIFFICULTY = DifficultyLimits()
#: LiDAR-only evaluation without a difficulty rule: every box counts at every level
NO_DIFFICULTY = DifficultyLimits(
    min_height=(-math.inf,) * 3, max_occlusion=(math.inf,) * 3, max_truncation=(math.inf,) * 3
)

#: The two IoU threshold sets OpenPCDet prints: the official one and a looser one.
THRESHOLD_SETS: tuple[str, ...] = ("strict", "loose")

#: the metrics' names, in the order tables show them: bbox, bev, 3d, aos
METRICS: tuple[str, ...] = tuple(m.value for m in ALL_METRICS)
#: the names of the metrics with an overlap of their own: bbox, bev, 3d
OVERLAP_METRIC_NAMES: tuple[str, ...] = tuple(m.value for m in OVERLAP_METRICS)
#: the difficulties' names, easiest first
DIFFICULTIES: tuple[str, ...] = tuple(d.label for d in Difficulty)
#: the value a single number stands for unless told: the 3D metric, at the R40 recall, of the strict set
DEFAULT_METRIC = Metric.THREE_D.value
DEFAULT_RECALL = "R40"
DEFAULT_OSET = THRESHOLD_SETS[0]

#: IoU a match must *exceed* (strictly), per class and threshold set, as (bbox, bev, 3d).
CLASS_OVERLAPS: Mapping[str, Mapping[str, tuple[float, float, float]]] = MappingProxyType(
    {
        "Car": {"strict": (0.7, 0.7, 0.7), "loose": (0.7, 0.5, 0.5)},
        "Pedestrian": {"strict": (0.5, 0.5, 0.5), "loose": (0.5, 0.25, 0.25)},
        "Cyclist": {"strict": (0.5, 0.5, 0.5), "loose": (0.5, 0.25, 0.25)},
        "Van": {"strict": (0.7, 0.7, 0.7), "loose": (0.7, 0.5, 0.5)},
        "Person_sitting": {"strict": (0.5, 0.5, 0.5), "loose": (0.5, 0.25, 0.25)},
        "Truck": {"strict": (0.7, 0.7, 0.7), "loose": (0.5, 0.5, 0.5)},
    }
)
DEFAULT_CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
#: the object classes of KITTI's labels (DontCare marks regions, it is no object class)
KITTI_CLASSES: tuple[str, ...] = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc")
KNOWN_CLASSES: tuple[str, ...] = tuple(CLASS_OVERLAPS)

#: Ground truth of a neighbour class is ignored for the evaluated class: never a miss, and a detection
#: matched to it is neither a hit nor a false positive. Names compare case-insensitively.
NEIGHBOURS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "car": ("van",),
        "pedestrian": ("person_sitting",),
    }
)
DONTCARE = "DontCare"

#: Precision is sampled at 41 recall steps (0, 1/40, ..., 1).
N_SAMPLE_PTS = 41
#: Which of the 41 samples each AP averages: R40 = samples 1..40, R11 = samples 0, 4, ..., 40.
RECALL_SAMPLE_INDICES: Mapping[str, tuple[int, ...]] = MappingProxyType(
    {
        "R11": tuple(range(0, N_SAMPLE_PTS, 4)),
        "R40": tuple(range(1, N_SAMPLE_PTS)),
    }
)
RECALL_MODES: tuple[str, ...] = ("R11", "R40")
#: COCO-style AP: the mean of the AP at ten IoU thresholds evenly spaced over a per-class interval (the
#: same for bbox, bev and 3d); classes not listed use the first interval.
COCO_IOU_RANGES: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "car": (0.5, 0.95),
        "van": (0.5, 0.95),
        "truck": (0.5, 0.95),
        "pedestrian": (0.25, 0.7),
        "cyclist": (0.25, 0.7),
        "person_sitting": (0.25, 0.7),
    }
)
COCO_STEPS = 10


def did_you_mean(name: str, candidates: Sequence[str]) -> str:
    """``"; did you mean 'Car'?"`` for the candidate closest to a mistyped class name (compared
    case-insensitively), or ``""`` when none is close."""
    by_lower = {c.lower(): c for c in candidates}
    close = difflib.get_close_matches(name.lower(), list(by_lower), n=1, cutoff=0.6)
    return f"; did you mean {by_lower[close[0]]!r}?" if close and close[0] != name.lower() else ""


def coco_thresholds(cls: str) -> tuple[float, ...]:
    """The ten IoU thresholds of a class for COCO-style AP (e.g. Car 0.50, 0.55, ..., 0.95)."""
    lo, hi = COCO_IOU_RANGES.get(cls.lower(), COCO_IOU_RANGES["car"])
    return tuple(float(v) for v in np.linspace(lo, hi, COCO_STEPS))


#: alpha value meaning "no orientation given".
INVALID_ALPHA = -10.0
#: Coordinate meaning "not given" in a KITTI result line (BEV-only or 2D-only submissions).
MISSING_COORD = -1000.0


@dataclass(frozen=True)
class Protocol:
    """The rules on which the two reference evaluators differ."""

    name: str
    #: Metrics in which detections covered by a DontCare region (intersection / detection area above the
    #: class threshold) are not counted as false positives.
    dontcare_metrics: frozenset[Metric]
    #: "all_valid": AOS only if no detection at all has alpha == -10 (devkit);
    #: "first_detection": AOS only if the first detection of the first non-empty frame has alpha != -10.
    aos_rule: Literal["all_valid", "first_detection"]
    #: True: a class/metric no detection can be scored on is not evaluated (None), as the devkit does;
    #: False: it is reported as 0.0.
    skip_undetected: bool
    #: DontCare recognised case-insensitively (devkit) or only as the exact string "DontCare".
    dontcare_case_insensitive: bool


OFFICIAL = Protocol(
    name="official",
    dontcare_metrics=frozenset(OVERLAP_METRICS),
    aos_rule="all_valid",
    skip_undetected=True,
    dontcare_case_insensitive=True,
)
OPENPCDET = Protocol(
    name="openpcdet",
    dontcare_metrics=frozenset({Metric.BBOX}),
    aos_rule="first_detection",
    skip_undetected=False,
    dontcare_case_insensitive=False,
)
PROTOCOLS: Mapping[str, Protocol] = MappingProxyType({p.name: p for p in (OFFICIAL, OPENPCDET)})


def get_protocol(name: str | Protocol) -> Protocol:
    """Look a protocol up by name (``official`` or ``openpcdet``)."""
    if isinstance(name, Protocol):
        return name
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ConfigError(f"unknown protocol {name!r}; expected one of {sorted(PROTOCOLS)}") from None


def _check_overlap(cls: str, oset: str, values: object) -> tuple[float, float, float]:
    try:
        triple = tuple(float(v) for v in values)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ConfigError(f"IoU thresholds for {cls}/{oset} must be three numbers (bbox, bev, 3d)") from None
    if len(triple) != 3 or not all(0.0 <= v < 1.0 for v in triple):
        raise ConfigError(
            f"IoU thresholds for {cls}/{oset} must be three numbers in [0, 1) (bbox, bev, 3d), got {values!r}"
        )
    return triple


@dataclass(frozen=True)
class DistanceRange:
    """A distance bin [lo, hi) in metres, the distance being ``sqrt(x**2 + z**2)`` of a box's location in
    the camera frame (its ground-plane distance from the camera).

    The rule: within a bin, ground truth outside it is *ignored* -- never a miss, and a detection matched
    to it is neither a hit nor a false positive -- and a detection outside it that would count is
    ignored too: not a false positive when unmatched, and, like a too-small detection, it makes a box it
    matches neither a hit nor a miss. So a box is judged only against what lies in its bin, and objects
    straddling a boundary neither reward nor punish.
    """

    lo: float
    hi: float

    def __post_init__(self) -> None:
        if not (0.0 <= self.lo < self.hi) or math.isnan(self.hi):
            raise ConfigError(f"a distance range needs 0 <= lo < hi, got [{self.lo}, {self.hi})")

    @property
    def label(self) -> str:
        return f"{self.lo:g}m+" if math.isinf(self.hi) else f"{self.lo:g}-{self.hi:g}m"

    def contains(self, distance: np.ndarray) -> np.ndarray:
        return (distance >= self.lo) & (distance < self.hi)


def parse_ranges(text: str) -> tuple[DistanceRange, ...]:
    """``0,30,50,inf`` -> [0, 30), [30, 50), [50, inf)."""
    try:
        edges = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"expected distance edges like 0,30,50,inf, got {text!r}") from None
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise ConfigError(f"expected at least two increasing distance edges like 0,30,50,inf, got {text!r}")
    return tuple(DistanceRange(a, b) for a, b in zip(edges, edges[1:]))


def load_protocol_file(path: str | os.PathLike[str]) -> dict[str, object]:
    """Evaluation settings from a TOML file, as keyword arguments of :class:`EvalConfig`.

    ::

        protocol = "official"              # or "openpcdet"
        classes = ["Car", "Bus"]
        lidar_only = false
        coco = false
        ranges = [0, 30, 50, inf]          # or "0,30,50,inf"

        [overlaps.Bus]                     # IoU thresholds (bbox, bev, 3d) per threshold set
        strict = [0.7, 0.7, 0.7]
        loose = [0.5, 0.5, 0.5]            # one set given alone is used for both

        [neighbours]                       # ground truth of these classes is ignored for the key class
        Bus = ["Tram"]                     # (replaces the defaults Car: Van, Pedestrian: Person_sitting)

        [difficulty]                       # easy, moderate, hard
        min_height = [40, 25, 25]
        max_occlusion = [0, 1, 2]
        max_truncation = [0.15, 0.3, 0.5]
    """
    import tomllib

    name = str(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"cannot read the protocol file {name}: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{name}: not valid TOML: {e}") from None
    known = {"protocol", "classes", "lidar_only", "coco", "ranges", "overlaps", "neighbours", "difficulty"}
    if set(data) - known:
        raise ConfigError(f"{name}: unknown keys {sorted(set(data) - known)}; expected {sorted(known)}")
    out: dict[str, object] = {}
    if "protocol" in data:
        out["protocol"] = get_protocol(str(data["protocol"]))
    if "classes" in data:
        if not isinstance(data["classes"], list) or not all(isinstance(c, str) for c in data["classes"]):
            raise ConfigError(f"{name}: classes must be a list of names")
        out["classes"] = tuple(data["classes"])
    for flag in ("lidar_only", "coco"):
        if flag in data:
            if not isinstance(data[flag], bool):
                raise ConfigError(f"{name}: {flag} must be true or false")
            out[flag] = data[flag]
    if "ranges" in data:
        r = data["ranges"]
        out["ranges"] = parse_ranges(r if isinstance(r, str) else ",".join(str(v) for v in r))
    if "overlaps" in data:
        overlaps: dict[str, dict[str, object]] = {}
        for cls, sets in dict(data["overlaps"]).items():
            if isinstance(sets, list):
                overlaps[cls] = dict.fromkeys(THRESHOLD_SETS, sets)
            elif isinstance(sets, dict):
                overlaps[cls] = dict(sets)
            else:
                raise ConfigError(f"{name}: overlaps.{cls} must be a list of three numbers or a table of sets")
        out["overlaps"] = overlaps
    if "neighbours" in data:
        nb = dict(data["neighbours"])
        if not all(isinstance(v, list) and all(isinstance(x, str) for x in v) for v in nb.values()):
            raise ConfigError(f"{name}: each neighbours entry must be a list of class names")
        out["neighbours"] = {k: tuple(v) for k, v in nb.items()}
    if "difficulty" in data:
        d = dict(data["difficulty"])
        if set(d) - {"min_height", "max_occlusion", "max_truncation"}:
            raise ConfigError(f"{name}: difficulty takes min_height, max_occlusion, max_truncation")
        try:
            limits = {k: tuple(float(x) for x in v) for k, v in d.items()}
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: difficulty limits must be lists of three numbers") from None
        if any(len(v) != 3 for v in limits.values()):
            raise ConfigError(f"{name}: difficulty limits must be lists of three numbers (easy, moderate, hard)")
        out["difficulty"] = DifficultyLimits(**{**KITTI_DIFFICULTY.__dict__, **limits})
    return out


def parse_iou_override(text: str) -> tuple[str, str | None, tuple[float, float, float]]:
    """``Car=0.7,0.6,0.6`` (both threshold sets) or ``Car:loose=0.7,0.5,0.5``: (class, set or None, triple)."""
    try:
        key, values = text.split("=", 1)
        cls, _, oset = key.strip().partition(":")
        triple = tuple(float(v) for v in values.split(","))
    except ValueError:
        raise ConfigError(f"expected CLASS[:SET]=BBOX,BEV,3D, got {text!r}") from None
    if len(triple) != 3 or not cls:
        raise ConfigError(f"expected CLASS[:SET]=BBOX,BEV,3D, got {text!r}")
    if oset and oset not in THRESHOLD_SETS:
        raise ConfigError(f"threshold set must be one of {', '.join(THRESHOLD_SETS)}, got {oset!r}")
    return cls, oset or None, (triple[0], triple[1], triple[2])


def overlaps_from_overrides(texts: Sequence[str]) -> dict[str, dict[str, tuple[float, float, float]]]:
    """``EvalConfig.overlaps`` from ``--iou``-style overrides (a later one wins)."""
    overlaps: dict[str, dict[str, tuple[float, float, float]]] = {}
    for text in texts:
        cls, oset, triple = parse_iou_override(text)
        for s in [oset] if oset else THRESHOLD_SETS:
            overlaps.setdefault(cls, {})[s] = triple
    return overlaps


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate: classes, protocol, thresholds, difficulty limits.

    ``overlaps`` overrides :data:`CLASS_OVERLAPS` per class and threshold set, e.g.
    ``{"Car": {"strict": (0.7, 0.6, 0.6)}}``; a class outside the KITTI six needs both sets given
    or one set that is then used for both.
    """

    classes: tuple[str, ...] = DEFAULT_CLASSES
    protocol: Protocol = OFFICIAL
    overlaps: Mapping[str, Mapping[str, tuple[float, float, float]]] = field(default_factory=dict)
    difficulty: DifficultyLimits = KITTI_DIFFICULTY
    threshold_sets: tuple[str, ...] = THRESHOLD_SETS
    #: distance bins [lo, hi) in metres, each evaluated in addition to the whole set (see :class:`DistanceRange`)
    ranges: tuple[DistanceRange, ...] = ()
    #: also compute COCO-style AP, averaged over :func:`coco_thresholds` (whole set, all three metrics)
    coco: bool = False
    #: ground truth of these classes is ignored for the key class (lower-case names); default :data:`NEIGHBOURS`
    neighbours: Mapping[str, tuple[str, ...]] = field(default_factory=lambda: dict(NEIGHBOURS))
    #: LiDAR-only: BEV and 3D only (no 2D box, no AOS), no 2D height filter; difficulty by the occlusion and
    #: truncation limits of ``difficulty`` if given, else none (every box counts at every level)
    lidar_only: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "ranges", tuple(self.ranges))
        object.__setattr__(
            self,
            "neighbours",
            MappingProxyType({k.lower(): tuple(v.lower() for v in vs) for k, vs in self.neighbours.items()}),
        )
        if self.lidar_only:
            limits = NO_DIFFICULTY if self.difficulty == KITTI_DIFFICULTY else self.difficulty
            object.__setattr__(
                self,
                "difficulty",
                DifficultyLimits(
                    min_height=(-math.inf,) * 3,
                    max_occlusion=limits.max_occlusion,
                    max_truncation=limits.max_truncation,
                ),
            )
        for r in self.ranges:
            if not isinstance(r, DistanceRange):
                raise ConfigError(f"ranges must be DistanceRange values, got {r!r}")
        if isinstance(self.classes, str):
            object.__setattr__(self, "classes", (self.classes,))
        object.__setattr__(self, "protocol", get_protocol(self.protocol))
        if not self.classes:
            raise ConfigError("no classes to evaluate")
        if len({c.lower() for c in self.classes}) != len(self.classes):
            raise ConfigError(f"classes repeat: {list(self.classes)}")
        for s in self.threshold_sets:
            if s not in THRESHOLD_SETS:
                raise ConfigError(f"unknown threshold set {s!r}; expected one of {list(THRESHOLD_SETS)}")
        canonical = {c.lower(): c for c in CLASS_OVERLAPS}
        resolved: dict[str, dict[str, tuple[float, float, float]]] = {}
        given = {k.lower(): v for k, v in self.overlaps.items()}
        unknown = set(given) - {c.lower() for c in self.classes}
        if unknown:
            raise ConfigError(f"IoU thresholds given for classes not evaluated: {sorted(unknown)}")
        for cls in self.classes:
            base = dict(CLASS_OVERLAPS.get(canonical.get(cls.lower(), cls), {}))
            user = {k: _check_overlap(cls, k, v) for k, v in given.get(cls.lower(), {}).items()}
            for k in user:
                if k not in THRESHOLD_SETS:
                    raise ConfigError(f"unknown threshold set {k!r} for {cls}; expected one of {list(THRESHOLD_SETS)}")
            if not base and len(user) == 1:
                (only,) = user.values()
                user = dict.fromkeys(THRESHOLD_SETS, only)
            base.update(user)
            if not base:
                raise ConfigError(
                    f"class {cls!r} has no default IoU thresholds{did_you_mean(cls, KNOWN_CLASSES)} (known: "
                    f"{', '.join(KNOWN_CLASSES)}); for a class of your own, give them, e.g. --iou {cls}=0.7,0.7,0.7"
                )
            resolved[cls] = base
        object.__setattr__(self, "overlaps", MappingProxyType(resolved))

    def overlap(self, cls: str, oset: str, metric: Metric) -> float:
        """The IoU a match of class ``cls`` must exceed in ``metric`` (AOS uses the bbox threshold)."""
        m = Metric.BBOX if metric is Metric.AOS else metric
        return self.overlaps[cls][oset][OVERLAP_INDEX[m]]


def _names(text: str) -> tuple[str, ...]:
    return tuple(p.strip() for p in text.split(",") if p.strip())


def config_from_options(
    *,
    base: Mapping[str, Any] | None = None,
    classes: str | None = None,
    protocol: str | None = None,
    threshold_sets: str | None = None,
    iou: Sequence[str] = (),
    ranges: str | None = None,
    coco: bool = False,
    lidar_only: bool = False,
) -> EvalConfig:
    """An :class:`EvalConfig` from options written as the CLI's flags and the service's form fields are.

    ``base``: keyword arguments of :class:`EvalConfig` to start from (a protocol file's); ``classes`` and
    ``threshold_sets``: comma-separated names; ``protocol``: a name of :data:`PROTOCOLS`; ``iou``:
    ``Car=0.7,0.6,0.6`` or ``Car:loose=...`` overrides, added to ``base``'s (a later one wins); ``ranges``:
    ``0,30,50,inf``; ``coco``/``lidar_only`` switch those on (they never switch ``base``'s off).

    Raises ConfigError naming the option at fault.
    """
    kwargs: dict[str, Any] = dict(base or {})
    if classes is not None:
        kwargs["classes"] = _names(classes)
    if protocol is not None:
        if protocol not in PROTOCOLS:
            raise ConfigError(f"unknown protocol {protocol!r}; expected one of {sorted(PROTOCOLS)}")
        kwargs["protocol"] = PROTOCOLS[protocol]
    if threshold_sets is not None:
        kwargs["threshold_sets"] = _names(threshold_sets)
    if iou:
        try:
            overrides = overlaps_from_overrides(iou)
        except ConfigError as e:
            raise ConfigError(f"iou: {e}") from None
        overlaps = {k: dict(v) for k, v in dict(kwargs.get("overlaps", {})).items()}
        for cls, sets in overrides.items():
            overlaps.setdefault(cls, {}).update(sets)
        kwargs["overlaps"] = overlaps
    if ranges:
        kwargs["ranges"] = parse_ranges(ranges)
    if coco:
        kwargs["coco"] = True
    if lidar_only:
        kwargs["lidar_only"] = True
    return EvalConfig(**kwargs)
