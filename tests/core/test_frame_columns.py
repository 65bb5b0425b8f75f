"""Annotations.from_frames takes the frames readers usually give as whole columns (one concatenation per field,
the checks over all frames at once), and anything else frame by frame: both routes must give the same arrays,
and the same refusal for the same input (the first problem in frame order, the reader's own included)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from kitti_eval.core.frames import Annotations, _Columns
from kitti_eval.errors import InputError

FIELDS = ("name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score")


def _frame(rng: np.random.Generator, n: int, kind: str) -> dict[str, Any]:
    """One frame as OpenPCDet writes it: float32 arrays, or its float64 zero template when empty."""
    if n == 0:
        out = {f: np.zeros(0) for f in FIELDS}
        out["bbox"] = np.zeros([0, 4])
        out["dimensions"] = out["location"] = np.zeros([0, 3])
        out["boxes_lidar"] = np.zeros([0, 7])
        if kind == "ground_truth":
            del out["score"]
        return out
    f32 = np.float32
    out = {
        "name": rng.choice(np.array(["Car", "Pedestrian", "Cyclist", "DontCare"]), n),
        "truncated": rng.random(n).astype(f32),
        "occluded": rng.integers(0, 3, n).astype(f32 if kind == "detections" else np.int64),
        "alpha": rng.uniform(-3, 3, n).astype(f32),
        "bbox": rng.uniform(0, 1000, (n, 4)).astype(f32),
        "dimensions": rng.uniform(0.5, 4, (n, 3)).astype(f32),
        "location": rng.uniform(-20, 40, (n, 3)).astype(f32),
        "rotation_y": rng.uniform(-3, 3, n).astype(f32),
        "boxes_lidar": rng.uniform(-20, 40, (n, 7)).astype(f32),
    }
    if kind == "detections":
        out["score"] = rng.random(n).astype(f32)
    return out


def _frames(kind: str = "detections", count: int = 40, seed: int = 0) -> list[tuple[object, dict[str, Any]]]:
    rng = np.random.default_rng(seed)
    ids: list[object] = [f"{i:06d}" if kind == "detections" else i for i in range(count)]
    return [(fid, _frame(rng, 0 if i % 7 == 3 else int(rng.integers(1, 9)), kind)) for i, fid in enumerate(ids)]


def _one_by_one(kind: str, frames: Any, **options: Any) -> Annotations:
    """The frame-by-frame route alone (the reference for the columns)."""
    c = _Columns.frame_by_frame(
        kind,  # type: ignore[arg-type]
        "src",
        frames,
        options.get("keep_lidar", False),
        options.get("max_frames"),
        options.get("known_frames"),
    )
    return Annotations._checked(kind, "src", c)  # type: ignore[arg-type]


def _assert_same(a: Annotations, b: Annotations) -> None:
    assert a.frame_ids == b.frame_ids
    assert dict(a.missing_fields) == dict(b.missing_fields)
    for f in ("offsets", *FIELDS):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        assert np.array_equal(x, y), f
    if a.boxes_lidar is None or b.boxes_lidar is None:
        assert a.boxes_lidar is None and b.boxes_lidar is None
    else:
        assert np.array_equal(a.boxes_lidar, b.boxes_lidar, equal_nan=True)


def _outcome(build: Callable[[], Annotations]) -> Annotations | tuple[str, str | None, str | None]:
    try:
        return build()
    except InputError as e:
        return (str(e), e.frame, e.field)


@pytest.mark.parametrize("kind", ["detections", "ground_truth"])
@pytest.mark.parametrize("keep_lidar", [False, True])
def test_usual_frames_are_read_as_whole_columns_into_the_same_arrays(kind: str, keep_lidar: bool) -> None:
    frames = _frames(kind)
    ids = tuple(f"{i:06d}" for i in range(len(frames)))
    assert _Columns.of(kind, frames, ids, keep_lidar=keep_lidar) is not None  # type: ignore[arg-type]
    got = Annotations.from_frames(kind, "src", iter(frames), keep_lidar=keep_lidar)  # type: ignore[arg-type]
    want = _one_by_one(kind, frames, keep_lidar=keep_lidar)
    _assert_same(got, want)
    assert got.num_boxes == sum(len(f["name"]) for _, f in frames) > 100
    assert got.bbox.dtype == np.float64 and got.name.dtype.kind == "U"
    if kind == "ground_truth":
        assert (got.score == -1).all()


def test_a_field_no_frame_has_is_filled_and_named_as_missing() -> None:
    frames = [(fid, {k: v for k, v in f.items() if k not in ("alpha", "bbox")}) for fid, f in _frames()]
    got = Annotations.from_frames("detections", "src", frames)
    _assert_same(got, _one_by_one("detections", frames))
    assert dict(got.missing_fields) == {"alpha": "000000", "bbox": "000000"}
    assert (got.alpha == -10).all() and (got.bbox == 0).all()


def _mutated(change: Callable[[list[tuple[object, dict[str, Any]]]], None]) -> list[tuple[object, dict[str, Any]]]:
    frames = [(fid, dict(f)) for fid, f in _frames()]
    change(frames)
    return frames


def _set(i: int, field: str, value: Any) -> Callable[[list[tuple[object, dict[str, Any]]]], None]:
    def change(frames: list[tuple[object, dict[str, Any]]]) -> None:
        frames[i][1][field] = value(frames[i][1]) if callable(value) else value

    return change


def _drop(i: int, field: str) -> Callable[[list[tuple[object, dict[str, Any]]]], None]:
    return lambda frames: frames[i][1].pop(field)


def _frame_id(i: int, value: object) -> Callable[[list[tuple[object, dict[str, Any]]]], None]:
    def change(frames: list[tuple[object, dict[str, Any]]]) -> None:
        frames[i] = (value, frames[i][1])

    return change


MUTATIONS: dict[str, Callable[[list[tuple[object, dict[str, Any]]]], None]] = {
    "nan location": _set(5, "location", lambda f: np.where(np.arange(len(f["name"]))[:, None] == 1, np.nan, 1.0)),
    "inf score": _set(8, "score", lambda f: np.full(len(f["name"]), np.inf, np.float32)),
    "2 boxes in bbox": _set(6, "bbox", np.zeros((2, 4))),
    "bbox of 5": _set(6, "bbox", lambda f: np.zeros((len(f["name"]), 5))),
    "bbox flat": _set(6, "bbox", lambda f: np.zeros(4 * len(f["name"]))),
    "every bbox flat": lambda frames: [f.__setitem__("bbox", f["bbox"].reshape(-1)) for _, f in frames],
    "rotation_y as a column": _set(9, "rotation_y", lambda f: f["rotation_y"][:, None]),
    "0-d alpha": _set(9, "alpha", np.float64(1.0)),
    "list location": _set(9, "location", lambda f: f["location"].tolist()),
    "str score": _set(9, "score", lambda f: f["score"].astype(str)),
    "bool alpha": _set(9, "alpha", lambda f: f["alpha"] > 0),
    "object dims": _set(9, "dimensions", lambda f: f["dimensions"].astype(object)),
    "None alpha": _set(9, "alpha", None),
    "boxes in an empty frame": _set(3, "bbox", np.zeros((2, 4))),
    "empty str in an empty frame": _set(3, "score", np.zeros(0, "U3")),
    "empty bytes in an empty frame": _set(3, "score", np.zeros(0, "S3")),
    "empty (3, 0) names": _set(3, "name", np.zeros((3, 0))),
    "no name": _drop(4, "name"),
    "no score": _drop(4, "score"),
    "no alpha in one frame": _drop(4, "alpha"),
    "bytes names": _set(4, "name", lambda f: f["name"].astype("S")),
    "object names": _set(4, "name", lambda f: f["name"].astype(object)),
    "int names": _set(4, "name", lambda f: np.arange(len(f["name"]))),
    "2-D names": _set(4, "name", lambda f: f["name"][:, None]),
    "big-endian names": _set(4, "name", lambda f: f["name"].astype(">U10")),
    "list names": _set(4, "name", lambda f: f["name"].tolist()),
    "not text names": _set(4, "name", lambda f: np.array([0x110000] * len(f["name"]), "<u4").view("<U1")),
    "duplicate frame": _frame_id(7, "000002"),
    "int frame id": _frame_id(7, 7),
    "bool frame id": _frame_id(7, True),
    "empty frame id": _frame_id(7, " "),
    "float frame id": _frame_id(7, 7.0),
    "negative frame id": _frame_id(7, -7),
    "ordered dict": lambda frames: frames.__setitem__(2, (frames[2][0], OrderedDict(frames[2][1]))),
    "list frame": lambda frames: frames.__setitem__(2, (frames[2][0], [1, 2])),
    "two problems": lambda frames: (_set(5, "bbox", np.zeros((1, 4)))(frames), _set(2, "score", "x")(frames)),
}


@pytest.mark.parametrize("name", MUTATIONS)
def test_anything_else_gives_what_frame_by_frame_gives(name: str) -> None:
    frames = _mutated(MUTATIONS[name])
    got = _outcome(lambda: Annotations.from_frames("detections", "src", iter(frames)))
    want = _outcome(lambda: _one_by_one("detections", frames))
    if isinstance(want, Annotations):
        assert isinstance(got, Annotations)
        _assert_same(got, want)
    else:
        assert got == want


def test_the_first_problem_in_frame_order_is_reported_even_when_the_reader_fails_later() -> None:
    frames = _mutated(_set(5, "bbox", np.zeros((1, 4))))

    def reader(fail_at: int) -> Iterator[tuple[object, dict[str, Any]]]:
        for i, pair in enumerate(frames):
            if i == fail_at:
                raise InputError("entry has no frame_id", source="src", frame=f"#{i}")
            yield pair

    with pytest.raises(InputError, match="frame 000005, field 'bbox': expected shape"):
        Annotations.from_frames("detections", "src", reader(20))
    with pytest.raises(InputError, match="frame #4: entry has no frame_id"):
        Annotations.from_frames("detections", "src", reader(4))


def test_frames_past_the_limit_are_not_read() -> None:
    taken = 0

    def reader() -> Iterator[tuple[object, dict[str, Any]]]:
        nonlocal taken
        for pair in _frames(count=40):
            taken += 1
            yield pair

    with pytest.raises(InputError, match="frame 000010: more than the limit of 10 frames"):
        Annotations.from_frames("detections", "src", reader(), max_frames=10)
    assert taken == 11
    assert Annotations.from_frames("detections", "src", _frames(count=10), max_frames=10).num_frames == 10


def test_a_frame_outside_the_known_ones_is_refused_by_name() -> None:
    frames = _frames()
    known = {fid for fid, _ in frames[:-1]}
    with pytest.raises(InputError, match="frame 000039: predictions for a frame that is not in the ground truth"):
        Annotations.from_frames("detections", "src", frames, known_frames=known)
    assert Annotations.from_frames("detections", "src", frames[:-1], known_frames=known).num_frames == 39


def test_the_columns_are_fresh_arrays() -> None:
    frames = _frames()
    frames[0][1]["bbox"] = frames[0][1]["bbox"].astype(np.float64)
    got = Annotations.from_frames("detections", "src", frames)
    got.bbox[:] = -5
    assert not np.shares_memory(got.bbox, frames[0][1]["bbox"]) and (frames[0][1]["bbox"] != -5).all()


def test_frame_ids_of_every_accepted_type_are_one_key() -> None:
    from kitti_eval.core.frames import normalize_frame_id

    for value in (15, np.int64(15), np.uint8(15), "15", " 000015 ", np.str_("15"), b"15"):
        assert normalize_frame_id(value) == "000015"
    assert normalize_frame_id(1234567) == "1234567" and normalize_frame_id("a7") == "a7"
    for value, error in ((-1, ValueError), (np.int64(-1), ValueError), (True, TypeError), (1.0, TypeError)):
        with pytest.raises(error):
            normalize_frame_id(value)
