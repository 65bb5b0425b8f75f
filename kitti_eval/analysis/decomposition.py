"""Why AP is lost: TIDE's error decomposition and nuScenes' true-positive errors, on the devkit's matching.

**Error decomposition** (Bolya et al., "TIDE", ECCV 2020, adapted to KITTI). For one class C, metric
(bbox, bev, 3d; AOS on the bbox matching), difficulty and IoU threshold ``t`` (the strict set by default),
every detection and ground-truth box gets at most one error type, read off the devkit's **pass 1** with
every detection taking part (each ground-truth box in file order takes the unassigned detection of
highest score with overlap > t; :func:`kitti_eval.core.matching.frame_pass1`): the score-first matching
that chooses the score thresholds, and TIDE's own ("taken by a higher-scoring detection"). The
protocol's ignore rules stay as they are: ground truth of a neighbour class or outside the difficulty
(ignored, code 1) counts as C's own for overlaps but is never missed; a detection under the difficulty's
height is ignored whatever its class and never an error; DontCare regions keep suppressing false
positives in the metrics the protocol says. Overlaps are those of the metric (2D, BEV or 3D IoU);
"own" ground truth is C's and its neighbours' boxes, "another class" is any other box but DontCare.

A detection of C that counts (not too small), is **not taken in pass 1** and is **not covered by a
DontCare region** (> t) is a false positive of exactly one type, tried in this order:

===============  =========================================================  ==============================
type             rule                                                        TIDE's fix, in KITTI's terms
===============  =========================================================  ==============================
duplicate        overlap > t with own ground truth (which pass 1 gave to a   suppressed
                 higher-scoring detection)
classification   overlap > t with ground truth of another class              re-labelled: it leaves C
                                                                             (suppressed in C's matching)
localization     own overlap in [0.1, t]                                     moved onto that box (overlap
                                                                             1 with it, 0 with every other
                                                                             box and region of the frame)
                                                                             if no detection took it in
                                                                             pass 1 and no higher-scoring
                                                                             fix claimed it; else
                                                                             suppressed
both             another class's overlap in [0.1, t] (own < 0.1)             suppressed
background       overlap < 0.1 with every ground-truth box                   suppressed
===============  =========================================================  ==============================

Classification also runs the other way: a detection of **another class** (any name but DontCare) whose
overlap with its own class's ground truth (that class and its neighbours) is <= t, and whose overlap
with C's ground truth is > t, would be C's true positive with C's label. Fixing classification for C
re-labels it C (it joins C's matching as a counting detection) if no detection took that box in pass 1
and no higher-scoring fix claimed it; else it stays out. A counting ground-truth box of C is **missed**
when pass 1 gave it no detection and no localization or classification error points at it (its box of
highest overlap); the fix removes it from the evaluation (it takes no part, so there is one box fewer to
find: TIDE lowers the number of ground truth). For AOS, **orientation**: a detection taken in pass 1 by a
counting box with ``|alpha_det - alpha_gt| > pi/2`` (wrapped); the fix turns it around (alpha + pi).
Localization and classification claims are settled together by descending score (then file order).

Each number is ``AP(after fixing only that type) - AP(as evaluated)`` in AP points (R40 and R11), where
both APs run the devkit's whole procedure on the changed inputs: pass 1 again, the score thresholds
recomputed from its true positives (at most 41, recall steps of 1/40), pass 2 at each. Fixing every type
at once leaves only true positives and absorbed detections: 100 when at least 41 counting boxes remain
and pass 2's overlap-first choice agrees with pass 1 (KITTI's R40 never reaches 100 with fewer).

Speed: each frame's counts are step functions of the score threshold
(:func:`kitti_eval.core.matching.frame_events_many`), computed once; a fix re-matches only the frames it
changes, and a false positive that can match nothing (every type but duplicate, and a suppressed
localization error) only loses its own step.

**True-positive errors** (nuScenes' TP metrics), for the detections of C matched in pass 2 of the 3D
matching at the same thresholds (a counting detection taking a counting box): translation, the distance
of the two bottom centres in the ground plane (camera x, z; metres); scale, ``1 - IoU`` of the two boxes
aligned in centre and heading (``1 - prod(min(l, h, w)) / (V_det + V_gt - prod(min))``); orientation, the
smallest difference of ``rotation_y`` (radians, in [0, pi]). Each is a 41-point curve, the mean over the
true positives at each score threshold of the matching (None past the last), and one number: the mean of
the curve over the thresholds whose recall (TP / counting boxes) is at least 0.1.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.ap import average_precision, curve_from_counts
from ..core.arrays import kernel_input
from ..core.cpus import default_workers
from ..core.evaluation import Plan, Totals, plan_evaluation, result_from_counts
from ..core.frames import Annotations
from ..core.kernel_cache import njit
from ..core.matching import (
    VALID,
    Candidates,
    FrameEvents,
    Frames,
    MatchingInputs,
    MatchJob,
    PRCounts,
    best_overlaps,
    checked_inputs,
    checked_layout,
    find_candidates,
    frame_events_many,
    frame_pass1,
    frame_pass2,
    rank_descending,
    score_thresholds,
    widest_step,
)
from ..core.protocol import (
    DEFAULT_OSET,
    DEFAULT_RECALL,
    METRICS,
    N_SAMPLE_PTS,
    RECALL_MODES,
    Difficulty,
    EvalConfig,
    Metric,
)
from ..core.result import AOS_TYPES, ERROR_TYPES, EvalResult
from ..errors import ConfigError

__all__ = [
    "ERROR_TYPES",
    "AOS_TYPES",
    "TP_ERRORS",
    "BACKGROUND_IOU",
    "MIN_RECALL",
    "Decomposition",
    "SlotErrors",
    "TPErrors",
    "decompose",
    "decompose_plan",
    "evaluate_with_errors",
    "group_maxima",
    "pass1_taken",
    "tp_error_sums",
    "errors_document",
    "render_errors",
]

#: nuScenes' true-positive errors
TP_ERRORS: tuple[str, ...] = ("translation", "scale", "orientation")
#: below this overlap with every box, a false positive is background (TIDE's background threshold)
BACKGROUND_IOU = 0.1
#: true-positive errors are averaged over the score thresholds reaching this recall (nuScenes' min_recall)
MIN_RECALL = 0.1
#: the metric whose matching the true-positive errors are read from
TP_METRIC = Metric.THREE_D


# --------------------------------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True)
def _group_maxima(
    pair_offsets: np.ndarray, gt_offsets: np.ndarray, dt_offsets: np.ndarray, ov: np.ndarray, groups: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each detection's largest overlap with the ground truth of each group of ``groups`` (G, M) and the
    row of that box (the first in file order on ties; -1 and 0.0 without an overlap > 0): the matching's
    :func:`kitti_eval.core.matching.best_overlaps`, with the rows."""
    n_dt = dt_offsets[dt_offsets.shape[0] - 1]
    best = np.zeros((groups.shape[0], n_dt), dtype=np.float64)
    arg = np.full((groups.shape[0], n_dt), -1, dtype=np.int64)
    best_overlaps(pair_offsets, ov, gt_offsets, dt_offsets, groups, best, arg)
    return best, arg


@njit(cache=True, nogil=True)
def _pass1_taken(c: Candidates, min_overlap: float, n_dt: int) -> np.ndarray:
    """Pass 1 on every frame of ``c`` (built with each box's row as its alpha): the ground-truth row each
    detection was taken by, -1 if none."""
    out = np.full(n_dt, -1, dtype=np.int64)
    widest = widest_step(c.d_ptr)
    assigned = np.empty(widest, dtype=np.int64)
    scratch = np.empty(widest, dtype=np.float64)
    for f in range(c.valid.shape[0]):
        frame_pass1(c, f, min_overlap, scratch, assigned)
        ga, d0 = c.g_ptr[f], c.d_ptr[f]
        for a in range(c.d_ptr[f + 1] - d0):
            if assigned[a] >= 0:
                out[int(c.d_alpha[d0 + a])] = int(c.g_alpha[ga + assigned[a]])
    return out


@njit(cache=True, nogil=True, inline="always")
def _pair_errors(d: np.ndarray, g: np.ndarray) -> tuple[float, float, float]:
    """Translation, scale and orientation errors of a detection's box ``d`` against ``g`` (x, y, z, l, h, w,
    ry): ground-plane centre distance, 1 - IoU of the boxes aligned in centre and heading, yaw difference."""
    translation = math.sqrt((d[0] - g[0]) ** 2 + (d[2] - g[2]) ** 2)
    inter = min(d[3], g[3]) * min(d[4], g[4]) * min(d[5], g[5])
    union = d[3] * d[4] * d[5] + g[3] * g[4] * g[5] - inter
    scale = 1.0 - inter / union if union > 0.0 else 1.0
    turn = (d[6] - g[6]) % (2.0 * math.pi)
    return translation, scale, min(turn, 2.0 * math.pi - turn)


@njit(cache=True, nogil=True)
def _tp_error_events(
    c: Candidates, min_overlap: float, dt_boxes: np.ndarray, gt_boxes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pass 2's true positives as step functions of the score threshold (as ``_events`` in matching), with
    their summed errors: when the threshold falls to ``ev_score``, (tp, translation, scale, orientation)
    change by ``ev_delta``. ``c`` is built with each box's row as its alpha."""
    widest = widest_step(c.d_ptr)
    taken = np.empty(widest, dtype=np.int64)
    below = np.empty(widest, dtype=np.bool_)
    ranked = np.empty(widest, dtype=np.float64)
    n_max = c.d_ptr[c.d_ptr.shape[0] - 1]
    ev_score = np.empty(n_max, dtype=np.float64)
    ev_delta = np.zeros((n_max, 4), dtype=np.float64)
    n_ev = 0
    prev = np.zeros(4, dtype=np.float64)
    now = np.zeros(4, dtype=np.float64)
    for f in range(c.valid.shape[0]):
        ga, d0, m = c.g_ptr[f], c.d_ptr[f], c.d_ptr[f + 1] - c.d_ptr[f]
        rank_descending(c.d_score[d0 : d0 + m], ranked)
        prev[:] = 0.0
        a = 0
        while a < m:
            level = ranked[a]
            while a < m and ranked[a] >= level:
                a += 1
            frame_pass2(c, f, min_overlap, level, False, taken, below)
            now[:] = 0.0
            for b in range(m):
                i = taken[b]
                if i >= 0 and c.g_code[ga + i] == VALID and c.d_code[d0 + b] == VALID:
                    t, s, o = _pair_errors(dt_boxes[int(c.d_alpha[d0 + b])], gt_boxes[int(c.g_alpha[ga + i])])
                    now[0] += 1.0
                    now[1] += t
                    now[2] += s
                    now[3] += o
            ev_score[n_ev] = level
            for q in range(4):
                ev_delta[n_ev, q] = now[q] - prev[q]
                prev[q] = now[q]
            n_ev += 1
    return ev_score[:n_ev], ev_delta[:n_ev]


# --------------------------------------------------------------------------------------------------- wrappers


def group_maxima(
    pair_offsets: npt.ArrayLike,
    overlaps: npt.ArrayLike,
    gt_offsets: npt.ArrayLike,
    dt_offsets: npt.ArrayLike,
    groups: npt.ArrayLike,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Each detection's largest overlap with each group of ground truth, and which box it is.

    Parameters: the CSR layout of :func:`kitti_eval.core.matching.pr_counts` (``overlaps`` (P,)), and
    ``groups`` (G, M) bool, the boxes of each group. Returns ``best`` (G, N) float64 (0.0 where no overlap
    is > 0) and ``arg`` (G, N) int64, the row of that box (the first on ties, -1 without one).
    """
    po, (ov,), go, do = checked_layout(pair_offsets, [overlaps], gt_offsets, dt_offsets)
    gr = kernel_input(groups, np.bool_)
    if gr.ndim != 2 or gr.shape[1] != int(go[-1]):
        raise ValueError(f"Expected `groups` with shape (G, {int(go[-1])}), got {gr.shape}")
    return _group_maxima(po, go, do, ov, gr)


def _index_candidates(m: MatchingInputs, min_overlap: float) -> Candidates:
    """The candidates (:func:`kitti_eval.core.matching.find_candidates`) of the one matching of ``m`` (checked
    inputs) with each box's row in place of its alpha, so that what a kernel reads off them can be mapped back
    to the boxes."""
    ov, ignored_gt, ignored_det = m.overlaps[0], m.ignored_gt[0], m.ignored_det[0]
    groups = np.stack([ignored_gt != -1, m.dontcare])
    best, _ = _group_maxima(m.pair_offsets, m.gt_offsets, m.dt_offsets, ov, groups)
    n_gt, n_dt = ignored_gt.shape[0], ignored_det.shape[0]
    frames = Frames(
        m.pair_offsets,
        m.gt_offsets,
        m.dt_offsets,
        m.score,
        np.arange(n_gt, dtype=np.float64),
        np.arange(n_dt, dtype=np.float64),
    )
    return find_candidates(frames, ov, ignored_gt, ignored_det, m.dontcare, best[0], best[1], float(min_overlap))


def _one_matching(inputs: MatchingInputs) -> MatchingInputs:
    """The checked inputs of one matching: one overlap array, one row of ignore codes (``ignored_gt`` (M,),
    ``ignored_det`` (N,), or (1, M) and (1, N)); no orientation."""
    return checked_inputs(inputs.one_matching()._replace(gt_alpha=None, dt_alpha=None))


def pass1_taken(inputs: MatchingInputs, min_overlap: float) -> npt.NDArray[np.int64]:
    """(N,) the ground-truth row that took each detection in the devkit's pass 1 (every detection taking
    part), -1 if none. ``inputs``: one matching's, as :func:`kitti_eval.core.matching.pr_counts` takes them."""
    m = _one_matching(inputs)
    return _pass1_taken(_index_candidates(m, min_overlap), float(min_overlap), int(m.dt_offsets[-1]))


def tp_error_sums(
    inputs: MatchingInputs,
    dt_boxes: npt.ArrayLike,
    gt_boxes: npt.ArrayLike,
    min_overlap: float,
    thresholds: npt.ArrayLike,
) -> npt.NDArray[np.float64]:
    """(T, 4): at each score threshold, pass 2's true positives and their summed translation, scale and
    orientation errors (see the module docstring). ``inputs``: one matching's, as
    :func:`kitti_eval.core.matching.pr_counts` takes them; boxes are (x, y, z, l, h, w, ry) rows."""
    m = _one_matching(inputs)
    db = kernel_input(dt_boxes, np.float64)
    gb = kernel_input(gt_boxes, np.float64)
    if db.shape != (m.ignored_det.shape[1], 7) or gb.shape != (m.ignored_gt.shape[1], 7):
        raise ValueError("Expected `dt_boxes` (N, 7) and `gt_boxes` (M, 7)")
    c = _index_candidates(m, min_overlap)
    ev_score, ev_delta = _tp_error_events(c, float(min_overlap), db, gb)
    return _at_thresholds(ev_score, ev_delta, np.asarray(thresholds, dtype=np.float64))


def _at_thresholds(ev_score: np.ndarray, ev_delta: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """(T, K): the sums of the events scoring at least each threshold."""
    order = np.argsort(-ev_score, kind="stable")
    return _at_thresholds_sorted(ev_score[order], ev_delta[order], thresholds)


def _at_thresholds_sorted(desc: np.ndarray, delta: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """:func:`_at_thresholds` of events already sorted by score, descending."""
    cum = np.concatenate([np.zeros((1, delta.shape[1])), np.cumsum(delta, axis=0)])
    return cum[np.searchsorted(-desc, -thresholds, side="right")]


# --------------------------------------------------------------------------------------------------- results


@dataclass(frozen=True)
class SlotErrors:
    """One (class, metric, difficulty): the AP as evaluated and after fixing each type alone (``fixed[type]``)
    and every type at once (``fixed["all"]``), each by recall mode; ``counts[type]``: the boxes of each type."""

    ap: Mapping[str, float]
    fixed: Mapping[str, Mapping[str, float]]
    counts: Mapping[str, int]

    def delta(self, kind: str, recall: str = DEFAULT_RECALL) -> float:
        """AP points gained by fixing ``kind`` (a type, or "all")."""
        return self.fixed[kind][recall] - self.ap[recall]


@dataclass(frozen=True)
class TPErrors:
    """One (class, difficulty): nuScenes' true-positive errors on the 3D matching.

    ``mean[name]``: the mean over the thresholds with recall >= 0.1 (None without one); ``curves[name]``:
    41 values, the mean error of the true positives at each score threshold (None past the last or
    without true positives); ``recall``: the recall at each threshold (None past the last).
    """

    mean: Mapping[str, float | None]
    curves: Mapping[str, Sequence[float | None]]
    recall: Sequence[float | None]


@dataclass(frozen=True)
class Decomposition:
    """``errors[cls][metric][difficulty]`` (metric: bbox, bev, 3d, aos; None where not evaluated) and
    ``tp_errors[cls][difficulty]`` (None where the 3D metric is not evaluated), at one threshold set."""

    classes: tuple[str, ...]
    oset: str
    errors: Mapping[str, Mapping[str, Mapping[str, SlotErrors | None]]]
    tp_errors: Mapping[str, Mapping[str, TPErrors | None]]
    timings: Mapping[str, float] = field(default_factory=dict, compare=False)


# --------------------------------------------------------------------------------------------------- the rules


@dataclass(frozen=True, eq=False)
class _Job:
    """One matching's inputs (every frame) and what pass 1 made of them."""

    job: MatchJob
    ov: np.ndarray  # (P,) the metric's overlaps
    ig: np.ndarray  # (M,) ignore codes
    idet: np.ndarray  # (N,)
    dc: np.ndarray  # (M,) DontCare rows that suppress false positives in this metric (all False if none)
    taken: np.ndarray  # (N,) pass 1: the ground-truth row that took each detection, -1
    own_best: np.ndarray  # (N,) largest overlap with C's own ground truth (codes 0 and 1)
    own_arg: np.ndarray  # (N,) that box's row
    other_best: np.ndarray  # (N,) with ground truth of another class (not DontCare)
    kin_best: np.ndarray  # (N,) with the detection's own class's ground truth (its name and neighbours)
    dc_best: np.ndarray  # (N,) with the DontCare rows in ``dc``
    is_dontcare_det: np.ndarray  # (N,) detections named DontCare: never re-labelled


@dataclass(frozen=True, eq=False)
class _Labels:
    """The error type of each box (see the module docstring)."""

    duplicate: np.ndarray
    classification: np.ndarray  # C's detections that belong to another class
    incoming: np.ndarray  # other classes' detections that belong to C
    localization: np.ndarray
    both: np.ndarray
    background: np.ndarray
    missed: np.ndarray  # (M,)
    orientation: np.ndarray
    gt_taken: np.ndarray  # (M,) taken in pass 1

    def counts(self) -> dict[str, int]:
        n = {
            "classification": int(self.classification.sum() + self.incoming.sum()),
            "localization": int(self.localization.sum()),
            "both": int(self.both.sum()),
            "duplicate": int(self.duplicate.sum()),
            "background": int(self.background.sum()),
            "missed": int(self.missed.sum()),
            "orientation": int(self.orientation.sum()),
        }
        return n


def _wrapped_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| wrapped to [0, pi]."""
    d = np.mod(a - b, 2 * np.pi)
    return np.minimum(d, 2 * np.pi - d)


def _labels(j: _Job, plan_gt_alpha: np.ndarray, dt_alpha: np.ndarray) -> _Labels:
    """Each box's error type, by the rules of the module docstring, in their order."""
    t = j.job.min_overlap
    open_fp = (j.idet == VALID) & (j.taken < 0) & ~(j.dc_best > t)
    duplicate = open_fp & (j.own_best > t)
    rest = open_fp & ~duplicate
    classification = rest & (j.other_best > t)
    rest &= ~classification
    localization = rest & (j.own_best >= BACKGROUND_IOU)
    rest &= ~localization
    both = rest & (j.other_best >= BACKGROUND_IOU)
    background = rest & ~both
    incoming = (j.idet == -1) & ~j.is_dontcare_det & (j.kin_best <= t) & (j.own_best > t)
    gt_taken = np.zeros(j.ig.shape[0], dtype=np.bool_)
    gt_taken[j.taken[j.taken >= 0]] = True
    pointed = np.zeros_like(gt_taken)
    pointed[j.own_arg[localization | incoming]] = True
    missed = (j.ig == VALID) & ~gt_taken & ~pointed
    counted = (j.idet == VALID) & (j.taken >= 0)
    counted[counted] = j.ig[j.taken[counted]] == VALID
    orientation = counted.copy()
    orientation[counted] = _wrapped_difference(dt_alpha[counted], plan_gt_alpha[j.taken[counted]]) > np.pi / 2
    return _Labels(duplicate, classification, incoming, localization, both, background, missed, orientation, gt_taken)


@dataclass(frozen=True, eq=False)
class _Fix:
    """What fixing a set of types changes in one matching's inputs."""

    suppress: np.ndarray  # (N,) detections that leave the matching
    join: np.ndarray  # (N,) detections of another class that join it, counting
    move: np.ndarray  # (N,) detections moved onto ``target``
    target: np.ndarray  # (N,) the box each moved detection lands on
    drop_gt: np.ndarray  # (M,) ground truth removed from the evaluation
    flip: np.ndarray  # (N,) detections turned around (alpha + pi)


def _fix(lab: _Labels, j: _Job, score: np.ndarray, kinds: frozenset[str]) -> _Fix:
    """The changes of fixing ``kinds`` together (TIDE's fixes, see the module docstring)."""
    n = score.shape[0]
    suppress = np.zeros(n, dtype=np.bool_)
    for kind in ("duplicate", "classification", "both", "background"):
        if kind in kinds:
            suppress |= getattr(lab, kind)
    claims = np.zeros(n, dtype=np.bool_)
    if "localization" in kinds:
        claims |= lab.localization
    if "classification" in kinds:
        claims |= lab.incoming
    cand = np.flatnonzero(claims)
    cand = cand[np.lexsort((cand, -score[cand]))]  # by score, descending, then file order
    targets = j.own_arg[cand]
    first = np.zeros(len(cand), dtype=np.bool_)
    first[np.unique(targets, return_index=True)[1]] = True
    wins = first & ~lab.gt_taken[targets]
    move = np.zeros(n, dtype=np.bool_)
    join = np.zeros(n, dtype=np.bool_)
    won = cand[wins]
    move[won] = lab.localization[won]
    join[won] = lab.incoming[won]
    lost = cand[~wins]
    suppress[lost[lab.localization[lost]]] = True
    drop_gt = lab.missed.copy() if "missed" in kinds else np.zeros_like(lab.missed)
    flip = lab.orientation.copy() if "orientation" in kinds else np.zeros_like(lab.orientation)
    return _Fix(suppress, join, move, j.own_arg.copy(), drop_gt, flip)


# --------------------------------------------------------------------------------------------------- AP from events


def _ranges(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The concatenation of ``arange(s, e)`` for each pair."""
    lens = ends - starts
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    shift = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
    return np.arange(total, dtype=np.int64) + shift


@dataclass(frozen=True, eq=False)
class _Shared:
    """What every matching of the decomposition shares: the frames' layout and the boxes' fields."""

    pair_offsets: np.ndarray
    gt_offsets: np.ndarray
    dt_offsets: np.ndarray
    score: np.ndarray
    gt_alpha: np.ndarray
    dt_alpha: np.ndarray
    dontcare: np.ndarray
    dt_frame: np.ndarray
    gt_frame: np.ndarray


def _events_of(s: _Shared, j: _Job, fix: _Fix, frames: np.ndarray) -> FrameEvents:  # the changed frames, matched again
    """The events of ``frames`` (sorted frame indices) with ``fix`` applied."""
    g0, g1 = s.gt_offsets[frames], s.gt_offsets[frames + 1]
    d0, d1 = s.dt_offsets[frames], s.dt_offsets[frames + 1]
    p0, p1 = s.pair_offsets[frames], s.pair_offsets[frames + 1]
    gt_rows, dt_rows, pair_rows = _ranges(g0, g1), _ranges(d0, d1), _ranges(p0, p1)

    def offsets(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(hi - lo)]).astype(np.int64)

    go, do, po = offsets(g0, g1), offsets(d0, d1), offsets(p0, p1)
    ov = j.ov[pair_rows]
    ig = j.ig[gt_rows].copy()
    ig[fix.drop_gt[gt_rows]] = -1
    idet = j.idet[dt_rows].copy()
    idet[fix.suppress[dt_rows]] = -1
    idet[fix.join[dt_rows]] = VALID
    alpha = s.dt_alpha[dt_rows].copy()
    alpha[fix.flip[dt_rows]] += np.pi
    moved = dt_rows[fix.move[dt_rows]]
    if len(moved):
        pos = np.searchsorted(frames, s.dt_frame[moved])  # each moved detection's frame in the subset
        f = frames[pos]
        n_gt = s.gt_offsets[f + 1] - s.gt_offsets[f]
        base = po[pos] + (moved - s.dt_offsets[f]) * n_gt
        ov[_ranges(base, base + n_gt)] = 0.0
        ov[base + fix.target[moved] - s.gt_offsets[f]] = 1.0
    job = MatchJob(0, 0, j.job.min_overlap, j.job.compute_aos, j.job.dontcare)
    inputs = MatchingInputs(
        po, [ov], go, do, ig[None], idet[None], s.dontcare[gt_rows], s.score[dt_rows], s.gt_alpha[gt_rows], alpha
    )
    (events,) = frame_events_many(inputs, [job], workers=1)
    return events


def _aps(n_valid: int, tp_score: np.ndarray, parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """AP (and AOS, under "aos_R40"/"aos_R11") from events given as parts of (scores sorted descending,
    deltas): the devkit's thresholds from pass 1's true-positive scores, pass 2's counts at each."""
    thresholds = score_thresholds(tp_score, n_valid)
    counts = np.zeros((len(thresholds), 4))
    for ev_score, ev_delta in parts:
        counts += _at_thresholds_sorted(ev_score, ev_delta, thresholds)
    counts[:, 2] += n_valid
    curve = curve_from_counts(
        PRCounts(
            thresholds, counts[:, 0].copy(), counts[:, 1].copy(), counts[:, 2].copy(), counts[:, 3].copy(), n_valid
        )
    )
    out = {r: average_precision(curve.precision, r) for r in RECALL_MODES}
    out.update({f"aos_{r}": average_precision(curve.orientation, r) for r in RECALL_MODES})
    return out


def _fixed_aps(s: _Shared, j: _Job, orig: FrameEvents, fix: _Fix) -> dict[str, float]:
    """AP after ``fix``: the changed frames matched again, the others' events kept; a suppressed detection
    that can match nothing (no own overlap > t) in an unchanged frame loses only its false-positive step."""
    t = j.job.min_overlap
    candidate = (j.idet != -1) & (j.own_best > t)
    changed = np.zeros(orig.valid.shape[0], dtype=np.bool_)
    changed[s.dt_frame[(fix.suppress & candidate) | fix.join | fix.move | fix.flip]] = True
    changed[s.gt_frame[fix.drop_gt]] = True
    frames = np.flatnonzero(changed)
    free = fix.suppress & ~candidate & ~changed[s.dt_frame]
    n_valid = int(orig.valid.sum() - orig.valid[frames].sum())
    tp = [orig.tp_score[~changed[orig.tp_frame]]]
    kept = orig.ev_delta * ~changed[orig.ev_frame][:, None]
    gone_score = -np.sort(-s.score[free])
    gone = np.zeros((len(gone_score), 4))
    gone[:, 1] = -1.0
    parts = [(orig.ev_score, kept), (gone_score, gone)]
    if len(frames):
        sub = _events_of(s, j, fix, frames)
        n_valid += int(sub.valid.sum())
        tp.append(sub.tp_score)
        parts.append((sub.ev_score, sub.ev_delta))
    return _aps(n_valid, np.concatenate(tp), parts)


def _slot_errors(s: _Shared, j: _Job, orig: FrameEvents, lab: _Labels, with_aos: bool) -> list[tuple[str, SlotErrors]]:
    """The decomposition of one matching: for its metric, and for AOS when it carries it."""
    base = _aps(int(orig.valid.sum()), orig.tp_score, [(orig.ev_score, orig.ev_delta)])
    kinds = AOS_TYPES if with_aos else ERROR_TYPES
    fixed = {k: _fixed_aps(s, j, orig, _fix(lab, j, s.score, frozenset([k]))) for k in kinds}
    fixed["all"] = _fixed_aps(s, j, orig, _fix(lab, j, s.score, frozenset(kinds)))
    counts = lab.counts()
    metric_types = (*ERROR_TYPES, "all")
    out = [
        (
            "ap",
            SlotErrors(
                {r: base[r] for r in RECALL_MODES},
                {k: {r: fixed[k][r] for r in RECALL_MODES} for k in metric_types},
                {k: counts[k] for k in ERROR_TYPES},
            ),
        )
    ]
    if with_aos:
        out.append(
            (
                "aos",
                SlotErrors(
                    {r: base[f"aos_{r}"] for r in RECALL_MODES},
                    {k: {r: fixed[k][f"aos_{r}"] for r in RECALL_MODES} for k in (*AOS_TYPES, "all")},
                    {k: counts[k] for k in AOS_TYPES},
                ),
            )
        )
    return out


def _tp_errors(s: _Shared, j: _Job, orig: FrameEvents, dt_boxes: np.ndarray, gt_boxes: np.ndarray) -> TPErrors:
    n_valid = int(orig.valid.sum())
    thresholds = score_thresholds(orig.tp_score, n_valid)
    inputs = MatchingInputs(s.pair_offsets, [j.ov], s.gt_offsets, s.dt_offsets, j.ig, j.idet, j.dc, s.score)
    sums = tp_error_sums(inputs, dt_boxes, gt_boxes, j.job.min_overlap, thresholds)
    n_thr = len(thresholds)
    curves: dict[str, list[float | None]] = {}
    means: dict[str, float | None] = {}
    recall: list[float | None] = [float(sums[k, 0] / n_valid) for k in range(n_thr)] + [None] * (N_SAMPLE_PTS - n_thr)
    for q, name in enumerate(TP_ERRORS, start=1):
        values = [float(sums[k, q] / sums[k, 0]) if sums[k, 0] > 0 else None for k in range(n_thr)]
        curves[name] = values + [None] * (N_SAMPLE_PTS - n_thr)
        picked = [v for v, r in zip(values, recall) if v is not None and r is not None and r >= MIN_RECALL]
        means[name] = float(np.mean(picked)) if picked else None
    return TPErrors(means, curves, recall)


# --------------------------------------------------------------------------------------------------- entry points


def decompose(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig | None = None,
    *,
    oset: str = DEFAULT_OSET,
    workers: int | None = None,
) -> Decomposition:
    """The error decomposition and true-positive errors of ``dt`` against ``gt`` (see the module docstring)."""
    return decompose_plan(plan_evaluation(gt, dt, config), oset=oset, workers=workers)


def evaluate_with_errors(
    gt: Annotations,
    dt: Annotations,
    config: EvalConfig | None = None,
    *,
    keep_curves: bool = False,
    oset: str = DEFAULT_OSET,
) -> tuple[EvalResult, Decomposition]:
    """:func:`~kitti_eval.core.evaluation.evaluate` and the decomposition, from one plan (the overlaps and
    ignore codes are computed once for both)."""
    plan = plan_evaluation(gt, dt, config)
    result = result_from_counts(plan, plan.counts(), Totals.of(plan), keep_curves=keep_curves)
    return result, decompose_plan(plan, oset=oset)


def decompose_plan(plan: Plan, *, oset: str = DEFAULT_OSET, workers: int | None = None) -> Decomposition:
    """:func:`decompose` on a planned evaluation (its overlaps and ignore codes, computed once)."""
    import time

    if oset not in plan.config.threshold_sets:
        raise ConfigError(f"unknown threshold set {oset!r}; the evaluation has {', '.join(plan.config.threshold_sets)}")
    t0 = time.perf_counter()
    gt, dt = plan.gt, plan.dt
    fo = plan.overlaps
    overlaps = (fo.bbox, fo.bev, fo.d3)
    s = _Shared(
        pair_offsets=fo.pair_offsets,
        gt_offsets=kernel_input(gt.offsets, np.int64),
        dt_offsets=kernel_input(dt.offsets, np.int64),
        score=kernel_input(dt.score, np.float64),
        gt_alpha=kernel_input(gt.alpha, np.float64),
        dt_alpha=kernel_input(dt.alpha, np.float64),
        dontcare=plan.dontcare,
        dt_frame=np.repeat(np.arange(gt.num_frames), np.diff(dt.offsets)),
        gt_frame=np.repeat(np.arange(gt.num_frames), np.diff(gt.offsets)),
    )
    slots = [sl for sl in plan.slots if sl.oset == oset]
    jobs = sorted({sl.job for sl in slots if sl.job is not None})
    orig_events = dict(zip(jobs, plan.events([plan.jobs[k] for k in jobs], workers=workers)))
    # the detections' own-class groups (name and neighbours, case-insensitive), for classification's other way
    gt_names = np.char.lower(gt.name.astype(str))
    dt_names = np.char.lower(dt.name.astype(str))
    kin_names = sorted(set(dt_names.tolist()))
    neighbours = {k.lower(): {n.lower() for n in v} for k, v in plan.config.neighbours.items()}
    kin_groups = np.stack(
        [np.isin(gt_names, sorted({name} | neighbours.get(name, set()))) & ~plan.dontcare for name in kin_names]
        or [np.zeros(gt.num_boxes, dtype=np.bool_)]
    )
    kin_of_det = np.searchsorted(np.array(kin_names or [""]), dt_names) if dt.num_boxes else np.zeros(0, np.int64)
    is_dontcare_det = dt.is_class("DontCare")
    kin_best_by_metric: dict[int, np.ndarray] = {}

    def kin_best(metric: int) -> np.ndarray:
        if metric not in kin_best_by_metric:
            best, _ = _group_maxima(s.pair_offsets, s.gt_offsets, s.dt_offsets, overlaps[metric], kin_groups)
            kin_best_by_metric[metric] = best[kin_of_det, np.arange(dt.num_boxes)] if dt.num_boxes else np.zeros(0)
        return kin_best_by_metric[metric]

    for m in sorted({plan.jobs[k].overlap for k in jobs}):
        kin_best(m)  # filled once, before the threads share it

    def prepare(k: int) -> _Job:
        job = plan.jobs[k]
        ov = overlaps[job.overlap]
        ig, idet = plan.ignored_gt[job.codes], plan.ignored_det[job.codes]
        dc = kernel_input(plan.dontcare if job.dontcare else np.zeros(gt.num_boxes, dtype=np.bool_), np.bool_)
        groups = np.stack([ig != -1, (ig == -1) & ~plan.dontcare, dc])
        best, arg = _group_maxima(s.pair_offsets, s.gt_offsets, s.dt_offsets, ov, groups)
        frames = Frames(
            s.pair_offsets,
            s.gt_offsets,
            s.dt_offsets,
            s.score,
            np.arange(gt.num_boxes, dtype=np.float64),
            np.arange(dt.num_boxes, dtype=np.float64),
        )
        c = find_candidates(frames, ov, ig, idet, dc, best[0], best[2], float(job.min_overlap))
        taken = _pass1_taken(c, float(job.min_overlap), dt.num_boxes)
        return _Job(
            job, ov, ig, idet, dc, taken, best[0], arg[0], best[1], kin_best(job.overlap), best[2], is_dontcare_det
        )

    results: dict[int, list[tuple[str, SlotErrors]]] = {}
    tp_results: dict[int, TPErrors] = {}
    aos_jobs = {sl.job for sl in slots if sl.job is not None and sl.with_aos and sl.metric is Metric.BBOX}
    tp_jobs = {sl.job for sl in slots if sl.job is not None and sl.metric is TP_METRIC}
    dt_boxes = kernel_input(dt.boxes_camera, np.float64)
    gt_boxes = kernel_input(gt.boxes_camera, np.float64)

    def run(k: int) -> None:
        j = prepare(k)
        lab = _labels(j, s.gt_alpha, s.dt_alpha)
        results[k] = _slot_errors(s, j, orig_events[k], lab, k in aos_jobs)
        if k in tp_jobs:
            tp_results[k] = _tp_errors(s, j, orig_events[k], dt_boxes, gt_boxes)

    n_workers = default_workers() if workers is None else max(1, int(workers))
    _map(run, jobs, n_workers)
    errors: dict[str, dict[str, dict[str, SlotErrors | None]]] = {
        cls: {m: {d.label: None for d in Difficulty} for m in METRICS} for cls in plan.config.classes
    }
    tp: dict[str, dict[str, TPErrors | None]] = {
        cls: {d.label: None for d in Difficulty} for cls in plan.config.classes
    }
    for sl in slots:
        if sl.job is None:
            continue
        for which, value in results[sl.job]:
            if which == "ap":
                errors[sl.cls][sl.metric.value][sl.difficulty.label] = value
            elif sl.with_aos and sl.metric is Metric.BBOX:
                errors[sl.cls]["aos"][sl.difficulty.label] = value
        if sl.metric is TP_METRIC:
            tp[sl.cls][sl.difficulty.label] = tp_results[sl.job]
    return Decomposition(tuple(plan.config.classes), oset, errors, tp, {"decomposition": time.perf_counter() - t0})


def _map(fn: Callable[[int], None], items: Sequence[int], workers: int) -> None:
    """``fn`` over ``items`` on ``workers`` threads (the kernels release the GIL), largest first."""
    if workers <= 1 or len(items) <= 1:
        for k in items:
            fn(k)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for _ in pool.map(fn, items):
            pass


# --------------------------------------------------------------------------------------------------- documents


def errors_document(dec: Decomposition, *, full: bool = True) -> dict[str, Any]:
    """The decomposition as JSON-ready data.

    ``errors[class][metric][difficulty][type]`` (R40) and ``errors_r11`` (R11): AP points gained by fixing
    each type alone (None where the value is not evaluated); ``tp_errors[class][difficulty][name]``: the
    mean true-positive errors. With ``full``, also ``error_ap`` and ``error_all_fixed`` (the AP as evaluated
    and after fixing every type, same layout without the type), ``error_counts`` (boxes of each type) and
    ``tp_error_curves`` (41 values per error, and the recall at each threshold).
    """

    def table(fn: Callable[[SlotErrors, str], Any]) -> dict[str, Any]:
        return {
            cls: {
                metric: {d: (None if e is None else fn(e, metric)) for d, e in by_diff.items()}
                for metric, by_diff in by_metric.items()
            }
            for cls, by_metric in dec.errors.items()
        }

    def kinds(metric: str) -> tuple[str, ...]:
        return AOS_TYPES if metric == "aos" else ERROR_TYPES

    doc: dict[str, Any] = {
        "errors": table(lambda e, m: {k: e.delta(k, "R40") for k in kinds(m)}),
        "errors_r11": table(lambda e, m: {k: e.delta(k, "R11") for k in kinds(m)}),
        "tp_errors": {
            cls: {d: (None if v is None else dict(v.mean)) for d, v in by_diff.items()}
            for cls, by_diff in dec.tp_errors.items()
        },
    }
    if full:
        doc = {"threshold_set": dec.oset, "background_iou": BACKGROUND_IOU, **doc}

        def ap_as_evaluated(recall: str) -> Callable[[SlotErrors, str], float]:
            return lambda e, m: e.ap[recall]

        def ap_all_fixed(recall: str) -> Callable[[SlotErrors, str], float]:
            return lambda e, m: e.fixed["all"][recall]

        doc["error_ap"] = {r: table(ap_as_evaluated(r)) for r in RECALL_MODES}
        doc["error_all_fixed"] = {r: table(ap_all_fixed(r)) for r in RECALL_MODES}
        doc["error_counts"] = table(lambda e, m: dict(e.counts))
        doc["tp_error_curves"] = {
            cls: {
                d: (None if v is None else {**{k: list(c) for k, c in v.curves.items()}, "recall": list(v.recall)})
                for d, v in by_diff.items()
            }
            for cls, by_diff in dec.tp_errors.items()
        }
    return doc


_SHORT = {
    "classification": "cls",
    "localization": "loc",
    "both": "both",
    "duplicate": "dupl",
    "background": "bkg",
    "missed": "miss",
    "orientation": "orient",
    "all": "all",
}


def _cell(value: float | None, width: int, digits: int = 2) -> str:
    text = "-" if value is None else f"{value:.{digits}f}"
    return text.rjust(width) if text != f"-{0:.{digits}f}" else f"{0:.{digits}f}".rjust(width)


def _rows(dec: Decomposition, recall: str) -> list[tuple[str, str, str, SlotErrors]]:
    return [
        (cls, metric, d, e)
        for cls in dec.classes
        for metric in METRICS
        for d, e in dec.errors[cls][metric].items()
        if e is not None
    ]


def render_errors(dec: Decomposition, fmt: str = "table", *, recall: str = DEFAULT_RECALL) -> str:
    """The decomposition as a text table, Markdown or JSON (:func:`errors_document`; both recall modes)."""
    import json

    if fmt == "json":
        return json.dumps(errors_document(dec), indent=2, allow_nan=False) + "\n"
    if recall not in RECALL_MODES:
        raise ConfigError(f"unknown recall mode {recall!r}; expected R40 or R11")
    kinds = (*AOS_TYPES, "all")
    if fmt == "markdown":
        out = [
            f"### Error decomposition: AP {recall} ({dec.oset} IoU) and the points fixing each error type alone adds",
            "",
            "| Class | Metric | Difficulty | AP | " + " | ".join(kinds) + " |",
            "|---|---|---|" + "---:|" * (len(kinds) + 1),
        ]
        for cls, metric, d, e in _rows(dec, recall):
            cells = [_cell(e.delta(k, recall) if k in e.fixed else None, 1).strip() for k in kinds]
            out.append(f"| {cls} | {metric} | {d} | {e.ap[recall]:.2f} | " + " | ".join(cells) + " |")
        out += ["", "### True-positive errors (3D matching, mean over recall >= 0.1)", ""]
        out += [
            "| Class | Difficulty | translation (m) | scale (1 - IoU) | orientation (rad) |",
            "|---|---|---:|---:|---:|",
        ]
        for cls in dec.classes:
            for d, v in dec.tp_errors[cls].items():
                if v is not None:
                    cells = [_cell(v.mean[k], 1, 3).strip() for k in TP_ERRORS]
                    out.append(f"| {cls} | {d} | " + " | ".join(cells) + " |")
        return "\n".join(out) + "\n"
    lines = [
        f"Error decomposition: AP {recall} ({dec.oset} IoU) and the AP points gained by fixing each error type alone",
        f"{'class':<11}{'metric':<7}{'difficulty':<11}{'AP':>7}" + "".join(f"{_SHORT[k]:>8}" for k in kinds),
    ]
    for cls, metric, d, e in _rows(dec, recall):
        row = "".join(_cell(e.delta(k, recall) if k in e.fixed else None, 8) for k in kinds)
        lines.append(f"{cls:<11}{metric:<7}{d:<11}{e.ap[recall]:>7.2f}{row}")
    lines += [
        "",
        f"True-positive errors of the 3D matching ({dec.oset} IoU), mean over recall >= {MIN_RECALL:g}",
        f"{'class':<11}{'difficulty':<11}{'translation (m)':>17}{'scale (1-IoU)':>15}{'orientation (rad)':>19}",
    ]
    for cls in dec.classes:
        for d, v in dec.tp_errors[cls].items():
            if v is not None:
                t, s, o = (_cell(v.mean[k], w, 3) for k, w in zip(TP_ERRORS, (17, 15, 19)))
                lines.append(f"{cls:<11}{d:<11}{t}{s}{o}")
    return "\n".join(lines) + "\n"
