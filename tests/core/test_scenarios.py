"""Hand-computed AP scenarios: each expected value is written as the arithmetic that produces it.

Reading guide. With ``n`` valid ground-truth boxes all found, the score thresholds are one per true
positive while ``n <= 41`` (recall steps of 1/n are at most 1/40 apart... and at least as wide), so the
41-sample precision curve holds ``n`` filled samples and zeros after: R40 averages samples 1..40, R11
samples 0, 4, ..., 40. With n = 40 the last sample is empty: R40 = 39/40, R11 = 10/11. With n = 41 every
sample is filled: 100.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from builders import annotations, box, dontcare, hits, one_car_per_frame

from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.protocol import OFFICIAL, OPENPCDET, EvalConfig

CAR = EvalConfig(classes=("Car",))
CAR_PCDET = EvalConfig(classes=("Car",), protocol=OPENPCDET)


def run(gt_frames, dt_frames, config=CAR, ids=None):
    gt = annotations("ground_truth", gt_frames, ids)
    dt = annotations("detections", dt_frames, ids)
    return evaluate(gt, dt, config)


def test_all_found_forty():
    r = run(one_car_per_frame(40), hits(40))
    for metric in ("bbox", "bev", "3d", "aos"):
        assert r.get("Car", metric, "moderate", "R40") == pytest.approx(39 / 40 * 100)
        assert r.get("Car", metric, "moderate", "R11") == pytest.approx(10 / 11 * 100)
    assert r.num_gt["Car"] == {"easy": 40, "moderate": 40, "hard": 40}


def test_all_found_forty_one_fills_every_sample():
    r = run(one_car_per_frame(41), hits(41))
    for metric in ("bbox", "bev", "3d", "aos"):
        assert r.get("Car", metric, "hard", "R40") == pytest.approx(100.0)
        assert r.get("Car", metric, "hard", "R11") == pytest.approx(100.0)


def test_single_hit_fills_only_sample_zero():
    # one ground truth, one perfect detection: one threshold, precision 1 at sample 0 only
    r = run(one_car_per_frame(1), hits(1))
    assert r.get("Car", "3d", "easy", "R11") == pytest.approx(1 / 11 * 100)
    assert r.get("Car", "3d", "easy", "R40") == pytest.approx(0.0)


def test_one_false_positive_above_every_hit():
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # overlaps nothing, scores highest
    r = run(one_car_per_frame(40), dets)
    # at the k-th threshold: k+1 TP and 1 FP -> precision (k+1)/(k+2), rising; its envelope is 40/41
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 * (40 / 41) / 40 * 100)
    assert r.get("Car", "bbox", "easy", "R11") == pytest.approx(10 * (40 / 41) / 11 * 100)


def test_one_false_positive_below_every_hit_costs_nothing():
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=0.01))
    r = run(one_car_per_frame(40), dets)
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)


def test_van_absorbs_a_car_detection():
    gts = one_car_per_frame(40)
    gts[0].append(box("Van", x=-15.0, z=40.0, x1=900.0))
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # a Car detection on the Van
    r = run(gts, dets)
    assert r.get("Car", "3d", "moderate", "R40") == pytest.approx(39 / 40 * 100)  # neither TP nor FP
    # a Truck is not a neighbour of Car: the same detection is a false positive
    gts[0][-1]["name"] = "Truck"
    r = run(gts, dets)
    assert r.get("Car", "3d", "moderate", "R40") == pytest.approx(39 / 41 * 100)


def test_person_sitting_is_ignored_for_pedestrian_not_counted():
    ped = dict(dims=(0.8, 1.7, 0.6), width_px=30.0, height_px=80.0)
    gts = [[box("Pedestrian", **ped)] for _ in range(40)]
    gts[0].append(box("Person_sitting", x=5.0, x1=700.0, **ped))
    dets = [[box("Pedestrian", score=0.9 - i / 1000, **ped)] for i in range(40)]
    r = run(gts, dets, EvalConfig(classes=("Pedestrian",)))
    assert r.num_gt["Pedestrian"]["easy"] == 40  # the sitting person is no miss
    assert r.get("Pedestrian", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)


def test_dontcare_region_suppresses_a_false_positive():
    gts = one_car_per_frame(40)
    gts[0].append(dontcare([880.0, 140.0, 1000.0, 220.0]))
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # inside the DontCare region in 2D
    for config in (CAR, CAR_PCDET):
        r = run(gts, dets, config)
        assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)  # suppressed in 2D
        # the DontCare line has no 3D box (-1000): no suppression in BEV/3D in either protocol
        assert r.get("Car", "bev", "easy", "R40") == pytest.approx(39 / 41 * 100)


def test_dontcare_with_a_real_3d_box_suppresses_bev_only_in_official():
    gts = one_car_per_frame(40)
    gts[0].append(dontcare([880.0, 140.0, 1000.0, 220.0], location=(-15.0, 1.6, 40.0), dims=(8.0, 3.0, 8.0)))
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))
    official = run(gts, dets, CAR)
    pcdet = run(gts, dets, CAR_PCDET)
    assert official.get("Car", "bev", "easy", "R40") == pytest.approx(39 / 40 * 100)
    assert pcdet.get("Car", "bev", "easy", "R40") == pytest.approx(39 / 41 * 100)


def test_dontcare_must_cover_more_than_the_threshold_of_the_detection():
    gts = one_car_per_frame(40)
    # covers 60 of the detection's 80 px width: 0.75 > 0.7 suppresses; 50 px: 0.625 does not
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))
    gts[0].append(dontcare([920.0, 150.0, 1200.0, 210.0]))
    assert run(gts, dets).get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)
    gts[0][-1] = dontcare([930.0, 150.0, 1200.0, 210.0])
    assert run(gts, dets).get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 41 * 100)


def test_height_exactly_forty_pixels_is_not_easy():
    gts = one_car_per_frame(40)
    gts[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, height_px=40.0))
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, height_px=40.0, score=0.5))
    r = run(gts, dets)
    # easy: y2 - y1 <= 40 ignores the box, and the detection matched to it is neither TP nor FP
    assert r.num_gt["Car"]["easy"] == 40
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)
    # moderate: 41 boxes, all found: every sample filled
    assert r.num_gt["Car"]["moderate"] == 41
    assert r.get("Car", "bbox", "moderate", "R40") == pytest.approx(100.0)


def test_a_detection_under_the_height_limit_is_ignored_not_false():
    dets = hits(40)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, height_px=24.5, score=1.0))  # < 25 px
    r = run(one_car_per_frame(40), dets)
    assert r.get("Car", "bbox", "hard", "R40") == pytest.approx(39 / 40 * 100)


def test_truncation_and_occlusion_limits_are_inclusive():
    gts = one_car_per_frame(40)
    gts[0][0]["truncated"] = 0.15  # == easy limit: still easy
    gts[1][0]["occluded"] = 1.0  # > easy limit 0: not easy, but moderate
    r = run(gts, hits(40))
    assert r.num_gt["Car"] == {"easy": 39, "moderate": 40, "hard": 40}


def test_orientation_similarity_of_a_quarter_turn_is_one_half():
    dets = hits(40, alpha=math.pi / 2)
    r = run(one_car_per_frame(40), dets)
    # (1 + cos(pi/2)) / 2 = 0.5 at every filled sample
    assert r.get("Car", "aos", "easy", "R40") == pytest.approx(39 * 0.5 / 40 * 100)
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)


def test_alpha_minus_ten_drops_aos_officially_anywhere_but_openpcdet_only_first():
    dets = hits(40)
    dets[5][0]["alpha"] = -10.0
    official = run(one_car_per_frame(40), dets, CAR)
    assert official.aos_evaluated is False
    assert official.get("Car", "aos", "easy") is None
    assert official.get("Car", "bbox", "easy") == pytest.approx(39 / 40 * 100)
    pcdet = run(one_car_per_frame(40), dets, CAR_PCDET)
    assert pcdet.aos_evaluated is True  # OpenPCDet only looks at the first detection
    # the -10 detection's similarity is (1 + cos(0 - (-10))) / 2; the envelope keeps the best sample
    assert pcdet.get("Car", "aos", "easy") is not None
    dets[0][0]["alpha"] = -10.0
    assert run(one_car_per_frame(40), dets, CAR_PCDET).get("Car", "aos", "easy") is None


def test_class_without_detections_is_skipped_officially_and_zero_in_openpcdet():
    config = EvalConfig(classes=("Car", "Cyclist"))
    r = run(one_car_per_frame(40), hits(40), config)
    assert all(r.get("Cyclist", m, "easy") is None for m in ("bbox", "bev", "3d", "aos"))
    r = run(one_car_per_frame(40), hits(40), EvalConfig(classes=("Car", "Cyclist"), protocol=OPENPCDET))
    assert all(r.get("Cyclist", m, "easy") == 0.0 for m in ("bbox", "bev", "3d", "aos"))


def test_class_with_detections_but_no_ground_truth_scores_zero():
    dets = hits(40)
    dets[0].append(box("Cyclist", x=-15.0, z=40.0, x1=900.0, dims=(1.8, 1.7, 0.6), score=0.7))
    r = run(one_car_per_frame(40), dets, EvalConfig(classes=("Car", "Cyclist")))
    assert r.num_gt["Cyclist"]["hard"] == 0
    assert r.get("Cyclist", "3d", "hard") == 0.0


def test_bev_only_detections_are_not_scored_in_3d_officially():
    dets = [[box("Car", score=0.9 - i / 1000, dims=(3.9, -1.0, 1.6))] for i in range(40)]  # h <= 0
    r = run(one_car_per_frame(40), dets)
    assert r.get("Car", "bev", "easy") == pytest.approx(39 / 40 * 100)
    assert r.get("Car", "3d", "easy") is None
    assert run(one_car_per_frame(40), dets, CAR_PCDET).get("Car", "3d", "easy") == 0.0


def test_match_needs_overlap_strictly_above_threshold():
    # 2D: ground truth [0, 0, 10, 100] (area 1000), detection [3, 0, 10, 100] (area 700):
    # IoU = 700 / (1000 + 700 - 700) = 0.7 exactly, which is not above 0.7
    gts = [[box("Car", bbox=[0.0, 0.0, 10.0, 100.0])] for _ in range(40)]
    at = [[box("Car", bbox=[3.0, 0.0, 10.0, 100.0], score=0.9 - i / 1000)] for i in range(40)]
    assert run(gts, at).get("Car", "bbox", "easy") == 0.0
    # [2.9, 0, 10, 100]: IoU = 710 / 1000 = 0.71 > 0.7
    above = [[box("Car", bbox=[2.9, 0.0, 10.0, 100.0], score=0.9 - i / 1000)] for i in range(40)]
    assert run(gts, above).get("Car", "bbox", "easy") == pytest.approx(39 / 40 * 100)


def test_frames_without_predictions_count_as_empty_and_are_reported():
    gt = annotations("ground_truth", one_car_per_frame(41))
    dt = annotations("detections", hits(40))  # frame 000040 has no entry
    r = evaluate(gt, dt, CAR)
    assert r.frames_without_predictions == ("000040",)
    assert any("no predictions" in w for w in r.warnings)
    # 41 valid boxes, 40 found: thresholds at recall k/41 -> samples of recall 1..40/41 filled
    assert r.num_gt["Car"]["easy"] == 41
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(39 / 40 * 100)


def test_ground_truth_against_itself_is_perfect_in_every_metric():
    # 41 identical-box pairs, including yaw at +-pi and rotated boxes: exact IoU is 1
    gts = [[box("Car", ry=r, alpha=r) for r in (math.pi, -math.pi, 0.3, -1.2)][k % 4 : k % 4 + 1] for k in range(41)]
    dets = [[{**g[0], "score": 0.5 + k / 100}] for k, g in enumerate(gts)]
    for config in (CAR, CAR_PCDET):
        r = run(gts, dets, config)
        for metric in ("bbox", "bev", "3d", "aos"):
            for d in ("easy", "moderate", "hard"):
                assert r.get("Car", metric, d, "R40") == pytest.approx(100.0)
                assert r.get("Car", metric, d, "R11") == pytest.approx(100.0)


def test_official_is_default_and_protocols_differ_only_where_documented():
    assert EvalConfig().protocol is OFFICIAL
    assert OFFICIAL.dontcare_metrics > OPENPCDET.dontcare_metrics


def test_distance_ranges_ignore_what_lies_outside():
    from kitti_eval.core.protocol import parse_ranges

    near = one_car_per_frame(40)  # z = 20 m
    far = [[box("Car", z=40.0, x1=300.0)] for _ in range(40)]  # z = 40 m, never detected
    dets = hits(40) + [[] for _ in range(40)]
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # a false positive at 42.7 m
    config = EvalConfig(classes=("Car",), ranges=parse_ranges("0,30,50"))
    r = run(near + far, dets, config)
    # whole set: 80 boxes, 40 found below one false positive: thresholds at recall 1/80, 2/80, 4/80, ...,
    # 40/80 -> 21 samples, precision (k+1)/(k+2) rising to 40/41
    assert r.num_gt["Car"]["easy"] == 80
    assert r.get("Car", "bbox", "easy", "R40") == pytest.approx(20 * (40 / 41) / 40 * 100)
    near_range, far_range = r.ranges
    assert (near_range["label"], far_range["label"]) == ("0-30m", "30-50m")
    # 0-30 m: the far boxes and the far false positive are ignored -> 40 of 40 found
    assert near_range["num_gt"]["Car"]["easy"] == 40
    assert near_range["ap"]["strict"]["R40"]["Car"]["3d"]["easy"] == pytest.approx(39 / 40 * 100)
    # 30-50 m: 40 boxes, nothing found (the near detections are outside and ignored)
    assert far_range["num_gt"]["Car"]["easy"] == 40
    assert far_range["ap"]["strict"]["R40"]["Car"]["3d"]["easy"] == 0.0
    doc = r.to_dict()
    assert [x["label"] for x in doc["ranges"]] == ["0-30m", "30-50m"] and doc["ranges"][1]["max"] == 50.0


def test_a_box_on_a_range_edge_belongs_to_the_farther_range():
    from kitti_eval.core.protocol import DistanceRange, parse_ranges

    edge = [[box("Car", z=30.0)] for _ in range(41)]
    r = run(
        edge,
        [[box("Car", z=30.0, score=0.9 - i / 1000)] for i in range(41)],
        EvalConfig(classes=("Car",), ranges=parse_ranges("0,30,inf")),
    )
    assert [x["num_gt"]["Car"]["easy"] for x in r.ranges] == [0, 41]
    assert r.ranges[1]["label"] == "30m+" and r.ranges[1]["ap"]["strict"]["R11"]["Car"]["bev"]["hard"] == 100.0
    assert DistanceRange(0, 30).label == "0-30m"
    with pytest.raises(Exception, match="increasing"):
        parse_ranges("0,50,30")


def test_coco_style_ap_is_the_mean_over_ten_thresholds():
    # detections shifted 0.4 m along their 4 m length: BEV and 3D IoU = 3.6 / 4.4 = 0.818..., a match at
    # the thresholds 0.50, 0.55, ..., 0.80 (7 of 10) and not at 0.85, 0.90, 0.95; the 2D boxes are exact
    dets = [[box("Car", x=0.4, dims=(4.0, 1.5, 1.6), score=0.9 - i / 1000)] for i in range(40)]
    gts = [[box("Car", dims=(4.0, 1.5, 1.6))] for _ in range(40)]
    r = run(gts, dets, EvalConfig(classes=("Car",), coco=True))
    assert r.coco["R40"]["Car"]["bev"]["easy"] == pytest.approx(7 / 10 * (39 / 40 * 100))
    assert r.coco["R40"]["Car"]["3d"]["hard"] == pytest.approx(7 / 10 * (39 / 40 * 100))
    assert r.coco["R40"]["Car"]["bbox"]["easy"] == pytest.approx(39 / 40 * 100)
    assert r.coco["R11"]["Car"]["bev"]["easy"] == pytest.approx(7 / 10 * (10 / 11 * 100))
    assert run(gts, dets).coco is None and run(gts, dets).to_dict()["coco"] is None


def test_coco_thresholds_per_class():
    from kitti_eval.core.protocol import coco_thresholds

    assert coco_thresholds("Car")[0] == 0.5 and coco_thresholds("Car")[-1] == 0.95
    assert coco_thresholds("Cyclist")[0] == 0.25 and coco_thresholds("cyclist")[-1] == pytest.approx(0.7)
    assert len(coco_thresholds("Bus")) == 10


def _lidar_frames(kind, frames):
    """Frames as a LiDAR-only dataset has them: no 2D box, alpha, truncation or occlusion."""
    from kitti_eval.core.frames import Annotations

    keep = ("name", "dimensions", "location", "rotation_y", "score")
    out = []
    for i, objs in enumerate(frames):
        d = {
            k: np.array([o[k] for o in objs], dtype="<U20" if k == "name" else np.float64)
            for k in keep
            if kind == "detections" or k != "score"
        }
        for k, width in (("dimensions", 3), ("location", 3)):
            d[k] = d[k].reshape(-1, width)
        out.append((f"{i:06d}", d))
    return Annotations.from_frames(kind, f"<lidar {kind}>", out)


def test_lidar_only_mode_scores_bev_and_3d_without_image_fields():
    from kitti_eval.errors import InputError

    gt = _lidar_frames("ground_truth", one_car_per_frame(40))
    dt = _lidar_frames("detections", hits(40))
    with pytest.raises(InputError, match="--lidar-only") as err:
        evaluate(gt, dt, CAR)
    assert err.value.field == "bbox"
    r = evaluate(gt, dt, EvalConfig(classes=("Car",), lidar_only=True))
    assert r.get("Car", "bbox", "easy") is None and r.get("Car", "aos", "easy") is None
    for d in ("easy", "moderate", "hard"):  # no difficulty rule: every level is the same
        assert r.get("Car", "bev", d) == pytest.approx(39 / 40 * 100)
        assert r.get("Car", "3d", d, "R11") == pytest.approx(10 / 11 * 100)


def test_lidar_only_mode_has_no_height_filter():
    gts = [[box("Car", height_px=10.0)] for _ in range(41)]  # far too small for any 2D difficulty
    dets = [[box("Car", height_px=10.0, score=0.9 - i / 1000)] for i in range(41)]
    assert run(gts, dets).num_gt["Car"]["hard"] == 0
    r = run(gts, dets, EvalConfig(classes=("Car",), lidar_only=True))
    assert r.num_gt["Car"] == {"easy": 41, "moderate": 41, "hard": 41}
    assert r.get("Car", "3d", "easy") == pytest.approx(100.0)


def test_protocol_file_custom_class_neighbours_and_difficulty(tmp_path):
    from kitti_eval.core.protocol import load_protocol_file

    f = tmp_path / "bus.toml"
    f.write_text(
        'classes = ["Bus"]\n[overlaps.Bus]\nstrict = [0.7, 0.6, 0.6]\n'
        '[neighbours]\nBus = ["Tram"]\n[difficulty]\nmin_height = [40, 25, 10]\n'
    )
    config = EvalConfig(**load_protocol_file(f))
    assert config.overlaps["Bus"] == {"strict": (0.7, 0.6, 0.6), "loose": (0.7, 0.6, 0.6)}
    bus = dict(dims=(12.0, 3.2, 2.5), width_px=150.0, height_px=90.0)
    gts = [[box("Bus", **bus)] for _ in range(40)]
    gts[0].append(box("Tram", x=-15.0, z=40.0, x1=900.0, **bus))
    gts[1].append(box("Bus", x=12.0, z=60.0, x1=600.0, dims=(12.0, 3.2, 2.5), height_px=20.0))  # 20 px tall
    dets = [[box("Bus", score=0.9 - i / 1000, **bus)] for i in range(40)]
    dets[0].append(box("Bus", x=-15.0, z=40.0, x1=900.0, score=1.0, **bus))  # a Bus detection on the Tram
    r = run(gts, dets, config)
    assert r.get("Bus", "3d", "moderate") == pytest.approx(39 / 40 * 100)  # the Tram absorbs it: no FP
    assert r.num_gt["Bus"] == {"easy": 40, "moderate": 40, "hard": 41}  # 20 px counts only above 10 px


def test_bad_protocol_files(tmp_path):
    from kitti_eval.core.protocol import load_protocol_file
    from kitti_eval.errors import ConfigError

    for text, needle in (
        ("bogus = 1", "unknown keys"),
        ("classes = 'Car'", "list of names"),
        ("[difficulty]\nmin_height = [1, 2]", "three numbers"),
        ("x = [", "not valid TOML"),
    ):
        f = tmp_path / "p.toml"
        f.write_text(text)
        with pytest.raises(ConfigError, match=needle):
            load_protocol_file(f)


@pytest.mark.parametrize(
    "dims, found_in",
    [
        ((0.0, 1.5, 1.6), ("bbox",)),  # no length: no BEV area, overlaps nothing in BEV and 3D
        ((3.9, 1.5, 0.0), ("bbox",)),  # no width: the same
        ((3.9, 0.0, 1.6), ("bbox", "bev")),  # no height: a rectangle in BEV, nothing in 3D
        ((-1.0, -1.0, -1.0), ("bbox",)),  # mmdetection3d's -1 Cars: a 1 x 1 m square, IoU 1 / 6.24 with the Car
    ],
)
@pytest.mark.parametrize("side", ["ground_truth", "detections"])
def test_a_box_whose_size_is_not_positive_is_evaluated_as_written(dims, found_in, side):
    """41 Cars found by 41 detections, scores descending; the last frame's box (ground truth or detection) has the
    size given. Where it overlaps nothing, that Car is missed and its detection, scoring lowest, is a false
    positive below every threshold: 40 of 41 found, precision 1 at 40 thresholds, one per sample 0..39 (the
    reading guide), so R40 = 39/40 and R11 = 10/11. Elsewhere all 41 are found: 100.

    On ground truth with exactly one zero dimension the devkit crashes; kitti-eval reads it as what it is, a box
    without BEV area (l or w) or without height (h), which overlaps nothing there."""
    gts, dets = one_car_per_frame(41), hits(41)
    (gts if side == "ground_truth" else dets)[40][0]["dimensions"] = list(dims)
    r = run(gts, dets, EvalConfig(classes=("Car",), protocol=OFFICIAL))
    for metric in ("bbox", "bev", "3d"):
        want = (100.0, 100.0) if metric in found_in else (39 / 40 * 100, 10 / 11 * 100)
        got = (r.get("Car", metric, "moderate", "R40"), r.get("Car", metric, "moderate", "R11"))
        assert got == pytest.approx(want), (metric, side)
    assert r.num_gt["Car"]["moderate"] == 41  # never refused, never ignored
    assert any("box (DontCare aside) has a size that is not positive" in w for w in r.warnings)
