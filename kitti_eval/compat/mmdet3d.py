"""Drop-ins for mmdetection3d 1.x's KITTI evaluation functions: swap one import, keep the calling code.

    # from mmdet3d.evaluation import kitti_eval, kitti_eval_coco_style
    from kitti_eval.compat.mmdet3d import kitti_eval, kitti_eval_coco_style

    result_str, ap_dict = kitti_eval(gt_annos, dt_annos, ["Pedestrian", "Cyclist", "Car"])

Same arguments (lists of per-frame KITTI annos dicts paired by position, classes as names or mmdetection3d's
indices 0 Car, 1 Pedestrian, 2 Cyclist, 3 Van, 4 Person_sitting), the same printed text (an AP11 section and
an AP40 section, each with an ``Overall`` block when several classes are evaluated) and the same ``ap_dict``
keys (``KITTI/Car_3D_AP40_moderate_strict``, ``KITTI/Overall_2D_AP11_easy``, ...; mmdetection3d's
``KittiMetric`` logs them as ``Kitti metric/pred_instances_3d/<key>``, rounded to four decimals). The IoU
thresholds are mmdetection3d's table, which equals kitti-eval's defaults for those five classes. The rules are
the ``openpcdet`` protocol's (DontCare regions suppress false positives in 2D only, a class without
detections scores 0), computed with exact float64 IoU on the CPU.

Where mmdetection3d 1.x (``mmdet3d/evaluation/functional/kitti_utils/eval.py``) behaves otherwise:

* IoU: mmdetection3d computes BEV and 3D IoU in float32 with a CUDA kernel (a GPU is needed; its unit tests
  of BEV and 3D AP skip without one; recent development versions add a float32 CPU twin). Here it is exact
  float64: the numbers agree with mmdetection3d's tests to their tolerance, and on boxes where the float32
  kernel loses polygon vertices (identical or collinear edges) kitti-eval gives the true IoU.
* AOS is printed when some detection has an alpha other than -10 and some ground-truth frame's first box
  does, as mmdetection3d decides; mmdetection3d raises ``IndexError`` when a ground-truth frame without boxes
  comes before the first such frame, here empty frames are skipped. When every frame's first detection has
  alpha -10 but a later one does not, the ``openpcdet`` protocol computes no AOS: the rows are left out and a
  warning says so (mmdetection3d would print them).
* ``eval_types``: mmdetection3d appends ``'aos'`` to the list it is given (its default list included, so the
  default changes after the first call); here the argument is never modified. An unknown type is a
  :class:`~kitti_eval.errors.ConfigError` (mmdetection3d ignores it); without ``'bbox'`` the AOS rows are left
  out (mmdetection3d fails formatting ``None`` when AOS applies).
* Classes: mmdetection3d's ``clean_data`` knows Car, Pedestrian and Cyclist only and fails with
  ``IndexError`` for Van and Person_sitting; here those two are evaluated with the thresholds of the table
  (Van as Car, Person_sitting as Pedestrian). Names compare case-insensitively; any other class is a
  ``ConfigError``.
* ``kitti_eval_coco_style`` passes its AOS flag to ``do_eval`` where a list of metric names is expected and
  fails with ``TypeError`` in mmdetection3d 1.x; here it returns the text it was written to print: per class,
  R11 AP averaged over ten IoU thresholds (Car and Van 0.50:0.05:0.95, the others 0.25:0.05:0.70), two
  decimals, AOS when the first detection of the first frame with detections has an alpha other than -10.
* Frames: both lists must have the same length (an ``InputError``; mmdetection3d asserts). Boxes of any size
  are read as mmdetection3d reads them (its unit tests have ground-truth Cars with dimensions -1); what the
  evaluation has to say about the input (such sizes among it) comes as ``UserWarning``.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..core.evaluation import evaluate
from ..core.frames import Annotations
from ..core.protocol import (
    DIFFICULTIES,
    INVALID_ALPHA,
    METRICS,
    OPENPCDET,
    OVERLAP_METRIC_NAMES,
    EvalConfig,
    coco_thresholds,
)
from ..core.result import EvalResult
from ..errors import ConfigError, InputError
from ._common import warn_about

__all__ = ["kitti_eval", "kitti_eval_coco_style", "ap_dict", "result_text", "CLASS_BY_INDEX", "EVAL_TYPES"]

#: mmdetection3d's class indices (its ``class_to_name``).
CLASS_BY_INDEX = ("Car", "Pedestrian", "Cyclist", "Van", "Person_sitting")
#: what ``eval_types`` may hold
EVAL_TYPES = METRICS
#: (metric of EvalResult, its name in ap_dict keys, its row label in the text), in the text's row order
_ROWS = (("bbox", "2D", "bbox"), ("bev", "BEV", "bev "), ("3d", "3D", "3d  "))
#: the order mmdetection3d fills ap_dict in: 3D, BEV, 2D
_KEY_ORDER = ("3d", "bev", "bbox")
_KEY = {m: k for m, k, _ in _ROWS}
_SETS = (("strict", "strict"), ("loose", "loose"))


def _class_names(current_classes: Any) -> tuple[str, ...]:
    if not isinstance(current_classes, (list, tuple)):
        current_classes = [current_classes]
    by_lower = {c.lower(): c for c in CLASS_BY_INDEX}
    names = []
    for c in current_classes:
        if isinstance(c, (int, np.integer)) and not isinstance(c, (bool, np.bool_)):
            if not 0 <= int(c) < len(CLASS_BY_INDEX):
                raise ConfigError(
                    f"class index {c} out of range 0..{len(CLASS_BY_INDEX) - 1} ({', '.join(CLASS_BY_INDEX)})"
                )
            names.append(CLASS_BY_INDEX[int(c)])
        elif isinstance(c, str) and c.lower() in by_lower:
            names.append(by_lower[c.lower()])
        else:
            raise ConfigError(
                f"mmdetection3d's kitti_eval evaluates {', '.join(CLASS_BY_INDEX)} (or indices 0..4), got {c!r}"
            )
    if not names:
        raise ConfigError("no classes to evaluate")
    return tuple(names)


def _eval_types(eval_types: Any) -> frozenset[str]:
    if isinstance(eval_types, str):
        eval_types = [eval_types]
    types = list(eval_types)
    if not types:
        raise ConfigError("eval_types must contain at least one of 'bbox', 'bev', '3d'")
    unknown = [t for t in types if t not in EVAL_TYPES]
    if unknown:
        raise ConfigError(f"unknown eval_types {unknown}; expected some of {list(EVAL_TYPES)}")
    if "aos" in types and "bbox" not in types:
        raise ConfigError("eval_types: 'aos' needs 'bbox' (orientation is scored on the 2D matching)")
    return frozenset(types)


def _paired(
    gt_annos: Sequence[Mapping[str, Any]], dt_annos: Sequence[Mapping[str, Any]]
) -> tuple[Annotations, Annotations]:
    """Both lists as Annotations, frames paired by position (a frame's id is its position, zero-padded)."""
    if len(gt_annos) != len(dt_annos):
        raise InputError(
            f"{len(gt_annos)} ground-truth frames but {len(dt_annos)} prediction frames; "
            "this function pairs frames by position"
        )
    gt = Annotations.from_frames("ground_truth", "gt_annos", ((f"{i:06d}", a) for i, a in enumerate(gt_annos)))
    dt = Annotations.from_frames("detections", "dt_annos", ((f"{i:06d}", a) for i, a in enumerate(dt_annos)))
    return gt, dt


def _first_rows(annos: Annotations) -> np.ndarray:
    """The row of the first box of every frame that has boxes, in frame order."""
    starts = annos.offsets[:-1]
    return starts[annos.counts > 0]


def _mmdet3d_aos(gt: Annotations, dt: Annotations) -> bool:
    """mmdetection3d's rule: some detection has an alpha, and some ground-truth frame's first box has one."""
    pred_alpha = bool(np.any(dt.alpha != INVALID_ALPHA))
    valid_alpha_gt = bool(np.any(gt.alpha[_first_rows(gt)] != INVALID_ALPHA))
    return pred_alpha and valid_alpha_gt


def _aos_first_order(dt: Annotations) -> list[str] | None:
    """A frame order in which the ``openpcdet`` protocol computes AOS (the first detection of the first frame
    with detections has an alpha): one such frame moved to the front; None if no frame starts that way."""
    first = _first_rows(dt)
    good = np.flatnonzero(dt.alpha[first] != INVALID_ALPHA)
    if not len(good):
        return None
    frame = int(np.flatnonzero(dt.counts > 0)[good[0]])
    return [dt.frame_ids[frame], *(fid for i, fid in enumerate(dt.frame_ids) if i != frame)]


def _mean(values: Sequence[float]) -> float:
    """The mean as numpy takes it over the class axis: summed in order, then divided."""
    total = 0.0
    for v in values:
        total += v
    return total / len(values)


def _value(v: float | None) -> float:
    return float("nan") if v is None else float(v)


def _with_aos(gt: Annotations, dt: Annotations, want_aos: bool) -> tuple[Annotations, Annotations, bool]:
    """The frames in an order in which the ``openpcdet`` protocol computes AOS if ``want_aos`` (the sums behind
    AP do not depend on the order of frames), and whether AOS will be there to show."""
    if not want_aos or (dt.num_boxes and dt.alpha[0] != INVALID_ALPHA):
        return gt, dt, want_aos
    order = _aos_first_order(dt)
    if order is None:
        warnings.warn(
            "AOS is not shown: every frame's first detection has alpha -10 (mmdetection3d would score the "
            "alphas of the later detections)",
            stacklevel=3,
        )
        return gt, dt, False
    return gt.subset(order), dt.subset(order), True


def ap_dict(result: EvalResult, eval_types: Sequence[str] = OVERLAP_METRIC_NAMES) -> dict[str, float]:
    """mmdetection3d's ``ap_dict`` of a result: per recall mode (AP11, then AP40), per class, threshold set and
    difficulty the 3D, BEV and 2D values (those in ``eval_types``), then the ``Overall`` means over the classes
    at the strict thresholds when there are several classes."""
    types = _eval_types(eval_types)
    out: dict[str, float] = {}
    for recall, tag in (("R11", "AP11"), ("R40", "AP40")):
        for cls in result.classes:
            for oset, suffix in _SETS:
                if oset not in result.threshold_sets:
                    continue
                by_metric = result.ap[oset][recall][cls]
                for d in DIFFICULTIES:
                    for metric in _KEY_ORDER:
                        if metric in types:
                            out[f"KITTI/{cls}_{_KEY[metric]}_{tag}_{d}_{suffix}"] = _value(by_metric[metric][d])
        if len(result.classes) > 1:
            for d in DIFFICULTIES:
                for metric in _KEY_ORDER:
                    if metric in types:
                        values = [_value(result.ap["strict"][recall][c][metric][d]) for c in result.classes]
                        out[f"KITTI/Overall_{_KEY[metric]}_{tag}_{d}"] = _mean(values)
    return out


def result_text(
    result: EvalResult, eval_types: Sequence[str] = OVERLAP_METRIC_NAMES, *, aos: bool | None = None
) -> str:
    """mmdetection3d's printed text of a result: an AP11 and an AP40 section, each with a block per class and
    threshold set (the rows of ``eval_types``, and AOS when ``aos``, by default when the result has AOS and
    ``'bbox'`` is evaluated) and an ``Overall`` block (the mean over the classes, strict thresholds) when
    there are several classes."""
    types = _eval_types(eval_types)
    show_aos = (result.aos_evaluated if aos is None else aos) and "bbox" in types
    lines: list[str] = []
    for recall, tag in (("R11", "AP11"), ("R40", "AP40")):
        lines += ["", f"----------- {tag} Results ------------", ""]
        metrics = [(m, label) for m, _, label in _ROWS if m in types]
        if show_aos:
            metrics.append(("aos", "aos "))
        for cls in result.classes:
            for oset in result.threshold_sets:
                ious = result.overlaps[cls][oset]
                lines.append(f"{cls} {tag}@{ious['bbox']:.2f}, {ious['bev']:.2f}, {ious['3d']:.2f}:")
                for m, label in metrics:
                    digits = 2 if m == "aos" else 4
                    vals = ", ".join(f"{_value(result.ap[oset][recall][cls][m][d]):.{digits}f}" for d in DIFFICULTIES)
                    lines.append(f"{label} {tag}:{vals}")
        if len(result.classes) > 1:
            lines += ["", f"Overall {tag}@{', '.join(DIFFICULTIES)}:"]
            for m, label in metrics:
                digits = 2 if m == "aos" else 4
                means = [
                    _mean([_value(result.ap["strict"][recall][c][m][d]) for c in result.classes]) for d in DIFFICULTIES
                ]
                lines.append(f"{label} {tag}:" + ", ".join(f"{v:.{digits}f}" for v in means))
    return "\n".join(lines) + "\n"


def kitti_eval(
    gt_annos: Sequence[Mapping[str, Any]],
    dt_annos: Sequence[Mapping[str, Any]],
    current_classes: Any,
    eval_types: Sequence[str] = OVERLAP_METRIC_NAMES,
) -> tuple[str, dict[str, float]]:
    """Evaluate like mmdetection3d 1.x's function of the same name; returns ``(result_str, ap_dict)``.

    ``gt_annos`` and ``dt_annos`` are lists of per-frame KITTI annos dicts paired by position;
    ``current_classes`` names or indices (0 Car, 1 Pedestrian, 2 Cyclist, 3 Van, 4 Person_sitting);
    ``eval_types`` some of ``'bbox'``, ``'bev'``, ``'3d'`` (``'aos'`` is added when the alphas allow it, as
    mmdetection3d does, and needs ``'bbox'``). Raises ConfigError for unknown classes or types, InputError for
    malformed frames.
    """
    types = _eval_types(eval_types)
    config = EvalConfig(classes=_class_names(current_classes), protocol=OPENPCDET)
    gt, dt = _paired(gt_annos, dt_annos)
    gt, dt, want_aos = _with_aos(gt, dt, _mmdet3d_aos(gt, dt))
    result = evaluate(gt, dt, config)
    warn_about(result)
    show_aos = want_aos and result.aos_evaluated and "bbox" in types
    return result_text(result, sorted(types), aos=show_aos), ap_dict(result, sorted(types - {"aos"}))


def kitti_eval_coco_style(
    gt_annos: Sequence[Mapping[str, Any]], dt_annos: Sequence[Mapping[str, Any]], current_classes: Any
) -> str:
    """COCO-style KITTI AP as mmdetection3d 1.x's function of the same name meant to print it: per class,
    R11 AP averaged over ten IoU thresholds for bbox, BEV and 3D (and AOS), two decimals."""
    config = EvalConfig(classes=_class_names(current_classes), protocol=OPENPCDET, coco=True)
    result = evaluate(*_paired(gt_annos, dt_annos), config)
    warn_about(result)
    assert result.coco is not None
    show_aos = result.aos_evaluated
    lines: list[str] = []
    for cls in result.classes:
        t = coco_thresholds(cls)
        step = (t[-1] - t[0]) / (len(t) - 1)
        lines.append(f"{cls} coco AP@{t[0]:.2f}:{step:.2f}:{t[-1]:.2f}:")
        metrics = [(m, label) for m, _, label in _ROWS] + ([("aos", "aos ")] if show_aos else [])
        for m, label in metrics:
            lines.append(
                f"{label} AP:" + ", ".join(f"{_value(result.coco['R11'][cls][m][d]):.2f}" for d in DIFFICULTIES)
            )
    return "\n".join(lines) + "\n"
