"""The mmengine adapter (``val_evaluator = dict(type='kitti_eval.KittiMetric', ...)``).

mmengine's evaluator needs torch, which the test machine may not have: the adapter is tested on a stand-in
for ``BaseMetric`` that keeps its contract (``results`` filled by ``process``, one entry a sample, gathered
from the ranks and handed to ``compute_metrics``, keys prefixed), always; with mmengine's registry when
mmengine is installed; and with mmengine's own evaluator when torch is there too.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pytest
from numba.core import event
from test_metric import _Compiles

from kitti_eval import ConfigError, InputError
from kitti_eval.compat.mmdet3d import kitti_eval
from kitti_eval.compat.mmdet3d_evaluator import adapter_class, predictions_to_kitti
from kitti_eval.io.calib import Calib, calib_from_info

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"
CLASSES = ["Pedestrian", "Cyclist", "Car"]  # mmdetection3d's KITTI 3-class metainfo
CATEGORIES = {"Pedestrian": 0, "Cyclist": 1, "Car": 2, "Van": 3, "Truck": 4, "Person_sitting": 5, "Tram": 6, "Misc": 7}

# LiDAR (x forward, y left, z up) to camera (x right, y down, z forward); P2 with f = 700, centre (600, 180)
VELO_TO_RECT = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
P2 = np.array([[700.0, 0.0, 600.0, 0.0], [0.0, 700.0, 180.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
CALIB = Calib(VELO_TO_RECT, P2, (375, 1242))


def test_lidar_boxes_by_hand():
    boxes = np.array(
        [
            [20.0, 2.0, -1.6, 4.0, 1.6, 1.5, 0.0],  # ahead, 2 m to the left
            [80.0, 0.0, -1.6, 4.0, 1.6, 1.5, 0.0],  # beyond x = 70.4: dropped
            [5.0, -30.0, -1.6, 4.0, 1.6, 1.5, 0.0],  # in range, but its image box starts right of the image
            [10.0, -8.0, -1.6, 4.0, 1.6, 1.5, 0.0],  # reaches past the right edge: clipped to W = 1242
        ]
    )
    out = predictions_to_kitti(boxes, [0.9, 0.8, 0.7, 0.6], [2, 2, 0, 1], CALIB, CLASSES)
    assert out["name"].tolist() == ["Car", "Cyclist"]
    np.testing.assert_allclose(out["location"], [[-2.0, 1.6, 20.0], [8.0, 1.6, 10.0]])
    np.testing.assert_allclose(out["dimensions"], [[4.0, 1.5, 1.6]] * 2)  # (x_size, z_size, y_size) = l, h, w
    np.testing.assert_allclose(out["rotation_y"], [-math.pi / 2] * 2)  # -yaw - pi/2
    np.testing.assert_allclose(out["alpha"], [math.atan2(2, 20) - math.pi / 2, math.atan2(-8, 10) - math.pi / 2])
    # ry = -pi/2: the box spans x_cam -2 -+ 0.8 and z_cam 20 -+ 2, y_cam 0.1 .. 1.6
    first = [600 - 700 * 2.8 / 18, 180 + 700 * 0.1 / 22, 600 - 700 * 1.2 / 22, 180 + 700 * 1.6 / 18]
    np.testing.assert_allclose(out["bbox"][0], first)
    np.testing.assert_allclose(
        out["bbox"][1], [600 + 700 * 7.2 / 12, 180 + 700 * 0.1 / 12, 1242.0, 180 + 700 * 1.6 / 8]
    )
    np.testing.assert_allclose(out["score"], [0.9, 0.6])
    assert out["truncated"].tolist() == [0.0, 0.0] and out["occluded"].tolist() == [0.0, 0.0]
    # a narrower range drops the first too
    narrow = predictions_to_kitti(
        boxes, [0.9] * 4, [2] * 4, CALIB, CLASSES, pcd_limit_range=(0, -40, -1.5, 70.4, 40, 0)
    )
    assert len(narrow["score"]) == 0 and narrow["bbox"].shape == (0, 4)


def test_camera_boxes_by_hand():
    out = predictions_to_kitti(
        [[-2.0, 1.6, 20.0, 4.0, 1.5, 1.6, -math.pi / 2 + 2 * math.pi]], [0.5], [2], CALIB, CLASSES, box_type="Camera"
    )
    np.testing.assert_allclose(out["rotation_y"], [-math.pi / 2])  # wrapped to [-pi, pi)
    np.testing.assert_allclose(out["alpha"], [-math.atan2(-2.0, 20.0) - math.pi / 2])
    np.testing.assert_allclose(
        out["bbox"][0], [600 - 700 * 2.8 / 18, 180 + 700 * 0.1 / 22, 600 - 700 * 1.2 / 22, 180 + 700 * 1.6 / 18]
    )


def test_bad_predictions_name_the_frame():
    with pytest.raises(InputError, match="expected shape") as e:
        predictions_to_kitti(np.zeros((2, 6)), [1, 1], [0, 0], CALIB, CLASSES, frame="000004")
    assert (e.value.frame, e.value.field) == ("000004", "bboxes_3d")
    with pytest.raises(InputError, match="class indices 0..2"):
        predictions_to_kitti(np.zeros((1, 7)), [1], [3], CALIB, CLASSES)
    with pytest.raises(InputError, match="1 boxes but 2 scores"):
        predictions_to_kitti(np.zeros((1, 7)), [1, 1], [0], CALIB, CLASSES)
    with pytest.raises(InputError, match="no image size"):
        predictions_to_kitti(np.zeros((1, 7)), [1], [0], Calib(VELO_TO_RECT, P2, None), CLASSES)


# ------------------------------------------------------------------------------------------- adapter


class StandInBaseMetric:
    """mmengine's BaseMetric contract, without torch: ``process`` appends one entry a sample to ``results``;
    ``evaluate`` hands the gathered entries to ``compute_metrics`` and prefixes the keys."""

    default_prefix: str | None = None

    def __init__(self, collect_device: str = "cpu", prefix: str | None = None, collect_dir: str | None = None) -> None:
        self.results: list[Any] = []
        self.prefix = prefix or self.default_prefix
        self.dataset_meta: dict | None = None

    def evaluate_gathered(self, results: list[Any]) -> dict[str, float]:
        metrics = self.compute_metrics(results)
        return {f"{self.prefix}/{k}": v for k, v in metrics.items()}


class FakeTensor:
    """What a CPU torch tensor offers the adapter: detach(), cpu(), numpy()."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = values

    def detach(self) -> FakeTensor:
        return self

    def cpu(self) -> FakeTensor:
        return self

    def numpy(self) -> np.ndarray:
        return self.values


class LiDARInstance3DBoxes:  # the name mmdetection3d's box class has; the adapter reads .tensor
    def __init__(self, values: np.ndarray) -> None:
        self.tensor = FakeTensor(values)


def mmdet3d_infos(infos: list[dict]) -> dict:
    """OpenPCDet infos as an mmdetection3d 1.x info file (metainfo/data_list, v2 calibration)."""
    data_list = []
    for info in infos:
        a, calib = info["annos"], calib_from_info(info)
        cam2img = np.eye(4)
        cam2img[:3] = calib.p2
        h, w = (int(v) for v in info["image"]["image_shape"])
        instances = [
            {
                "bbox": a["bbox"][j].tolist(),
                "bbox_label": CATEGORIES.get(str(a["name"][j]), -1),
                "bbox_3d": [*a["location"][j], *a["dimensions"][j], a["rotation_y"][j]],
                "truncated": float(a["truncated"][j]),
                "occluded": int(a["occluded"][j]),
                "alpha": float(a["alpha"][j]),
            }
            for j in range(len(a["name"]))
        ]
        data_list.append(
            {
                "sample_idx": int(info["image"]["image_idx"]),
                "images": {
                    "CAM2": {
                        "height": h,
                        "width": w,
                        "cam2img": cam2img.tolist(),
                        "lidar2cam": calib.velo_to_rect.tolist(),
                    }
                },
                "instances": instances,
            }
        )
    return {"metainfo": {"categories": CATEGORIES}, "data_list": data_list}


@pytest.fixture(scope="module")
def golden(tmp_path_factory):
    # trusted committed fixtures
    infos = pickle.loads((GOLDEN / "kitti_infos_val.pkl").read_bytes())
    results = pickle.loads((GOLDEN / "result.pkl").read_bytes())
    ann_file = tmp_path_factory.mktemp("mmdet3d") / "kitti_infos_val.pkl"
    ann_file.write_bytes(pickle.dumps(mmdet3d_infos(infos)))
    samples = []
    for r in results:
        boxes = np.asarray(r["boxes_lidar"], dtype=np.float64).copy()
        boxes[:, 2] -= boxes[:, 5] / 2  # OpenPCDet's geometric centre -> mmdetection3d's bottom centre
        samples.append(
            {
                "sample_idx": int(r["frame_id"]),
                "pred_instances_3d": {
                    "bboxes_3d": LiDARInstance3DBoxes(boxes.astype(np.float32)),
                    "scores_3d": FakeTensor(np.asarray(r["score"], dtype=np.float32)),
                    "labels_3d": FakeTensor(np.array([CLASSES.index(n) for n in r["name"]], dtype=np.int64)),
                },
            }
        )
    return infos, results, str(ann_file), samples


def test_adapter_over_two_ranks(golden):
    """Two ranks process alternate batches; mmengine gathers their entries (pickled, interleaved) and the
    main rank computes mmdetection3d's keys, rounded to four decimals, and logs its text."""
    infos, results, ann_file, samples = golden
    logs: list[str] = []
    cls = adapter_class(StandInBaseMetric, lambda msg, logger=None: logs.append(msg))
    ranks = [cls(ann_file=ann_file), cls(ann_file=ann_file)]
    for rank in ranks:
        rank.dataset_meta = {"classes": CLASSES}
    for k in range(0, len(samples), 4):
        ranks[(k // 4) % 2].process({}, samples[k : k + 4])
    assert all(isinstance(e, tuple) and set(e[1]) >= {"bbox", "score"} for e in ranks[0].results)
    assert all(isinstance(v, np.ndarray) for e in ranks[0].results for v in e[1].values())  # no tensors kept
    gathered = [e for part in zip(*(pickle.loads(pickle.dumps(r.results)) for r in ranks)) for e in part]
    gathered += pickle.loads(pickle.dumps(ranks[0].results[len(ranks[1].results) :]))
    assert len(gathered) == len(samples)
    out = ranks[0].evaluate_gathered(gathered)

    # exactly what mmdetection3d's kitti_eval (the drop-in) gives on the converted predictions, rounded
    converted = dict(gathered)
    gt = [i["annos"] for i in infos]
    _, want = kitti_eval(gt, [converted[r["frame_id"]] for r in results], CLASSES)
    assert out == {f"Kitti metric/pred_instances_3d/{k}": float(f"{v:.4f}") for k, v in want.items()}
    assert len(out) == 126 and "Kitti metric/pred_instances_3d/KITTI/Car_3D_AP40_moderate_strict" in out
    # and, to those four decimals, the numbers of the camera fields OpenPCDet wrote for the same boxes,
    # though the adapter drops the boxes mmdetection3d drops (outside the image or the point-cloud range)
    kept = sum(len(a["score"]) for a in converted.values())
    assert kept < sum(len(r["score"]) for r in results)
    _, stored = kitti_eval(gt, results, CLASSES)
    for key, value in stored.items():
        assert out[f"Kitti metric/pred_instances_3d/{key}"] == pytest.approx(value, abs=1e-4), key
    assert logs[0].startswith("Results of pred_instances_3d:\n\n----------- AP11 Results ------------\n\n")
    assert "aos  AP40:" in logs[0]


def test_adapter_options(golden):
    infos, results, ann_file, samples = golden
    cls = adapter_class(StandInBaseMetric, lambda *a, **k: None)
    m = cls(ann_file=ann_file, classes=["Car"], protocol="official", prefix="val")
    m.dataset_meta = {"classes": CLASSES}  # the model's labels index these
    m.process({}, samples[:10])
    out = m.evaluate_gathered(m.results)
    assert all(k.startswith("val/pred_instances_3d/KITTI/Car_") for k in out) and len(out) == 2 * 2 * 3 * 3
    for kwargs, message in (
        ({"metric": "img_bbox"}, "metric='bbox'"),
        ({"submission_prefix": "x"}, "submission files"),
        ({"default_cam_key": "CAM3"}, "CAM2"),
        ({"pcd_limit_range": [0, 1]}, "six numbers"),
        ({"pred_box_type_3d": "Depth"}, "'LiDAR' or 'Camera'"),
        ({"classes": ["Bus"]}, "no default IoU thresholds"),
    ):
        with pytest.raises(ConfigError, match=message):
            cls(ann_file=ann_file, **kwargs)
    no_classes = cls(ann_file=ann_file)
    with pytest.raises(ConfigError, match="no classes"):
        no_classes.process({}, samples[:1])
    unknown = cls(ann_file=ann_file, classes=CLASSES)
    with pytest.raises(InputError, match="no calibration") as e:
        unknown.process({}, [{**samples[0], "sample_idx": 999}])
    assert e.value.frame == "000999"


def test_mmengine_registry_finds_the_dotted_type(golden):
    """With mmengine installed: a config's type='kitti_eval.KittiMetric', built under mmdetection3d's scope,
    reaches kitti-eval's registry node (mmengine imports kitti_eval.registry by itself)."""
    registry = pytest.importorskip("mmengine.registry")
    from kitti_eval.compat import mmdet3d_evaluator as mmdet3d_metric

    infos, results, ann_file, samples = golden
    import kitti_eval.registry as node

    assert node.METRICS is not None and node.METRICS.scope == "kitti_eval"
    mmdet3d_scope = registry.METRICS._children.get("mmdet3d_like") or registry.Registry(
        "metric", parent=registry.METRICS, scope="mmdet3d_like"
    )
    stand_in = None
    if mmdet3d_metric.KittiMetric is None:  # no torch: register the class on the stand-in BaseMetric
        stand_in = adapter_class(StandInBaseMetric, lambda *a, **k: None)
        node.METRICS.register_module(name="KittiMetric", module=stand_in, force=True)
    try:
        with registry.DefaultScope.overwrite_default_scope("mmdet3d_like"):
            metric = mmdet3d_scope.build(dict(type="kitti_eval.KittiMetric", ann_file=ann_file, classes=["Car"]))
        assert type(metric).__name__ == "KittiMetric" and metric.ann_file == ann_file
        assert type(metric) is (stand_in or mmdet3d_metric.KittiMetric)
    finally:
        if stand_in is not None:
            node.METRICS._module_dict.pop("KittiMetric", None)


def test_mmengine_evaluator_end_to_end(golden):
    """With mmengine and torch: mmengine's own Evaluator builds the metric from the config dict, feeds it and
    evaluates (one process)."""
    evaluator_module = pytest.importorskip("mmengine.evaluator")
    infos, results, ann_file, samples = golden
    evaluator = evaluator_module.Evaluator(dict(type="kitti_eval.KittiMetric", ann_file=ann_file))
    evaluator.dataset_meta = {"classes": CLASSES}
    for k in range(0, len(samples), 8):
        evaluator.process(data_samples=samples[k : k + 8], data_batch={})
    out = evaluator.evaluate(len(samples))
    _, stored = kitti_eval([i["annos"] for i in infos], results, CLASSES)
    assert out["Kitti metric/pred_instances_3d/KITTI/Car_3D_AP40_moderate_strict"] == pytest.approx(
        stored["KITTI/Car_3D_AP40_moderate_strict"], abs=1e-4
    )


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_adapter_compiles_nothing(golden):
    """Reading ann_file (the pickle scan) and evaluating use the kernels the session's warm-up loaded."""
    infos, results, ann_file, samples = golden
    cls = adapter_class(StandInBaseMetric, lambda *a, **k: None)
    compiles = _Compiles()
    with event.install_listener("numba:compile", compiles):
        m = cls(ann_file=ann_file, classes=CLASSES)
        m.process({}, samples)
        m.evaluate_gathered(m.results)
    assert compiles.names == []


def test_adapter_reads_ground_truth_of_size_minus_one_and_logs_it(golden, tmp_path):
    """mmdetection3d's info files may hold Cars written with sizes -1 (its own test data does): evaluated, and
    the warning logged at WARNING level before the table."""
    infos, _, ann_file, samples = golden
    doc = pickle.loads(Path(ann_file).read_bytes())  # written by the fixture
    car = next(inst for inst in doc["data_list"][0]["instances"] if inst["bbox_label"] == CATEGORIES["Car"])
    car["bbox_3d"][3:6] = [-1.0, -1.0, -1.0]
    changed = tmp_path / "infos.pkl"
    changed.write_bytes(pickle.dumps(doc))
    logs: list[tuple[str, int]] = []
    cls = adapter_class(StandInBaseMetric, lambda msg, logger=None, level=20: logs.append((msg, level)))
    metric = cls(ann_file=str(changed))
    metric.dataset_meta = {"classes": CLASSES}
    metric.process({}, samples)
    out = metric.evaluate_gathered(metric.results)
    assert len(out) == 126
    warnings = [msg for msg, level in logs if level == 30]
    assert len(warnings) == 1 and "1 ground-truth box (DontCare aside) has a size that is not positive" in warnings[0]
    assert logs[-1][0].startswith("Results of pred_instances_3d:")
