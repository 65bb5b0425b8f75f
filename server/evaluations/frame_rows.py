"""What an evaluation stores of each frame, so that its frame listings and frame views read one frame's row (or
one part of every frame's) instead of the kept predictions whole.

The evaluation's job, which has the inputs loaded and matched, writes one row per frame of the ground truth
(table ``evaluation_frames``, in the ground truth's order):

- ``detections``: the frame's detections, every field a frame view shows (names, the numeric fields, the
  ``boxes_lidar`` when kept);
- ``events``: for every (class, difficulty, metric, threshold set) of the result, in the order of
  :attr:`kitti_eval.core.evaluation.Plan.slots`, the frame's valid ground truth and its share of the matching as
  steps of the score threshold (:class:`~kitti_eval.core.matching.FrameEvents`: each step's score, and its
  changes of TP, FP and FN as whole numbers, one byte each when they fit), headed by what the whole set decided
  for the matching (:class:`~kitti_eval.core.evaluation.Facts`).

A listing adds the steps of one slot up (:func:`kitti_eval.analysis.diagnostics.counts_at`, as
:func:`~kitti_eval.analysis.diagnostics.frame_stats` does); a frame view matches the frame's detections alone
under the stored facts. Both answer what reading the predictions whole answers (a differential test pins them).
A question these rows cannot answer (a class the evaluation did not evaluate) is answered the old way.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from kitti_eval.analysis.diagnostics import FrameQuestion, FrameStats, counts_at, not_evaluated, parse_slot, with_class
from kitti_eval.core.evaluation import Facts, Plan, scored_metrics
from kitti_eval.core.frames import NUMERIC_FIELDS, Annotations
from kitti_eval.core.protocol import OVERLAP_METRICS, Difficulty, EvalConfig, Metric

__all__ = ["FrameRow", "frame_rows", "slot_index", "stats_from_rows", "frame_detections", "facts_of", "readable"]

#: the layout of a row's blobs; a row of another layout is not read (the frames are answered the old way)
FORMAT = 1
#: the numeric fields of a detection, in a row's order, and how many numbers each holds
_FIELDS = tuple((f, int(np.prod(shape))) for f, shape in NUMERIC_FIELDS.items())
_WIDTH = sum(w for _, w in _FIELDS)
_LIDAR = 7
#: how the changes of the counts are written, by their width in bytes
_CHANGES = {1: "<i1", 4: "<i4", 8: "<f8"}


@dataclass(frozen=True)
class FrameRow:
    """One frame's row: its place in the ground truth, its id, and the two blobs (see the module)."""

    frame_index: int
    frame_id: str
    detections: bytes
    events: bytes


def _slots(config: EvalConfig) -> list[tuple[str, Difficulty, Metric, str]]:
    """The (class, difficulty, metric, set) of every slot, in :attr:`Plan.slots`' order."""
    return [
        (cls, d, m, oset)
        for cls in config.classes
        for d in Difficulty
        for m in OVERLAP_METRICS
        for oset in config.threshold_sets
    ]


def slot_index(config: EvalConfig, cls: str, metric: Metric, difficulty: Difficulty, oset: str) -> int | None:
    """Where a slot's steps are in a row of an evaluation made with ``config`` (None: not among them)."""
    try:
        return _slots(config).index((cls, difficulty, metric, oset))
    except ValueError:
        return None


def _detections_blob(dt: Annotations, lo: int, hi: int) -> bytes:
    names = [str(n) for n in dt.name[lo:hi]]
    lidar = dt.boxes_lidar is not None
    head = json.dumps({"names": names, "lidar": lidar}).encode()
    cols = [getattr(dt, f)[lo:hi].reshape(hi - lo, w) for f, w in _FIELDS]
    if dt.boxes_lidar is not None:
        cols.append(dt.boxes_lidar[lo:hi].reshape(hi - lo, _LIDAR))
    body = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f8").tobytes()
    return struct.pack("<I", len(head)) + head + body


def frame_rows(plan: Plan) -> Iterator[FrameRow]:
    """The rows of an evaluation's frames, from the plan its result was computed from."""
    config, dt = plan.config, plan.dt
    slots = plan.slots
    assert [(s.cls, s.difficulty, s.metric, s.oset) for s in slots] == _slots(config)
    jobs = sorted({s.job for s in slots if s.job is not None})
    n = plan.gt.num_frames
    steps: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    for j, ev in zip(jobs, plan.events([plan.jobs[j] for j in jobs])):
        order = np.argsort(ev.ev_frame, kind="stable")  # by frame, each frame's steps in the matching's order
        starts = np.searchsorted(ev.ev_frame[order], np.arange(n + 1))
        steps[j] = (ev.valid, ev.ev_score[order], np.ascontiguousarray(ev.ev_delta[order, :3]), starts)
    scored = [scored_metrics(dt, cls) for cls in config.classes]
    head = [FORMAT, len(config.classes), int(plan.compute_aos)]
    head += [int(s[m]) for s in scored for m in OVERLAP_METRICS]
    head.append(len(slots))
    for f in range(n):
        pairs: list[int] = []
        scores: list[np.ndarray] = []
        deltas: list[np.ndarray] = []
        for s in slots:
            if s.job is None:
                pairs += [0, -1]
                continue
            valid, sc, de, starts = steps[s.job]
            a, b = int(starts[f]), int(starts[f + 1])
            pairs += [int(valid[f]), b - a]
            scores.append(sc[a:b])
            deltas.append(de[a:b])
        changes = np.concatenate(deltas) if deltas else np.zeros((0, 3))
        # a step changes a count by one, mostly: whole numbers, in one byte when they fit
        width = 8 if not np.array_equal(np.rint(changes), changes) else 1 if np.all(np.abs(changes) <= 127) else 4
        events = np.asarray(head[:3] + [width] + head[3:] + pairs, dtype="<i8").tobytes()
        if scores:
            events += np.concatenate(scores).astype("<f8").tobytes()
            events += changes.astype(_CHANGES[width]).tobytes()
        lo, hi = int(dt.offsets[f]), int(dt.offsets[f + 1])
        yield FrameRow(f, plan.gt.frame_ids[f], _detections_blob(dt, lo, hi), events)


@dataclass(frozen=True)
class _Head:
    classes: int
    compute_aos: bool
    width: int  # bytes of each change of a count
    scored: npt.NDArray[np.int64]  # (C, 3)
    pairs: npt.NDArray[np.int64]  # (S, 2): valid, steps (-1: not evaluated)
    size: int  # bytes


def _head(events: bytes) -> _Head | None:
    fixed = np.frombuffer(events, dtype="<i8", count=4)
    if int(fixed[0]) != FORMAT:
        return None
    c = int(fixed[1])
    n_slots = int(np.frombuffer(events, dtype="<i8", count=1, offset=8 * (4 + 3 * c))[0])
    start = 8 * (5 + 3 * c)
    pairs = np.frombuffer(events, dtype="<i8", count=2 * n_slots, offset=start).reshape(n_slots, 2)
    scored = np.frombuffer(events, dtype="<i8", count=3 * c, offset=32).reshape(c, 3)
    return _Head(c, bool(fixed[2]), int(fixed[3]), scored, pairs, start + 16 * n_slots)


def readable(config: EvalConfig, events: bytes) -> bool:
    """Whether a row of an evaluation made with ``config`` is of this layout and has its slots."""
    head = _head(events)
    return head is not None and head.classes == len(config.classes) and len(head.pairs) == len(_slots(config))


def facts_of(config: EvalConfig, events: bytes) -> Facts:
    """What the whole set decided for the matching (the same in every row of an evaluation)."""
    head = _head(events)
    assert head is not None
    scored = {
        cls: {m: bool(head.scored[k, i]) for i, m in enumerate(OVERLAP_METRICS)} for k, cls in enumerate(config.classes)
    }
    return Facts(scored, head.compute_aos)


def stats_from_rows(
    rows: Iterable[tuple[int, str, bytes]],
    config: EvalConfig,
    question: FrameQuestion,
) -> FrameStats | None:
    """:func:`~kitti_eval.analysis.diagnostics.frame_stats` from the rows (frame index, frame id, events) of an
    evaluation made with ``config``, read one by one; None when they cannot answer (a class it did not evaluate,
    rows of another layout)."""
    cls, oset, score_threshold = question.cls, question.oset, question.score_threshold
    m, d = parse_slot(with_class(config, cls), question.metric, question.difficulty, oset)
    s = slot_index(config, cls, m, d, oset)
    if s is None:
        return None
    ids: list[str] = []
    valid: list[int] = []
    frames: list[np.ndarray] = []
    scores: list[np.ndarray] = []
    deltas: list[np.ndarray] = []
    for f, frame_id, events in rows:
        head = _head(events)
        if head is None or head.classes != len(config.classes) or len(head.pairs) != len(_slots(config)):
            return None
        if f != len(ids):
            raise ValueError(f"frame row {f} out of order")
        steps = head.pairs[:, 1]
        if steps[s] < 0:
            raise not_evaluated(cls, m, config)
        before, total, k = int(np.clip(steps[:s], 0, None).sum()), int(np.clip(steps, 0, None).sum()), int(steps[s])
        ids.append(frame_id)
        valid.append(int(head.pairs[s, 0]))
        scores.append(np.frombuffer(events, dtype="<f8", count=k, offset=head.size + 8 * before))
        at = head.size + 8 * total + 3 * head.width * before
        deltas.append(np.frombuffer(events, dtype=_CHANGES[head.width], count=3 * k, offset=at).reshape(k, 3))
        frames.append(np.full(k, f, dtype=np.int64))
    if not ids:
        return None
    tp, fp, fn = counts_at(
        np.asarray(valid, dtype=np.int64),
        np.concatenate(frames),
        np.concatenate(scores),
        np.concatenate(deltas).astype(np.float64),
        score_threshold,
    )
    return FrameStats(tuple(ids), tp, fp, fn, cls, m.value, d.label, oset, float(score_threshold))


def frame_detections(detections: bytes, frame_id: str, *, source: str) -> Annotations:
    """One frame's stored detections, as a set of that frame alone."""
    (size,) = struct.unpack_from("<I", detections)
    head = json.loads(detections[4 : 4 + size])
    names: Sequence[str] = head["names"]
    n = len(names)
    width = _WIDTH + (_LIDAR if head["lidar"] else 0)
    body = np.frombuffer(detections, dtype="<f8", offset=4 + size).reshape(n, width)
    cols: dict[str, np.ndarray] = {}
    at = 0
    for f, w in _FIELDS:
        shape = NUMERIC_FIELDS[f]
        cols[f] = body[:, at : at + w].astype(np.float64).reshape(n, *shape)
        at += w
    return Annotations(
        kind="detections",
        source=source,
        frame_ids=(frame_id,),
        offsets=np.array([0, n], dtype=np.int64),
        name=np.array(names, dtype=np.str_),
        truncated=cols["truncated"],
        occluded=cols["occluded"],
        alpha=cols["alpha"],
        bbox=cols["bbox"],
        dimensions=cols["dimensions"],
        location=cols["location"],
        rotation_y=cols["rotation_y"],
        score=cols["score"],
        boxes_lidar=body[:, at : at + _LIDAR].astype(np.float64) if head["lidar"] else None,
    )
