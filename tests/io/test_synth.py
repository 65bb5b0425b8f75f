"""kitti_eval.synth: OpenPCDet's structures exactly, self-consistent geometry, writers, the bundled demo."""

from __future__ import annotations

import gzip
import pickle
from pathlib import Path

import numpy as np
import pytest

from kitti_eval import synth

GT_KEYS = [
    "name",
    "truncated",
    "occluded",
    "alpha",
    "bbox",
    "dimensions",
    "location",
    "rotation_y",
    "score",
    "difficulty",
    "index",
    "gt_boxes_lidar",
    "num_points_in_gt",
]
GT_DTYPES = {
    "truncated": np.float64,
    "occluded": np.float64,
    "alpha": np.float64,
    "bbox": np.float32,
    "dimensions": np.float64,
    "location": np.float32,
    "rotation_y": np.float64,
    "score": np.float64,
    "difficulty": np.int32,
    "index": np.int32,
    "gt_boxes_lidar": np.float64,
    "num_points_in_gt": np.int32,
}
DET_KEYS = [
    "name",
    "truncated",
    "occluded",
    "alpha",
    "bbox",
    "dimensions",
    "location",
    "rotation_y",
    "score",
    "boxes_lidar",
    "frame_id",
]
DET_DTYPES = {
    "truncated": np.float64,
    "occluded": np.float64,
    "alpha": np.float32,
    "bbox": np.float32,
    "dimensions": np.float32,
    "location": np.float32,
    "rotation_y": np.float32,
    "score": np.float32,
    "boxes_lidar": np.float32,
}
TRAILING = {"bbox": (4,), "dimensions": (3,), "location": (3,), "gt_boxes_lidar": (7,), "boxes_lidar": (7,)}


@pytest.fixture(scope="module")
def data() -> tuple[list[dict], list[dict]]:
    return synth.generate(120, seed=11, dets_per_frame=15.0, empty_gt_frac=0.05, empty_pred_frac=0.05)


def _real(annos: dict) -> np.ndarray:
    return annos["index"] >= 0


def _frames_with_objects(infos: list[dict]):
    for info in infos:
        a = info["annos"]
        if len(a["name"]) and _real(a).any():
            yield a


def _project(calib: dict, loc: np.ndarray, dims: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """Independent twin: the 8 corners through P2, min/max, clipped to the 1242 x 375 image."""
    out = []
    for (x, y, z), (l, h, w), r in zip(loc.astype(float), dims.astype(float), ry.astype(float)):
        rot = np.array([[np.cos(r), 0, np.sin(r)], [0, 1, 0], [-np.sin(r), 0, np.cos(r)]])
        corners = np.array([[sx * l / 2, sy * h, sz * w / 2] for sx in (-1, 1) for sy in (0, -1) for sz in (-1, 1)])
        pts = corners @ rot.T + [x, y, z]
        uvw = np.c_[pts, np.ones(8)] @ calib["P2"][:3].T
        assert np.all(uvw[:, 2] > 0), "a box behind the camera"
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        out.append(
            [np.clip(u.min(), 0, 1241), np.clip(v.min(), 0, 374), np.clip(u.max(), 0, 1241), np.clip(v.max(), 0, 374)]
        )
    return np.array(out).reshape(-1, 4)


def _to_lidar(calib: dict, loc: np.ndarray, dims: np.ndarray, ry: np.ndarray) -> np.ndarray:
    m = np.linalg.inv(calib["R0_rect"].astype(np.float64) @ calib["Tr_velo_to_cam"])
    pts = np.c_[loc.astype(float), np.ones(len(loc))] @ m.T
    pts[:, 2] += dims[:, 1] / 2
    return np.c_[pts[:, :3], dims[:, 0], dims[:, 2], dims[:, 1], -(ry + np.pi / 2)]


def _assert_same(a: object, b: object, path: str = "", ulps: int = 0) -> None:
    """Equal structure, types, dtypes and shapes; float arrays equal to ``ulps`` units in the last place of
    their dtype at the array's largest magnitude (0: bit for bit, for two runs on one machine)."""
    assert type(a) is type(b), path
    if isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            _assert_same(a[k], b[k], f"{path}/{k}", ulps)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{path}[{i}]", ulps)
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        if ulps and a.dtype.kind == "f" and a.size:
            tol = ulps * float(np.finfo(a.dtype).eps) * float(np.abs(a).max())
            np.testing.assert_allclose(b, a, rtol=0, atol=tol, err_msg=path)
        else:
            np.testing.assert_array_equal(a, b, err_msg=path)
    else:
        assert a == b, path


#: the bundled demo was written on one machine and is regenerated on another: numpy's sin, cos and arctan2
#: may take other SIMD paths there (the generator's own arithmetic is exact), so its floats may differ in
#: the last bits, never more
_DEMO_ULPS = 4


# ----------------------------------------------------------------------------------------------- structure


def test_deterministic_for_a_seed() -> None:
    _assert_same(synth.generate(25, seed=5, dets_per_frame=8), synth.generate(25, seed=5, dets_per_frame=8))
    other = synth.generate(25, seed=6, dets_per_frame=8)[0]
    same = synth.generate(25, seed=5, dets_per_frame=8)[0]
    assert any(
        len(a["annos"]["name"]) != len(b["annos"]["name"]) or not np.array_equal(a["annos"]["bbox"], b["annos"]["bbox"])
        for a, b in zip(same, other)
    )


def test_ground_truth_does_not_depend_on_detection_settings() -> None:
    infos_a, res_a = synth.generate(30, seed=2, dets_per_frame=5)
    infos_b, res_b = synth.generate(30, seed=2, dets_per_frame=30)
    _assert_same(infos_a, infos_b)
    assert sum(len(r["name"]) for r in res_b) > 3 * sum(len(r["name"]) for r in res_a)


def test_a_detector_seed_draws_other_detections_of_the_same_ground_truth() -> None:
    infos, results = synth.generate(30, seed=2, dets_per_frame=8)
    infos_a, res_a = synth.generate(30, seed=2, dets_per_frame=8, detector_seed=11)
    infos_b, res_b = synth.generate(30, seed=2, dets_per_frame=8, detector_seed=12)
    _assert_same(infos, infos_a)
    _assert_same(infos, infos_b)
    _assert_same((infos_a, res_a), synth.generate(30, seed=2, dets_per_frame=8, detector_seed=11))
    scores = [np.concatenate([r["score"] for r in res]) for res in (results, res_a, res_b)]
    assert len({s.tobytes() for s in scores}) == 3


def test_location_noise_makes_a_less_precise_detector_of_the_same_ground_truth() -> None:
    from kitti_eval.core.evaluation import evaluate
    from kitti_eval.core.frames import Annotations

    infos, sharp = synth.generate(200, seed=4, dets_per_frame=8, detector_seed=1)
    infos_b, blurred = synth.generate(200, seed=4, dets_per_frame=8, detector_seed=1, location_noise=0.1)
    _assert_same(infos, infos_b)
    gt = Annotations.from_frames("ground_truth", "gt", [(i["image"]["image_idx"], i["annos"]) for i in infos])
    ap = [
        evaluate(gt, Annotations.from_frames("detections", "dt", [(r["frame_id"], r) for r in res])).get(
            "Car", "3d", "moderate"
        )
        for res in (sharp, blurred)
    ]
    assert ap[0] is not None and ap[1] is not None and ap[0] - ap[1] > 10
    with pytest.raises(ValueError, match="location_noise"):
        synth.generate(5, location_noise=-1.0)


def test_infos_structure_matches_openpcdet(data) -> None:
    infos, _ = data
    assert isinstance(infos, list) and len(infos) == 120
    for k, info in enumerate(infos):
        assert list(info) == ["point_cloud", "image", "calib", "annos"]
        assert info["point_cloud"] == {"num_features": 4, "lidar_idx": f"{k:06d}"}
        assert type(info["image"]["image_idx"]) is str and info["image"]["image_idx"] == f"{k:06d}"
        shape = info["image"]["image_shape"]
        assert shape.dtype == np.int32 and shape.tolist() == [375, 1242]
        calib = info["calib"]
        assert list(calib) == ["P2", "R0_rect", "Tr_velo_to_cam"]
        assert [m.dtype for m in calib.values()] == [np.float64, np.float32, np.float64]
        assert all(m.shape == (4, 4) and m[3].tolist() == [0, 0, 0, 1] for m in calib.values())
        a = info["annos"]
        assert list(a) == GT_KEYS
        n = len(a["name"])
        for key, dtype in GT_DTYPES.items():
            rows = int(_real(a).sum()) if key == "gt_boxes_lidar" else n
            assert a[key].dtype == dtype, key
            assert a[key].shape == (rows, *TRAILING.get(key, ())), key
        if n:
            assert a["name"].dtype == f"<U{max(len(s) for s in a['name'])}"
            assert np.all(a["score"] == -1)
            assert a["index"][_real(a)].tolist() == list(range(int(_real(a).sum())))
    np.testing.assert_allclose(
        infos[0]["calib"]["P2"][:3],
        [[721.5377, 0, 609.5593, 44.85728], [0, 721.5377, 172.854, 0.2163791], [0, 0, 1, 0.002745884]],
        rtol=1e-6,
    )


def test_results_structure_matches_openpcdet(data) -> None:
    _, results = data
    assert isinstance(results, list) and len(results) == 120
    for k, r in enumerate(results):
        assert list(r) == DET_KEYS
        assert type(r["frame_id"]) is np.str_ and r["frame_id"] == f"{k:06d}"
        n = len(r["score"])
        if n == 0:
            continue
        assert r["name"].dtype == "<U10" and set(r["name"]) <= {"Car", "Pedestrian", "Cyclist"}
        for key, dtype in DET_DTYPES.items():
            assert r[key].dtype == dtype and r[key].shape == (n, *TRAILING.get(key, ())), key
        assert np.all(r["truncated"] == 0) and np.all(r["occluded"] == 0)
        assert np.all(np.diff(r["score"]) <= 0), "detections by descending score"
        assert np.all((r["score"] > 0) & (r["score"] < 1))
    assert type(synth.generate(3, numpy_frame_ids=False)[1][0]["frame_id"]) is str


def test_empty_frame_templates_are_openpcdet_s() -> None:
    infos, results = synth.generate(4, seed=1, empty_gt_frac=1.0, empty_pred_frac=1.0)
    for k, r in enumerate(results):
        assert list(r) == DET_KEYS
        for key in DET_KEYS[:-1]:  # name included: float64 zeros, not strings
            assert r[key].dtype == np.float64 and r[key].shape == (0, *TRAILING.get(key, ())), key
        assert r["frame_id"] == f"{k:06d}"
    for info in infos:
        a = info["annos"]
        assert list(a) == GT_KEYS and a["name"].dtype == np.float64 and a["name"].shape == (0,)
        for key, dtype in GT_DTYPES.items():
            assert a[key].dtype == dtype and a[key].shape == (0, *TRAILING.get(key, ())), key


def test_empty_frames_occur_at_the_requested_rate() -> None:
    infos, results = synth.generate(2000, seed=3, empty_gt_frac=0.1, empty_pred_frac=0.2, dets_per_frame=12)
    assert 0.07 < np.mean([len(i["annos"]["name"]) == 0 for i in infos]) < 0.13
    assert 0.16 < np.mean([len(r["name"]) == 0 for r in results]) < 0.24


def test_dontcare_rows_are_last_and_kitti_shaped(data) -> None:
    infos, _ = data
    seen = 0
    for info in infos:
        a = info["annos"]
        dc = a["name"] == "DontCare"
        assert np.array_equal(dc, ~_real(a))
        if dc.any():
            first = int(np.argmax(dc))
            assert dc[first:].all(), "DontCare rows last"
            seen += int(dc.sum())
            assert np.all(a["truncated"][dc] == -1) and np.all(a["occluded"][dc] == -1)
            assert np.all(a["alpha"][dc] == -10) and np.all(a["rotation_y"][dc] == -10)
            assert np.all(a["dimensions"][dc] == -1) and np.all(a["location"][dc] == -1000)
            assert np.all(a["num_points_in_gt"][dc] == -1)
            b = a["bbox"][dc]
            assert np.all((b[:, 0] >= 0) & (b[:, 2] <= 1241) & (b[:, 1] >= 0) & (b[:, 3] <= 374))
            assert np.all((b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1]))
    assert seen > 100


# ------------------------------------------------------------------------------------------------ geometry


def test_gt_2d_box_is_the_clipped_projection(data) -> None:
    infos, _ = data
    for info in infos:
        a = info["annos"]
        r = _real(a)
        if r.any():
            want = _project(info["calib"], a["location"][r], a["dimensions"][r], a["rotation_y"][r])
            np.testing.assert_allclose(a["bbox"][r], want, atol=0.005 + 1e-3, rtol=0)


def test_detection_2d_box_is_the_clipped_projection(data) -> None:
    infos, results = data
    for info, det in zip(infos, results):
        if len(det["score"]):
            want = _project(info["calib"], det["location"], det["dimensions"], det["rotation_y"])
            np.testing.assert_allclose(det["bbox"], want, atol=5e-5 + 2e-3, rtol=0)


def test_alpha_is_yaw_minus_viewing_angle(data) -> None:
    infos, results = data
    for a in _frames_with_objects(infos):
        r = _real(a)
        loc = a["location"][r].astype(float)
        want = a["rotation_y"][r] - np.arctan2(loc[:, 0], loc[:, 2])
        diff = np.angle(np.exp(1j * (a["alpha"][r] - want)))
        assert np.all(np.abs(diff) <= 0.005 + 1e-6)
        assert np.all(np.abs(a["alpha"][r]) <= np.pi) and np.all(np.abs(a["rotation_y"][r]) <= np.pi)
    for det in results:
        if len(det["score"]):
            loc = det["location"].astype(float)
            want = det["rotation_y"] - np.arctan2(loc[:, 0], loc[:, 2])  # unwrapped, as OpenPCDet's
            np.testing.assert_allclose(det["alpha"], want, atol=5e-5 + 1e-6, rtol=0)


def test_lidar_boxes_come_from_the_inverse_calibration(data) -> None:
    infos, results = data
    for info, det in zip(infos, results):
        a = info["annos"]
        r = _real(a)
        want = _to_lidar(info["calib"], a["location"][r], a["dimensions"][r], a["rotation_y"][r])
        np.testing.assert_allclose(a["gt_boxes_lidar"], want, atol=1e-4, rtol=0)
        if len(det["score"]):
            want = _to_lidar(
                info["calib"], det["location"], det["dimensions"].astype(float), det["rotation_y"].astype(float)
            )
            np.testing.assert_allclose(det["boxes_lidar"], want, atol=2e-4, rtol=0)


def test_ground_truth_is_realistic() -> None:
    infos, _ = synth.generate(1500, seed=9)
    annos = [i["annos"] for i in infos if len(i["annos"]["name"])]
    name = np.concatenate([a["name"][_real(a)] for a in annos])
    loc = np.concatenate([a["location"][_real(a)] for a in annos]).astype(float)
    dims = np.concatenate([a["dimensions"][_real(a)] for a in annos])
    occ = np.concatenate([a["occluded"][_real(a)] for a in annos])
    trunc = np.concatenate([a["truncated"][_real(a)] for a in annos])
    n_dc = sum(int((~_real(a)).sum()) for a in annos)
    assert 6.0 < len(name) / 1500 < 6.8 and 1.3 < n_dc / 1500 < 1.7
    assert set(name) == {"Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc"}
    assert 0.6 < np.mean(name == "Car") < 0.8
    assert np.all((loc[:, 1] > 1.449) & (loc[:, 1] < 1.951))
    assert np.all((loc[:, 2] > 3.99) & (loc[:, 2] < 70.01))
    assert np.mean(np.abs(loc[:, 0]) < loc[:, 2]) > 0.9  # mostly inside the camera's field of view
    typical = {"Car": (3.88, 1.53, 1.63), "Pedestrian": (0.84, 1.76, 0.66), "Cyclist": (1.76, 1.74, 0.6)}
    for cls, lhw in typical.items():
        med = np.median(dims[name == cls], axis=0)
        np.testing.assert_allclose(med, lhw, rtol=0.1)
        assert np.all(np.std(dims[name == cls], axis=0) > 0.02)
    assert set(np.unique(occ)) == {0, 1, 2, 3}
    far, near = loc[:, 2] > 40, loc[:, 2] < 20
    assert occ[far].mean() > occ[near].mean() + 0.3
    assert 0.05 < np.mean(trunc > 0) < 0.3 and np.all((trunc >= 0) & (trunc <= 0.85))
    # truncated objects touch the image border
    b = np.concatenate([a["bbox"][_real(a)] for a in annos])
    edge = (b[:, 0] <= 0.01) | (b[:, 2] >= 1240.99) | (b[:, 1] <= 0.01) | (b[:, 3] >= 373.99)
    assert np.all(edge[trunc > 0.01])
    assert np.all(~edge[trunc == 0] | (np.abs(b[trunc == 0] - [0, 0, 1241, 374]) < 0.02).any(axis=1))


def test_objects_do_not_overlap_in_birds_eye_view(data) -> None:
    infos, _ = data
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 9), np.linspace(-0.5, 0.5, 9)), -1).reshape(-1, 2)
    for a in _frames_with_objects(infos):
        r = _real(a)
        xz, dims, ry = a["location"][r][:, [0, 2]].astype(float), a["dimensions"][r], a["rotation_y"][r]
        for i in range(len(ry)):
            c, s = np.cos(ry[i]), np.sin(ry[i])
            pts = xz[i] + (grid * [dims[i, 0], dims[i, 2]]) @ np.array([[c, -s], [s, c]])  # footprint of i
            for j in range(len(ry)):
                if j != i:
                    cj, sj = np.cos(ry[j]), np.sin(ry[j])
                    rel = (pts - xz[j]) @ np.array([[cj, sj], [-sj, cj]])  # into j's (length, width) axes
                    inside = (np.abs(rel[:, 0]) < dims[j, 0] / 2) & (np.abs(rel[:, 1]) < dims[j, 2] / 2)
                    assert not inside.any()


def test_difficulty_follows_openpcdet_levels(data) -> None:
    infos, _ = data
    for info in infos:
        a = info["annos"]
        for b, t, o, d in zip(a["bbox"], a["truncated"], a["occluded"], a["difficulty"]):
            h = float(b[3]) - float(b[1]) + 1
            want = (
                0
                if h >= 40 and t <= 0.15 and o <= 0
                else 1
                if h >= 25 and t <= 0.3 and o <= 1
                else 2
                if h >= 25 and t <= 0.5 and o <= 2
                else -1
            )
            assert d == want


def test_detections_are_realistic() -> None:
    infos, results = synth.generate(1000, seed=4, dets_per_frame=20.0)
    n = np.array([len(r["score"]) for r in results])
    assert 19.0 < n.mean() < 21.0 and n.max() > 30
    names = np.concatenate([r["name"] for r in results if len(r["score"])])
    assert 0.45 < np.mean(names == "Car") < 0.8 and np.mean(names == "Cyclist") > 0.03
    # detections near a same-class object score higher than the rest
    hit_scores, miss_scores = [], []
    for info, r in zip(infos, results):
        a = info["annos"]
        if not len(r["score"]):
            continue
        gl = a["location"][_real(a)][:, [0, 2]] if len(a["name"]) else np.zeros((0, 2))
        gn = a["name"][_real(a)] if len(a["name"]) else np.zeros(0, "<U1")
        for name, loc, s in zip(r["name"], r["location"][:, [0, 2]], r["score"]):
            d = np.hypot(*(gl - loc).T) if len(gl) else np.array([np.inf])
            same = {"Car", "Van"} if name == "Car" else {name}
            near = len(gl) and d.min() < 0.3 and gn[np.argmin(d)] in same
            (hit_scores if near else miss_scores).append(float(s))
    assert len(hit_scores) > 2000 and len(miss_scores) > 5000
    assert np.mean(hit_scores) > np.mean(miss_scores) + 0.25


def test_arguments_are_checked() -> None:
    with pytest.raises(ValueError, match="frames"):
        synth.generate(-1)
    with pytest.raises(ValueError, match="empty_gt_frac"):
        synth.generate(3, empty_gt_frac=1.5)
    assert synth.generate(0) == ([], [])


# ------------------------------------------------------------------------------------------------- writers


def test_pickle_writers_round_trip(data, tmp_path: Path) -> None:
    infos, results = data
    for name in ("infos.pkl", "infos.pkl.gz"):
        synth.write_infos(tmp_path / name, infos)
        raw = (tmp_path / name).read_bytes()
        if name.endswith(".gz"):
            raw = gzip.decompress(raw)
        assert raw[:2] == b"\x80\x04"  # protocol 4, as OpenPCDet writes
        _assert_same(pickle.loads(raw), infos)
    synth.write_results(tmp_path / "result.pkl.gz", results)
    with gzip.open(tmp_path / "result.pkl.gz", "rb") as fh:
        _assert_same(pickle.load(fh), results)
    synth.write_results(tmp_path / "again" / "result.pkl.gz", results)  # same data, same bytes
    assert (tmp_path / "again" / "result.pkl.gz").read_bytes() == (tmp_path / "result.pkl.gz").read_bytes()


def test_label_dir_round_trips_to_two_decimals(data, tmp_path: Path) -> None:
    infos, _ = data
    synth.write_label_dir(tmp_path, infos)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{k:06d}.txt" for k in range(len(infos))]
    for info in infos:
        a = info["annos"]
        lines = (tmp_path / f"{info['image']['image_idx']}.txt").read_text().splitlines()
        assert len(lines) == len(a["name"])
        for k, line in enumerate(lines):
            f = line.split(" ")
            assert len(f) == 15 and f[0] == a["name"][k]
            if f[0] == "DontCare":
                assert f[1:4] == ["-1", "-1", "-10"] and f[8:] == ["-1"] * 3 + ["-1000"] * 3 + ["-10"]
            else:
                assert int(f[2]) == a["occluded"][k] and all(len(v.split(".")[1]) == 2 for v in f[4:])
                assert abs(float(f[1]) - a["truncated"][k]) < 1e-9 and abs(float(f[3]) - a["alpha"][k]) < 1e-9
                h, w, l_ = (float(v) for v in f[8:11])
                np.testing.assert_allclose([l_, h, w], a["dimensions"][k], atol=1e-9)
                np.testing.assert_allclose([float(v) for v in f[11:14]], a["location"][k], atol=1e-5)
                assert abs(float(f[14]) - a["rotation_y"][k]) < 1e-9
            np.testing.assert_allclose([float(v) for v in f[4:8]], a["bbox"][k], atol=1e-4)


def test_result_dir_round_trips_to_four_decimals(data, tmp_path: Path) -> None:
    _, results = data
    synth.write_result_dir(tmp_path, results)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{k:06d}.txt" for k in range(len(results))]
    empties = 0
    for r in results:
        text = (tmp_path / f"{r['frame_id']}.txt").read_text()
        if not len(r["score"]):
            assert text == ""
            empties += 1
            continue
        rows = [line.split(" ") for line in text.splitlines()]
        assert len(rows) == len(r["score"])
        for k, f in enumerate(rows):
            assert len(f) == 16 and f[0] == r["name"][k] and f[1:3] == ["-1", "-1"]
            assert all(len(v.split(".")[1]) == 4 for v in f[3:])
            v = [float(x) for x in f[3:]]
            want = [
                r["alpha"][k],
                *r["bbox"][k],
                r["dimensions"][k][1],
                r["dimensions"][k][2],
                r["dimensions"][k][0],
                *r["location"][k],
                r["rotation_y"][k],
                r["score"][k],
            ]
            np.testing.assert_allclose(v, np.array(want, dtype=np.float64), atol=6e-5, rtol=0)
    assert empties > 0


# -------------------------------------------------------------------------------------- demo and the CLI


def test_bundled_demo_is_generate_200_seed_7() -> None:
    assert synth.DEMO_ARGS == {"frames": 200, "seed": 7, "dets_per_frame": 12.0}
    gt_path, pred_path = synth.demo_paths()
    assert gt_path.name == "kitti_infos_val.pkl.gz" and pred_path.name == "result.pkl.gz"
    for p in (gt_path, pred_path):
        assert p.is_file() and p.stat().st_size < 512 * 1024
    with gzip.open(gt_path, "rb") as fh:
        infos = pickle.load(fh)
    with gzip.open(pred_path, "rb") as fh:
        results = pickle.load(fh)
    _assert_same((infos, results), synth.generate(**synth.DEMO_ARGS), ulps=_DEMO_ULPS)
    assert 11 < sum(len(r["score"]) for r in results) / 200 < 13


def test_the_bundled_weaker_model_is_the_demo_blurred_and_scores_lower() -> None:
    """The second demo prediction: generate(**DEMO_WEAKER_ARGS), the demo's own detector with its positions
    blurred, on the same ground truth; its Car 3D AP is below the demo's, so comparisons and gates have a drop."""
    from kitti_eval import evaluate, load_detections, load_ground_truth
    from kitti_eval.demo import DEMO_WEAKER_ARGS, demo_weaker_path

    assert DEMO_WEAKER_ARGS == {**synth.DEMO_ARGS, "location_noise": 0.1}
    path = demo_weaker_path()
    assert path.name == "result_weaker.pkl.gz" and path.parent == synth.demo_paths()[1].parent
    assert path.stat().st_size < 512 * 1024
    with gzip.open(path, "rb") as fh:
        results = pickle.load(fh)
    _assert_same(results, synth.generate(**DEMO_WEAKER_ARGS)[1], ulps=_DEMO_ULPS)
    gt = load_ground_truth(synth.demo_paths()[0])
    strong, weak = (evaluate(gt, load_detections(p)) for p in (synth.demo_paths()[1], path))
    assert strong.get("Car", "3d", "moderate") == pytest.approx(60.33954716517563, abs=1e-9)
    assert weak.get("Car", "3d", "moderate") == pytest.approx(45.86, abs=0.01)


def test_demo_comparison_forgives_last_bits_only() -> None:
    """The tolerance of the demo check still catches a changed generator: a nudge of 1e-9 m fails."""
    infos, _ = synth.generate(3, seed=7)
    boxes = infos[0]["annos"]["gt_boxes_lidar"]
    assert boxes.dtype == np.float64 and boxes.size
    last_bit = [dict(i, annos=dict(i["annos"])) for i in infos]
    last_bit[0]["annos"]["gt_boxes_lidar"] = np.nextafter(boxes, np.inf)
    _assert_same(infos, last_bit, ulps=_DEMO_ULPS)
    nudged = [dict(i, annos=dict(i["annos"])) for i in infos]
    nudged[0]["annos"]["gt_boxes_lidar"] = boxes + np.eye(*boxes.shape) * 1e-9
    with pytest.raises(AssertionError, match="gt_boxes_lidar"):
        _assert_same(infos, nudged, ulps=_DEMO_ULPS)
    with pytest.raises(AssertionError):
        _assert_same(infos, synth.generate(3, seed=8)[0], ulps=_DEMO_ULPS)


def test_lidar_calibration_is_the_exact_inverse() -> None:
    """The closed-form camera -> LiDAR matrix inverts R0_rect @ Tr_velo_to_cam to rounding."""
    calib = synth._calib()
    forward = calib["R0_rect"].astype(np.float64) @ calib["Tr_velo_to_cam"]
    np.testing.assert_allclose(synth._RECT_TO_LIDAR @ forward, np.eye(4), rtol=0, atol=1e-15)
    np.testing.assert_allclose(synth._RECT_TO_LIDAR, np.linalg.inv(forward), rtol=0, atol=1e-15)


def test_command_line(tmp_path: Path, capsys) -> None:
    argv = ["--frames", "6", "--seed", "3", "--dets-per-frame", "9", "--out", str(tmp_path), "--txt"]
    assert synth.main(argv) == 0
    out = capsys.readouterr()
    assert out.out == "" and len(out.err.strip().splitlines()) == 1 and "6 frames" in out.err
    with open(tmp_path / "kitti_infos_val.pkl", "rb") as fh:
        infos = pickle.load(fh)
    with open(tmp_path / "result.pkl", "rb") as fh:
        results = pickle.load(fh)
    _assert_same((infos, results), synth.generate(6, seed=3, dets_per_frame=9))
    assert len(list((tmp_path / "label_2").iterdir())) == 6 and len(list((tmp_path / "pred").iterdir())) == 6
    assert synth.main(["--frames", "2", "--out", str(tmp_path / "z"), "--gzip"]) == 0
    assert (tmp_path / "z" / "result.pkl.gz").is_file()
    assert (tmp_path / "z" / "kitti_infos_val.pkl.gz").is_file()
    with pytest.raises(SystemExit):
        synth.main(["--frames", "2"])
