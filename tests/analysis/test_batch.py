"""Many checkpoints in one process: equal to single evaluations, ordered by epoch, best named, plotted."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.analysis.batch import epoch_of, expand_predictions
from kitti_eval.cli import main

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"
GT = GOLDEN / "kitti_infos_val.pkl"


@pytest.fixture()
def checkpoints(tmp_path):
    """Three epochs: epoch_10 keeps every detection, epoch_2 a third, epoch_5 two thirds."""
    results = pickle.loads((GOLDEN / "result.pkl").read_bytes())  # trusted committed fixture
    paths = []
    for epoch, keep_every in ((2, 3), (10, 1), (5, 2)):
        thinned = []
        for r in results:
            n = len(r["score"])
            keep = np.arange(n) % keep_every == 0
            thinned.append(
                {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v) for k, v in r.items()}
            )
        p = tmp_path / "output" / "pointpillar" / "eval" / f"epoch_{epoch}" / "val" / "result.pkl"
        p.parent.mkdir(parents=True)
        p.write_bytes(pickle.dumps(thinned))
        paths.append(p)
    return tmp_path, paths


def test_batch_equals_single_evaluations(capsys, checkpoints):
    root, paths = checkpoints
    pattern = str(root / "output" / "*" / "eval" / "epoch_*" / "val" / "result.pkl")
    assert main(["--gt", str(GT), "--pred", pattern, "--format", "json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["epoch"] for r in doc["results"]] == [2, 5, 10]
    for entry in doc["results"]:
        assert main(["--gt", str(GT), "--pred", entry["path"], "--format", "json"]) == 0
        single = json.loads(capsys.readouterr().out)
        assert entry["result"]["ap"] == single["ap"]
    assert doc["best"]["epoch"] == 10


def test_batch_table_names_the_best_and_plots(capsys, checkpoints, tmp_path):
    root, paths = checkpoints
    png = tmp_path / "ap.png"
    assert (
        main(
            [
                "--gt",
                str(GT),
                "--pred",
                str(paths[0]),
                "--pred",
                str(paths[1]),
                "--plot",
                str(png),
                "--value",
                "Car/3d/moderate",
                "--value",
                "Car/bev/hard/R11",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:3] == ["checkpoint", "Car/3d/moderate/R40/strict", "Car/bev/hard/R11/strict"]
    assert out[1].startswith("epoch 2") and out[2].startswith("epoch 10") and out[2].endswith("<- best")
    assert out[-1].startswith("best: epoch 10")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_expand_and_epochs(tmp_path):
    for name in ("epoch_9", "epoch_10", "epoch_80"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "result.pkl").write_bytes(b"")
    got = expand_predictions([str(tmp_path / "epoch_*" / "result.pkl")])
    assert [epoch_of(p) for p in got] == [9, 10, 80]  # natural order, not 10 < 80 < 9
    with pytest.raises(Exception, match="no file matches"):
        expand_predictions([str(tmp_path / "nothing_*.pkl")])


def test_a_bad_checkpoint_is_reported_and_the_rest_evaluated(capsys, checkpoints, tmp_path):
    root, paths = checkpoints
    bad = tmp_path / "epoch_99" / "result.pkl"
    bad.parent.mkdir()
    bad.write_bytes(b"not a pickle")
    code = main(["--gt", str(GT), "--pred", str(paths[1]), "--pred", str(bad)])
    out, err = capsys.readouterr()
    assert code == 1 and "epoch_99" in err and "skipped" in err and "epoch 10" in out


def test_plot_dir_writes_pr_curves_and_overlays(capsys, checkpoints, tmp_path):
    out = tmp_path / "curves"
    assert main(["--gt", str(GT), "--pred", str(checkpoints[1][1]), "--plot-dir", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        f"{c}_{m}_strict.png" for c in ("Car", "Pedestrian", "Cyclist") for m in ("bbox", "bev", "3d", "aos")
    )
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in out.iterdir())
    over = tmp_path / "overlay"
    assert (
        main(
            [
                "--gt",
                str(GT),
                "--pred",
                str(checkpoints[1][0]),
                "--pred",
                str(checkpoints[1][1]),
                "--plot-dir",
                str(over),
            ]
        )
        == 0
    )
    assert sorted(p.name for p in over.iterdir()) == [
        f"{c}_3d_moderate_overlay.png" for c in ("Car", "Cyclist", "Pedestrian")
    ]
