"""KittiMetric: batches in any size and order, on several ranks, merged, equal evaluate() on the whole set."""

from __future__ import annotations

import io
import math
import pickle
import random
from pathlib import Path

import numba
import numpy as np
import pytest
from numba.core import event

from kitti_eval import Annotations, ConfigError, EvalConfig, InputError, KittiMetric, evaluate
from kitti_eval.core.protocol import OPENPCDET, DifficultyLimits, DistanceRange, Protocol, parse_ranges
from kitti_eval.incremental import _COLUMNS, config_from_state, config_state
from kitti_eval.io.safe_pickle import load_pickle

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "small"


@pytest.fixture(scope="module")
def golden():
    # trusted committed fixtures: OpenPCDet infos (ids in image.image_idx) and result.pkl (frame_id)
    infos = pickle.loads((GOLDEN / "kitti_infos_val.pkl").read_bytes())
    results = pickle.loads((GOLDEN / "result.pkl").read_bytes())
    return infos, results


def whole(infos, results):
    gt = Annotations.from_frames("ground_truth", "gt_frames", ((i["image"]["image_idx"], i["annos"]) for i in infos))
    dt = Annotations.from_frames("detections", "dt_frames", ((r["frame_id"], r) for r in results))
    return gt, dt


def fed(config: EvalConfig, infos, results, frames, batch: int) -> KittiMetric:
    """A metric updated with ``frames`` (positions in infos) in batches of ``batch``."""
    by_id = {r["frame_id"]: r for r in results}
    m = KittiMetric(config=config)
    for k in range(0, len(frames), batch):
        part = [infos[i] for i in frames[k : k + batch]]
        m.update(part, [by_id[i["image"]["image_idx"]] for i in part if i["image"]["image_idx"] in by_id])
    return m


CONFIGS = {
    "official": EvalConfig(),
    "openpcdet": EvalConfig(classes=("Car", "Pedestrian", "Cyclist"), protocol=OPENPCDET),
    "ranges+coco": EvalConfig(protocol=OPENPCDET, ranges=parse_ranges("0,20,40,inf"), coco=True),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_four_ranks_merged_equal_evaluate(golden, name):
    """The golden set shuffled over four ranks, each updating in its own batch size; the states travel as
    pickles; the merge equals evaluate() on all frames at once: every AP, every curve, every count."""
    infos, results = golden
    results = [r for r in results if r["frame_id"] not in ("000007", "000031")]  # two frames without predictions
    config = CONFIGS[name]
    order = list(range(len(infos)))
    random.Random(14).shuffle(order)
    ranks = [fed(config, infos, results, order[k::4], batch) for k, batch in enumerate((1, 3, 7, 50))]
    assert [len(m) for m in ranks] == [13, 13, 12, 12]
    merged = KittiMetric.from_state_dict(pickle.loads(pickle.dumps(ranks[0].state_dict())))
    merged.merge(pickle.loads(pickle.dumps(ranks[1])))  # a pickled metric
    merged.merge(ranks[2].state_dict())  # a state dict
    merged.merge(ranks[3])
    got = merged.compute(keep_curves=True)
    want = evaluate(*whole(infos, results), config, keep_curves=True)
    assert got.to_dict(include_curves=True) == want.to_dict(include_curves=True)
    assert got.frames_without_predictions == ("000007", "000031")
    assert got.curves is not None and want.curves is not None
    for oset, by_cls in want.curves.items():
        for cls, by_metric in by_cls.items():
            for metric, by_d in by_metric.items():
                for d, curve in by_d.items():
                    mine = got.curves[oset][cls][metric][d]
                    for attr in ("precision", "recall", "orientation", "thresholds"):
                        assert np.array_equal(getattr(mine, attr), getattr(curve, attr)), (oset, cls, metric, d)
    assert got.ap == want.ap and got.num_gt == want.num_gt and got.num_det == want.num_det
    assert [len(m) for m in ranks] == [13, 13, 12, 12]  # merging changed none of them


def test_order_of_updates_does_not_matter(golden):
    """Frames are evaluated in frame-id order, so even OpenPCDet's order-dependent AOS rule (the first
    detection of the first frame) gives one answer however the batches come."""
    infos, results = golden
    results = [dict(r) for r in results]
    results[0] = {**results[0], "alpha": np.full(len(results[0]["alpha"]), -10.0)}  # frame 000000: no alpha
    config = CONFIGS["openpcdet"]
    forward = fed(config, infos, results, list(range(50)), 5).compute()
    backward = fed(config, infos, results, list(range(49, -1, -1)), 5).compute()
    assert not forward.aos_evaluated and forward.to_dict() == backward.to_dict()
    assert forward.to_dict() == evaluate(*whole(infos, results), config).to_dict()


def test_a_frame_given_twice_is_an_error_naming_it(golden):
    infos, results = golden
    m = KittiMetric()
    m.update(infos[:3], results[:3])
    before = m.compute().to_dict()
    with pytest.raises(InputError, match="given twice") as e:
        m.update(infos[2:4], results[2:4])
    assert (e.value.source, e.value.frame) == ("gt_frames", "000002")
    assert len(m) == 3 and m.compute().to_dict() == before  # nothing of the failed update was added
    with pytest.raises(InputError, match="appears twice") as e:
        m.update([infos[5], infos[5]], [])
    assert e.value.frame == "000005"
    other = KittiMetric()
    other.update(infos[1:2], results[1:2])
    with pytest.raises(InputError, match="in both metrics") as e:
        m.merge(other)
    assert e.value.frame == "000001" and len(m) == 3
    with pytest.raises(InputError, match="itself"):
        m.merge(m)


def test_predictions_need_their_ground_truth_in_the_same_update(golden):
    infos, results = golden
    m = KittiMetric()
    with pytest.raises(InputError, match="not in the same update") as e:
        m.update(infos[:2], results[:3])
    assert (e.value.source, e.value.frame) == ("dt_frames", "000002")
    with pytest.raises(InputError, match="no frame_id") as e:
        m.update(infos[:1], [{k: v for k, v in results[0].items() if k != "frame_id"}])
    assert e.value.source == "dt_frames"
    bad = {**results[0], "score": results[0]["score"][:-1]}
    with pytest.raises(InputError, match="expected shape") as e:
        m.update(infos[:1], [bad])
    assert (e.value.frame, e.value.field) == ("000000", "score")
    assert len(m) == 0


def test_configurations_must_agree(golden):
    infos, results = golden
    a, b = KittiMetric(protocol="openpcdet"), KittiMetric(protocol="official")
    b.update(infos[:2], results[:2])
    with pytest.raises(ConfigError, match="different configurations.*protocol"):
        a.merge(b)
    with pytest.raises(ConfigError, match="another configuration"):
        a.load_state_dict(b.state_dict())
    with pytest.raises(ConfigError, match="another configuration.*classes"):
        KittiMetric(classes="Car").load_state_dict(KittiMetric(classes=["Car", "Van"]).state_dict())
    with pytest.raises(ConfigError, match="unknown option"):
        KittiMetric(threshold="strict")
    with pytest.raises(ConfigError, match="either config or"):
        KittiMetric(classes="Car", config=EvalConfig())
    with pytest.raises(ConfigError, match="unknown protocol"):
        KittiMetric(protocol="mmdet3d")
    with pytest.raises(InputError, match="not a kitti_eval.KittiMetric state"):
        a.load_state_dict({"frames": []})


def test_config_state_round_trip():
    custom = Protocol(
        name="mine",
        dontcare_metrics=frozenset(),
        aos_rule="all_valid",
        skip_undetected=False,
        dontcare_case_insensitive=True,
    )
    for config in (
        EvalConfig(),
        EvalConfig(
            classes=("Car", "Bus"),
            protocol=custom,
            overlaps={"Bus": {"strict": (0.7, 0.6, 0.6), "loose": (0.5, 0.5, 0.5)}},
            difficulty=DifficultyLimits(min_height=(30.0, 20.0, 20.0)),
            threshold_sets=("strict",),
            ranges=(DistanceRange(0.0, 30.0), DistanceRange(30.0, math.inf)),
            coco=True,
            neighbours={"Bus": ("Tram",)},
        ),
        EvalConfig(lidar_only=True),
    ):
        state = config_state(config)
        back = config_from_state(pickle.loads(pickle.dumps(state)))
        assert config_state(back) == state
        assert back.overlaps == config.overlaps and back.difficulty == config.difficulty
        assert back.protocol == config.protocol and back.ranges == config.ranges
    assert config_from_state(config_state(EvalConfig(protocol=OPENPCDET))).protocol is OPENPCDET
    with pytest.raises(ConfigError, match="not a KittiMetric configuration"):
        config_from_state({"classes": ["Car"]})


def test_state_dict_is_plain_data(golden):
    """A state holds only numpy arrays and plain containers: kitti-eval's own restricted unpickler, which
    refuses anything else, reads it back (so states can travel through files too)."""
    infos, results = golden
    m = KittiMetric(protocol="openpcdet")
    m.update(infos[:10], results[:10])
    state = load_pickle(io.BytesIO(pickle.dumps(m.state_dict())), source="state")
    assert isinstance(state, dict)
    again = KittiMetric.from_state_dict(state)
    assert again.compute().to_dict() == m.compute().to_dict()
    assert state["ground_truth"]["frame_ids"].tolist() == [f"{i:06d}" for i in range(10)]
    assert state["ground_truth"]["offsets"][-1] == len(state["ground_truth"]["name"])


def test_state_dict_is_checked():
    m = KittiMetric()
    state = KittiMetric().state_dict()
    for column, value, message in (
        ("offsets", np.array([0, 1], dtype=np.int64), "offsets do not describe 0 frames"),
        ("score", np.zeros(1), "expected 0 rows"),
        ("name", np.zeros(0), "dtype kind 'U'"),
    ):
        broken = {**state, "detections": {**state["detections"], column: value}}
        with pytest.raises(InputError, match=message):
            m.load_state_dict(broken)


def test_reset_and_empty(golden):
    infos, results = golden
    m = KittiMetric()
    with pytest.raises(InputError, match="no frames to evaluate"):
        m.compute()
    m.update([], [])  # an empty batch adds nothing
    m.update(infos[:4], results[:4])
    first = m.compute().to_dict()
    m.reset()
    assert len(m) == 0
    with pytest.raises(InputError, match="no frames to evaluate"):
        m.compute()
    m.update(infos[:4], results[:4])  # the same frames again: allowed after a reset
    assert m.compute().to_dict() == first


def test_input_layouts_agree(golden):
    """OpenPCDet infos and annos lists, {frame id: annos} dicts, mmdetection3d result dicts (sample_idx or
    sample_id), Annotations: the same frames, the same numbers; inputs are never changed."""
    infos, results = golden
    infos, results = infos[:12], results[:12]
    before = pickle.dumps((infos, results))
    reference = KittiMetric()
    reference.update(infos, results)
    want = reference.compute().to_dict()
    gt_by_id = {i["image"]["image_idx"]: i["annos"] for i in infos}
    mm = [
        {**{k: v for k, v in r.items() if k != "frame_id"}, "sample_id": np.full(len(r["score"]), int(r["frame_id"]))}
        for r in results
    ]
    for gt, dt in (
        (gt_by_id, {r["frame_id"]: r for r in results}),
        ([{**a, "frame_id": f} for f, a in gt_by_id.items()], results),
        (infos, mm),
        whole(infos, results),
    ):
        m = KittiMetric()
        m.update(gt, dt)
        assert m.compute().to_dict() == want
    assert pickle.dumps((infos, results)) == before


def test_lidar_only_predictions_use_the_calibration_of_the_infos(golden):
    """Predictions with only boxes_lidar are converted with the calibration each info carries, as the CLI
    does; the values agree with the camera fields OpenPCDet wrote (README: bbox, BEV and 3D AP equal)."""
    infos, results = golden
    lidar_only = [{k: r[k] for k in ("name", "score", "boxes_lidar", "frame_id")} for r in results]
    m, ref = KittiMetric(), KittiMetric()
    m.update(infos, lidar_only)
    ref.update(infos, results)
    got, want = m.compute(), ref.compute()
    for cls in got.classes:
        for metric in ("bbox", "bev", "3d"):
            for d in ("easy", "moderate", "hard"):
                assert got.get(cls, metric, d) == pytest.approx(want.get(cls, metric, d), abs=1e-9)


def _array_bytes(annos: Annotations) -> int:
    return sum(getattr(annos, f).nbytes for f in ("offsets", *_COLUMNS))


def test_memory_per_frame_is_the_batch_evaluations(golden):
    """One frame at a time, the metric holds the same columns a batch evaluation loads, in O(log frames)
    blocks, not the dicts it was given."""
    infos, results = golden
    m = KittiMetric()
    for i in range(len(infos)):
        m.update(infos[i : i + 1], results[i : i + 1])
        assert len(m._blocks) <= int(math.log2(i + 1)) + 1
    held = sum(_array_bytes(a) for block in m._blocks for a in block)
    gt, dt = whole(infos, results)
    assert held <= _array_bytes(gt) + _array_bytes(dt)
    assert all(isinstance(a, Annotations) for block in m._blocks for a in block)


class _Compiles(event.Listener):
    def __init__(self) -> None:
        self.names: list[str] = []

    def on_start(self, ev: event.Event) -> None:
        self.names.append(ev.data["dispatcher"].py_func.__qualname__)

    def on_end(self, ev: event.Event) -> None:
        pass


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_new_entry_points_compile_nothing(golden):
    """The metric, the mmdetection3d drop-ins and the mmengine adapter run on the kernels every other entry
    point uses (the session's warm-up loaded them): no compilation. The listener does see one."""
    from kitti_eval.compat.mmdet3d import kitti_eval, kitti_eval_coco_style

    infos, results = golden
    compiles = _Compiles()
    with event.install_listener("numba:compile", compiles):
        for config in CONFIGS.values():
            a, b = KittiMetric(config=config), KittiMetric(config=config)
            a.update(infos[:20], results[:20])
            b.update(infos[20:], results[20:])
            a.merge(b).compute(keep_curves=True)
        gt = [i["annos"] for i in infos]
        kitti_eval(gt, results, [0, 1, 2])
        kitti_eval_coco_style(gt, results, [0, 1, 2])
    assert compiles.names == []

    @numba.njit
    def twice(x):  # noqa: ANN001, ANN202
        return 2 * x

    with event.install_listener("numba:compile", compiles):
        assert twice(21) == 42
    assert compiles.names == [twice.py_func.__qualname__]


def test_reading_warnings_are_kept_once_and_bounded(golden):
    """Warnings about the inputs (here: ids taken from point_cloud.lidar_idx) are collected once each, and at
    most twenty of them."""
    infos, results = golden
    m = KittiMetric()
    for i in range(30):
        info = {k: v for k, v in infos[i].items() if k != "image"}
        m.update([info], results[i : i + 1])
    assert len(m.warnings) == 20
    assert all("point_cloud.lidar_idx is used as the frame id" in w for w in m.warnings)
    assert len(set(m.warnings)) == 20
