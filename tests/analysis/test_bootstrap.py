"""The paired bootstrap: exact on the full sample, covers known differences, narrow when nothing changed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kitti_eval.analysis.bootstrap import _resampled_values, frame_weights, paired_bootstrap
from kitti_eval.core.evaluation import evaluate, plan_evaluation
from kitti_eval.core.frames import Annotations
from kitti_eval.core.protocol import OPENPCDET, EvalConfig
from kitti_eval.core.result import ValueKey
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.synth import generate

GOLDEN = Path(__file__).parents[1] / "data" / "golden"


@pytest.mark.parametrize("case", ["small", "edge", "quirks"])
@pytest.mark.parametrize("protocol", ["official", "openpcdet"])
def test_every_frame_once_reproduces_evaluate(case, protocol):
    gt = load_ground_truth(GOLDEN / case / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / case / "result.pkl")
    config = EvalConfig(protocol=protocol)
    doc = evaluate(gt, dt, config).to_dict()
    values = _resampled_values(plan_evaluation(gt, dt, config), np.ones((1, gt.num_frames), np.int64), workers=2)
    assert values
    for key, v in values.items():
        assert v[0] == pytest.approx(key.read(doc), abs=1e-9), key
    # and every value the protocol evaluates is there
    n_evaluated = sum(1 for k in _keys(doc) if k.read(doc) is not None)
    assert len(values) == n_evaluated


def _keys(doc):
    from kitti_eval.analysis.gate import keys_of

    return keys_of(doc)


def test_weights_zero_outside_a_subset_equal_evaluating_the_subset():
    gt = load_ground_truth(GOLDEN / "small" / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "small" / "result.pkl")
    config = EvalConfig()
    keep = np.zeros(gt.num_frames, np.int64)
    keep[::3] = 1
    values = _resampled_values(plan_evaluation(gt, dt, config), keep[None], workers=1)
    ids = [fid for fid, k in zip(gt.frame_ids, keep) if k]
    doc = evaluate(gt.subset(ids), dt.subset(ids), config).to_dict()
    for key, v in values.items():
        expected = key.read(doc)
        if expected is not None:
            assert v[0] == pytest.approx(expected, abs=1e-9), key


def _as_annotations(kind, frames, source):
    return Annotations.from_frames(
        kind,
        source,
        [((r.get("frame_id") or r["image"]["image_idx"]), r if kind == "detections" else r["annos"]) for r in frames],
    )


def test_interval_covers_a_known_difference_and_is_zero_when_nothing_changed():
    infos, results = generate(300, seed=11, dets_per_frame=12.0)
    gt = _as_annotations("ground_truth", infos, "gt")
    a = _as_annotations("detections", results, "a")
    # B: the same detections with every Car score halved below 0.3 removed -> a real difference
    worse = []
    rng = np.random.default_rng(0)
    for r in results:
        r = dict(r)
        if len(r["score"]):
            keep = ~((np.asarray(r["name"]) == "Car") & (rng.random(len(r["score"])) < 0.3))
            r = {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == keep.shape else v) for k, v in r.items()}
        worse.append(r)
    b = _as_annotations("detections", worse, "b")
    config = EvalConfig(classes=("Car",), protocol=OPENPCDET)
    res_a, res_b, intervals = paired_bootstrap(gt, a, b, config, resamples=200, seed=3)
    key = ValueKey("Car", "bev", "moderate")
    true_delta = key.read(res_b.to_dict()) - key.read(res_a.to_dict())
    lo, hi = intervals[key]
    assert true_delta < 0 and lo <= true_delta <= hi and hi < 0  # a significant drop, covered
    # A against itself: every interval is exactly [0, 0]
    _, _, same = paired_bootstrap(gt, a, a, config, resamples=50, seed=3)
    assert same and all(iv == (0.0, 0.0) for iv in same.values())


@pytest.mark.parametrize("case", ["small", "edge", "quirks"])
def test_the_blocked_sweep_equals_one_sweep_per_resample(case):
    """Bit for bit: each resample adds the same terms in the same order in both, and the bisection finds the
    thresholds the step-by-step rule takes. 70 resamples: two full blocks and a part of one; some frames
    drawn often, some never."""
    from naive import resampled_curves_naive

    from kitti_eval.analysis.bootstrap import _resampled_curves

    gt = load_ground_truth(GOLDEN / case / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / case / "result.pkl")
    plan = plan_evaluation(gt, dt, EvalConfig())
    weights = frame_weights(gt.num_frames, 70, seed=4)
    weights[:3] = 0  # nothing drawn: no curve at all
    weights[3, :] = 0
    weights[3, 0] = gt.num_frames  # one frame drawn every time
    checked = 0
    for ev in plan.events(workers=1):
        got = _resampled_curves(ev.valid, ev.tp_score, ev.tp_frame, ev.ev_score, ev.ev_frame, ev.ev_delta, weights)
        want = resampled_curves_naive(ev, weights)
        np.testing.assert_array_equal(got, want)
        checked += int(np.isfinite(want).any())
    assert checked > 10


def test_weights_are_reproducible_and_sum_to_frames():
    w1, w2 = frame_weights(100, 20, seed=5), frame_weights(100, 20, seed=5)
    np.testing.assert_array_equal(w1, w2)
    assert (w1.sum(axis=1) == 100).all() and not np.array_equal(w1, frame_weights(100, 20, seed=6))


def test_cli_compare_and_significant_gate(capsys, tmp_path):
    import json

    from kitti_eval.cli import main

    g = GOLDEN / "small"
    gt, pred = g / "kitti_infos_val.pkl", g / "result.pkl"
    assert (
        main(
            [
                "compare",
                str(pred),
                str(pred),
                "--gt",
                str(gt),
                "--bootstrap",
                "50",
                "--format",
                "json",
                "--classes",
                "Car",
            ]
        )
        == 0
    )
    doc = json.loads(capsys.readouterr().out)
    assert doc["resamples"] == 50 and all(v["delta"] in (0.0, None) for v in doc["values"])
    assert all(v["interval95"] == [0.0, 0.0] for v in doc["values"] if v["a"] is not None)
    # a JSON result and predictions mix without a bootstrap
    saved = tmp_path / "a.json"
    assert main(["--gt", str(gt), "--pred", str(pred), "--format", "json", "-o", str(saved)]) == 0
    assert main(["compare", str(saved), str(pred), "--gt", str(gt)]) == 0
    assert "Car/3d/moderate/R40/strict" in capsys.readouterr().out
    assert main(["compare", str(saved), str(pred), "--gt", str(gt), "--bootstrap", "10"]) == 2
    # the gate with --significant: identical predictions cannot drop significantly
    assert (
        main(
            [
                "gate",
                "--gt",
                str(gt),
                "--pred",
                str(pred),
                "--baseline",
                str(pred),
                "--max-drop",
                "0",
                "--significant",
                "--bootstrap",
                "30",
                "--classes",
                "Car",
            ]
        )
        == 0
    )
    assert main(["gate", "--result", str(saved), "--baseline", str(saved), "--max-drop", "0", "--significant"]) == 2
