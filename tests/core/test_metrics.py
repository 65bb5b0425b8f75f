"""Curves and AP (kitti_eval.core.ap): the interpolation and the R11/R40 averages, stated as arithmetic."""

from __future__ import annotations

import numpy as np
import pytest

from kitti_eval.core.ap import average_precision, average_precisions, curve_from_counts, envelope
from kitti_eval.core.matching import PRCounts


def test_r40_and_r11_of_a_ramp() -> None:
    ramp = np.arange(41) / 40.0  # sample i holds i / 40
    # R40: samples 1..40 -> mean of 1/40 .. 40/40 = (41 / 2) / 40; R11: samples 0, 4, .., 40 -> mean 20 / 40
    assert average_precision(ramp, "R40") == pytest.approx(41 / 2 / 40 * 100, abs=1e-12)
    assert average_precision(ramp, "R11") == pytest.approx(20 / 40 * 100, abs=1e-12)
    assert average_precision(np.full(41, 0.25), "R40") == pytest.approx(25.0, abs=1e-12)
    only_first = np.zeros(41)
    only_first[0] = 1.0  # sample 0 counts for R11 (1 of 11), not for R40
    assert average_precision(only_first, "R11") == pytest.approx(100 / 11, abs=1e-12)
    assert average_precision(only_first, "R40") == 0.0


def test_many_curves_are_summed_as_one_is() -> None:
    """Row by row the same additions in the same order, so the results are equal to the bit."""
    rng = np.random.default_rng(3)
    curves = envelope(rng.random((50, 41)))
    for recall in ("R11", "R40"):
        many = average_precisions(curves, recall)
        assert [average_precision(c, recall) for c in curves] == many.tolist()


def test_envelope_is_the_running_maximum_from_the_right() -> None:
    values = np.array([0.2, 0.9, 0.1, 0.5, 0.0])
    np.testing.assert_array_equal(envelope(values), [0.9, 0.9, 0.5, 0.5, 0.0])
    with_nan = np.array([0.2, 0.3, np.nan, 0.5, 0.1])
    out = envelope(with_nan)
    assert np.isnan(out[:3]).all() and out[3:].tolist() == [0.5, 0.1]  # a NaN spreads to earlier samples
    rows = np.array([[0.1, 0.4], [0.3, 0.2]])
    np.testing.assert_array_equal(envelope(rows), [[0.4, 0.4], [0.3, 0.2]])  # along the last axis
    assert envelope(values) is not values and values.tolist() == [0.2, 0.9, 0.1, 0.5, 0.0]


def test_curve_from_counts_by_hand() -> None:
    # two thresholds: 3 TP 1 FP 1 FN, then 4 TP 4 FP 0 FN; orientation similarity 2.5 then 3.0
    counts = PRCounts(
        thresholds=np.array([0.9, 0.5]),
        tp=np.array([3.0, 4.0]),
        fp=np.array([1.0, 4.0]),
        fn=np.array([1.0, 0.0]),
        similarity=np.array([2.5, 3.0]),
        num_valid_gt=4,
    )
    c = curve_from_counts(counts)
    assert c.precision[:3].tolist() == [3 / 4, 4 / 8, 0.0]
    assert c.recall[:3].tolist() == [4 / 4, 4 / 4, 0.0]  # interpolated like precision: 3/4 becomes max(3/4, 4/4)
    assert c.orientation[:3].tolist() == [2.5 / 4, 3.0 / 8, 0.0]
    assert c.num_valid_gt == 4 and c.thresholds.tolist() == [0.9, 0.5]
    assert (c.precision[2:] == 0).all()
