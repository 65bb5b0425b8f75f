"""An incremental KITTI metric for validation loops: update it as batches arrive, compute once at the end.

    from kitti_eval import KittiMetric

    metric = KittiMetric(classes=("Car", "Pedestrian", "Cyclist"), protocol="openpcdet")
    for batch in val_loader:
        ...
        metric.update(gt_frames, dt_frames)   # this batch's ground truth and predictions, frames by id
    result = metric.compute()                 # an EvalResult
    metric.reset()                            # for the next epoch

``compute()`` returns what :func:`~kitti_eval.core.evaluation.evaluate` returns for all frames at once, in
frame-id order: every AP and every curve equal, whatever the batches and the order they came in. Each update
is validated at once (an error names the argument, the frame and the field) and kept as the compact columns
of :class:`~kitti_eval.core.frames.Annotations`, never as the dicts given, so a metric holds what a batch
evaluation holds: about 120 bytes a box plus the class name.

Data-parallel ranks each update their own metric; one rank then gathers and merges them::

    states = all_gather_object(metric.state_dict())     # plain dicts of numpy arrays; a metric pickles too
    merged = KittiMetric.from_state_dict(states[0])
    for state in states[1:]:
        merged.merge(state)
    result = merged.compute()

A frame given twice (in one update, in two, or on two ranks) is an :class:`~kitti_eval.errors.InputError`
naming it; merging metrics of different configurations is a :class:`~kitti_eval.errors.ConfigError`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from .core.evaluation import evaluate
from .core.frames import Annotations, Kind
from .core.protocol import (
    PROTOCOLS,
    DifficultyLimits,
    DistanceRange,
    EvalConfig,
    Metric,
    Protocol,
)
from .core.result import EvalResult
from .errors import ConfigError, InputError

__all__ = ["KittiMetric", "config_state", "config_from_state"]

#: what :meth:`KittiMetric.state_dict` writes under "format", and its layout's version
STATE_FORMAT = "kitti_eval.KittiMetric"
STATE_VERSION = 1

_META = ("kind", "source", "frame_ids", "offsets", "missing_fields", "boxes_lidar")
#: the per-box columns of Annotations (name, truncated, occluded, alpha, bbox, dimensions, location, ...)
_COLUMNS = tuple(f.name for f in dataclasses.fields(Annotations) if f.name not in _META)
_CONFIG_FIELDS = frozenset(f.name for f in dataclasses.fields(EvalConfig))
_SOURCES: Mapping[Kind, str] = {"ground_truth": "gt_frames", "detections": "dt_frames"}
#: a metric keeps at most this many blocks of frames before joining them into one
_MAX_BLOCKS = 32
#: warnings kept (one update can warn about its batch; a run of batches need not grow the list without end)
_MAX_WARNINGS = 20


# ------------------------------------------------------------------------------------- configuration


def config_state(config: EvalConfig) -> dict[str, Any]:
    """An :class:`EvalConfig` as plain data (lists, dicts, numbers, strings): picklable, comparable, and
    turned back by :func:`config_from_state`."""
    p = config.protocol
    d = config.difficulty
    return {
        "classes": list(config.classes),
        "protocol": {
            "name": p.name,
            "dontcare_metrics": sorted(m.value for m in p.dontcare_metrics),
            "aos_rule": p.aos_rule,
            "skip_undetected": p.skip_undetected,
            "dontcare_case_insensitive": p.dontcare_case_insensitive,
        },
        "overlaps": {c: {s: list(t) for s, t in sets.items()} for c, sets in config.overlaps.items()},
        "difficulty": {
            "min_height": list(d.min_height),
            "max_occlusion": list(d.max_occlusion),
            "max_truncation": list(d.max_truncation),
        },
        "threshold_sets": list(config.threshold_sets),
        "ranges": [[r.lo, r.hi] for r in config.ranges],
        "coco": config.coco,
        "neighbours": {k: list(v) for k, v in config.neighbours.items()},
        "lidar_only": config.lidar_only,
    }


def config_from_state(state: Mapping[str, Any]) -> EvalConfig:
    """The :class:`EvalConfig` of :func:`config_state`'s output; ConfigError if it is not one."""
    try:
        p = state["protocol"]
        protocol = Protocol(
            name=str(p["name"]),
            dontcare_metrics=frozenset(Metric(m) for m in p["dontcare_metrics"]),
            aos_rule=p["aos_rule"],
            skip_undetected=bool(p["skip_undetected"]),
            dontcare_case_insensitive=bool(p["dontcare_case_insensitive"]),
        )
        d = state["difficulty"]
        known = PROTOCOLS.get(protocol.name)
        return EvalConfig(
            classes=tuple(state["classes"]),
            protocol=known if known == protocol and known is not None else protocol,
            overlaps={c: {s: tuple(t) for s, t in sets.items()} for c, sets in state["overlaps"].items()},
            difficulty=DifficultyLimits(
                min_height=tuple(d["min_height"]),
                max_occlusion=tuple(d["max_occlusion"]),
                max_truncation=tuple(d["max_truncation"]),
            ),
            threshold_sets=tuple(state["threshold_sets"]),
            ranges=tuple(DistanceRange(float(lo), float(hi)) for lo, hi in state["ranges"]),
            coco=bool(state["coco"]),
            neighbours={k: tuple(v) for k, v in state["neighbours"].items()},
            lidar_only=bool(state["lidar_only"]),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ConfigError(f"not a KittiMetric configuration ({type(e).__name__}: {e})") from None


def _config_difference(a: Mapping[str, Any], b: Mapping[str, Any]) -> str:
    keys = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    return "; ".join(f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in keys[:3])


# --------------------------------------------------------------------------------------- frame blocks


def _bare(a: Annotations) -> Annotations:
    """The same arrays in a fresh container: no LiDAR boxes, no cached derived arrays."""
    return Annotations(
        kind=a.kind,
        source=a.source,
        frame_ids=a.frame_ids,
        offsets=a.offsets,
        missing_fields=dict(a.missing_fields),
        **{c: getattr(a, c) for c in _COLUMNS},
    )


def _joined(parts: Sequence[Annotations]) -> Annotations:
    """Frames of several containers of one kind, one after the other, in one container (copied once)."""
    if len(parts) == 1:
        return parts[0]
    counts = np.concatenate([p.counts for p in parts])
    offsets = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    missing: dict[str, str] = {}
    for p in parts:
        for f, frame in p.missing_fields.items():
            missing.setdefault(f, frame)
    return Annotations(
        kind=parts[0].kind,
        source=parts[0].source,
        frame_ids=tuple(fid for p in parts for fid in p.frame_ids),
        offsets=offsets,
        missing_fields=missing,
        **{c: np.concatenate([getattr(p, c) for p in parts]) for c in _COLUMNS},
    )


def _columns(a: Annotations) -> dict[str, Any]:
    out: dict[str, Any] = {
        "frame_ids": np.array(a.frame_ids, dtype=str) if a.frame_ids else np.zeros(0, dtype="<U1"),
        "offsets": a.offsets,
        "missing_fields": dict(a.missing_fields),
    }
    out.update({c: getattr(a, c) for c in _COLUMNS})
    return out


def _from_columns(kind: Kind, cols: Mapping[str, Any]) -> Annotations:
    """Annotations back from :func:`_columns`, shapes and dtypes checked (InputError naming the column)."""
    source = "state_dict"
    try:
        ids = tuple(str(v) for v in np.asarray(cols["frame_ids"]).reshape(-1))
        offsets = np.asarray(cols["offsets"])
        columns = {c: np.asarray(cols[c]) for c in _COLUMNS}
        missing = {str(k): str(v) for k, v in dict(cols.get("missing_fields") or {}).items()}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"not a KittiMetric state ({kind}: {type(e).__name__}: {e})", source=source) from None
    if offsets.dtype != np.int64 or offsets.shape != (len(ids) + 1,) or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
        raise InputError(f"{kind}: offsets do not describe {len(ids)} frames", source=source, field="offsets")
    if len(set(ids)) != len(ids):
        raise InputError(f"{kind}: a frame appears twice", source=source, field="frame_ids")
    rows = int(offsets[-1])
    for c, arr in columns.items():
        want = "U" if c == "name" else "f"
        if arr.dtype.kind != want or len(arr) != rows:
            raise InputError(f"{kind}: expected {rows} rows of dtype kind {want!r}", source=source, field=c)
    return Annotations(
        kind=kind, source=_SOURCES[kind], frame_ids=ids, offsets=offsets, missing_fields=missing, **columns
    )


def _with_sample_ids(obj: object) -> object:
    """mmdetection3d result dicts that carry ``sample_id`` (some 1.x versions) instead of ``sample_idx``."""
    if isinstance(obj, (list, tuple)) and obj and all(isinstance(e, Mapping) for e in obj):
        first = obj[0]
        if "sample_id" in first and "sample_idx" not in first and "frame_id" not in first:
            return [{**e, "sample_idx": e["sample_id"]} if "sample_id" in e else e for e in obj]
    return obj


# ---------------------------------------------------------------------------------------------- metric


class KittiMetric:
    """KITTI AP accumulated over batches; see the module's documentation.

    Parameters
    ----------
    classes : classes to evaluate (default: Car, Pedestrian, Cyclist)
    protocol : ``"official"`` (default) or ``"openpcdet"``, or a :class:`~kitti_eval.core.protocol.Protocol`
    config : a whole :class:`EvalConfig` instead of ``classes``, ``protocol`` and ``options``
    options : further :class:`EvalConfig` fields (``overlaps``, ``difficulty``, ``ranges``, ``coco``,
        ``lidar_only``, ...)
    """

    def __init__(
        self,
        classes: Sequence[str] | str | None = None,
        protocol: str | Protocol | None = None,
        *,
        config: EvalConfig | None = None,
        **options: Any,
    ) -> None:
        if config is not None:
            if classes is not None or protocol is not None or options:
                raise ConfigError("give either config or classes / protocol / options, not both")
            if not isinstance(config, EvalConfig):
                raise ConfigError(f"config must be an EvalConfig, got {type(config).__name__}")
        else:
            unknown = sorted(set(options) - _CONFIG_FIELDS)
            if unknown:
                hint = (
                    " (ann_file is an argument of the mmengine metric, kitti_eval.compat.mmdet3d_evaluator, which an "
                    "mmdetection3d config builds when mmengine and torch are installed)"
                    if "ann_file" in unknown
                    else ""
                )
                raise ConfigError(f"unknown option(s) {unknown}; EvalConfig takes {sorted(_CONFIG_FIELDS)}{hint}")
            kwargs = dict(options)
            if classes is not None:
                kwargs["classes"] = (classes,) if isinstance(classes, str) else tuple(classes)
            if protocol is not None:
                kwargs["protocol"] = protocol
            config = EvalConfig(**kwargs)
        self._config = config
        self._config_state = config_state(config)
        self._blocks: list[tuple[Annotations, Annotations]] = []
        self._frames: set[str] = set()
        #: what reading the inputs noticed (e.g. a frame id taken from ``point_cloud.lidar_idx``), once each
        self.warnings: list[str] = []

    @property
    def config(self) -> EvalConfig:
        return self._config

    @property
    def num_frames(self) -> int:
        """Ground-truth frames added so far."""
        return len(self._frames)

    def __len__(self) -> int:
        return len(self._frames)

    def __repr__(self) -> str:
        return (
            f"KittiMetric({self.num_frames} frames, classes={list(self._config.classes)}, "
            f"protocol={self._config.protocol.name!r})"
        )

    # ---------------------------------------------------------------------------------------- update

    def update(self, gt_frames: Any, dt_frames: Any) -> None:
        """Add one batch: its ground-truth frames and the predictions for them.

        Both are matched by frame id, never by position. Accepted: a list of OpenPCDet info dicts (ids from
        ``image.image_idx``) or of annos dicts with ``frame_id`` (OpenPCDet's ``generate_prediction_dicts``
        output), a dict ``{frame id: annos dict}``, mmdetection3d 1.x's infos (``{'metainfo', 'data_list'}``)
        and its KITTI-format result dicts (``sample_idx`` or ``sample_id``), or an
        :class:`~kitti_eval.core.frames.Annotations`. Predictions with only ``boxes_lidar`` are converted with
        the calibration in ``gt_frames`` (infos). A ground-truth frame without predictions counts as empty.

        Raises InputError (naming ``gt_frames`` or ``dt_frames``, the frame and the field) for malformed
        frames, for predictions of a frame whose ground truth is not in the same update, and for a frame
        given before; nothing is added then.
        """
        calibs = None
        if not isinstance(gt_frames, Annotations):
            from .io.camera import calibs_from_object

            calibs = calibs_from_object(gt_frames)
        gt = self._read(gt_frames, "ground_truth", None)
        dt = self._read(dt_frames, "detections", calibs)
        known = set(gt.frame_ids)
        unknown = [fid for fid in dt.frame_ids if fid not in known]
        if unknown:
            raise InputError(
                "predictions for a frame whose ground truth is not in the same update (each update(gt, dt) "
                "carries the ground truth of the frames it has predictions for)",
                source=_SOURCES["detections"],
                frame=unknown[0],
            )
        again = [fid for fid in gt.frame_ids if fid in self._frames]
        if again:
            raise InputError(
                "frame given twice: an earlier update had it", source=_SOURCES["ground_truth"], frame=again[0]
            )
        if not gt.num_frames:
            return
        self._frames.update(gt.frame_ids)
        self._push([(gt, dt)])

    def _read(self, obj: Any, kind: Kind, calibs: Any) -> Annotations:
        source = _SOURCES[kind]
        if isinstance(obj, Annotations):
            if obj.kind != kind:
                raise InputError(f"expected {kind.replace('_', ' ')}, got {obj.kind.replace('_', ' ')}", source=source)
            annos = _bare(obj)
        elif isinstance(obj, (list, tuple, dict)) and not obj:
            annos = Annotations.from_frames(kind, source, [])
        else:
            from .io.reading import LoadOptions, read_object

            loaded = read_object(_with_sample_ids(obj), kind, source, LoadOptions(calibs=calibs))
            annos = loaded.annotations
            self._warn(loaded.warnings)
        if annos.missing_fields and not self._config.lidar_only:
            field = "bbox" if "bbox" in annos.missing_fields else next(iter(annos.missing_fields))
            raise InputError(
                f"no '{field}' (an image field) for some boxes; a set without 2D boxes is evaluated with "
                "lidar_only=True (BEV and 3D)",
                source=source,
                frame=annos.missing_fields[field],
                field=field,
            )
        return annos

    def _warn(self, found: Iterable[str]) -> None:
        for w in found:
            if w not in self.warnings and len(self.warnings) < _MAX_WARNINGS:
                self.warnings.append(w)

    def _push(self, blocks: Iterable[tuple[Annotations, Annotations]]) -> None:
        """Add blocks of frames, joining the last two while the earlier is not larger (each frame is copied
        O(log frames) times and a metric holds O(log frames) blocks)."""
        self._blocks += blocks
        while len(self._blocks) >= 2 and self._blocks[-2][0].num_frames <= self._blocks[-1][0].num_frames:
            b = self._blocks.pop()
            a = self._blocks.pop()
            self._blocks.append((_joined([a[0], b[0]]), _joined([a[1], b[1]])))
        if len(self._blocks) > _MAX_BLOCKS:
            self._consolidated()

    def _consolidated(self) -> tuple[Annotations, Annotations]:
        """All frames in one block, in frame-id order (kept so, until the next update)."""
        if not self._blocks:
            empty = [Annotations.from_frames(k, _SOURCES[k], []) for k in ("ground_truth", "detections")]
            return empty[0], empty[1]
        if len(self._blocks) > 1 or list(self._blocks[0][0].frame_ids) != sorted(self._blocks[0][0].frame_ids):
            gt = _joined([b[0] for b in self._blocks])
            dt = _joined([b[1] for b in self._blocks])
            for order, annos in ((sorted(gt.frame_ids), gt), (sorted(dt.frame_ids), dt)):
                if list(annos.frame_ids) != order:  # frames that came in order are not copied again
                    annos = annos.subset(order)
                if annos.kind == "ground_truth":
                    gt = annos
                else:
                    dt = annos
            self._blocks = [(gt, dt)]
        return self._blocks[0]

    # --------------------------------------------------------------------------------------- results

    def compute(self, *, keep_curves: bool = False, workers: int | None = None) -> EvalResult:
        """Evaluate every frame added so far: ``evaluate(gt, dt, config)`` on all of them, in frame-id order.

        Raises InputError when no frame was added.
        """
        gt, dt = self._consolidated()
        if not gt.num_frames:
            raise InputError("no frames to evaluate: update() was not called since the metric was made or reset")
        # fresh containers: what evaluate() caches on them is dropped with them
        return evaluate(_bare(gt), _bare(dt), self._config, keep_curves=keep_curves, workers=workers)

    def reset(self) -> None:
        """Forget every frame (e.g. at the start of the next validation epoch)."""
        self._blocks = []
        self._frames = set()
        self.warnings = []

    # ------------------------------------------------------------------------------- state and merge

    def state_dict(self) -> dict[str, Any]:
        """The configuration and every frame as plain data: dicts, lists, strings and numpy arrays (shared
        with the metric: treat them as read-only). Picklable; :meth:`load_state_dict` and
        :meth:`from_state_dict` read it."""
        gt, dt = self._consolidated()
        return {
            "format": STATE_FORMAT,
            "version": STATE_VERSION,
            "config": config_state(self._config),
            "ground_truth": _columns(gt),
            "detections": _columns(dt),
            "warnings": list(self.warnings),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Replace this metric's frames with those of ``state``; ConfigError if it was made with another
        configuration, InputError if it is not a state of this class."""
        if not isinstance(state, Mapping) or state.get("format") != STATE_FORMAT:
            raise InputError(f"not a {STATE_FORMAT} state", source="state_dict")
        if state.get("version") != STATE_VERSION:
            raise InputError(f"state version {state.get('version')!r}; expected {STATE_VERSION}", source="state_dict")
        if state.get("config") != self._config_state:
            theirs = state.get("config")
            diff = _config_difference(self._config_state, theirs) if isinstance(theirs, Mapping) else repr(theirs)
            raise ConfigError(f"the state was made with another configuration ({diff})")
        gt = _from_columns("ground_truth", state["ground_truth"])
        dt = _from_columns("detections", state["detections"])
        unknown = set(dt.frame_ids) - set(gt.frame_ids)
        if unknown:
            raise InputError("predictions for a frame without ground truth", source="state_dict", frame=min(unknown))
        self._blocks = [(gt, dt)] if gt.num_frames else []
        self._frames = set(gt.frame_ids)
        self.warnings = [str(w) for w in state.get("warnings", ())]

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Any]) -> KittiMetric:
        """A metric with the configuration and frames of ``state``."""
        if not isinstance(state, Mapping) or not isinstance(state.get("config"), Mapping):
            raise InputError(f"not a {STATE_FORMAT} state", source="state_dict")
        metric = cls(config=config_from_state(state["config"]))
        metric.load_state_dict(state)
        return metric

    def merge(self, other: KittiMetric | Mapping[str, Any]) -> KittiMetric:
        """Add the frames of another metric (or of its :meth:`state_dict`); returns this metric.

        Raises ConfigError when the two were made with different configurations and InputError naming a
        frame both have; nothing is added then. ``other`` is not changed.
        """
        if not isinstance(other, KittiMetric):
            other = KittiMetric.from_state_dict(other)
        if other is self:
            raise InputError("a metric cannot be merged with itself (every frame would appear twice)")
        if other._config_state != self._config_state:
            diff = _config_difference(self._config_state, other._config_state)
            raise ConfigError(f"cannot merge metrics with different configurations ({diff})")
        both = self._frames & other._frames
        if both:
            raise InputError("frame in both metrics", source="merge", frame=min(both))
        self._frames |= other._frames
        self._warn(other.warnings)
        self._push(list(other._blocks))
        return self

    def __getstate__(self) -> dict[str, Any]:
        return self.state_dict()

    def __setstate__(self, state: Mapping[str, Any]) -> None:
        self.__init__(config=config_from_state(state["config"]))  # type: ignore[misc]
        self.load_state_dict(state)
