"""A set given in shards, evaluated part by part, equals the set evaluated in one piece."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.analysis.sharded import evaluate_sharded, parts_of
from kitti_eval.core.evaluation import evaluate
from kitti_eval.core.protocol import EvalConfig, config_from_options
from kitti_eval.core.result import EvalResult
from kitti_eval.errors import InputError
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.io.safe_pickle import load_pickle
from kitti_eval.synth import generate, write_label_dir, write_result_dir

GOLDEN = Path(__file__).parents[1] / "data" / "golden"


def assert_same(a: EvalResult, b: EvalResult) -> None:
    """Every AP value (and COCO and range values) within 1e-9, the curves too, and every count equal."""

    def walk(x: object, y: object, where: str) -> None:
        if isinstance(x, dict):
            assert isinstance(y, dict) and x.keys() == y.keys(), where
            for k in x:
                walk(x[k], y[k], f"{where}/{k}")
        elif isinstance(x, (list, tuple)):
            assert isinstance(y, (list, tuple)) and len(x) == len(y), where
            for k, (u, v) in enumerate(zip(x, y)):
                walk(u, v, f"{where}[{k}]")
        elif x is None or y is None:
            assert x is None and y is None, where
        elif isinstance(x, float):
            assert math.isclose(x, y, rel_tol=0, abs_tol=1e-9), (where, x, y)  # type: ignore[arg-type]
        else:
            assert x == y, where

    da, db = a.to_dict(), b.to_dict()
    for key in ("ap", "num_gt", "num_det", "frames", "frames_without_predictions", "aos_evaluated", "coco", "ranges"):
        walk(da.get(key), db.get(key), key)
    assert (a.curves is None) == (b.curves is None)
    if a.curves is not None and b.curves is not None:
        for oset, by_cls in a.curves.items():
            for cls, by_metric in by_cls.items():
                for metric, by_diff in by_metric.items():
                    for diff, ca in by_diff.items():
                        cb = b.curves[oset][cls][metric][diff]
                        for field in ("precision", "recall", "orientation", "thresholds"):
                            np.testing.assert_allclose(getattr(ca, field), getattr(cb, field), rtol=0, atol=1e-12)


def split(items: list, cuts: list[int]) -> list[list]:
    edges = [0, *cuts, len(items)]
    return [items[a:b] for a, b in zip(edges[:-1], edges[1:])]


def dump_all(folder: Path, stem: str, pieces: list[list]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, piece in enumerate(pieces):
        paths.append(folder / f"{stem}-{k}.pkl")
        paths[-1].write_bytes(pickle.dumps(piece, protocol=4))
    return paths


@pytest.mark.parametrize("case", ["small", "quirks", "edge", "sizes"])
@pytest.mark.parametrize("protocol", ["official", "openpcdet"])
def test_golden_cases_in_shards_equal_the_whole(tmp_path: Path, case: str, protocol: str) -> None:
    infos = load_pickle(GOLDEN / case / "kitti_infos_val.pkl", source="infos")
    results = load_pickle(GOLDEN / case / "result.pkl", source="result")
    assert isinstance(infos, list) and isinstance(results, list)
    config = config_from_options(protocol=protocol)
    whole = evaluate(
        load_ground_truth(GOLDEN / case / "kitti_infos_val.pkl"),
        load_detections(GOLDEN / case / "result.pkl"),
        config,
        keep_curves=True,
    )
    n = len(infos)
    # paired by position: three ground-truth files and the three prediction files of the same frames
    gts = dump_all(tmp_path / "paired", "gt", split(infos, [n // 3, 2 * n // 3]))
    preds = dump_all(tmp_path / "paired", "pred", split(results, [n // 3, 2 * n // 3]))
    sharded = evaluate_sharded(gts, preds, config, keep_curves=True)
    assert_same(sharded, whole)
    # the size warnings count the whole set, name its first box, and name the inputs as the sharded run does
    sizes = [w.split(": ", 1)[1] for w in whole.warnings if "not positive" in w]
    assert [w.split(": ", 1)[1] for w in sharded.warnings if "not positive" in w] == sizes
    assert len(sizes) == (2 if case == "sizes" else 0)
    # not paired: four prediction files cutting across the ground-truth files, in another order
    pieces = split(results, [n // 5, n // 2, 3 * n // 4])
    preds = dump_all(tmp_path / "crossed", "pred", pieces[::-1])
    assert_same(evaluate_sharded(gts, preds, config, keep_curves=True), whole)


def test_txt_folders_as_shards_and_the_options_that_add_jobs(tmp_path: Path) -> None:
    infos, results = generate(300, seed=3)
    for k, (a, b) in enumerate(((0, 120), (120, 200), (200, 300))):
        write_label_dir(tmp_path / f"label_{k}", infos[a:b])
        write_result_dir(tmp_path / f"pred_{k}", results[a:b])
    gts = [tmp_path / f"label_{k}" for k in range(3)]
    preds = [tmp_path / f"pred_{k}" for k in range(3)]
    whole_gt = tmp_path / "label_all"
    whole_pred = tmp_path / "pred_all"
    write_label_dir(whole_gt, infos)
    write_result_dir(whole_pred, results)
    config = config_from_options(ranges="0,30,50,inf", coco=True)
    whole = evaluate(load_ground_truth(whole_gt), load_detections(whole_pred), config, keep_curves=True)
    sharded = evaluate_sharded(gts, preds, config, keep_curves=True)
    assert_same(sharded, whole)
    assert sharded.frames == 300 and sharded.ranges and sharded.coco


def test_a_frame_in_two_files_or_in_no_ground_truth_is_named(tmp_path: Path) -> None:
    infos, results = generate(30, seed=1)
    gts = dump_all(tmp_path, "gt", [infos[:20], infos[15:]])  # frames 15..19 twice
    preds = dump_all(tmp_path, "pred", [results[:20], results[20:]])
    with pytest.raises(InputError, match=r"frame 000015 is in two ground-truth files: .*gt-0.pkl and .*gt-1.pkl"):
        evaluate_sharded(gts, preds)
    gts = dump_all(tmp_path, "gt", [infos[:15], infos[15:]])
    preds = dump_all(tmp_path, "pred", [results[:20], results[18:]])
    with pytest.raises(InputError, match=r"frame 000018 is in two prediction files: .*pred-0.pkl and .*pred-1.pkl"):
        evaluate_sharded(gts, preds)
    gts = dump_all(tmp_path, "gt", [infos[:15], infos[15:25]])  # frames 25.. have no ground truth
    preds = dump_all(tmp_path, "pred", [results[:15], results[15:]])
    with pytest.raises(InputError, match="not in the ground truth") as err:
        evaluate_sharded(gts, preds)
    assert err.value.frame == "000025"


def test_parts_take_the_prediction_files_that_hold_their_frames(tmp_path: Path) -> None:
    infos, results = generate(30, seed=2)
    gts = dump_all(tmp_path, "gt", [infos[:10], infos[10:20], infos[20:]])
    preds = dump_all(tmp_path, "pred", [results[25:], results[:12], results[12:25]])
    parts = parts_of(gts, preds)
    assert [p.gt for p in parts] == [str(g) for g in gts]
    assert [[Path(x).name for x in p.preds] for p in parts] == [
        ["pred-1.pkl"],
        ["pred-1.pkl", "pred-2.pkl"],
        ["pred-0.pkl", "pred-2.pkl"],
    ]


def test_one_file_of_each_is_the_plain_evaluation(tmp_path: Path) -> None:
    infos, results = generate(50, seed=4)
    (gt,) = dump_all(tmp_path, "gt", [infos])
    (pred,) = dump_all(tmp_path, "pred", [results])
    config = EvalConfig()
    assert_same(evaluate_sharded([gt], [pred], config), evaluate(load_ground_truth(gt), load_detections(pred), config))


@pytest.mark.slow  # a local Dask cluster's processes
def test_the_cli_evaluates_shards_in_this_process_and_on_a_local_dask_cluster(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from kitti_eval.cli import main

    infos, results = generate(150, seed=5)
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pred,) = dump_all(tmp_path / "whole", "pred", [results])
    whole = evaluate(load_ground_truth(gt), load_detections(pred), EvalConfig()).to_dict()["ap"]
    dump_all(tmp_path / "shards", "gt", split(infos, [50, 100]))
    dump_all(tmp_path / "shards", "pred", split(results, [30, 70, 120]))
    argv = ["--gt", str(tmp_path / "shards" / "gt-*.pkl"), "--pred", str(tmp_path / "shards" / "pred-*.pkl")]
    argv += ["--sharded", "--format", "json"]

    def values(doc: dict) -> list[float | None]:
        flat: list[float | None] = []
        for oset in doc.values():
            for rec in oset.values():
                for cls in rec.values():
                    for metric in cls.values():
                        flat.extend(metric.values())
        return flat

    assert main(argv) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["frames"] == 150
    np.testing.assert_allclose(values(got["ap"]), values(whole), rtol=0, atol=1e-9)
    assert main([a for a in argv if a != "--sharded"] + ["--cluster", "local:2"]) == 2
    assert "--cluster evaluates a set given in shards: add --sharded" in capsys.readouterr().err
    pytest.importorskip("distributed")
    assert main([*argv, "--cluster", "local:2"]) == 0
    got = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(values(got["ap"]), values(whole), rtol=0, atol=1e-9)


class _DiesOnce:
    """Runs ``fn``, except that the first call anywhere ends its worker process (a lost worker)."""

    def __init__(self, fn: object, marker: Path) -> None:
        self.fn, self.marker = fn, marker

    def __call__(self, part: object) -> object:
        import os

        try:
            fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return self.fn(part)  # type: ignore[operator]
        os.close(fd)
        os._exit(1)


@pytest.mark.slow
def test_a_worker_lost_mid_run_changes_nothing(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    import sys

    import cloudpickle

    from kitti_eval.analysis.cluster import cluster_mapper

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    infos, results = generate(90, seed=6)
    gts = dump_all(tmp_path, "gt", split(infos, [30, 60]))
    preds = dump_all(tmp_path, "pred", split(results, [30, 60]))
    whole = evaluate_sharded(gts, preds, keep_curves=True)
    with cluster_mapper("local:2") as run:
        lost = evaluate_sharded(
            gts, preds, keep_curves=True, mapper=lambda fn, items: run(_DiesOnce(fn, tmp_path / "died"), items)
        )
    assert (tmp_path / "died").exists()  # a worker did die
    assert_same(lost, whole)


@pytest.mark.parametrize("slot", [("Car", "3d", "moderate", "strict"), ("Pedestrian", "aos", "hard", "loose")])
def test_the_frames_of_a_set_in_shards_equal_the_whole(tmp_path: Path, slot: tuple[str, str, str, str]) -> None:
    from kitti_eval.analysis.diagnostics import FrameQuestion, frame_stats
    from kitti_eval.analysis.sharded import frame_stats_sharded

    infos, results = generate(120, seed=7)
    gts = dump_all(tmp_path, "gt", split(infos, [40, 90]))
    preds = dump_all(tmp_path, "pred", split(results, [20, 100]))  # crossing the ground-truth files
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pred,) = dump_all(tmp_path / "whole", "pred", [results])
    cls, metric, difficulty, oset = slot
    question = FrameQuestion(cls, metric, difficulty, oset, score_threshold=0.3)
    whole = frame_stats(load_ground_truth(gt), load_detections(pred), EvalConfig(), question)
    parts = frame_stats_sharded(gts, preds, EvalConfig(), question)
    assert parts.frame_ids == whole.frame_ids and len(whole.frame_ids) == 120
    for field in ("tp", "fp", "fn"):
        np.testing.assert_array_equal(getattr(parts, field), getattr(whole, field))
    assert parts.worst(10) == whole.worst(10) and sum(whole.tp) > 0


def test_kitti_eval_frames_sharded_lists_the_same_worst_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from kitti_eval.cli import main

    infos, results = generate(90, seed=8)
    dump_all(tmp_path / "shards", "gt", split(infos, [30, 60]))
    dump_all(tmp_path / "shards", "pred", split(results, [45]))
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pred,) = dump_all(tmp_path / "whole", "pred", [results])
    assert main(["frames", "--gt", str(gt), "--pred", str(pred), "--worst", "5", "--format", "json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    argv = ["frames", "--gt", str(tmp_path / "shards" / "gt-*.pkl"), "--pred", str(tmp_path / "shards" / "pred-*.pkl")]
    assert main([*argv, "--sharded", "--worst", "5", "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == whole and len(whole["frames"]) == 5
    assert main([*argv[:3], "--pred", str(pred), "--pred", str(pred)]) == 2
    assert "one --pred, or --sharded" in capsys.readouterr().err


def test_the_paired_bootstrap_of_a_set_in_shards_equals_the_whole(tmp_path: Path) -> None:
    from kitti_eval.analysis.bootstrap import paired_bootstrap
    from kitti_eval.analysis.sharded import paired_bootstrap_sharded

    infos, results_a = generate(120, seed=9)
    _, results_b = generate(120, seed=10)  # other detections of the same frames: the second model
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pa,) = dump_all(tmp_path / "whole", "a", [results_a])
    (pb,) = dump_all(tmp_path / "whole", "b", [results_b])
    res_a, res_b, whole = paired_bootstrap(
        load_ground_truth(gt), load_detections(pa), load_detections(pb), resamples=60, seed=3
    )
    gts = dump_all(tmp_path, "gt", split(infos, [40, 80]))
    preds_a = dump_all(tmp_path, "a", split(results_a, [40, 80]))  # paired
    preds_b = dump_all(tmp_path, "b", split(results_b, [10, 70]))  # crossing
    sh_a, sh_b, parts = paired_bootstrap_sharded(gts, preds_a, preds_b, resamples=60, seed=3)
    assert_same(sh_a, res_a)
    assert_same(sh_b, res_b)
    assert parts.keys() == whole.keys() and len(whole) > 50
    for key, (lo, hi) in whole.items():
        assert parts[key] == pytest.approx((lo, hi), abs=1e-9), key


def test_kitti_eval_compare_sharded_with_a_bootstrap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from kitti_eval.cli import main

    infos, results_a = generate(90, seed=11)
    _, results_b = generate(90, seed=12)
    for name, items in (("gt", infos), ("a", results_a), ("b", results_b)):
        dump_all(tmp_path / "whole", name, [items])
        dump_all(tmp_path / "shards", name, split(items, [30, 60]))
    w, sh = tmp_path / "whole", tmp_path / "shards"
    tail = ["--bootstrap", "40", "--format", "json"]
    assert main(["compare", str(w / "a-0.pkl"), str(w / "b-0.pkl"), "--gt", str(w / "gt-0.pkl"), *tail]) == 0
    whole = json.loads(capsys.readouterr().out)
    argv = ["compare", str(sh / "a-*.pkl"), str(sh / "b-*.pkl"), "--gt", str(sh / "gt-*.pkl"), "--sharded", *tail]
    assert main(argv) == 0
    parts = json.loads(capsys.readouterr().out)
    assert [v["key"] for v in parts["values"]] == [v["key"] for v in whole["values"]]
    for p, q in zip(parts["values"], whole["values"]):
        for field in ("a", "b", "delta"):
            assert (p[field] is None) == (q[field] is None) and (p[field] is None or abs(p[field] - q[field]) < 1e-9)
        assert (p["interval95"] is None) == (q["interval95"] is None)
        if p["interval95"] is not None:
            np.testing.assert_allclose(p["interval95"], q["interval95"], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_ten_times_kitti_val_in_shards_on_a_local_cluster_equals_the_whole(tmp_path: Path) -> None:
    """37,690 frames (~300k ground-truth boxes, 1.5 M detections) in 10 shards, on a Dask LocalCluster of 2
    processes, against the same set evaluated in one piece: every value and curve to 1e-9."""
    pytest.importorskip("distributed")
    from kitti_eval.analysis.cluster import cluster_mapper
    from kitti_eval.speed_sharded import _write_shards

    _write_shards(tmp_path, 10)
    infos: list = []
    results: list = []
    for k in range(10):
        infos += load_pickle(tmp_path / f"gt-{k:03d}.pkl", source="gt")  # type: ignore[arg-type]
        results += load_pickle(tmp_path / f"pred-{k:03d}.pkl", source="pred")  # type: ignore[arg-type]
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pred,) = dump_all(tmp_path / "whole", "pred", [results])
    del infos, results
    config = EvalConfig()
    whole = evaluate(load_ground_truth(gt), load_detections(pred), config, keep_curves=True)
    assert whole.frames == 37_690
    gts = sorted(tmp_path.glob("gt-*.pkl"))
    preds = sorted(tmp_path.glob("pred-*.pkl"))
    with cluster_mapper("local:2") as run:
        assert_same(evaluate_sharded(gts, preds, config, keep_curves=True, mapper=run), whole)


def test_a_ground_truth_file_without_any_predictions_counts_its_frames_as_empty(tmp_path: Path) -> None:
    infos, results = generate(60, seed=13)
    gts = dump_all(tmp_path, "gt", split(infos, [20, 40]))
    preds = dump_all(tmp_path, "pred", [results[:20], results[40:]][::-1])  # nothing for frames 20..39
    (gt,) = dump_all(tmp_path / "whole", "gt", [infos])
    (pred,) = dump_all(tmp_path / "whole", "pred", [results[:20] + results[40:]])
    whole = evaluate(load_ground_truth(gt), load_detections(pred), EvalConfig())
    sharded = evaluate_sharded(gts, preds)
    assert_same(sharded, whole)
    assert len(sharded.frames_without_predictions) == 20


def test_the_loaders_warnings_reach_the_result_once_each(tmp_path: Path) -> None:
    infos, results = generate(40, seed=14)
    for info in infos[20:]:
        del info["image"]["image_idx"]  # frame ids from point_cloud.lidar_idx: a warning per file
    gts = dump_all(tmp_path, "gt", split(infos, [20]))
    preds = dump_all(tmp_path, "pred", split(results, [20]))
    warnings = evaluate_sharded(gts, preds).warnings
    fallback = [w for w in warnings if "image_idx" in w]
    assert len(fallback) == 1 and fallback[0].startswith(str(gts[1])) and "20 entries" in fallback[0]


def test_kitti_eval_gate_sharded_with_and_without_significance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from kitti_eval.cli import main

    infos, results_a = generate(90, seed=15)
    _, results_b = generate(90, seed=16)
    for name, items in (("gt", infos), ("base", results_a), ("now", results_b)):
        dump_all(tmp_path / "whole", name, [items])
        dump_all(tmp_path / "shards", name, split(items, [30, 60]))
    w, sh = tmp_path / "whole", tmp_path / "shards"
    rules = ["--max-drop", "0.5", "--min", "Car/3d/moderate >= 1"]
    for extra in ([], ["--significant", "--bootstrap", "30"]):
        whole = main(["gate", "--gt", str(w / "gt-0.pkl"), "--pred", str(w / "now-0.pkl"), "--baseline",
                      str(w / "base-0.pkl"), *rules, *extra])  # fmt: skip
        out_whole = capsys.readouterr().out
        sharded = main(["gate", "--gt", str(sh / "gt-*.pkl"), "--pred", str(sh / "now-*.pkl"), "--baseline",
                        str(sh / "base-*.pkl"), "--sharded", *rules, *extra])  # fmt: skip
        out_sharded = capsys.readouterr().out
        assert sharded == whole and out_sharded == out_whole, extra
    code = main(["gate", "--gt", str(sh / "gt-*.pkl"), "--pred", str(sh / "now-*.pkl"), "--sharded",
                 "--rule", "Car/3d/moderate/localization <= 5"])  # fmt: skip
    assert code == 2 and "need the set in one piece" in capsys.readouterr().err


def test_shards_given_as_a_shell_expands_a_glob(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An unquoted glob reaches the CLI as several files after one --gt (or --pred): the same as the quoted glob."""
    import json

    from kitti_eval.cli import main

    infos, results = generate(60, seed=11)
    gts = dump_all(tmp_path, "gt", split(infos, [20, 40]))
    preds = dump_all(tmp_path, "pred", split(results, [30]))
    quoted = ["--gt", str(tmp_path / "gt-*.pkl"), "--pred", str(tmp_path / "pred-*.pkl"), "--sharded"]
    assert main([*quoted, "--format", "json"]) == 0
    want = json.loads(capsys.readouterr().out)["ap"]
    expanded = ["--gt", *map(str, gts), "--pred", *map(str, preds)]
    assert main([*expanded, "--sharded", "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out)["ap"] == want
    assert main(["frames", *expanded, "--sharded", "--format", "json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["frames"]) == 60
    for argv in (expanded, ["frames", *expanded]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"error: 3 --gt files given ({gts[0]}, {gts[1]}, {gts[2]}): several ground-truth files" in err
        assert "add --sharded; to evaluate many checkpoints give one --gt and several --pred" in err
