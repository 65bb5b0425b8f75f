"""Loaders: KITTI txt folders and OpenPCDet-style pickles into Annotations, and their error messages."""

from __future__ import annotations

import gzip
import pickle
import tarfile
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.errors import InputError, UnsafePickleError
from kitti_eval.io.loaders import (
    PICKLE_FORMATS,
    annotations_from_object,
    describe_format,
    detect_format,
    load_detections,
    load_ground_truth,
    parse_kitti_txt,
)

# ---------------------------------------------------------------------------------- a tiny data set
# Three frames in KITTI's own style: 000000 has two cars, a pedestrian and a DontCare region; 000001 is
# empty; 000002 has a cyclist. Dimensions are (l, h, w) here, as in the pickles.

# (name, truncated, occluded, alpha, bbox, (l, h, w), location, rotation_y[, score])
GT = {
    "000000": [
        ("Car", 0.0, 0, -1.58, (587.01, 173.33, 614.12, 200.12), (3.64, 1.65, 1.67), (-0.65, 1.71, 46.70), -1.59),
        ("Car", 0.12, 1, 1.85, (387.63, 181.54, 423.81, 203.12), (4.26, 1.52, 1.57), (-16.53, 2.39, 58.49), 1.57),
        ("Pedestrian", 0.0, 0, -0.20, (712.40, 143.00, 810.73, 307.92), (1.20, 1.89, 0.48), (1.84, 1.47, 8.41), 0.01),
        (
            "DontCare",
            -1.0,
            -1,
            -10.0,
            (800.38, 163.67, 825.45, 184.07),
            (-1.0, -1.0, -1.0),
            (-1000.0, -1000.0, -1000.0),
            -10.0,
        ),
    ],
    "000001": [],
    "000002": [
        ("Cyclist", 0.0, 2, 2.10, (400.0, 170.0, 450.0, 240.0), (1.76, 1.74, 0.60), (-5.20, 1.80, 15.40), 1.77),
    ],
}
DET = {
    "000000": [
        ("Car", -1, -1, -1.5811, (586.9, 173.1, 614.5, 200.2), (3.7, 1.6, 1.65), (-0.62, 1.70, 46.65), -1.5936, 0.9512),
        ("Pedestrian", -1, -1, -0.21, (710.0, 145.0, 812.0, 305.0), (1.1, 1.85, 0.5), (1.80, 1.45, 8.40), 0.02, 0.6125),
    ],
    "000001": [
        ("Car", -1, -1, 0.5, (100.0, 180.0, 160.0, 210.0), (3.9, 1.5, 1.6), (-20.0, 1.7, 40.0), 0.05, 0.1033),
    ],
    "000002": [],
}


def _txt_line(obj: tuple, with_score: bool) -> str:
    name, trunc, occ, alpha, bbox, (length, height, width), loc, ry = obj[:8]
    fields = [
        name,
        f"{trunc:.2f}",
        f"{occ:d}",
        f"{alpha:.2f}",
        *(f"{v:.2f}" for v in bbox),
        f"{height:.2f}",
        f"{width:.2f}",
        f"{length:.2f}",  # the file order: h w l
        *(f"{v:.2f}" for v in loc),
        f"{ry:.2f}",
    ]
    if with_score:
        fields.append(f"{obj[8]:.4f}")
    return " ".join(fields)


def write_txt(folder: Path, frames: dict, with_score: bool) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for fid, objs in frames.items():
        (folder / f"{fid}.txt").write_text("".join(_txt_line(o, with_score) + "\n" for o in objs))
    return folder


def annos(objs: list[tuple], detections: bool) -> dict[str, np.ndarray]:
    """One frame as OpenPCDet stores it (float32 boxes; its float64 zero template when empty)."""
    if not objs and detections:
        return {
            "name": np.zeros(0),
            "truncated": np.zeros(0),
            "occluded": np.zeros(0),
            "alpha": np.zeros(0),
            "bbox": np.zeros((0, 4)),
            "dimensions": np.zeros((0, 3)),
            "location": np.zeros((0, 3)),
            "rotation_y": np.zeros(0),
            "score": np.zeros(0),
            "boxes_lidar": np.zeros((0, 7)),
        }
    n = len(objs)
    out = {
        "name": np.array([o[0] for o in objs], dtype="<U10") if objs else np.zeros(0, dtype="<U10"),
        "truncated": np.array([o[1] for o in objs], dtype=np.float64),
        "occluded": np.array([o[2] for o in objs], dtype=np.float64),
        "alpha": np.array([o[3] for o in objs], dtype=np.float32 if detections else np.float64),
        "bbox": np.array([o[4] for o in objs], dtype=np.float32).reshape(n, 4),
        "dimensions": np.array([o[5] for o in objs], dtype=np.float32).reshape(n, 3),
        "location": np.array([o[6] for o in objs], dtype=np.float32).reshape(n, 3),
        "rotation_y": np.array([o[7] for o in objs], dtype=np.float32 if detections else np.float64),
    }
    if detections:
        out["truncated"][:] = 0.0
        out["occluded"][:] = 0.0
        out["score"] = np.array([o[8] for o in objs], dtype=np.float32)
        out["boxes_lidar"] = np.zeros((n, 7), dtype=np.float32)
    else:
        out["score"] = np.full(n, -1.0)
        out["difficulty"] = np.zeros(n, dtype=np.int32)
        out["index"] = np.array([i if o[0] != "DontCare" else -1 for i, o in enumerate(objs)], dtype=np.int32)
    return out


def infos(frames: dict = GT) -> list[dict]:
    return [
        {
            "point_cloud": {"num_features": 4, "lidar_idx": fid},
            "image": {"image_idx": fid, "image_shape": np.array([375, 1242], dtype=np.int32)},
            "calib": {
                "P2": np.eye(4, dtype=np.float32),
                "R0_rect": np.eye(4, dtype=np.float32),
                "Tr_velo_to_cam": np.eye(4, dtype=np.float32),
            },
            "annos": annos(objs, detections=False),
        }
        for fid, objs in frames.items()
    ]


def results(frames: dict = DET) -> list[dict]:
    out = []
    for fid, objs in frames.items():
        entry = annos(objs, detections=True)
        entry["frame_id"] = np.str_(fid)
        out.append(entry)
    return out


def dump(path: Path, obj: object, *, compress: bool = False) -> Path:
    data = pickle.dumps(obj, protocol=4)
    path.write_bytes(gzip.compress(data) if compress else data)
    return path


def assert_same(a, b, atol: float = 0.0) -> None:
    assert a.frame_ids == b.frame_ids
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.name, b.name)
    for f in ("truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=0, atol=atol, err_msg=f)


# ---------------------------------------------------------------------------------------- txt route


def test_ground_truth_txt_folder(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "label_2", GT, with_score=False)
    (folder / "README.md").write_text("not a label")
    (folder / "._000000.txt").write_bytes(b"\x00\x05\x16\x07 macOS resource fork")
    gt = load_ground_truth(folder)
    assert gt.kind == "ground_truth" and gt.source == str(folder)
    assert gt.frame_ids == ("000000", "000001", "000002")
    assert gt.counts.tolist() == [4, 0, 1]
    assert gt.name.tolist() == ["Car", "Car", "Pedestrian", "DontCare", "Cyclist"]  # DontCare kept
    # the file says h w l = 1.65 1.67 3.64; Annotations hold l h w
    np.testing.assert_array_equal(gt.dimensions[0], [3.64, 1.65, 1.67])
    np.testing.assert_array_equal(gt.dimensions[2], [1.20, 1.89, 0.48])
    np.testing.assert_array_equal(gt.location[0], [-0.65, 1.71, 46.70])
    np.testing.assert_array_equal(gt.bbox[1], [387.63, 181.54, 423.81, 203.12])
    assert gt.truncated[1] == 0.12 and gt.occluded[1] == 1.0 and gt.alpha[0] == -1.58
    assert gt.rotation_y[4] == 1.77
    assert (gt.score == -1.0).all()
    assert gt.dimensions.dtype == np.float64


def test_ground_truth_txt_accepts_a_16th_field_and_ignores_it(tmp_path: Path) -> None:
    folder = tmp_path / "gt16"
    folder.mkdir()
    (folder / "000007.txt").write_text(_txt_line(DET["000000"][0], with_score=True) + "\n")
    gt = load_ground_truth(folder)
    assert gt.frame_ids == ("000007",)
    assert (gt.score == -1.0).all()
    np.testing.assert_array_equal(gt.dimensions[0], [3.7, 1.6, 1.65])
    assert gt.rotation_y[0] == -1.59


def test_detections_txt_folder(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    dt = load_detections(folder)
    assert dt.kind == "detections"
    assert dt.frame_ids == ("000000", "000001", "000002") and dt.counts.tolist() == [2, 1, 0]
    np.testing.assert_array_equal(dt.score, [0.9512, 0.6125, 0.1033])
    np.testing.assert_array_equal(dt.dimensions[1], [1.1, 1.85, 0.5])
    assert dt.truncated.tolist() == [-1.0, -1.0, -1.0]  # as OpenPCDet writes them


def test_openpcdet_final_result_data_layout(tmp_path: Path) -> None:
    write_txt(tmp_path / "final_result" / "data", DET, with_score=True)
    dt = load_detections(tmp_path / "final_result")
    assert dt.frame_ids == ("000000", "000001", "000002")


def test_blank_lines_and_crlf(tmp_path: Path) -> None:
    folder = tmp_path / "pred"
    folder.mkdir()
    line = _txt_line(DET["000000"][0], with_score=True)
    (folder / "000003.txt").write_bytes((line + "\r\n\r\n" + line + "\r\n").encode())
    dt = load_detections(folder)
    assert dt.counts.tolist() == [2]


def test_non_numeric_frame_names_are_kept(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", {"scene_a": DET["000000"], "15": DET["000001"]}, with_score=True)
    assert load_detections(folder).frame_ids == ("000015", "scene_a")


def test_detections_with_15_fields_name_the_frame_and_line(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    text = (folder / "000000.txt").read_text().splitlines()
    text.insert(1, "")
    text.append(_txt_line(DET["000000"][0], with_score=False))
    (folder / "000000.txt").write_text("\n".join(text) + "\n")
    with pytest.raises(InputError) as err:
        load_detections(folder)
    assert err.value.frame == "000000"
    assert (
        "line 4: expected 16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score), got 15"
    ) in str(err.value)


def test_ground_truth_with_14_fields(tmp_path: Path) -> None:
    folder = tmp_path / "gt"
    folder.mkdir()
    (folder / "000004.txt").write_text("Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71\n")
    with pytest.raises(InputError, match=r"frame 000004: line 1: expected 15 fields .* got 13"):
        load_ground_truth(folder)


def test_mixed_15_and_16_fields_in_one_ground_truth_file(tmp_path: Path) -> None:
    folder = tmp_path / "gt"
    folder.mkdir()
    (folder / "000004.txt").write_text(
        _txt_line(GT["000000"][0], False) + "\n" + _txt_line(DET["000000"][0], True) + "\n"
    )
    with pytest.raises(InputError, match="line 2: 16 fields, but earlier lines have 15"):
        load_ground_truth(folder)


def test_a_non_number_names_the_field(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    lines = (folder / "000001.txt").read_text().split()
    lines[4] = "1O0.0"  # x1 with a letter O
    (folder / "000001.txt").write_text(" ".join(lines) + "\n")
    with pytest.raises(InputError) as err:
        load_detections(folder)
    assert err.value.frame == "000001" and err.value.field == "x1"
    assert "line 1: x1 is not a number: '1O0.0'" in str(err.value)


def test_a_non_finite_value_of_a_txt_file_is_named_by_its_file_and_line(tmp_path: Path) -> None:
    """The file and the line (1-based, as every other refusal of a txt line), not the folder and a box's place."""
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    second = (folder / "000001.txt").read_text().replace("0.1033", "nan")
    (folder / "000001.txt").write_text(_txt_line(DET["000000"][0], True) + "\n\n" + second)
    with pytest.raises(InputError, match="non-finite") as err:
        load_detections(folder)
    assert err.value.frame == "000001" and err.value.field == "score"
    assert err.value.source == str(folder / "000001.txt")
    assert "line 3: score is nan, a non-finite value" in str(err.value) and "box" not in str(err.value)
    fields = _txt_line(DET["000000"][0], False).split()
    with pytest.raises(InputError, match="line 1: ry is inf, a non-finite value"):
        parse_kitti_txt(" ".join([*fields[:-1], "inf"]), "ground_truth", frame="1", source="s")


def test_two_files_of_one_frame_are_refused_naming_both(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    (folder / "1.txt").write_text((folder / "000001.txt").read_text())
    with pytest.raises(InputError) as err:
        load_detections(folder)
    assert err.value.frame == "000001" and err.value.source == str(folder)
    assert "two files of frame 000001: 000001.txt and 1.txt" in str(err.value)


@pytest.mark.parametrize(
    ("spelled", "said"),
    [
        (
            "0x1p3",
            "x1 is not a number: '0x1p3'; it is a hexadecimal float, which the official devkit reads (C's strtod) "
            "as 8.0, and kitti-eval reads decimal numbers only",
        ),
        (
            "587.01\x1c",
            "x1 is not a number: '587.01\\x1c'; U+001C is not a field separator for the devkit (only space, tab, "
            "CR, LF, VT and FF are); the devkit would read 587.01, then take '\\x1c' as the next field",
        ),
    ],
)
def test_a_number_the_devkit_reads_otherwise_is_refused_saying_how_it_reads_it(spelled: str, said: str) -> None:
    fields = _txt_line(DET["000000"][0], True).split()
    fields[4] = spelled
    with pytest.raises(InputError) as err:
        parse_kitti_txt(" ".join(fields), "detections", frame="1", source="s")
    assert f"line 1: {said}" in str(err.value) and err.value.field == "x1"


def test_parse_kitti_txt_directly() -> None:
    names, values = parse_kitti_txt(_txt_line(DET["000000"][0], True) + "\n\n", "detections", frame="1", source="s")
    assert names == ["Car"] and len(values) == 15 and values[-1] == 0.9512
    names, values = parse_kitti_txt(_txt_line(DET["000000"][0], True), "ground_truth", frame="1", source="s")
    assert len(values) == 14 and values[-1] == -1.59
    assert parse_kitti_txt("", "detections", frame="1", source="s") == ([], [])


def test_empty_folder_and_missing_path(tmp_path: Path) -> None:
    (tmp_path / "empty" / "label_2").mkdir(parents=True)
    with pytest.raises(InputError, match="no .txt files in the folder; it has subfolders label_2"):
        load_ground_truth(tmp_path / "empty")
    missing = tmp_path / "nowhere" / "result.pkl"
    with pytest.raises(InputError, match="no such file or directory") as err:
        load_detections(missing)
    assert str(missing) in str(err.value)


def test_a_single_txt_file_is_refused_with_a_hint(tmp_path: Path) -> None:
    folder = write_txt(tmp_path / "pred", DET, with_score=True)
    with pytest.raises(InputError, match="pass the folder"):
        load_detections(folder / "000000.txt")


# ------------------------------------------------------------------------------------- pickle route


def test_openpcdet_infos(tmp_path: Path) -> None:
    gt = load_ground_truth(dump(tmp_path / "kitti_infos_val.pkl", infos()))
    txt = load_ground_truth(write_txt(tmp_path / "label_2", GT, with_score=False))
    assert gt.frame_ids == ("000000", "000001", "000002") and gt.counts.tolist() == [4, 0, 1]
    assert "DontCare" in gt.name.tolist()
    assert_same(gt, txt, atol=1e-4)  # float32 in the pickle


def test_openpcdet_result(tmp_path: Path) -> None:
    dt = load_detections(dump(tmp_path / "result.pkl", results()))
    txt = load_detections(write_txt(tmp_path / "pred", DET, with_score=True))
    assert dt.counts.tolist() == [2, 1, 0]  # frame 000002 uses OpenPCDet's float zero template
    txt_trunc = txt.truncated.copy()
    assert (txt_trunc == -1).all() and (dt.truncated == 0).all()
    np.testing.assert_allclose(dt.dimensions, txt.dimensions, atol=1e-6)
    np.testing.assert_allclose(dt.score, txt.score, atol=1e-6)
    np.testing.assert_array_equal(dt.name, txt.name)


def test_gzipped_pickles(tmp_path: Path) -> None:
    gt = load_ground_truth(dump(tmp_path / "kitti_infos_val.pkl.gz", infos(), compress=True))
    dt = load_detections(dump(tmp_path / "result.pkl.gz", results(), compress=True))
    assert gt.num_boxes == 5 and dt.num_boxes == 3


def test_frame_id_sources_in_infos(tmp_path: Path) -> None:
    entries = infos()
    del entries[0]["image"]  # -> point_cloud.lidar_idx
    entries[1]["image"].pop("image_idx")
    entries[1]["point_cloud"].pop("lidar_idx")
    entries[1]["frame_id"] = 1  # -> frame_id, an int
    gt = annotations_from_object(entries, "ground_truth", source="infos")
    assert gt.frame_ids == ("000000", "000001", "000002")
    del entries[1]["frame_id"]
    with pytest.raises(InputError, match="infos entry #1 has no frame id"):
        annotations_from_object(entries, "ground_truth", source="infos")


def test_infos_without_annos_are_a_test_split(tmp_path: Path) -> None:
    entries = infos()
    for e in entries:
        del e["annos"]
    with pytest.raises(InputError, match=r"no labels \('annos' missing in entry #0\): a test split") as err:
        load_ground_truth(dump(tmp_path / "kitti_infos_test.pkl", entries))
    assert err.value.frame == "000000"


def test_infos_entry_errors_name_the_entry() -> None:
    entries = infos()
    entries[2] = "000002"
    with pytest.raises(InputError, match=r"ground-truth entry #2 is str, expected a dict"):
        annotations_from_object(entries, "ground_truth", source="infos")
    entries = infos()
    entries[1]["annos"] = [1, 2]
    with pytest.raises(InputError, match="'annos' is list") as err:
        annotations_from_object(entries, "ground_truth", source="infos")
    assert err.value.frame == "000001" and err.value.field == "annos"
    entries = infos()
    entries[1]["image"] = "000001.png"
    with pytest.raises(InputError, match="'image' is str"):
        annotations_from_object(entries, "ground_truth", source="infos")


def test_field_errors_come_from_from_frames() -> None:
    entries = infos()
    entries[2]["annos"]["dimensions"] = np.zeros((1, 2))
    with pytest.raises(InputError, match=r"expected shape \(1, 3\), got \(1, 2\)") as err:
        annotations_from_object(entries, "ground_truth", source="infos")
    assert err.value.frame == "000002" and err.value.field == "dimensions"


def test_result_entry_without_frame_id(tmp_path: Path) -> None:
    entries = results()
    del entries[1]["frame_id"]
    with pytest.raises(InputError, match=r"result entry #1 has no frame_id"):
        load_detections(dump(tmp_path / "result.pkl", entries))


def test_result_frame_ids_of_every_kind() -> None:
    entries = results()
    entries[0]["frame_id"] = "000000"
    entries[1]["frame_id"] = 1
    entries[2]["frame_id"] = np.array("000002")
    dt = annotations_from_object(entries, "detections", source="r")
    assert dt.frame_ids == ("000000", "000001", "000002")
    entries[2]["frame_id"] = [2]
    with pytest.raises(InputError, match="frame_id is list, expected a string or an integer"):
        annotations_from_object(entries, "detections", source="r")


def test_duplicate_frame_is_reported(tmp_path: Path) -> None:
    entries = results()
    entries[2]["frame_id"] = "0"  # same frame as "000000"
    with pytest.raises(InputError, match=r"frame appears twice \(entries #0 and #2\)") as err:
        load_detections(dump(tmp_path / "result.pkl", entries))
    assert err.value.frame == "000000"


def test_dict_keyed_by_frame_id(tmp_path: Path) -> None:
    # PointPillars: {int image_idx: annos}; empty frames as 1-D empty arrays
    dets = {int(fid): annos(objs, detections=True) for fid, objs in DET.items()}
    dets[2] = {
        k: np.array([])
        for k in ("name", "truncated", "occluded", "alpha", "bbox", "dimensions", "location", "rotation_y", "score")
    }
    dt = load_detections(dump(tmp_path / "results.pkl", dets))
    assert dt.frame_ids == ("000000", "000001", "000002") and dt.counts.tolist() == [2, 1, 0]
    gt_annos = {fid: annos(objs, detections=False) for fid, objs in GT.items()}
    assert load_ground_truth(dump(tmp_path / "gt.pkl", gt_annos)).counts.tolist() == [4, 0, 1]
    gt_infos = {int(e["image"]["image_idx"]): e for e in infos()}  # PointPillars infos: values hold annos
    assert load_ground_truth(dump(tmp_path / "infos.pkl", gt_infos)).counts.tolist() == [4, 0, 1]


def test_ground_truth_as_annos_dicts_with_frame_id() -> None:
    entries = []
    for fid, objs in GT.items():
        a = annos(objs, detections=False)
        a["frame_id"] = fid
        entries.append(a)
    gt = annotations_from_object(entries, "ground_truth", source="gt")
    assert gt.frame_ids == ("000000", "000001", "000002") and gt.counts.tolist() == [4, 0, 1]
    del entries[0]["frame_id"]
    with pytest.raises(InputError, match="ground-truth entry #0 has no frame_id"):
        annotations_from_object(entries, "ground_truth", source="gt")


@pytest.mark.parametrize(
    "obj, found",
    [
        (np.zeros(3), "found a numpy array of shape (3,)"),
        ("000001", "found str"),
        (42, "found int"),
        ([1, 2], "ground-truth entry #0 is int"),
    ],
)
def test_wrong_top_level_type(tmp_path: Path, obj: object, found: str) -> None:
    with pytest.raises(InputError) as err:
        load_ground_truth(dump(tmp_path / "x.pkl", obj))
    assert "a list of per-frame dicts" in str(err.value) and found in str(err.value)


def test_other_layouts_get_specific_messages() -> None:
    with pytest.raises(InputError, match="OpenPCDet infos file .*not detections"):
        annotations_from_object(infos(), "detections", source="x")
    with pytest.raises(InputError, match="mmdetection3d 1.x info file"):
        annotations_from_object({"metainfo": {}, "data_list": []}, "ground_truth", source="x")
    with pytest.raises(InputError, match="single frame's annos dict"):
        annotations_from_object(results()[0], "detections", source="x")
    with pytest.raises(InputError, match="empty list: no frames"):
        annotations_from_object([], "detections", source="x")
    with pytest.raises(InputError, match="none of the expected keys"):
        annotations_from_object([{"boxes": 1}], "detections", source="x")


def test_detect_and_describe_format() -> None:
    assert detect_format(infos(), "ground_truth", source="x") == "openpcdet_infos"
    assert detect_format(results(), "detections", source="x") == "annos_list"
    assert detect_format({0: {}}, "detections", source="x") == "annos_by_frame"
    assert set(PICKLE_FORMATS) == {
        "openpcdet_infos",
        "annos_list",
        "annos_by_frame",
        "mmdet3d_infos",
        "mmdet3d_results",
    }
    assert (
        describe_format(infos()) == "a list of 3 entries, the first a dict with keys [annos, calib, image, point_cloud]"
    )
    assert describe_format({1: 2}) == "a dict with 1 keys [1]"
    assert describe_format(np.zeros((2, 3))) == "a numpy array of shape (2, 3) and dtype float64"


def test_unsafe_pickles_are_refused_by_the_loaders(tmp_path: Path) -> None:
    torch_like = tmp_path / "result.pkl"
    torch_like.write_bytes(b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\nq\x00)R.")
    with pytest.raises(UnsafePickleError, match="torch tensors"):
        load_detections(torch_like)
    with pytest.raises(InputError, match="larger than the limit"):
        load_detections(dump(tmp_path / "r.pkl", results()), max_bytes=100)


# ------------------------------------------------------------------------------------- golden small


def _golden_small() -> Path | None:
    here = Path(__file__).parents[1] / "data" / "golden" / "small"
    for d in (here, Path("/work/shared/golden/cases/small")):
        if (d / "result.pkl").is_file() and (d / "label_2.tar.gz").is_file():
            return d
    return None


@pytest.mark.skipif(_golden_small() is None, reason="golden small case not available")
def test_golden_small_case_both_routes_agree(tmp_path: Path) -> None:
    case = _golden_small()
    assert case is not None
    for tar in ("label_2.tar.gz", "pred.tar.gz"):
        with tarfile.open(case / tar) as tf:
            tf.extractall(tmp_path, filter="data")
    gt_txt = load_ground_truth(tmp_path / "label_2")
    gt_pkl = load_ground_truth(case / "kitti_infos_val.pkl")
    dt_txt = load_detections(tmp_path / "pred")
    dt_pkl = load_detections(case / "result.pkl")
    for a in (gt_txt, gt_pkl, dt_txt, dt_pkl):
        assert a.num_frames == 50
    assert gt_txt.frame_ids == gt_pkl.frame_ids and dt_txt.frame_ids == dt_pkl.frame_ids
    np.testing.assert_array_equal(gt_txt.counts, gt_pkl.counts)
    np.testing.assert_array_equal(dt_txt.counts, dt_pkl.counts)
    assert (gt_txt.counts == 0).any() and (dt_txt.counts == 0).any()  # both have an empty frame
    assert_same(gt_txt, gt_pkl, atol=1e-4)
    # detections: the txt files hold %.4f of the float32 pickle values; truncation/occlusion are -1 vs 0
    np.testing.assert_array_equal(dt_txt.name, dt_pkl.name)
    for f in ("alpha", "bbox", "dimensions", "location", "rotation_y", "score"):
        np.testing.assert_allclose(getattr(dt_txt, f), getattr(dt_pkl, f), rtol=0, atol=1e-4, err_msg=f)


def test_folder_of_empty_files(tmp_path: Path) -> None:
    folder = tmp_path / "pred"
    folder.mkdir()
    for fid in ("000001", "000002"):
        (folder / f"{fid}.txt").write_text("")
    dt = load_detections(folder)
    assert dt.frame_ids == ("000001", "000002") and dt.num_boxes == 0
    assert dt.bbox.shape == (0, 4) and dt.dimensions.shape == (0, 3)
