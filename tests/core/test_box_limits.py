"""The box limits over whole columns (the way a reader's columns are checked) and frame by frame (the way frames
are checked as they are read): the same refusal, of the same frame, for any counts and limits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kitti_eval.core.frames import Annotations, BoxLimits
from kitti_eval.errors import WorkLimitError


def _frame_by_frame(limits: BoxLimits, counts: list[int], ids: list[str]) -> str | None:
    total = 0
    for n, fid in zip(counts, ids, strict=True):
        total += n
        try:
            limits.check_frame(n, total, source="s", frame=fid)
        except WorkLimitError as e:
            return str(e)
    return None


def _columns(limits: BoxLimits, counts: list[int], ids: list[str]) -> str | None:
    try:
        limits.check_counts(np.array(counts, dtype=np.int64), ids, source="s")
    except WorkLimitError as e:
        return str(e)
    return None


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    counts=st.lists(st.integers(0, 30), max_size=12),
    per_frame=st.none() | st.integers(0, 30),
    per_input=st.none() | st.integers(0, 120),
)
def test_the_whole_columns_refuse_as_frame_by_frame(counts: list[int], per_frame: int | None, per_input: int | None):
    limits = BoxLimits(per_frame, per_input)
    ids = [f"{i:06d}" for i in range(len(counts))]
    assert _columns(limits, counts, ids) == _frame_by_frame(limits, counts, ids)


def _frames(counts: list[int]) -> list[tuple[str, dict]]:
    return [
        (
            f"{i:06d}",
            {
                "name": np.full(n, "Car"),
                "dimensions": np.ones((n, 3)),
                "location": np.zeros((n, 3)),
                "rotation_y": np.zeros(n),
                "score": np.linspace(0, 1, n),
            },
        )
        for i, n in enumerate(counts)
    ]


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    counts=st.lists(st.integers(0, 6), min_size=1, max_size=6),
    per_frame=st.integers(0, 6),
    per_input=st.integers(0, 20),
)
def test_both_readings_of_frames_refuse_the_same_frame(counts: list[int], per_frame: int, per_input: int) -> None:
    """Plain dicts of arrays are taken as whole columns, anything else frame by frame (a list for a name array
    sends the frames there): the same refusal either way."""
    limits = BoxLimits(per_frame, per_input)
    frames = _frames(counts)
    slow = [(fid, {**d, "name": list(d["name"])}) for fid, d in frames]
    outcomes = []
    for given_frames in (frames, slow):
        try:
            outcomes.append(Annotations.from_frames("detections", "s", given_frames, box_limits=limits).num_boxes)
        except WorkLimitError as e:
            outcomes.append(str(e))
    assert outcomes[0] == outcomes[1]


def test_no_limits_refuse_nothing() -> None:
    assert _columns(BoxLimits(), [10**9, 10**9], ["a", "b"]) is None
    with pytest.raises(WorkLimitError, match="2 boxes up to this frame, more than the limit of 1 in one input"):
        BoxLimits(per_input=1).check_frame(1, 2, source="s", frame="b")
