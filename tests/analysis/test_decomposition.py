"""The error decomposition and true-positive errors: hand-computed scenarios run over the library and its
slow twin (tests/helpers/naive_decomposition.py), the twin against the library on random sets, the kernels against
theirs, and the command line.

Reading guide (see tests/core/test_scenarios.py). 41 Car boxes in 41 frames, each found by a perfect detection
(scores 0.99, 0.989, ...): every one of the 41 samples has precision 1, AP 100. One false positive scoring
above every hit: at the k-th threshold k + 1 TP and 1 FP, precision (k + 1) / (k + 2), rising, so its
envelope is 41/42 everywhere: R40 = R11 = 100 * 41/42, and suppressing it gains 100/42 = 2.381 points.
"""

from __future__ import annotations

import json
import math

import numba
import numpy as np
import pytest
from builders import annotations, box, dontcare, hits, one_car_per_frame
from naive_decomposition import decompose_naive, pass1_naive, tp_errors_naive
from numba.core import event
from test_matching import flatten, random_frames

from kitti_eval import cli
from kitti_eval.analysis.decomposition import (
    AOS_TYPES,
    ERROR_TYPES,
    decompose,
    errors_document,
    group_maxima,
    pass1_taken,
    tp_error_sums,
)
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.frames import Annotations
from kitti_eval.core.matching import MatchingInputs
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.demo import demo_paths
from kitti_eval.synth import generate

CAR = EvalConfig(classes=("Car",))
CAR_PED = EvalConfig(classes=("Car", "Pedestrian"))
ONE_FP = 100 / 42  # suppressing one false positive that scores above 41 hits
PED = dict(dims=(0.8, 1.7, 0.6), width_px=30.0, height_px=80.0)


def fast(gt, dt, config):
    dec = decompose(gt, dt, config)
    out = {}
    for cls, by_metric in dec.errors.items():
        for metric, by_diff in by_metric.items():
            for d, e in by_diff.items():
                if e is not None:
                    out[(cls, metric, d)] = {"ap": dict(e.ap), **{k: dict(v) for k, v in e.fixed.items()}}
    return out


def slow(gt, dt, config):
    return decompose_naive(gt, dt, config)


IMPLS = pytest.mark.parametrize("impl", [fast, slow], ids=["library", "twin"])


def run(impl, gt_frames, dt_frames, config=CAR):
    return impl(annotations("ground_truth", gt_frames), annotations("detections", dt_frames), config)


def gains(table, key, recall="R40"):
    """AP points gained by fixing each type (and all) for one (class, metric, difficulty)."""
    e = table[key]
    return {k: e[k][recall] - e["ap"][recall] for k in e if k != "ap"}


def only(table, key, kind, value, recall="R40"):
    """Fixing ``kind`` gains ``value``; every other type gains nothing."""
    g = gains(table, key, recall)
    for k, v in g.items():
        if k == kind:
            assert v == pytest.approx(value), (key, k)
        elif k != "all":
            assert v == pytest.approx(0.0, abs=1e-9), (key, k, v)


@IMPLS
def test_background_false_positive_is_suppressed(impl):
    dets = hits(41)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # overlaps nothing
    t = run(impl, one_car_per_frame(41), dets)
    for metric in ("bbox", "bev", "3d", "aos"):
        only(t, ("Car", metric, "moderate"), "background", ONE_FP)
        only(t, ("Car", metric, "moderate"), "background", ONE_FP, "R11")
        assert t[("Car", metric, "moderate")]["all"]["R40"] == pytest.approx(100.0)


@IMPLS
def test_duplicate_is_suppressed(impl):
    dets = hits(41)
    dets[0].append(box("Car", score=0.995))  # the same box again: pass 1 gives the box to it, the hit is left
    t = run(impl, one_car_per_frame(41), dets)
    # the extra false positive counts from the second threshold on: sample 0 keeps precision 1
    for metric in ("bbox", "bev", "3d"):
        only(t, ("Car", metric, "hard"), "duplicate", ONE_FP)
        only(t, ("Car", metric, "hard"), "duplicate", 100 - (1 + 10 * 41 / 42) / 11 * 100, "R11")


@IMPLS
def test_localization_on_a_taken_box_is_suppressed(impl):
    dets = hits(41)
    # half a length along x (BEV/3D IoU 3.12 / 9.36 = 1/3) and half a width in 2D (IoU 40 / 120 = 1/3)
    dets[0].append(box("Car", x=1.95, x1=140.0, score=1.0))
    t = run(impl, one_car_per_frame(41), dets)
    for metric in ("bbox", "bev", "3d"):
        only(t, ("Car", metric, "easy"), "localization", ONE_FP)


@IMPLS
def test_localization_on_a_missed_box_moves_it_there(impl):
    # 41 boxes, 40 found: 40 thresholds, precision 1 at samples 0..39, R40 = 39/40; the 41st box has a
    # detection a third off (below every hit): moved onto it, 41 of 41 are found, 100. It is not missed.
    dets = hits(40) + [[box("Car", x=1.95, x1=140.0, score=0.5)]]
    t = run(impl, one_car_per_frame(41), dets)
    for metric in ("bbox", "bev", "3d"):
        assert t[("Car", metric, "moderate")]["ap"]["R40"] == pytest.approx(39 / 40 * 100)
        only(t, ("Car", metric, "moderate"), "localization", 100 - 39 / 40 * 100)


@IMPLS
def test_missed_box_is_removed(impl):
    # 82 boxes, 80 found: recall stops at 80/82, 40 thresholds, R40 = 39/40; without the two missed boxes
    # 80 of 80: the 41st threshold at recall 1, R40 = 100
    gts = one_car_per_frame(82)
    dets = hits(80) + [[], []]
    t = run(impl, gts, dets)
    for metric in ("bbox", "bev", "3d", "aos"):
        only(t, ("Car", metric, "moderate"), "missed", 100 - 39 / 40 * 100)
    # with at most 41 boxes, R40 counts only the true positives: removing a missed box changes nothing
    t = run(impl, one_car_per_frame(41), hits(40) + [[]])
    only(t, ("Car", "3d", "moderate"), "missed", 0.0)


@IMPLS
def test_car_detection_on_a_pedestrian_is_classification_for_both_classes(impl):
    gts = one_car_per_frame(41)
    peds = [[box("Pedestrian", x=8.0, x1=700.0, **PED)] for _ in range(41)]
    gts = [g + p for g, p in zip(gts, peds)]
    dets = hits(41)
    for i in range(40):
        dets[i].append(box("Pedestrian", x=8.0, x1=700.0, score=round(0.9 - i / 1000, 6), **PED))
    dets[40].append(box("Car", x=8.0, x1=700.0, score=1.0, **PED))  # the last pedestrian, called a Car
    t = run(impl, gts, dets, CAR_PED)
    for metric in ("bbox", "bev", "3d"):
        # for Car: a false positive on another class's box (IoU 1 > 0.7), above every hit: it leaves Car
        only(t, ("Car", metric, "moderate"), "classification", ONE_FP)
        # for Pedestrian: 40 of 41 found (R40 39/40); re-labelled, the Car detection finds the 41st
        only(t, ("Pedestrian", metric, "moderate"), "classification", 100 - 39 / 40 * 100)


@IMPLS
def test_both_wrong_class_and_badly_placed(impl):
    gts = one_car_per_frame(41)
    gts[0].append(box("Pedestrian", x=8.0, x1=700.0, **PED))
    dets = hits(41)
    # a Car detection 0.4 m (2D: 12 px) off the pedestrian: BEV/3D IoU 0.24 / 0.72 = 1/3, 2D 18 / 42
    dets[0].append(box("Car", x=8.4, x1=712.0, score=1.0, **PED))
    t = run(impl, gts, dets)
    for metric in ("bbox", "bev", "3d"):
        only(t, ("Car", metric, "moderate"), "both", ONE_FP)


@IMPLS
def test_orientation_turned_around(impl):
    dets = hits(41)
    dets[0][0]["alpha"] = math.pi  # the top hit faces backwards: similarity 0
    t = run(impl, one_car_per_frame(41), dets)
    # AOS at the k-th threshold: k of k + 1 similar, rising to 40/41; turned around: 100
    assert t[("Car", "aos", "moderate")]["ap"]["R40"] == pytest.approx(40 / 41 * 100)
    only(t, ("Car", "aos", "moderate"), "orientation", 100 / 41)
    for metric in ("bbox", "bev", "3d"):
        assert gains(t, ("Car", metric, "moderate"))["all"] == pytest.approx(0.0)


@IMPLS
def test_dontcare_and_neighbour_rules_stay(impl):
    gts = one_car_per_frame(41)
    gts[0].append(dontcare([880.0, 140.0, 1000.0, 220.0]))
    gts[1].append(box("Van", x=-15.0, z=60.0, x1=1100.0))
    dets = hits(41)
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # inside the DontCare region in 2D
    dets[1].append(box("Car", x=-15.0, z=60.0, x1=1100.0, score=1.0))  # on the Van: absorbed, no error
    t = run(impl, gts, dets)
    only(t, ("Car", "bbox", "easy"), "background", 0.0)  # not a false positive in 2D
    only(t, ("Car", "bev", "easy"), "background", ONE_FP)  # the DontCare line has no 3D box


@IMPLS
def test_ground_truth_against_itself_has_no_error(impl):
    gts = one_car_per_frame(41)
    gts[3].append(box("Pedestrian", x=8.0, x1=700.0, **PED))
    gts[5].append(box("Van", x=-8.0, x1=300.0))
    dets = [[{**b, "score": 0.5 + k / 100} for b in frame] for k, frame in enumerate(gts)]
    t = run(impl, gts, dets, CAR_PED)
    for key in t:
        for kind, v in gains(t, key).items():
            assert v == 0.0, (key, kind)


@IMPLS
def test_fixing_every_type_reaches_100(impl):
    gts = one_car_per_frame(42)
    gts[2].append(box("Pedestrian", x=8.0, x1=700.0, **PED))
    dets = hits(40) + [[box("Car", x=1.95, x1=140.0, score=0.5)], []]  # box 40 a third off, box 41 missed
    dets[0].append(box("Car", x=-15.0, z=40.0, x1=900.0, score=1.0))  # background
    dets[1].append(box("Car", score=0.9895))  # duplicate (a second box on frame 1, above its hit's 0.989)
    dets[2].append(box("Car", x=8.0, x1=700.0, score=0.97, **PED))  # classification
    dets[3][0]["alpha"] = math.pi  # orientation
    t = run(impl, gts, dets, CAR)
    for metric in ("bbox", "bev", "3d", "aos"):
        e = t[("Car", metric, "moderate")]
        assert e["all"]["R40"] == pytest.approx(100.0)
        assert e["all"]["R11"] == pytest.approx(100.0)
        g = gains(t, ("Car", metric, "moderate"))
        kinds = AOS_TYPES if metric == "aos" else ERROR_TYPES
        positive = {"background", "duplicate", "classification", "localization", "missed"}
        positive |= {"orientation"} if metric == "aos" else set()
        for kind in kinds:
            assert (g[kind] > 0) == (kind in positive), (metric, kind, g[kind])
            assert g[kind] <= g["all"] + 1e-9


@pytest.mark.parametrize("seed", range(3))
def test_library_equals_its_twin_on_random_sets(seed):
    infos, results = generate(12, seed=seed, dets_per_frame=10.0)
    gt = Annotations.from_frames("ground_truth", "gt", [(i["image"]["image_idx"], i["annos"]) for i in infos])
    dt = Annotations.from_frames("detections", "dt", [(r["frame_id"], r) for r in results])
    a, b = fast(gt, dt, None), slow(gt, dt, None)
    assert a.keys() == b.keys()
    for key in a:
        assert set(a[key]) <= set(b[key])  # the twin also has bbox AP after fixing orientation: unchanged
        for kind in a[key]:
            for r in ("R40", "R11"):
                assert a[key][kind][r] == pytest.approx(b[key][kind][r], abs=1e-9), (key, kind, r)


def test_decomposed_ap_is_the_evaluated_ap_and_counts_add_up():
    gt_path, pred_path = demo_paths()
    from kitti_eval.io.loaders import load_pair

    gt, dt = load_pair(gt_path, pred_path)
    dec, result = decompose(gt, dt), evaluate(gt, dt)
    for cls in dec.classes:
        for metric in ("bbox", "bev", "3d", "aos"):
            for d in ("easy", "moderate", "hard"):
                e = dec.errors[cls][metric][d]
                for r in ("R40", "R11"):
                    assert e.ap[r] == pytest.approx(result.get(cls, metric, d, r), abs=1e-9)
                    assert e.fixed["all"][r] <= 100.0 + 1e-9
    car = dec.errors["Car"]["3d"]["moderate"]
    assert car.fixed["all"]["R40"] == pytest.approx(100.0)  # 547 boxes: every sample filled once all is fixed


def test_true_positive_errors_by_hand():
    # every detection 0.1 m off in x, 10 % longer, turned by 0.1 rad: translation 0.1, scale 1 - 1/1.1
    dets = [[box("Car", x=0.1, dims=(3.9 * 1.1, 1.5, 1.6), ry=0.1, score=round(0.99 - i / 1000, 6))] for i in range(41)]
    dec = decompose(annotations("ground_truth", one_car_per_frame(41)), annotations("detections", dets), CAR)
    tp = dec.tp_errors["Car"]["moderate"]
    assert tp.mean["translation"] == pytest.approx(0.1)
    assert tp.mean["scale"] == pytest.approx(1 - 1 / 1.1)
    assert tp.mean["orientation"] == pytest.approx(0.1)
    assert tp.curves["translation"] == pytest.approx([0.1] * 41)
    assert tp.recall == pytest.approx([(k + 1) / 41 for k in range(41)])
    same = decompose(annotations("ground_truth", one_car_per_frame(41)), annotations("detections", hits(41)), CAR)
    assert same.tp_errors["Car"]["easy"].mean == {"translation": 0.0, "scale": 0.0, "orientation": 0.0}


# ---- the kernels and their twins: one body over both


def _naive_group_maxima(frames, groups_per_frame):
    best, arg, offset = [], [], 0
    for f, groups in zip(frames, groups_per_frame):
        for j in range(len(f["idet"])):
            row_b, row_a = [], []
            for g in groups:
                b, a = 0.0, -1
                for i in range(len(f["ig"])):
                    if g[i] and f["ov"][j][i] > b:
                        b, a = f["ov"][j][i], offset + i
                row_b.append(b)
                row_a.append(a)
            best.append(row_b)
            arg.append(row_a)
        offset += len(f["ig"])
    return np.array(best).reshape(-1, len(groups_per_frame[0]) if groups_per_frame else 0).T, np.array(arg).reshape(
        -1, len(groups_per_frame[0]) if groups_per_frame else 0
    ).T


def maxima_library(frames):
    po, ov, go, do, ig, *_ = flatten(frames)
    groups = np.stack([ig == 0, ig == 1, ig != -1])
    return group_maxima(po, ov, go, do, groups)


def maxima_twin(frames):
    per_frame = [[np.asarray(f["ig"]) == 0, np.asarray(f["ig"]) == 1, np.asarray(f["ig"]) != -1] for f in frames]
    return _naive_group_maxima(frames, per_frame)


def pass1_library(frames, t):
    po, ov, go, do, ig, idet, dc, score, *_ = flatten(frames)
    return pass1_taken(MatchingInputs(po, [ov], go, do, ig, idet, dc, score), t).tolist()


def pass1_twin(frames, t):
    out, offset = [], 0
    for f in frames:
        out += [i + offset if i >= 0 else -1 for i in pass1_naive(f, t)]
        offset += len(f["ig"])
    return out


def _boxes(rng, n):
    return np.column_stack([rng.normal(0, 1, (n, 3)), rng.uniform(0.5, 4, (n, 3)), rng.uniform(-4, 4, n)])


def tp_library(frames, t, thresholds, dt_boxes, gt_boxes):
    po, ov, go, do, ig, idet, dc, score, *_ = flatten(frames)
    inputs = MatchingInputs(po, [ov], go, do, ig, idet, dc, score)
    return tp_error_sums(inputs, dt_boxes, gt_boxes, t, thresholds).tolist()


def tp_twin(frames, t, thresholds, dt_boxes, gt_boxes):
    out = []
    for thr in thresholds:
        total, g0, d0 = [0.0] * 4, 0, 0
        for f in frames:
            ng, nd = len(f["ig"]), len(f["idet"])
            sums = tp_errors_naive(
                {**f, "ov": f["ov"].tolist()}, t, thr, dt_boxes[d0 : d0 + nd], gt_boxes[g0 : g0 + ng]
            )
            total = [a + b for a, b in zip(total, sums)]
            g0, d0 = g0 + ng, d0 + nd
        out.append(total)
    return out


@pytest.mark.parametrize("maxima", [maxima_library, maxima_twin], ids=["library", "twin"])
def test_group_maxima(maxima):
    frame = dict(
        ov=np.array([[0.2, 0.6, 0.0], [0.0, 0.0, 0.0]]),
        ig=np.array([0, 1, 0], dtype=np.int8),
        idet=np.array([0, 0], dtype=np.int8),
        dc=np.zeros(3, bool),
        score=np.array([0.5, 0.4]),
        gt_alpha=np.zeros(3),
        dt_alpha=np.zeros(2),
    )
    best, arg = maxima([frame, frame])
    assert best.tolist() == [[0.2, 0.0, 0.2, 0.0], [0.6, 0.0, 0.6, 0.0], [0.6, 0.0, 0.6, 0.0]]
    assert arg.tolist() == [[0, -1, 3, -1], [1, -1, 4, -1], [1, -1, 4, -1]]
    for seed in range(5):
        frames = random_frames(np.random.default_rng(seed), 6)
        b1, a1 = maxima_library(frames)
        b2, a2 = maxima(frames)
        assert b1.tolist() == b2.tolist() and a1.tolist() == a2.tolist()


@pytest.mark.parametrize("pass1", [pass1_library, pass1_twin], ids=["library", "twin"])
def test_pass1_taken(pass1):
    # box 0 takes the higher-scoring of the two above 0.5; box 1 the one left; the third detection is free
    frame = dict(
        ov=np.array([[0.9, 0.6], [0.8, 0.0], [0.3, 0.3]]),
        ig=np.array([0, 0], dtype=np.int8),
        idet=np.array([0, 0, 0], dtype=np.int8),
        dc=np.zeros(2, bool),
        score=np.array([0.5, 0.7, 0.9]),
        gt_alpha=np.zeros(2),
        dt_alpha=np.zeros(3),
    )
    assert pass1([frame], 0.5) == [1, 0, -1]
    for seed in range(8):
        frames = random_frames(np.random.default_rng(seed), 8)
        assert pass1(frames, 0.5) == pass1_library(frames, 0.5)


@pytest.mark.parametrize("tp_sums", [tp_library, tp_twin], ids=["library", "twin"])
def test_tp_error_sums(tp_sums):
    frame = dict(
        ov=np.array([[0.9]]),
        ig=np.array([0], dtype=np.int8),
        idet=np.array([0], dtype=np.int8),
        dc=np.zeros(1, bool),
        score=np.array([0.8]),
        gt_alpha=np.zeros(1),
        dt_alpha=np.zeros(1),
    )
    gt_box = np.array([[0.0, 1.0, 10.0, 4.0, 1.5, 2.0, 3.0]])
    dt_box = np.array([[3.0, 9.0, 14.0, 2.0, 1.5, 2.0, -3.0]])  # 5 m off in x, z; half as long; 2pi - 6 apart
    sums = tp_sums([frame], 0.5, [0.9, 0.8], dt_box, gt_box)
    assert sums[0] == [0.0, 0.0, 0.0, 0.0]
    assert sums[1] == pytest.approx([1.0, 5.0, 0.5, 2 * math.pi - 6.0])
    for seed in range(6):
        rng = np.random.default_rng(seed)
        frames = random_frames(rng, 8)
        n_gt, n_dt = sum(len(f["ig"]) for f in frames), sum(len(f["idet"]) for f in frames)
        gb, db = _boxes(rng, n_gt), _boxes(rng, n_dt)
        thresholds = [0.9, 0.6, 0.3, 0.0]
        expected = np.array(tp_library(frames, 0.5, thresholds, db, gb))
        assert np.array(tp_sums(frames, 0.5, thresholds, db, gb)) == pytest.approx(expected)


# ---- outputs


def test_errors_command_json_and_main_flag(tmp_path, capsys):
    gt_path, pred_path = demo_paths()
    out = tmp_path / "errors.json"
    assert cli.main(["errors", "--gt", str(gt_path), "--pred", str(pred_path), "--format", "json", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["errors"]["Car"]) == {"bbox", "bev", "3d", "aos"}
    assert set(doc["errors"]["Car"]["3d"]["moderate"]) == set(ERROR_TYPES)
    assert set(doc["errors"]["Car"]["aos"]["moderate"]) == set(AOS_TYPES)
    assert set(doc["tp_errors"]["Car"]["moderate"]) == {"translation", "scale", "orientation"}
    assert len(doc["tp_error_curves"]["Car"]["moderate"]["translation"]) == 41
    main = tmp_path / "main.json"
    args = ["--gt", str(gt_path), "--pred", str(pred_path), "--format", "json", "-o", str(main), "--errors", "-q"]
    assert cli.main(args) == 0
    full = json.loads(main.read_text())
    assert full["errors"] == doc["errors"] and full["tp_errors"] == doc["tp_errors"]
    assert full["errors_r11"] == doc["errors_r11"]
    assert full["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"] == pytest.approx(
        doc["error_ap"]["R40"]["Car"]["3d"]["moderate"], abs=1e-9
    )
    capsys.readouterr()
    assert cli.main(["errors", "--gt", str(gt_path), "--pred", str(pred_path)]) == 0
    text = capsys.readouterr().out
    head = "class metric difficulty AP cls loc both dupl bkg miss orient all"
    assert text.splitlines()[1].split() == head.split()
    assert cli.main(["errors", "--gt", str(gt_path), "--pred", str(pred_path), "--format", "markdown"]) == 0
    assert "| Car | 3d | moderate |" in capsys.readouterr().out


def test_errors_document_is_plain_json():
    gt_path, pred_path = demo_paths()
    from kitti_eval.io.loaders import load_pair

    doc = errors_document(decompose(*load_pair(gt_path, pred_path)), full=False)
    assert set(doc) == {"errors", "errors_r11", "tp_errors"}
    json.dumps(doc, allow_nan=False)


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_decomposition_compiles_nothing_once_warm(tmp_path):
    """The decomposition's kernels are warmed with the others, each in one compiled version."""
    from test_jit import _Compiles

    from kitti_eval import _jit
    from kitti_eval.analysis import decomposition

    _jit.warm_up()
    compiles = _Compiles()
    gt_path, pred_path = demo_paths()
    with event.install_listener("numba:compile", compiles):
        assert cli.main(["errors", "--gt", str(gt_path), "--pred", str(pred_path), "-o", str(tmp_path / "e.txt")]) == 0
    assert compiles.names == []
    kernels = [v for v in vars(decomposition).values() if isinstance(v, numba.core.registry.CPUDispatcher)]
    mine = [k for k in kernels if k.py_func.__module__ == decomposition.__name__]
    versions = {k.py_func.__name__: len(k.signatures) for k in mine}
    assert versions == {"_group_maxima": 1, "_pass1_taken": 1, "_tp_error_events": 1, "_pair_errors": 0}  # inlined
