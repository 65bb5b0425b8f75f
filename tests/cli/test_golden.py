"""Parity with the two reference evaluators on committed synthetic sets (tests/data/golden).

Each case holds the inputs in both forms (KITTI txt folders, OpenPCDet pickles) and the numbers that
the official C++ devkit and OpenPCDet's evaluator computed on them. Runs the real CLI in-process.
"""

from __future__ import annotations

import json
import math
import tarfile
from pathlib import Path

import pytest
from cli_runs import cli_json

DATA = Path(__file__).parents[1] / "data" / "golden"
CASES = sorted(p.name for p in DATA.iterdir() if p.is_dir())
DIFFS = ("easy", "moderate", "hard")
TOL = {"txt": 1e-6, "pkl": 1e-4}  # txt: both read the same decimals; pkl: float32 inputs


@pytest.fixture(scope="module", params=CASES)
def case(request, tmp_path_factory):
    src = DATA / request.param
    out = tmp_path_factory.mktemp(request.param)
    for name in ("label_2.tar.gz", "pred.tar.gz"):
        with tarfile.open(src / name) as tf:
            tf.extractall(out, filter="data")
    expected = json.loads((src / "expected.json").read_text())
    routes = {"txt": (out / "label_2", out / "pred"), "pkl": (src / "kitti_infos_val.pkl", src / "result.pkl")}
    return request.param, routes, expected


def run_json(gt, pred, protocol, tmp_path, *extra):
    return cli_json(gt, pred, tmp_path, "--protocol", protocol, *extra)


def close(got, want, tol):
    return got is not None and not math.isnan(got) and abs(got - want) <= tol


@pytest.mark.parametrize("route", ["txt", "pkl"])
def test_official_protocol_equals_the_devkit(case, route, tmp_path):
    name, routes, expected = case
    doc = run_json(*routes[route], "official", tmp_path)
    official = expected["official_cpp"]
    evaluated = official["classes_evaluated"]
    checked = 0
    for cls in ("Car", "Pedestrian", "Cyclist"):
        for metric, ref_metric in (("bbox", "2d"), ("bev", "bev"), ("3d", "3d"), ("aos", "aos")):
            for recall, key in (("R40", "ap_r40"), ("R11", "ap_r11_from41")):
                for d in DIFFS:
                    got = doc["ap"]["strict"][recall][cls][metric][d]
                    if ref_metric in evaluated.get(cls, []):
                        assert close(got, official[key][cls][ref_metric][d], TOL[route]), (cls, metric, recall, d)
                        checked += 1
                    else:  # the devkit does not evaluate it (no detection, or an alpha of -10)
                        assert got is None, (cls, metric, recall, d, got)
    assert checked >= 2 * 3 * 2 * 3  # at least two classes in three metrics


@pytest.mark.parametrize("route", ["txt", "pkl"])
def test_openpcdet_protocol_equals_openpcdet(case, route, tmp_path):
    name, routes, expected = case
    doc = run_json(*routes[route], "openpcdet", tmp_path)
    official = expected["official_cpp"]
    if expected["python_pcdet"] is None:
        _openpcdet_differs_from_the_devkit_only_in_bev_and_3d(doc, run_json(*routes[route], "official", tmp_path))
        return
    reference = expected["python_pcdet"][route]["ap"]
    for oset, by_recall in reference.items():
        for recall, by_cls in by_recall.items():
            for cls, by_metric in by_cls.items():
                for ref_metric, by_d in by_metric.items():
                    metric = "bbox" if ref_metric == "2d" else ref_metric
                    for d, want in by_d.items():
                        got = doc["ap"][oset][recall][cls][metric][d]
                        if name == "edge" and metric in ("bev", "3d"):
                            # OpenPCDet's float32 rotated IoU fails on the identical boxes of this case;
                            # exact IoU must give the devkit's numbers there instead
                            if oset == "strict":
                                key = "ap_r40" if recall == "R40" else "ap_r11_from41"
                                assert close(got, official[key][cls][metric][d], TOL[route])
                            continue
                        assert close(got, want, TOL[route]), (oset, recall, cls, metric, d, got, want)


def _openpcdet_differs_from_the_devkit_only_in_bev_and_3d(pcdet: dict, official: dict) -> None:
    """A case without OpenPCDet numbers (sizes): every class is detected and no alpha is -10, so the two
    protocols differ only where OpenPCDet leaves DontCare regions out, and on this case that is BEV alone: a
    2D-only detection lies at -1000 with l = w = -1 like every DontCare line, so in BEV the devkit finds it
    inside a DontCare region and does not count it while OpenPCDet counts a false positive; in 3D its height
    interval is empty, it overlaps no DontCare region, and both count it."""
    differs = set()
    for oset in ("strict", "loose"):
        for recall in ("R40", "R11"):
            for cls in ("Car", "Pedestrian", "Cyclist"):
                for metric in ("bbox", "aos", "bev", "3d"):
                    for d in DIFFS:
                        got = pcdet["ap"][oset][recall][cls][metric][d]
                        want = official["ap"][oset][recall][cls][metric][d]
                        if metric in ("bbox", "aos"):
                            assert got == want, (oset, recall, cls, metric, d)
                        else:
                            assert got <= want + 1e-9, (oset, recall, cls, metric, d)  # more false positives, if any
                            if got < want - 1e-9:
                                differs.add(metric)
    assert differs == {"bev"}


def test_official_curves_equal_the_devkit_curves(tmp_path):
    src = DATA / "small"
    curves = json.loads((src / "curves.json").read_text())["official_cpp"]
    for name in ("label_2.tar.gz", "pred.tar.gz"):
        with tarfile.open(src / name) as tf:
            tf.extractall(tmp_path, filter="data")
    doc = run_json(tmp_path / "label_2", tmp_path / "pred", "official", tmp_path, "--curves")
    for cls, by_metric in curves.items():
        for ref_metric, by_d in by_metric.items():
            metric = "bbox" if ref_metric == "2d" else ref_metric
            for d, want in by_d.items():
                got = doc["curves"]["strict"][cls][metric][d]["precision"]
                assert got == pytest.approx(want, abs=1e-12), (cls, metric, d)
