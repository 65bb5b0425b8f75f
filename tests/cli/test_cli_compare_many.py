"""``kitti-eval compare`` with several results: a table ranked by a key, each result with its 95% interval and
rank range from the same resamples, and whether its lead over the next is significant; table, JSON and
Markdown. Two results still compare value by value."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kitti_eval.analysis.bootstrap import frame_weights, interval95
from kitti_eval.analysis.ranking import resampled_key
from kitti_eval.cli import main
from kitti_eval.core.evaluation import plan_evaluation
from kitti_eval.core.protocol import EvalConfig
from kitti_eval.core.result import ValueKey
from kitti_eval.io.loaders import load_detections, load_ground_truth
from kitti_eval.synth import generate, write_infos, write_results

KEY = "Car/3d/moderate/R40/strict"


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """runs/gt.pkl, and runs/{a,b,worse}/result.pkl: two draws of one detector and a clearly worse one."""
    root = tmp_path_factory.mktemp("runs")
    infos, _ = generate(300, seed=21, dets_per_frame=12.0)
    write_infos(root / "gt.pkl", infos)
    for name, seed, moved in (("a", 1, 0.0), ("b", 2, 0.0), ("worse", 4, 0.1)):
        results = generate(300, seed=21, dets_per_frame=12.0, detector_seed=seed, location_noise=moved)[1]
        write_results(root / name / "result.pkl", results)
    return root


def _run(capsys, *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_the_ranked_table_is_the_librarys_ranking_of_the_same_resamples(runs, capsys) -> None:
    paths = [runs / n / "result.pkl" for n in ("a", "worse", "b")]
    code, out, _ = _run(capsys, "compare", *paths, "--gt", runs / "gt.pkl", "--bootstrap", 400, "--seed", 7)
    assert code == 0
    code, out, _ = _run(
        capsys,
        "compare",
        *paths,
        "--gt",
        runs / "gt.pkl",
        "--bootstrap",
        400,
        "--seed",
        7,
        "--key",
        KEY,
        "--format",
        "json",
    )
    doc = json.loads(out)
    assert doc["key"] == [KEY]
    assert doc["bootstrap"] == {"method": "paired bootstrap over frames", "resamples": 400, "seed": 7, "level": 0.95}
    gt = load_ground_truth(runs / "gt.pkl")
    weights = frame_weights(gt.num_frames, 400, 7)
    values = {
        str(p): resampled_key(plan_evaluation(gt, load_detections(p), EvalConfig()), [ValueKey.parse(KEY)], weights)
        for p in paths
    }
    rows = doc["results"]
    assert [r["rank"] for r in rows] == [1, 2, 3] and rows[2]["result"] == str(paths[1])  # the worse one last
    for r in rows:
        assert r["interval"] == list(interval95(values[r["result"]]))  # the same draws, the same arithmetic
    assert rows[0]["difference_to_next"] == list(interval95(values[rows[0]["result"]] - values[rows[1]["result"]]))
    assert [r["rank_range"] for r in rows] == [[1, 2], [1, 2], [3, 3]]
    assert [r["differs_from_next"] for r in rows] == [False, True, None]
    # the table says the same: the worse one's rank alone, the second's lead marked
    code, table, _ = _run(
        capsys, "compare", *paths, "--gt", runs / "gt.pkl", "--bootstrap", 400, "--seed", 7, "--key", KEY
    )
    lines = table.splitlines()
    assert lines[0].split() == ["rank", "result", KEY, "95%", "interval", "ranks", "lead"]
    assert lines[2].endswith("1-2    *") and lines[3].split()[-1] == "3" and str(paths[1]) in lines[3]
    assert f"{rows[2]['key']:.4f}" in lines[3] and "400 resamples (paired bootstrap over frames, seed 7)" in table


def test_pred_globs_markdown_and_no_bootstrap(runs, capsys) -> None:
    code, out, _ = _run(
        capsys, "compare", "--pred", str(runs / "*" / "result.pkl"), "--gt", runs / "gt.pkl", "--format", "markdown"
    )
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == "| rank | result | `key` |" and len([x for x in lines if x.startswith("| ")]) == 4
    assert (
        "key: the mean of Car/3d/moderate/R40/strict, Pedestrian/3d/moderate/R40/strict, "
        "Cyclist/3d/moderate/R40/strict." in out
    )
    assert "worse" in lines[4]  # last of three
    # a saved JSON result ranks beside predictions without a bootstrap, and not with one
    saved = runs / "a.json"
    assert (
        _run(capsys, "--gt", runs / "gt.pkl", "--pred", runs / "a" / "result.pkl", "--format", "json", "-o", saved)[0]
        == 0
    )
    code, out, _ = _run(
        capsys,
        "compare",
        saved,
        runs / "b" / "result.pkl",
        runs / "worse" / "result.pkl",
        "--gt",
        runs / "gt.pkl",
        "--format",
        "json",
    )
    doc = json.loads(out)
    assert code == 0 and doc["bootstrap"] is None and doc["results"][-1]["interval"] is None
    code, _, err = _run(
        capsys,
        "compare",
        saved,
        runs / "b" / "result.pkl",
        runs / "worse" / "result.pkl",
        "--gt",
        runs / "gt.pkl",
        "--bootstrap",
        10,
    )
    assert code == 2 and "--bootstrap needs predictions for every result" in err


def test_two_results_still_compare_value_by_value_in_any_order(runs, capsys) -> None:
    a, b, gt = runs / "a" / "result.pkl", runs / "b" / "result.pkl", runs / "gt.pkl"
    code, first, _ = _run(capsys, "compare", a, b, "--gt", gt, "--classes", "Car")
    assert code == 0 and first.startswith("value ") and f"{KEY} " in first
    code, interleaved, _ = _run(capsys, "compare", a, "--gt", gt, b, "--classes", "Car")
    assert code == 0 and interleaved == first
    for argv, said in (
        ([a], "compare takes two results"),
        ([a, b, "--key", KEY, "--errors"], "--errors, --sharded and --all compare two results"),
        (["--pred", a], "a ranked table needs two results or more"),
    ):
        code, _, err = _run(capsys, "compare", *argv, "--gt", gt)
        assert code == 2 and said in err, err
