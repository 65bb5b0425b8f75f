"""The OpenPCDet drop-in returns OpenPCDet's text and ret_dict."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest

from kitti_eval import ConfigError, InputError, get_official_eval_result

GOLDEN = Path(__file__).parent / "data" / "golden" / "small"


@pytest.fixture(scope="module")
def annos():
    # trusted committed fixtures, loaded the way OpenPCDet's KittiDataset.evaluation builds its inputs
    infos = pickle.loads((GOLDEN / "kitti_infos_val.pkl").read_bytes())
    results = pickle.loads((GOLDEN / "result.pkl").read_bytes())
    return [info["annos"] for info in infos], results


def test_ret_dict_matches_openpcdet(annos):
    gt, dt = annos
    text, ret = get_official_eval_result(gt, dt, ["Car", "Pedestrian", "Cyclist"])
    expected = json.loads((GOLDEN / "expected.json").read_text())["python_pcdet"]["pkl"]["ret_dict"]
    assert list(ret) == list(expected)  # same keys, same order
    for key, value in expected.items():
        assert ret[key] == pytest.approx(value, abs=1e-4), key
    assert text.startswith("Car AP@0.70, 0.70, 0.70:\nbbox AP:")


def test_class_indices_and_pr_details(annos):
    gt, dt = annos
    details: dict = {}
    _, by_index = get_official_eval_result(gt, dt, [0, 2], PR_detail_dict=details)
    _, by_name = get_official_eval_result(gt, dt, ["Car", "Cyclist"])
    assert by_index == by_name
    assert details["3d"].shape == (2, 3, 2, 41)
    assert 0 < details["bbox"][0, 1, 0, 0] <= 1


def test_inputs_are_not_modified(annos):
    gt, dt = annos
    before = pickle.dumps((gt, dt))
    get_official_eval_result(gt, dt, "Car")
    assert pickle.dumps((gt, dt)) == before


def test_errors(annos):
    gt, dt = annos
    with pytest.raises(InputError, match="by position"):
        get_official_eval_result(gt, dt[:-1], ["Car"])
    with pytest.raises(ConfigError, match="out of range"):
        get_official_eval_result(gt, dt, [7])


def test_import_paths_name_one_function():
    """The drop-in moved into a package; every import path users have written still reaches it."""
    import kitti_eval
    from kitti_eval import compat
    from kitti_eval.compat import openpcdet

    assert kitti_eval.get_official_eval_result is openpcdet.get_official_eval_result
    assert compat.get_official_eval_result is openpcdet.get_official_eval_result
    assert compat.ret_dict is openpcdet.ret_dict
