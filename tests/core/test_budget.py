"""The overlap budget: an evaluation whose frames pair more detections with ground-truth boxes than its limits
allow (per frame, in all) is refused before any overlap is computed, naming the frame, the count and the limit."""

from __future__ import annotations

import numpy as np
import pytest
from builders import annotations, box

from kitti_eval.core import budget, evaluation
from kitti_eval.core.evaluation import evaluate
from kitti_eval.errors import ConfigError, InputError, WorkLimitError


@pytest.fixture(autouse=True)
def _no_budget_from_outside(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(budget.MAX_FRAME_PAIRS_ENV, raising=False)
    monkeypatch.delenv(budget.MAX_PAIRS_ENV, raising=False)


def _frames(counts: list[int], *, score: float | None = None) -> list[list[dict]]:
    return [[box("Car", x=0.1 * k, score=score) for k in range(n)] for n in counts]


def test_the_defaults() -> None:
    assert budget.overlap_budget() == (4_000_000, 100_000_000)


def test_a_frame_over_the_budget_is_refused_before_any_overlap_is_computed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    gt = annotations("ground_truth", _frames([2, 30, 4]))
    dt = annotations("detections", _frames([3, 40, 1], score=0.5))
    calls = []
    real = evaluation.frame_overlaps
    monkeypatch.setattr(evaluation, "frame_overlaps", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setenv(budget.MAX_FRAME_PAIRS_ENV, "1000")
    with pytest.raises(
        WorkLimitError, match=r"40 detections x 30 ground-truth boxes = 1200 overlaps in one frame, more"
    ) as e:
        evaluate(gt, dt)
    assert "more than the limit of 1000 (KITTI_EVAL_MAX_FRAME_PAIRS)" in str(e.value)
    assert e.value.frame == "000001"
    assert isinstance(e.value, InputError)
    assert calls == []
    monkeypatch.setenv(budget.MAX_FRAME_PAIRS_ENV, "1200")
    evaluate(gt, dt)
    assert calls == [1]


def test_an_evaluation_over_the_budget_in_all_is_refused_at_the_frame_that_passes_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    gt = annotations("ground_truth", _frames([2, 3, 4]))
    dt = annotations("detections", _frames([3, 3, 1], score=0.5))  # 6 + 9 + 4 = 19 pairs
    monkeypatch.setenv(budget.MAX_PAIRS_ENV, "18")
    with pytest.raises(
        WorkLimitError, match=r"19 detection x ground-truth overlaps in all, more than the limit of 18"
    ) as e:
        evaluate(gt, dt)
    assert e.value.frame == "000002"
    monkeypatch.setenv(budget.MAX_PAIRS_ENV, "19")
    assert evaluate(gt, dt) is not None


def test_frames_without_predictions_cost_nothing() -> None:
    counts = np.array([0, 5, 7]), np.array([100, 0, 3])
    assert budget.check_overlap_budget(*counts, ["a", "b", "c"], source="s", budget=(21, 21)) == 21
    with pytest.raises(WorkLimitError, match="= 21 overlaps in one frame"):
        budget.check_overlap_budget(*counts, ["a", "b", "c"], source="s", budget=(20, 100))


def test_a_budget_that_is_not_a_number_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(budget.MAX_PAIRS_ENV, "0")
    with pytest.raises(ConfigError, match="KITTI_EVAL_MAX_PAIRS='0': expected a number > 0"):
        budget.overlap_budget()
