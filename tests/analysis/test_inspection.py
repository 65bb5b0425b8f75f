"""One frame labelled box by box: the labelling kernel against its literal twin, hand-made scenes whose
labels are stated, and the labels adding up to the per-frame counts behind the AP."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from builders import annotations, box, dontcare
from naive_matching import labels_naive, statistics_naive
from test_matching import random_frames

from kitti_eval.analysis.diagnostics import FrameQuestion, frame_stats, parse_slot, slot_job
from kitti_eval.analysis.inspection import inspect_frame, model_name, render_inspection, unique_names
from kitti_eval.cli import main
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.frame_labels import DET_LABELS, GT_LABELS, label_frame
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.demo import demo_paths
from kitti_eval.errors import ConfigError, InputError
from kitti_eval.io.loaders import load_detections, load_ground_truth

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"


def labels_kernel(frame, min_overlap, thresh=float("-inf")):
    got = label_frame(frame["ov"], frame["ig"], frame["idet"], frame["dc"], frame["score"], min_overlap, thresh)
    return (
        [DET_LABELS[c] for c in got.det_label],
        got.det_ref.tolist(),
        [GT_LABELS[c] for c in got.gt_label],
        got.gt_ref.tolist(),
    )


LABELLERS = [pytest.param(labels_kernel, id="kernel"), pytest.param(labels_naive, id="twin")]


def frame(ov, ig, idet, score, dc=None):
    ov = np.array(ov, dtype=float).reshape(len(idet), len(ig))
    return dict(
        ov=ov,
        ig=np.array(ig, np.int8),
        idet=np.array(idet, np.int8),
        dc=np.zeros(len(ig), bool) if dc is None else np.array(dc, bool),
        score=np.array(score, float),
    )


# ------------------------------------------------------------------------------------- hand-made frames


@pytest.mark.parametrize("labeller", LABELLERS)
def test_second_pass_takes_the_highest_overlap_not_the_highest_score(labeller):
    # two detections on one car: overlap 0.75 (score 0.9) and 0.85 (score 0.3); pass 2 picks by overlap
    f = frame([[0.75], [0.85]], ig=[0], idet=[0, 0], score=[0.9, 0.3])
    assert labeller(f, 0.7) == (["fp", "tp"], [-1, 0], ["matched"], [1])
    # above 0.5 only the first takes part and matches
    assert labeller(f, 0.7, 0.5) == (["tp", "below_threshold"], [0, -1], ["matched"], [0])


@pytest.mark.parametrize("labeller", LABELLERS)
def test_overlap_must_exceed_the_threshold(labeller):
    f = frame([[0.7]], ig=[0], idet=[0], score=[0.9])
    assert labeller(f, 0.7) == (["fp"], [-1], ["missed"], [-1])


@pytest.mark.parametrize("labeller", LABELLERS)
def test_a_too_small_detection_absorbs_a_box_that_then_is_no_miss(labeller):
    # the small detection (code 1) is taken only if no counting one qualifies
    f = frame([[0.9, 0.0], [0.8, 0.0]], ig=[0, 0], idet=[1, 1], score=[0.9, 0.8])
    assert labeller(f, 0.7) == (["ignored", "ignored"], [0, -1], ["absorbed", "missed"], [0, -1])
    g = frame([[0.9], [0.8]], ig=[0], idet=[1, 0], score=[0.9, 0.8])
    assert labeller(g, 0.7) == (["ignored", "tp"], [-1, 0], ["matched"], [1])


@pytest.mark.parametrize("labeller", LABELLERS)
def test_a_match_of_ignored_ground_truth_is_neither_hit_nor_error(labeller):
    # ground truth 0 is a Van (code 1 for Car), 1 another class (-1), 2 DontCare (-1, suppresses)
    f = frame(
        [[0.9, 0.9, 0.0], [0.0, 0.0, 0.8], [0.0, 0.0, 0.0], [0.2, 0.0, 0.0]],
        ig=[1, -1, -1],
        idet=[0, 0, -1, 0],
        score=[0.9, 0.8, 0.7, 0.6],
        dc=[False, False, True],
    )
    assert labeller(f, 0.7) == (
        ["ignored", "dontcare", "other_class", "fp"],
        [0, 2, -1, -1],
        ["ignored", "other_class", "other_class"],
        [0, -1, -1],
    )


@pytest.mark.parametrize("labeller", LABELLERS)
def test_empty_frames(labeller):
    assert labeller(frame(np.zeros((0, 2)), ig=[0, 1], idet=[], score=[]), 0.5) == (
        [],
        [],
        ["missed", "ignored"],
        [-1, -1],
    )
    assert labeller(frame(np.zeros((2, 0)), ig=[], idet=[0, -1], score=[0.5, 0.4]), 0.5) == (
        ["fp", "other_class"],
        [-1, -1],
        [],
        [],
    )


# ------------------------------------------------------------------------------------- random frames


@pytest.mark.parametrize("seed", range(6))
def test_kernel_equals_twin_and_counts_equal_the_statistics(seed):
    rng = np.random.default_rng(100 + seed)
    for f in random_frames(rng, 80):
        for thresh in (-np.inf, 0.25, 0.5, 0.9):
            want = labels_naive(f, 0.5, thresh)
            got = labels_kernel(f, 0.5, thresh)
            assert got == want
            det, _, gt, _ = got
            tp, fp, fn, _, _ = statistics_naive(f, 0.5, True, thresh)
            assert (det.count("tp"), det.count("fp"), gt.count("missed")) == (tp, fp, fn)


def test_labels_carry_the_overlap_of_the_pair():
    f = frame([[0.75], [0.85]], ig=[0], idet=[0, 0], score=[0.9, 0.3])
    got = label_frame(f["ov"], f["ig"], f["idet"], None, f["score"], 0.7)
    assert got.det_overlap[1] == 0.85 and np.isnan(got.det_overlap[0])
    assert (got.tp, got.fp, got.fn) == (1, 1, 0)


def test_inputs_are_checked_and_never_changed():
    f = frame([[0.9]], ig=[0], idet=[0], score=[0.9])
    before = {k: v.copy() for k, v in f.items()}
    label_frame(f["ov"], f["ig"], f["idet"], f["dc"], f["score"], 0.5)
    for k, v in f.items():
        np.testing.assert_array_equal(v, before[k])
    with pytest.raises(ValueError, match="overlaps"):
        label_frame(np.zeros((2, 1)), f["ig"], f["idet"], f["dc"], f["score"], 0.5)
    with pytest.raises(ValueError, match="dontcare"):
        label_frame(f["ov"], f["ig"], f["idet"], np.zeros(3, bool), f["score"], 0.5)


# ------------------------------------------------------------------------------ whole sets and reports


@pytest.mark.parametrize(
    "cls, metric, difficulty, thresh",
    [
        ("Car", "3d", "moderate", 0.0),
        ("Car", "bev", "easy", 0.5),
        ("Pedestrian", "bbox", "hard", 0.3),
        ("Cyclist", "3d", "moderate", 0.1),
    ],
)
def test_every_frames_labels_add_up_to_its_counts(cls, metric, difficulty, thresh):
    gt = load_ground_truth(GOLDEN / "kitti_infos_val.pkl")
    dt = load_detections(GOLDEN / "result.pkl")
    config = EvalConfig()
    stats = frame_stats(gt, dt, config, FrameQuestion(cls, metric, difficulty, score_threshold=thresh))
    plan = plan_evaluation(gt, dt, config)
    m, d = parse_slot(config, metric, difficulty, "strict")
    job = slot_job(plan, cls, m, d, "strict")
    fo = plan.overlaps
    ov_all = (fo.bbox, fo.bev, fo.d3)[job.overlap]
    checked = 0
    for f in range(gt.num_frames):
        g0, g1 = plan.gt.offsets[f], plan.gt.offsets[f + 1]
        d0, d1 = plan.dt.offsets[f], plan.dt.offsets[f + 1]
        ov = ov_all[fo.pair_offsets[f] : fo.pair_offsets[f + 1]].reshape(d1 - d0, g1 - g0)
        got = label_frame(
            ov,
            plan.ignored_gt[job.codes][g0:g1],
            plan.ignored_det[job.codes][d0:d1],
            plan.dontcare[g0:g1] if job.dontcare else None,
            plan.dt.score[d0:d1],
            job.min_overlap,
            thresh,
        )
        assert (got.tp, got.fp, got.fn) == (stats.tp[f], stats.fp[f], stats.fn[f]), gt.frame_ids[f]
        checked += got.tp + got.fp + got.fn
    assert checked > 0


def scene():
    """One frame: a car seen twice (one duplicate), a Van, a car too far occluded for moderate, DontCare."""
    gt = annotations(
        "ground_truth",
        [
            [
                box("Car", x=0.0, z=20.0, x1=100, width_px=80, height_px=60),
                box("Van", x=6.0, z=25.0, x1=400, width_px=80, height_px=60),
                box("Car", x=-6.0, z=30.0, x1=600, width_px=80, height_px=60, occluded=2),
                dontcare([900, 150, 1000, 210]),
                box("Car", x=12.0, z=40.0, x1=1100, width_px=60, height_px=40),
            ]
        ],
        ids=["000015"],
    )
    dt = annotations(
        "detections",
        [
            [
                box("Car", x=0.0, z=20.0, x1=100, width_px=80, height_px=60, score=0.9),  # TP of gt 0
                box("Car", x=0.1, z=20.1, x1=102, width_px=80, height_px=60, score=0.8),  # duplicate of gt 0
                box("Car", x=6.0, z=25.0, x1=400, width_px=80, height_px=60, score=0.7),  # on the Van: ignored
                box("Car", x=-6.0, z=30.0, x1=600, width_px=80, height_px=60, score=0.6),  # on the occluded car
                box("Car", x=30.0, z=60.0, x1=910, y1=160, width_px=40, height_px=40, score=0.5),  # in DontCare
                box("Pedestrian", x=2.0, z=10.0, dims=(0.8, 1.7, 0.6), x1=300, score=0.95),  # other class
                box("Car", x=-20.0, z=15.0, x1=10, width_px=50, height_px=40, score=0.05),  # a plain false positive
            ]
        ],
        ids=["000015"],
    )
    return gt, dt


def test_report_of_a_hand_made_scene():
    gt, dt = scene()
    report = inspect_frame(gt, [("mine", dt)], 15, EvalConfig(classes=("Car",)), metric="bbox")
    assert report["frame"] == "000015" and report["min_overlap"] == 0.7
    roles = [g["role"] for g in report["ground_truth"]]
    assert roles == ["counts", "ignored", "ignored", "dontcare", "counts"]
    assert "neighbour" in report["ground_truth"][1]["reason"]
    assert "occlusion 2 > 1" in report["ground_truth"][2]["reason"]
    model = report["models"]["mine"]
    labels = [(d["label"], d["gt"]) for d in model["detections"]]
    assert labels == [
        ("tp", 0),
        ("fp", None),
        ("ignored", 1),
        ("ignored", 2),
        ("dontcare", None),
        ("other_class", None),
        ("fp", None),
    ]
    assert model["detections"][0]["iou"] == pytest.approx(1.0)
    assert model["detections"][1]["reason"].startswith("duplicate: ground truth 0")
    assert model["detections"][4]["dontcare_region"] == 3
    assert "overlaps no ground truth" in model["detections"][6]["reason"]
    assert model["missed"] == [4]
    assert model["counts"] == {"tp": 1, "fp": 2, "fn": 1}
    assert [g["label"] for g in model["ground_truth"]] == ["matched", "ignored", "ignored", "dontcare", "missed"]
    # a score threshold drops the low ones: the plain false positive is gone, the rest stays
    high = inspect_frame(
        gt, [("mine", dt)], "000015", EvalConfig(classes=("Car",)), metric="bbox", score_threshold=0.55
    )["models"]["mine"]
    assert [d["label"] for d in high["detections"]][4:] == ["below_threshold", "other_class", "below_threshold"]
    assert high["counts"] == {"tp": 1, "fp": 1, "fn": 1}
    text = render_inspection(report)
    assert "mine (<detections>): TP 1  FP 2  FN 1" in text and "missed ground truth: 4" in text


def test_report_errors_name_the_frame_and_the_slot():
    gt, dt = scene()
    with pytest.raises(InputError, match="no such frame"):
        inspect_frame(gt, [("a", dt)], "000016")
    with pytest.raises(ConfigError, match="unknown metric"):
        inspect_frame(gt, [("a", dt)], "000015", metric="2d")
    with pytest.raises(ConfigError, match="repeat"):
        inspect_frame(gt, [("a", dt), ("a", dt)], "000015")


def test_model_names_from_paths():
    assert model_name("output/kitti_models/pv_rcnn/default/eval/epoch_80/val/default/result.pkl") == "pv_rcnn"
    assert model_name("/runs/second/result.pkl.gz") == "result"
    assert model_name("preds/pointpillar_val.pkl") == "pointpillar_val"
    assert model_name("results/kitti_txt") == "kitti_txt"
    assert unique_names(["result", "result", "a", "result"]) == ["result", "result (2)", "a", "result (3)"]


def test_cli_inspect_two_models_as_json(tmp_path, capsys):
    gt_path, pred_path = demo_paths()
    paths = []
    for model in ("pointpillar", "pv_rcnn"):
        p = tmp_path / "output" / "kitti_models" / model / "default" / "result.pkl.gz"
        p.parent.mkdir(parents=True)
        p.write_bytes(pred_path.read_bytes())
        paths += ["--pred", str(p)]
    gt = load_ground_truth(gt_path)
    fid = gt.frame_ids[3]
    assert main(["inspect", "--gt", str(gt_path), *paths, "--frame", str(int(fid)), "--format", "json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert list(report["models"]) == ["pointpillar", "pv_rcnn"]
    a, b = report["models"]["pointpillar"], report["models"]["pv_rcnn"]
    assert a["detections"] == b["detections"] and a["counts"] == b["counts"]
    dt = load_detections(pred_path, keep_lidar=True)
    first = dt.frame(fid)
    det0 = a["detections"][0]
    assert det0["score"] == pytest.approx(first["score"][0], rel=1e-6)
    assert det0["boxes_lidar"] == pytest.approx(dt.boxes_lidar[dt.offsets[dt.frame_index()[fid]]], rel=1e-6)
    assert det0["dimensions"] == pytest.approx(first["dimensions"][0], rel=1e-6)
    stats = frame_stats(gt, dt, EvalConfig(), FrameQuestion(score_threshold=-np.inf))
    f = gt.frame_index()[fid]
    assert a["counts"] == {"tp": stats.tp[f], "fp": stats.fp[f], "fn": stats.fn[f]}


def test_cli_inspect_errors(tmp_path, capsys):
    gt_path, pred_path = demo_paths()
    assert main(["inspect", "--gt", str(gt_path), "--pred", str(pred_path), "--frame", "999999"]) == 1
    assert "frame 999999" in capsys.readouterr().err
    assert (
        main(["inspect", "--gt", str(gt_path), "--pred", str(pred_path), "--name", "a", "--name", "b", "--frame", "1"])
        == 2
    )
    assert (
        main(
            [
                "inspect",
                "--gt",
                str(gt_path),
                "--pred",
                str(pred_path),
                "--pred",
                str(pred_path),
                "--name",
                "a",
                "--name",
                "a",
                "--frame",
                "1",
            ]
        )
        == 2
    )


def test_boxes_lidar_are_kept_only_when_asked_and_checked():
    _, pred_path = demo_paths()
    assert load_detections(pred_path).boxes_lidar is None
    kept = load_detections(pred_path, keep_lidar=True)
    assert kept.boxes_lidar.shape == (kept.num_boxes, 7) and np.isfinite(kept.boxes_lidar).all()
    sub = kept.subset(kept.frame_ids[2:4])
    np.testing.assert_array_equal(sub.boxes_lidar, kept.boxes_lidar[kept.offsets[2] : kept.offsets[4]])
    from kitti_eval.core.frames import Annotations

    fields = dict(
        name=np.array(["Car"]),
        bbox=np.zeros((1, 4)),
        dimensions=np.ones((1, 3)),
        location=np.ones((1, 3)),
        rotation_y=np.zeros(1),
        score=np.ones(1),
        boxes_lidar=np.zeros((1, 6)),
    )
    with pytest.raises(InputError) as e:
        Annotations.from_frames("detections", "r.pkl", [("7", fields)], keep_lidar=True)
    assert (e.value.frame, e.value.field) == ("000007", "boxes_lidar")
