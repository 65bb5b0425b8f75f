"""The matching kernels against their literal twin, on random frames with every ignore code."""

from __future__ import annotations

import numpy as np
import pytest
from naive_matching import pr_counts_naive, thresholds_naive

from kitti_eval.core.matching import MatchingInputs, pr_counts, score_thresholds


def random_frames(rng, n_frames, max_gt=6, max_dt=12):
    frames = []
    for _ in range(n_frames):
        ng, nd = int(rng.integers(0, max_gt + 1)), int(rng.integers(0, max_dt + 1))
        dc = rng.random(ng) < 0.15
        ig = rng.choice([0, 0, 0, 1, -1], size=ng).astype(np.int8)
        ig[dc] = -1
        idet = rng.choice([0, 0, 0, 1, -1], size=nd).astype(np.int8)
        ov = rng.random((nd, ng)) * (rng.random((nd, ng)) < 0.4)
        ov[rng.random((nd, ng)) < 0.1] = 0.7  # exactly at the threshold: never a match
        frames.append(
            dict(
                ov=ov,
                ig=ig,
                idet=idet,
                dc=dc,
                score=np.round(rng.random(nd), 2),  # ties on purpose
                gt_alpha=rng.uniform(-np.pi, np.pi, ng),
                dt_alpha=rng.uniform(-np.pi, np.pi, nd),
            )
        )
    return frames


def flatten(frames):
    gt_off, dt_off, pair_off = [0], [0], [0]
    cols = {k: [] for k in ("ov", "ig", "idet", "dc", "score", "gt_alpha", "dt_alpha")}
    for f in frames:
        for k in cols:
            cols[k].append(np.ravel(f[k]))
        gt_off.append(gt_off[-1] + len(f["ig"]))
        dt_off.append(dt_off[-1] + len(f["idet"]))
        pair_off.append(pair_off[-1] + f["ov"].size)
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    return (
        np.array(pair_off),
        cat["ov"].astype(float),
        np.array(gt_off),
        np.array(dt_off),
        cat["ig"].astype(np.int8),
        cat["idet"].astype(np.int8),
        cat["dc"].astype(bool),
        cat["score"],
        cat["gt_alpha"],
        cat["dt_alpha"],
    )


def matching_inputs(frames):
    """The frames' arrays as one matching's inputs (one overlap array, one row of ignore codes)."""
    po, ov, go, do, *rest = flatten(frames)
    return MatchingInputs(po, [ov], go, do, *rest)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("compute_aos", [False, True])
def test_kernel_equals_literal_twin(seed, compute_aos):
    rng = np.random.default_rng(seed)
    frames = random_frames(rng, int(rng.integers(1, 60)))
    got = pr_counts(matching_inputs(frames), 0.7 if seed % 2 else 0.5, compute_aos)
    thresholds, pr, n_gt = pr_counts_naive(frames, 0.7 if seed % 2 else 0.5, compute_aos)
    assert got.num_valid_gt == n_gt
    np.testing.assert_array_equal(got.thresholds, thresholds)
    pr = np.array(pr).reshape(-1, 4)
    np.testing.assert_array_equal(got.tp, pr[:, 0])
    np.testing.assert_array_equal(got.fp, pr[:, 1])
    np.testing.assert_array_equal(got.fn, pr[:, 2])
    np.testing.assert_allclose(got.similarity, pr[:, 3], rtol=1e-12, atol=1e-12)


def test_no_suppression_without_dontcare_rows():
    rng = np.random.default_rng(3)
    frames = random_frames(rng, 30)
    inputs = matching_inputs(frames)
    with_dc = pr_counts(inputs, 0.5, False)
    for f in frames:
        f["dc"] = np.zeros_like(f["dc"])
    without = pr_counts(inputs._replace(dontcare=None), 0.5, False)
    expected = np.array(pr_counts_naive(frames, 0.5, False)[1]).reshape(-1, 4)
    np.testing.assert_array_equal(without.fp, expected[:, 1])
    assert (without.fp >= with_dc.fp).all()


@pytest.mark.parametrize("n_gt", [1, 7, 40, 41, 80, 1000])
def test_score_thresholds_equal_twin(n_gt):
    rng = np.random.default_rng(n_gt)
    scores = np.round(rng.random(min(n_gt, 300)), 3)
    original = scores.copy()
    assert score_thresholds(scores, n_gt).tolist() == thresholds_naive(list(scores), n_gt)
    np.testing.assert_array_equal(scores, original)  # input not sorted in place
    assert len(score_thresholds(scores, n_gt)) <= 41


def test_recall_steps_for_many_hits_give_41_thresholds():
    # 80 true positives of 80: the thresholds sit at recall 1/80, 2/80, 4/80, 6/80, ..., 80/80
    scores = np.linspace(1.0, 0.2, 80)
    t = score_thresholds(scores, 80)
    assert len(t) == 41
    assert t[0] == scores[0] and t[1] == scores[1] and t[2] == scores[3] and t[-1] == scores[-1]


def test_empty_inputs():
    z = np.zeros(0)
    e8 = np.zeros(0, np.int8)
    got = pr_counts(
        MatchingInputs(np.zeros(2, np.int64), [z], np.zeros(2, np.int64), np.zeros(2, np.int64), e8, e8, None, z, z, z),
        0.7,
        True,
    )
    assert got.thresholds.shape == (0,) and got.num_valid_gt == 0


def test_shape_mismatch_is_rejected():
    z = np.zeros(0)
    e8 = np.zeros(0, np.int8)
    with pytest.raises(ValueError, match="same shape"):
        pr_counts(
            MatchingInputs(
                np.zeros(3, np.int64), [z], np.zeros(2, np.int64), np.zeros(2, np.int64), e8, e8, None, z, z, z
            ),
            0.7,
            False,
        )


def test_one_matching_takes_one_overlap_array():
    """pr_counts is one matching: a second overlap array would be one it cannot choose between."""
    inputs = matching_inputs(random_frames(np.random.default_rng(5), 4))
    with pytest.raises(ValueError, match="one `overlaps` array"):
        pr_counts(inputs._replace(overlaps=[inputs.overlaps[0]] * 2), 0.5, False)
    rows = inputs._replace(ignored_gt=inputs.ignored_gt[None], ignored_det=inputs.ignored_det[None])
    np.testing.assert_array_equal(pr_counts(rows, 0.5, True).tp, pr_counts(inputs, 0.5, True).tp)
