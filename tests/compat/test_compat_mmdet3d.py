"""The mmdetection3d drop-in: mmdetection3d's own unit-test scenarios, its text and keys, and where it differs.

The scenario below is the one frame of mmdetection3d 1.x's ``tests/test_evaluation/test_functional/
test_kitti_eval.py`` (``test_do_eval``, ``test_kitti_eval``, ``test_eval_class``): the same boxes, the same
expected numbers. Its ground truth has two Car boxes written with dimensions (-1, -1, -1) at (-1000, -1000,
-1000), as every reference reads them (:func:`kitti_eval.core.frames.unsized_boxes`): 1 x 1 m squares in BEV
far from every detection, and their 2D boxes are what matches.
"""

from __future__ import annotations

import copy
import json
import math
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest

from kitti_eval import OPENPCDET, Annotations, ConfigError, EvalConfig, InputError, evaluate
from kitti_eval.compat.mmdet3d import kitti_eval, kitti_eval_coco_style

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"
DIFFS = ("easy", "moderate", "hard")
CLASSES = ("Pedestrian", "Cyclist", "Car")  # mmdetection3d's current_classes = [1, 2, 0]


def scenario_gt() -> dict:
    return dict(
        name=np.array(["Pedestrian", "Cyclist", "Car", "Car", "Car", "DontCare", "DontCare"]),
        truncated=np.array([0.0, 0.0, 0.0, -1.0, -1.0, -1.0, -1.0]),
        occluded=np.array([0, 0, 3, -1, -1, -1, -1]),
        alpha=np.array([-1.57, 1.85, -1.65, -10.0, -10.0, -10.0, -10.0]),
        bbox=np.array(
            [
                [674.9179, 165.48549, 693.23694, 193.42134],
                [676.21954, 165.70988, 691.63745, 193.83748],
                [389.4093, 182.48041, 421.49072, 202.13422],
                [232.0577, 186.16724, 301.94623, 217.4024],
                [758.6537, 172.98509, 816.32434, 212.76743],
                [532.37, 176.35, 542.68, 185.27],
                [559.62, 175.83, 575.4, 183.15],
            ]
        ),
        dimensions=np.array(
            [[12.34, 2.85, 2.63], [3.69, 1.67, 1.87], [2.02, 1.86, 0.6], [-1.0] * 3, [-1.0] * 3, [-1.0] * 3, [-1.0] * 3]
        ),
        location=np.array(
            [[0.47, 1.49, 69.44], [-16.53, 2.39, 58.49], [4.59, 1.32, 45.84]] + [[-1000.0, -1000.0, -1000.0]] * 4
        ),
        rotation_y=np.array([-1.56, 1.57, -1.55, -10.0, -10.0, -10.0, -10.0]),
    )


def scenario_dt() -> dict:
    return dict(
        name=np.array(["Pedestrian", "Cyclist", "Car", "Car", "Car"]),
        truncated=np.zeros(5),
        occluded=np.zeros(5),
        alpha=np.array([1.0744612, 1.2775835, 1.82563, 2.1145396, -1.7676563]),
        bbox=scenario_gt()["bbox"][:5].copy(),  # each detection's 2D box is a ground-truth box
        dimensions=np.array(
            [
                [1.4441837, 1.7450154, 0.53160036],
                [1.6501029, 1.7540325, 0.5162356],
                [3.9313498, 1.4899347, 1.5655756],
                [4.0111866, 1.5350999, 1.585221],
                [3.7337692, 1.5117968, 1.5515774],
            ]
        ),
        location=np.array(
            [
                [4.6671643, 1.285098, 45.836895],
                [4.658241, 1.3088846, 45.85148],
                [-16.598526, 2.298814, 58.618088],
                [-18.629122, 2.2990575, 39.305355],
                [7.0964046, 1.5178275, 29.32426],
            ]
        ),
        rotation_y=np.array([1.174933, 1.3778262, 1.550529, 1.6742425, -1.5330327]),
        score=np.array([0.18151495, 0.57920843, 0.27795696, 0.23100418, 0.21541929]),
    )


def scenario_result(keep_curves: bool = False):
    gt = Annotations.from_frames("ground_truth", "gt", [("0", scenario_gt())])
    dt = Annotations.from_frames("detections", "dt", [("0", scenario_dt())])
    return evaluate(gt, dt, EvalConfig(classes=CLASSES, protocol=OPENPCDET), keep_curves=keep_curves)


def table(result, metric: str, recall: str) -> np.ndarray:
    """mmdetection3d's layout of do_eval's outputs: [class, difficulty, threshold set]."""
    return np.array(
        [[[result.ap[s][recall][c][metric][d] for s in ("strict", "loose")] for d in DIFFS] for c in CLASSES]
    )


def per_class(values: list[list[float]]) -> np.ndarray:
    """[class][difficulty] -> [class, difficulty, threshold set], the two sets equal (they are here)."""
    return np.repeat(np.array(values, dtype=float)[:, :, None], 2, axis=2)


# orientation similarity of the two matched moderate Cars: ground-truth alpha -10 against 2.1145396 (score
# 0.231) and -1.7676563 (score 0.215)
S_HIGH = (1 + math.cos(-10 - 2.1145396)) / 2
S_LOW = (1 + math.cos(-10 + 1.7676563)) / 2


def test_do_eval_scenario():
    """mmdetection3d's test_do_eval: every AP of the three classes, R11 and R40, both threshold sets.

    Hand-derived: nothing is easy (every box is under 40 px tall); at moderate and hard, Pedestrian and Cyclist
    have one valid box, matched exactly by its detection: one score threshold, precision 1 at sample 0 only,
    so R11 = 1/11 and R40 = 0. Car has two (the occluded one is ignored and absorbs its detection): two
    thresholds, R11 = 1/11, R40 = 1/40. No detection lies on a box of its class in BEV or 3D: 0.
    """
    r = scenario_result()
    eleventh = 100 / 11
    np.testing.assert_allclose(table(r, "bbox", "R11"), per_class([[0, eleventh, eleventh]] * 3), atol=1e-12)
    np.testing.assert_allclose(table(r, "bbox", "R40"), per_class([[0, 0, 0], [0, 0, 0], [0, 2.5, 2.5]]), atol=1e-12)
    for metric in ("bev", "3d"):
        for recall in ("R11", "R40"):
            assert np.all(table(r, metric, recall) == 0.0), (metric, recall)
    # mmdetection3d's expected values, to its eight decimals
    aos11 = per_class([[0, 0.55020816, 0.55020816], [0, 8.36633862, 8.36633862], [0, 8.63476893, 8.63476893]])
    aos40 = per_class([[0, 0, 0], [0, 0, 0], [0, 1.58140643, 1.58140643]])
    np.testing.assert_allclose(table(r, "aos", "R11"), aos11, atol=5e-9)
    np.testing.assert_allclose(table(r, "aos", "R40"), aos40, atol=5e-9)
    # and Car's by hand: sample 0 is the envelope max(S_HIGH, mean of both), sample 1 the mean of both
    assert r.ap["strict"]["R11"]["Car"]["aos"]["moderate"] == pytest.approx(
        max(S_HIGH, (S_HIGH + S_LOW) / 2) / 11 * 100
    )
    assert r.ap["strict"]["R40"]["Car"]["aos"]["hard"] == pytest.approx((S_HIGH + S_LOW) / 2 / 40 * 100)


def test_eval_class_scenario():
    """mmdetection3d's test_eval_class (2D only): the sums of the 41-point recall, precision and orientation
    curves over the three classes, three difficulties and both threshold sets: 16, 16 and 10.252829201850309
    (Pedestrian and Cyclist: one sample of 1 at moderate and hard; Car: two)."""
    r = scenario_result(keep_curves=True)
    curves = [r.curves[s][c]["bbox"][d] for s in ("strict", "loose") for c in CLASSES for d in DIFFS]
    assert sum(float(c.recall.sum()) for c in curves) == pytest.approx(16.0, abs=1e-12)
    assert sum(float(c.precision.sum()) for c in curves) == pytest.approx(16.0, abs=1e-12)
    assert sum(float(c.orientation.sum()) for c in curves) == pytest.approx(10.252829201850309, abs=1e-12)


def test_kitti_eval_scenario():
    """mmdetection3d's test_kitti_eval: the Overall 2D keys (the mean over the three classes, strict set)."""
    with pytest.warns(UserWarning, match="2 ground-truth boxes .* not positive"):
        text, ap = kitti_eval([scenario_gt()], [scenario_dt()], [1, 2, 0])
    assert ap["KITTI/Overall_2D_AP11_moderate"] == pytest.approx(9.090909090909092, abs=1e-12)
    assert ap["KITTI/Overall_2D_AP11_hard"] == pytest.approx(9.090909090909092, abs=1e-12)
    assert ap["KITTI/Overall_2D_AP40_moderate"] == pytest.approx(0.8333333333333334, abs=1e-12)
    assert ap["KITTI/Overall_2D_AP40_hard"] == pytest.approx(0.8333333333333334, abs=1e-12)
    assert ap["KITTI/Car_2D_AP40_moderate_loose"] == 2.5
    # per recall mode: 3 classes x 2 sets x 3 difficulties x (3D, BEV, 2D), then 3 x 3 Overall keys
    assert len(ap) == 2 * (3 * 2 * 3 * 3 + 3 * 3)
    assert list(ap)[:7] == [
        "KITTI/Pedestrian_3D_AP11_easy_strict",
        "KITTI/Pedestrian_BEV_AP11_easy_strict",
        "KITTI/Pedestrian_2D_AP11_easy_strict",
        "KITTI/Pedestrian_3D_AP11_moderate_strict",
        "KITTI/Pedestrian_BEV_AP11_moderate_strict",
        "KITTI/Pedestrian_2D_AP11_moderate_strict",
        "KITTI/Pedestrian_3D_AP11_hard_strict",
    ]
    assert list(ap)[54:57] == [
        "KITTI/Overall_3D_AP11_easy",
        "KITTI/Overall_BEV_AP11_easy",
        "KITTI/Overall_2D_AP11_easy",
    ]
    assert list(ap)[63] == "KITTI/Pedestrian_3D_AP40_easy_strict"
    assert list(ap)[-1] == "KITTI/Overall_2D_AP40_hard"
    assert all(type(v) is float for v in ap.values())
    lines = text.split("\n")
    assert lines[:9] == [
        "",
        "----------- AP11 Results ------------",
        "",
        "Pedestrian AP11@0.50, 0.50, 0.50:",
        "bbox AP11:0.0000, 9.0909, 9.0909",
        "bev  AP11:0.0000, 0.0000, 0.0000",
        "3d   AP11:0.0000, 0.0000, 0.0000",
        "aos  AP11:0.00, 0.55, 0.55",
        "Pedestrian AP11@0.50, 0.25, 0.25:",
    ]
    at = lines.index("Overall AP11@easy, moderate, hard:")
    assert lines[at - 1] == "" and lines[at + 1] == "bbox AP11:0.0000, 9.0909, 9.0909"
    # the mean of 0.55, 8.37 and 8.63 (unrounded)
    assert lines[at + 4] == f"aos  AP11:0.00, {(0.55020816 + 8.36633862 + 8.63476893) / 3:.2f}, 5.85"
    at = lines.index("----------- AP40 Results ------------")
    assert lines[at - 1 : at + 3] == [
        "",
        "----------- AP40 Results ------------",
        "",
        "Pedestrian AP40@0.50, 0.50, 0.50:",
    ]
    assert "Car AP40@0.70, 0.50, 0.50:\nbbox AP40:0.0000, 2.5000, 2.5000\n" in text
    assert text.endswith("\nbbox AP40:0.0000, 0.8333, 0.8333\nbev  AP40:0.0000, 0.0000, 0.0000\n"
                         "3d   AP40:0.0000, 0.0000, 0.0000\naos  AP40:0.00, 0.53, 0.53\n")  # fmt: skip


def test_the_cars_of_size_minus_one_are_reported_once():
    """mmdetection3d's -1 Cars are evaluated, and said: one warning for the ground truth, naming the first."""
    with pytest.warns(UserWarning) as record:
        kitti_eval([scenario_gt()], [scenario_dt()], [1, 2, 0])
    sizes = [str(w.message) for w in record if "not positive" in str(w.message)]
    assert len(sizes) == 1
    assert sizes[0].startswith(
        "gt_annos: 2 ground-truth boxes (DontCare aside) have a size that is not positive (the first: frame "
        "000000, box 3 (Car), (l, h, w) = (-1.0, -1.0, -1.0))"
    )


@pytest.fixture(scope="module")
def golden():
    # trusted committed fixtures; the lists mmdetection3d's KittiMetric hands kitti_eval
    infos = pickle.loads((GOLDEN / "kitti_infos_val.pkl").read_bytes())
    results = pickle.loads((GOLDEN / "result.pkl").read_bytes())
    expected = json.loads((GOLDEN / "expected.json").read_text())["python_pcdet"]["pkl"]
    return [info["annos"] for info in infos], results, expected


def test_golden_set_matches_the_python_evaluator(golden):
    """mmdetection3d's evaluator is, like OpenPCDet's, kitti-object-eval-python: on the golden set every
    value of ap_dict equals the numbers OpenPCDet's evaluator computed (float32 IoU: within 1e-4)."""
    gt, dt, expected = golden
    text, ap = kitti_eval(gt, dt, ["Car", "Pedestrian", "Cyclist"])
    metric_key = {"3D": "3d", "BEV": "bev", "2D": "2d"}
    checked = 0
    for recall, tag in (("R11", "AP11"), ("R40", "AP40")):
        for cls in ("Car", "Pedestrian", "Cyclist"):
            for s in ("strict", "loose"):
                for d in DIFFS:
                    for key, metric in metric_key.items():
                        want = expected["ap"][s][recall][cls][metric][d]
                        assert ap[f"KITTI/{cls}_{key}_{tag}_{d}_{s}"] == pytest.approx(want, abs=1e-4)
                        checked += 1
        for d in DIFFS:
            for key, metric in metric_key.items():
                mean = sum(expected["ap"]["strict"][recall][c][metric][d] for c in ("Car", "Pedestrian", "Cyclist")) / 3
                assert ap[f"KITTI/Overall_{key}_{tag}_{d}"] == pytest.approx(mean, abs=1e-4)
    assert checked == 108
    car = expected["ap"]["strict"]["R40"]["Car"]
    assert f"Car AP40@0.70, 0.70, 0.70:\nbbox AP40:{car['2d']['easy']:.4f}, " in text
    aos = ", ".join(f"{car['aos'][d]:.2f}" for d in DIFFS)
    assert f"aos  AP40:{aos}\n" in text


def test_eval_types_choose_rows_and_keys(golden):
    gt, dt, _ = golden
    full_text, full = kitti_eval(gt, dt, ["Car"])
    types = ["bev", "3d"]
    text, ap = kitti_eval(gt, dt, ["Car"], eval_types=types)
    assert types == ["bev", "3d"]  # never appended to
    assert ap == {k: v for k, v in full.items() if "_2D_" not in k}
    assert "bbox AP" not in text and "aos" not in text  # no 2D matching: no AOS (mmdetection3d fails here)
    assert "Overall" not in text and not any("Overall" in k for k in full)  # one class: no Overall block
    text, ap = kitti_eval(gt, dt, "Car", eval_types=["bbox", "aos"])
    assert ap == {k: v for k, v in full.items() if "_2D_" in k}
    assert [line for line in text.split("\n") if line.startswith(("bbox", "aos"))] == [
        line for line in full_text.split("\n") if line.startswith(("bbox", "aos"))
    ]
    with pytest.raises(ConfigError, match="at least one"):
        kitti_eval(gt, dt, ["Car"], eval_types=[])
    with pytest.raises(ConfigError, match="unknown eval_types"):
        kitti_eval(gt, dt, ["Car"], eval_types=["bbox", "BEV"])
    with pytest.raises(ConfigError, match="'aos' needs 'bbox'"):
        kitti_eval(gt, dt, ["Car"], eval_types=["3d", "aos"])


def test_classes_and_inputs(golden):
    gt, dt, _ = golden
    before = pickle.dumps((gt, dt))
    _, by_index = kitti_eval(gt, dt, [3, 4])
    _, by_name = kitti_eval(gt, dt, ["van", "Person_sitting"])  # mmdetection3d fails on both (IndexError)
    assert by_index == by_name
    assert "KITTI/Van_3D_AP40_moderate_strict" in by_name
    assert pickle.dumps((gt, dt)) == before
    with pytest.raises(ConfigError, match="Truck"):
        kitti_eval(gt, dt, ["Truck"])
    with pytest.raises(ConfigError, match="out of range"):
        kitti_eval(gt, dt, [5])
    with pytest.raises(InputError, match="by position"):
        kitti_eval(gt, dt[:-1], ["Car"])


def _car_frame(alpha_gt: float, alpha_dt: float, score: float, x: float = 0.0) -> tuple[dict, dict]:
    """One Car 60 px tall (easy), its detection the same box: a match in every metric."""
    box = dict(
        name=np.array(["Car"]),
        alpha=np.array([alpha_gt]),
        bbox=np.array([[100.0 + x, 100.0, 200.0 + x, 160.0]]),
        dimensions=np.array([[3.9, 1.5, 1.6]]),
        location=np.array([[x, 1.6, 20.0]]),
        rotation_y=np.array([0.0]),
    )
    gt = {**box, "truncated": np.zeros(1), "occluded": np.zeros(1)}
    return gt, {**box, "alpha": np.array([alpha_dt]), "score": np.array([score])}


def test_aos_follows_mmdet3ds_rule():
    """AOS rows appear when some detection and some frame's first ground-truth box have an alpha, even when
    the first frame's detection has none (OpenPCDet's rule would leave them out)."""
    (g0, d0), (g1, d1) = _car_frame(0.0, -10.0, 0.9), _car_frame(0.3, 0.3, 0.8, x=5.0)
    text, _ = kitti_eval([g0, g1], [d0, d1], ["Car"])
    # two matches at two thresholds; similarity (1 + cos(0 - -10)) / 2 and 1; sample 1 holds their mean
    s0 = (1 + math.cos(10.0)) / 2
    r40 = (s0 + 1) / 2 / 40 * 100
    assert f"aos  AP40:{r40:.2f}, {r40:.2f}, {r40:.2f}\n" in text
    assert "bbox AP40:2.5000, 2.5000, 2.5000\n" in text  # two thresholds: of R40's samples 1..40, sample 1
    # no alpha in any frame's first ground-truth box: no AOS, though OpenPCDet's rule would compute it
    g0n, g1n = ({**g, "alpha": np.array([-10.0])} for g in (g0, g1))
    text, _ = kitti_eval([g0n, g1n], [d1, d1], ["Car"])
    assert "aos" not in text
    # an empty ground-truth frame first (mmdetection3d: IndexError) is skipped
    empty_gt = {k: v[:0] for k, v in g0.items()}
    empty_dt = {k: v[:0] for k, v in d0.items()}
    text, _ = kitti_eval([empty_gt, g1], [empty_dt, d1], ["Car"])
    assert "aos  AP11:9.09, 9.09, 9.09\n" in text  # one exact match: sample 0 only


def test_aos_left_out_when_no_frame_starts_with_an_alpha():
    g, d = _car_frame(0.0, -10.0, 0.9)
    g2, d2 = _car_frame(0.0, 0.0, 0.5, x=300.0)
    gt = {k: np.concatenate([g[k], g2[k]]) for k in g}
    dt = {k: np.concatenate([d[k], d2[k]]) for k in d}
    with pytest.warns(UserWarning, match="AOS is not shown"):
        text, _ = kitti_eval([gt], [dt], ["Car"])
    assert "aos" not in text and "bbox AP40:" in text


def test_coco_style():
    """Ten IoU thresholds per class, R11, two decimals: the exact matches of the scenario pass all ten."""
    with warnings.catch_warnings(record=True) as record:
        warnings.filterwarnings("error", message="AOS")  # AOS is shown
        warnings.simplefilter("always")
        text = kitti_eval_coco_style([scenario_gt()], [scenario_dt()], [1, 2, 0])
    assert [str(w.message).split(" (the first")[0] for w in record] == [
        "gt_annos: 2 ground-truth boxes (DontCare aside) have a size that is not positive"
    ]
    assert text.split("\n")[:5] == [
        "Pedestrian coco AP@0.25:0.05:0.70:",
        "bbox AP:0.00, 9.09, 9.09",
        "bev  AP:0.00, 0.00, 0.00",
        "3d   AP:0.00, 0.00, 0.00",
        "aos  AP:0.00, 0.55, 0.55",
    ]
    assert "Car coco AP@0.50:0.05:0.95:\nbbox AP:0.00, 9.09, 9.09\n" in text
    assert text.endswith("aos  AP:0.00, 8.63, 8.63\n")


def test_coco_style_golden(golden):
    gt, dt, _ = golden
    text = kitti_eval_coco_style(copy.deepcopy(gt), dt, "Car")
    gt_a = Annotations.from_frames("ground_truth", "g", ((str(i), a) for i, a in enumerate(gt)))
    dt_a = Annotations.from_frames("detections", "d", ((str(i), a) for i, a in enumerate(dt)))
    r = evaluate(gt_a, dt_a, EvalConfig(classes=("Car",), protocol=OPENPCDET, coco=True))
    assert r.coco is not None
    want = ", ".join(f"{r.coco['R11']['Car']['3d'][d]:.2f}" for d in DIFFS)
    assert f"\n3d   AP:{want}\n" in text
    # the mean of the ten R11 values lies between the values at 0.50 and at 0.95
    assert 0 < r.coco["R11"]["Car"]["3d"]["moderate"] < r.ap["loose"]["R11"]["Car"]["3d"]["moderate"]


def test_monocular_2d_results_of_size_zero_are_evaluated(golden):
    """mmdetection3d's monocular metric writes 2D-only detections as dimensions 0 at location -1000, rotation 0
    and alpha 0, and evaluates them in 2D (``eval_types=['bbox']``): their 2D AP is that of the same 2D boxes
    with their 3D fields (2D matching reads only boxes and scores)."""
    gt, dt, _ = golden
    mono = []
    for d in dt:
        n = len(d["score"])
        mono.append(
            {
                **d,
                "dimensions": np.zeros((n, 3), np.float32),
                "location": np.full((n, 3), -1000.0, np.float32),
                "rotation_y": np.zeros(n),
                "alpha": np.zeros(n),
            }
        )
    with pytest.warns(UserWarning, match="predicted boxes .* a size that is not positive"):
        _, got = kitti_eval(gt, mono, ["Car", "Pedestrian", "Cyclist"], eval_types=["bbox"])
    _, want = kitti_eval(gt, dt, ["Car", "Pedestrian", "Cyclist"], eval_types=["bbox"])
    assert got == want and len(got) == 2 * (3 * 2 * 3 + 3)
