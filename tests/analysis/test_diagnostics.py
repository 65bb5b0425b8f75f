"""Per-frame counts: they add up to the AP's counts at every score threshold, and rank the worst frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from builders import annotations, box, hits, one_car_per_frame

from kitti_eval.analysis.diagnostics import FrameQuestion, frame_stats, render_frames
from kitti_eval.cli import main
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.matching import MatchingInputs, pr_counts_many
from kitti_eval.core.protocol import Difficulty, EvalConfig, Metric
from kitti_eval.io.loaders import load_detections, load_ground_truth

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"


@pytest.mark.parametrize(
    "cls, metric, difficulty", [("Car", "3d", "moderate"), ("Pedestrian", "bbox", "hard"), ("Cyclist", "bev", "hard")]
)
def test_frame_counts_add_up_to_the_ap_counts_at_each_threshold(cls, metric, difficulty):
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "result.pkl")
    config = EvalConfig()
    plan = plan_evaluation(gt, dt, config)
    (job,) = [
        j
        for c, d, m, s, j, _ in plan.slots
        if c == cls and d is Difficulty[difficulty.upper()] and m is Metric(metric) and s == "strict"
    ]
    fo = plan.overlaps
    inputs = MatchingInputs(
        fo.pair_offsets,
        (fo.bbox, fo.bev, fo.d3),
        plan.gt.offsets,
        plan.dt.offsets,
        plan.ignored_gt,
        plan.ignored_det,
        plan.dontcare,
        plan.dt.score,
        plan.gt.alpha,
        plan.dt.alpha,
    )
    (counts,) = pr_counts_many(inputs, [plan.jobs[job]])
    assert len(counts.thresholds) >= 3
    for k, t in enumerate(counts.thresholds):
        s = frame_stats(gt, dt, config, FrameQuestion(cls, metric, difficulty, score_threshold=t))
        assert (s.tp.sum(), s.fp.sum(), s.fn.sum()) == (counts.tp[k], counts.fp[k], counts.fn[k])


def test_worst_frames_by_errors_then_misses():
    gts = one_car_per_frame(4)
    dets = hits(4)
    dets[1] = []  # frame 1: one miss
    dets[2].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=0.5))  # frame 2: one false positive
    dets[3] = [box("Car", x=-15.0, z=40.0, x1=900.0, score=0.5)]  # frame 3: a miss and a FP
    s = frame_stats(
        annotations("ground_truth", gts), annotations("detections", dets), None, FrameQuestion("Car", "bbox", "easy")
    )
    assert s.tp.tolist() == [1, 0, 1, 0] and s.fp.tolist() == [0, 0, 1, 1] and s.fn.tolist() == [0, 1, 0, 1]
    assert s.worst(10) == [3, 1, 2]  # frame 0 has no error and is not listed
    above = frame_stats(
        annotations("ground_truth", gts),
        annotations("detections", dets),
        None,
        FrameQuestion("Car", "bbox", "easy", score_threshold=0.6),
    )
    assert above.fp.tolist() == [0, 0, 0, 0] and above.fn.tolist() == [0, 1, 0, 1]
    doc = json.loads(render_frames(s, "json", worst=2))
    assert [f["frame"] for f in doc["frames"]] == ["000003", "000001"]
    assert render_frames(s, "csv").splitlines()[0] == "frame,tp,fp,fn"


def test_cli_frames(capsys):
    code = main(
        [
            "frames",
            "--gt",
            str(GOLDEN / "kitti_infos_val.pkl"),
            "--pred",
            str(GOLDEN / "result.pkl"),
            "--worst",
            "3",
            "--format",
            "json",
        ]
    )
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and len(doc["frames"]) == 3
    errors = [f["fp"] + f["fn"] for f in doc["frames"]]
    assert errors == sorted(errors, reverse=True)
    assert (
        main(
            [
                "frames",
                "--gt",
                str(GOLDEN / "kitti_infos_val.pkl"),
                "--pred",
                str(GOLDEN / "result.pkl"),
                "--worst",
                "0",
            ]
        )
        == 2
    )
    assert np.all(np.array(errors) > 0)
