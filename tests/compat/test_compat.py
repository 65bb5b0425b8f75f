"""The OpenPCDet drop-in returns OpenPCDet's text and ret_dict."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest

from kitti_eval import ConfigError, InputError, get_official_eval_result

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"


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


def test_the_sizes_case_through_the_drop_in_equals_the_cli():
    """OpenPCDet reads boxes whose sizes are not positive; so does the drop-in: the golden 'sizes' case gives the
    numbers of the openpcdet protocol, and the two inputs' size warnings come as UserWarning."""
    from kitti_eval import EvalConfig, evaluate, load_detections, load_ground_truth
    from kitti_eval.core.protocol import OPENPCDET

    sizes = GOLDEN.parent / "sizes"
    infos = pickle.loads((sizes / "kitti_infos_val.pkl").read_bytes())  # trusted committed fixtures
    results = pickle.loads((sizes / "result.pkl").read_bytes())
    with pytest.warns(UserWarning) as record:
        _, ret = get_official_eval_result([i["annos"] for i in infos], results, ["Car", "Pedestrian", "Cyclist"])
    said = [str(w.message) for w in record if "not positive" in str(w.message)]
    assert [m.split(": ", 1)[1].split(" (the first")[0] for m in said] == [
        "76 ground-truth boxes (DontCare aside) have a size that is not positive",
        "404 predicted boxes (DontCare aside) have a size that is not positive",
    ]
    whole = evaluate(
        load_ground_truth(sizes / "kitti_infos_val.pkl"),
        load_detections(sizes / "result.pkl"),
        EvalConfig(protocol=OPENPCDET),
    )
    assert ret["Car_3d/moderate_R40"] == pytest.approx(whole.get("Car", "3d", "moderate", "R40"), abs=1e-9)
    assert ret["Cyclist_bev/hard_R40"] == pytest.approx(whole.get("Cyclist", "bev", "hard", "R40"), abs=1e-9)
