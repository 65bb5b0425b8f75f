"""Ranking many results with the paired bootstrap: a key under each resample is the bootstrap's own value, the
standings of a table from known draws, and on synthetic sets where the truth is known: the 95% interval of
the difference between two draws of one detector covers 0 about 95% of the time, and a clearly better
detector's rank range excludes the worse one's rank."""

from __future__ import annotations

from math import comb
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.analysis.bootstrap import _resampled_values, frame_weights, interval95
from kitti_eval.analysis.ranking import evaluate_resampled, key_of, rank_order, resampled_key, standings
from kitti_eval.core.evaluation import evaluate, plan_evaluation
from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.core.result import ValueKey
from kitti_eval.errors import ConfigError
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.synth import generate

GOLDEN = Path(__file__).parents[1] / "data" / "golden"
CAR = ValueKey("Car", "3d", "moderate")


def _annotations(kind: str, frames: list, source: str) -> Annotations:
    return Annotations.from_frames(
        kind,
        source,
        [((r.get("frame_id") or r["image"]["image_idx"]), r if kind == "detections" else r["annos"]) for r in frames],
    )


def test_a_resampled_key_is_the_bootstraps_value_and_every_frame_once_gives_the_key() -> None:
    gt = load_ground_truth(GOLDEN / "small" / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "small" / "result.pkl")
    plan = plan_evaluation(gt, dt, EvalConfig())
    weights = frame_weights(gt.num_frames, 200, seed=3)
    every = _resampled_values(plan, weights, workers=2)
    keys = [CAR, ValueKey("Pedestrian", "aos", "hard", "R11", "loose"), ValueKey("Cyclist", "bev", "easy")]
    for key in keys:
        # bit for bit: the same matching's events under the same draws, only fewer matchings run
        np.testing.assert_array_equal(resampled_key(plan, [key], weights), every[key])
    mean = resampled_key(plan, keys[:2], weights)
    np.testing.assert_allclose(mean, (every[keys[0]] + every[keys[1]]) / 2, rtol=0, atol=1e-12)
    doc = evaluate(gt, dt, EvalConfig()).to_dict()
    result, once = evaluate_resampled(gt, dt, EvalConfig(), keys[:2], np.ones((1, gt.num_frames), np.int64))
    assert result.to_dict()["ap"] == doc["ap"]
    assert once[0] == pytest.approx(key_of(doc, keys[:2]), abs=1e-9)
    with pytest.raises(ConfigError, match="not in this evaluation"):
        resampled_key(plan, [ValueKey("Van", "3d", "moderate")], weights)


def test_a_key_of_a_value_not_evaluated_is_nan() -> None:
    gt = load_ground_truth(GOLDEN / "small" / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "small" / "result.pkl")
    plan = plan_evaluation(gt, dt, EvalConfig(lidar_only=True))  # no 2D: bbox and AOS are not evaluated
    values = resampled_key(plan, [ValueKey("Car", "aos", "moderate")], frame_weights(gt.num_frames, 5, seed=1))
    assert values.shape == (5,) and np.isnan(values).all()
    assert standings([values])[0].interval is None


def test_standings_from_known_draws() -> None:
    steady = np.full(100, 3.0)
    crossing = np.linspace(1.0, 4.0, 100)  # above 3 in 33 resamples, exactly 3 in one (a tie: the table's order)
    last = np.zeros(100)
    first, second, third = standings([steady, crossing, last])
    assert first.interval == (3.0, 3.0) and second.interval == interval95(crossing)
    assert (first.rank_range, second.rank_range, third.rank_range) == ((1, 2), (1, 2), (3, 3))
    assert first.to_next == interval95(steady - crossing) and first.differs_from_next is False
    assert second.to_next is not None and second.to_next[0] > 0 and second.differs_from_next is True
    assert third.to_next is None and third.differs_from_next is None
    # one place still being computed: no rank range anywhere, no comparison beside it
    a, pending, c = standings([steady, None, last])
    assert a.interval == (3.0, 3.0) and pending.interval is None
    assert a.rank_range is pending.rank_range is c.rank_range is None
    assert a.differs_from_next is None and pending.differs_from_next is None
    assert rank_order([1.0, None, 3.0, 1.0]) == [2, 0, 3, 1]
    with pytest.raises(ValueError, match="same resamples"):
        standings([steady, np.zeros(5)])


def _binomial_band(n: int, p: float, outside: float) -> tuple[int, int]:
    """The counts [lo, hi] that Binomial(n, p) falls outside with probability at most ``outside`` on each side."""
    pmf = [comb(n, k) * p**k * (1 - p) ** (n - k) for k in range(n + 1)]
    lo = 0
    while sum(pmf[: lo + 1]) <= outside:
        lo += 1
    hi = n
    while sum(pmf[hi:]) <= outside:
        hi -= 1
    return lo, hi


@pytest.mark.slow  # 300 replicates of two draws, each ranked under 500 resamples: a minute
def test_the_interval_of_two_draws_of_one_detector_covers_zero_about_95_percent_of_the_time() -> None:
    """300 replicates, each a new 200-frame set with two detection sets drawn from the same detector (the
    synthetic generator's, other detector seeds): the true difference of their expected AP is 0, and a
    calibrated 95% interval covers it in about 95% of the replicates. Each replicate is one Bernoulli trial of
    the interval's coverage, so the count is Binomial(300, 0.95) if it is calibrated: the band below holds it
    with probability 99.9%, 271 to 296 (Monte Carlo error, not a fudge); the counts of an 85% interval (about
    255) and of one too wide to say anything (about 300) fall outside it. (These seeds give 281.) 500
    resamples, fewer than the board's 1000: the coverage is a property of the percentile interval, and the
    test has to run in seconds."""
    n, frames, resamples = 300, 200, 500
    config = EvalConfig(classes=("Car",))
    covered, widths = 0, []
    for rep in range(n):
        infos, a = generate(frames, seed=1000 + rep, dets_per_frame=12.0, detector_seed=2 * rep + 1)
        _, b = generate(frames, seed=1000 + rep, dets_per_frame=12.0, detector_seed=2 * rep + 2)
        gt = _annotations("ground_truth", infos, "gt")
        weights = frame_weights(frames, resamples, seed=rep)
        va, vb = (
            resampled_key(plan_evaluation(gt, _annotations("detections", d, "dt"), config), [CAR], weights, workers=1)
            for d in (a, b)
        )
        found = interval95(vb - va)
        assert found is not None
        covered += found[0] <= 0.0 <= found[1]
        widths.append(found[1] - found[0])
    lo, hi = _binomial_band(n, 0.95, 0.0005)
    assert (lo, hi) == (271, 296)  # 90.3% to 98.7%
    assert lo <= covered <= hi, covered
    assert 2.0 < float(np.median(widths)) < 30.0  # AP points: an interval that says something


def test_a_clearly_better_detectors_rank_range_excludes_the_worse_ones_rank() -> None:
    """Three results on a 300-frame set: two draws of one detector and a third draw of a less precise one (its
    boxes 10 cm further off: about 20 AP points worse). The two draws are told apart by nothing but noise:
    their rank ranges overlap and their difference is not significant; the worse one is third in every
    resample."""
    config = EvalConfig(classes=("Car",))
    infos, a = generate(300, seed=77, dets_per_frame=12.0, detector_seed=1)
    _, b = generate(300, seed=77, dets_per_frame=12.0, detector_seed=2)
    _, c = generate(300, seed=77, dets_per_frame=12.0, detector_seed=3, location_noise=0.1)
    gt = _annotations("ground_truth", infos, "gt")
    weights = frame_weights(gt.num_frames, 1000, seed=9)
    results = [
        evaluate_resampled(gt, _annotations("detections", d, name), config, [CAR], weights)
        for name, d in (("a", a), ("worse", c), ("b", b))
    ]
    points = [key_of(r.to_dict(), [CAR]) for r, _ in results]
    order = rank_order(points)
    assert order[-1] == 1  # the worse one is last
    table = standings([results[i][1] for i in order])
    best_two, worse = table[:2], table[2]
    assert worse.rank_range == (3, 3)
    assert all(s.rank_range is not None and s.rank_range[1] <= 2 for s in best_two)
    assert best_two[0].rank_range == (1, 2) and best_two[1].rank_range == (1, 2)
    assert best_two[0].differs_from_next is False and best_two[1].differs_from_next is True
    assert points[0] is not None and points[1] is not None and points[0] - points[1] > 10
