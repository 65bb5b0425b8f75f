"""The outputs on docs/frameworks.md ("Use it in your training framework") are what the code prints on the bundled
demo."""

from __future__ import annotations

import gzip
import pickle
import re
from pathlib import Path

import pytest

from kitti_eval import KittiMetric
from kitti_eval.compat import openpcdet
from kitti_eval.compat.mmdet3d import kitti_eval
from kitti_eval.demo import demo_paths

SECTION = "# Use it in your training framework"


@pytest.fixture(scope="module")
def section() -> str:
    text = (Path(__file__).resolve().parents[2] / "docs" / "frameworks.md").read_text()
    return text[text.index(SECTION) :]  # the page is the section


@pytest.fixture(scope="module")
def demo():
    gt_path, pred_path = demo_paths()
    # trusted: the demo files shipped in the package
    infos = pickle.loads(gzip.decompress(gt_path.read_bytes()))
    results = pickle.loads(gzip.decompress(pred_path.read_bytes()))
    return infos, results


def _blocks(section: str) -> list[str]:
    """The section's output blocks (fenced without a language), in order."""
    return [body for lang, body in re.findall(r"^```(\w*)\n(.*?)^```", section, re.S | re.M) if not lang]


def test_openpcdet_table(section, demo):
    infos, results = demo
    text, ret = openpcdet.get_official_eval_result(
        [i["annos"] for i in infos], results, ["Car", "Pedestrian", "Cyclist"]
    )
    shown = _blocks(section)[0]
    assert text.startswith(shown)
    assert f'`ret_dict["Car_3d/moderate_R40"]` is `{ret["Car_3d/moderate_R40"]!r}`' in section


def test_mmdet3d_text(section, demo):
    infos, results = demo
    text, ap = kitti_eval([i["annos"] for i in infos], results, ["Pedestrian", "Cyclist", "Car"])
    shown = _blocks(section)[1]
    assert shown.startswith("----------- AP40 Results")
    assert text.endswith("\n" + shown)
    assert f'`ap_dict["KITTI/Car_3D_AP40_moderate_strict"]` is `{ap["KITTI/Car_3D_AP40_moderate_strict"]!r}`' in section
    assert f'`ap_dict["KITTI/Overall_3D_AP40_moderate"]`\n`{ap["KITTI/Overall_3D_AP40_moderate"]!r}`' in section


def test_loop(section, demo):
    infos, results = demo
    batches = [(infos[k : k + 8], results[k : k + 8]) for k in range(0, len(infos), 8)]
    metric = KittiMetric(classes=("Car", "Pedestrian", "Cyclist"), protocol="openpcdet")
    for gt_batch, pred_batch in batches:
        metric.update(gt_batch, pred_batch)
    result = metric.compute()
    car, pedestrian = result.get("Car", "3d", "moderate"), result.get("Pedestrian", "bev", "hard", recall="R11")
    line = f"{len(metric)} {car!r} {pedestrian!r}"
    assert f"prints `{line}`" in section
