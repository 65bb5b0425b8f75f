"""Input formats beyond OpenPCDet pickles: mmdetection3d 1.x infos and results, zip/tar archives of txt
folders, split files, LiDAR-only predictions (calibration), and ``kitti-eval describe``.

Golden parity: tests/data/golden/small is converted into each format and must evaluate to the same AP.
"""

from __future__ import annotations

import io
import math
import pickle
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.cli import main
from kitti_eval.core.evaluation import evaluate
from kitti_eval.errors import InputError
from kitti_eval.io.calib import calib_from_info, lidar_to_camera, wrap_angle
from kitti_eval.io.describe import describe
from kitti_eval.io.loaders import (
    annotations_from_object,
    calibs_from_object,
    extract_txt_archive,
    load_detections,
    load_ground_truth,
    load_pair,
    read_split,
)
from kitti_eval.io.safe_pickle import load_pickle
from kitti_eval.synth import generate

SMALL = Path(__file__).parents[1] / "data" / "golden" / "small"
CATEGORIES = {
    "Pedestrian": 0,
    "Cyclist": 1,
    "Car": 2,
    "Van": 3,
    "Truck": 4,
    "Person_sitting": 5,
    "Tram": 6,
    "Misc": 7,
    "DontCare": -1,
}
CAMERA = ("location", "dimensions", "rotation_y", "alpha", "bbox")


# --------------------------------------------------------------------------------------------- helpers


def golden():
    return (load_pickle(SMALL / "kitti_infos_val.pkl", source="gt"), load_pickle(SMALL / "result.pkl", source="pred"))


def flat_ap(result) -> dict[tuple, float | None]:
    out: dict[tuple, float | None] = {}

    def walk(node, key):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, (*key, k))
        else:
            out[key] = node

    walk(result.to_dict()["ap"], ())
    return out


def max_ap_difference(a, b) -> float:
    fa, fb = flat_ap(a), flat_ap(b)
    assert fa.keys() == fb.keys()
    worst = 0.0
    for k in fa:
        x, y = fa[k], fb[k]
        if x is None or y is None or (isinstance(x, float) and math.isnan(x)):
            assert x is None and y is None or (math.isnan(x) and math.isnan(y)), k
            continue
        worst = max(worst, abs(x - y))
    return worst


def to_mmdet3d_infos(infos: list[dict]) -> dict:
    data_list = []
    for info in infos:
        a = info["annos"]
        calib = calib_from_info(info)
        h, w = (int(v) for v in info["image"]["image_shape"])
        instances = []
        for j in range(len(a["name"])):
            label = CATEGORIES[str(a["name"][j])]
            instances.append(
                {
                    "bbox": [float(v) for v in a["bbox"][j]],
                    "bbox_label": label,
                    "bbox_3d": [float(v) for v in (*a["location"][j], *a["dimensions"][j], a["rotation_y"][j])],
                    "bbox_label_3d": label,
                    "truncated": float(a["truncated"][j]),
                    "occluded": int(a["occluded"][j]),
                    "alpha": float(a["alpha"][j]),
                    "difficulty": 0,
                    "index": j,
                    "group_id": j,
                }
            )
        p2 = np.eye(4)
        p2[:3] = calib.p2
        data_list.append(
            {
                "sample_idx": int(info["image"]["image_idx"]),
                "images": {
                    "CAM2": {
                        "img_path": f"{info['image']['image_idx']}.png",
                        "height": h,
                        "width": w,
                        "cam2img": p2.tolist(),
                        "lidar2cam": calib.velo_to_rect.tolist(),
                    }
                },
                "instances": instances,
            }
        )
    return {
        "metainfo": {"categories": dict(CATEGORIES), "dataset": "kitti", "info_version": "1.1"},
        "data_list": data_list,
    }


def to_mmdet3d_results(results: list[dict]) -> list[dict]:
    out = []
    for r in results:
        d = {k: v for k, v in r.items() if k not in ("frame_id", "boxes_lidar")}
        n = len(r["score"])
        d["sample_idx"] = np.array([int(r["frame_id"])] * n, dtype=np.int64)  # empty for an empty frame
        out.append(d)
    return out


def lidar_only(results: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in CAMERA} for r in results]


def dump(path: Path, obj) -> Path:
    path.write_bytes(pickle.dumps(obj, protocol=4))
    return path


def txt_folders(tmp_path: Path) -> tuple[Path, Path]:
    for name in ("label_2.tar.gz", "pred.tar.gz"):
        with tarfile.open(SMALL / name) as tf:
            tf.extractall(tmp_path, filter="data")
    return tmp_path / "label_2", tmp_path / "pred"


def zip_folder(folder: Path, dest: Path, prefix: str) -> Path:
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(folder.iterdir()):
            zf.writestr(f"{prefix}/{f.name}", f.read_bytes())
    return dest


def zip_of(members: dict[str, bytes], dest: Path) -> Path:
    with zipfile.ZipFile(dest, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return dest


def tar_of(members: dict[str, bytes], dest: Path, special: tarfile.TarInfo | None = None) -> Path:
    with tarfile.open(dest, "w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
        if special is not None:
            tf.addfile(special)
    return dest


GOOD_LINE = b"Car 0 0 -1.5 100 100 200 200 1.5 1.6 3.9 1 1.5 20 0.1 0.9\n"


@pytest.fixture(scope="module")
def reference():
    infos, results = golden()
    gt = annotations_from_object(infos, "ground_truth", source="gt")
    dt = annotations_from_object(results, "detections", source="pred")
    return evaluate(gt, dt)


# ------------------------------------------------------------------------------------ mmdetection3d 1.x


def test_mmdet3d_infos_and_results_give_the_golden_ap(reference, tmp_path):
    infos, results = golden()
    gt_path = dump(tmp_path / "kitti_infos_val.pkl", to_mmdet3d_infos(infos))
    pred_path = dump(tmp_path / "results.pkl", to_mmdet3d_results(results))
    gt = load_ground_truth(gt_path)
    dt = load_detections(pred_path)
    assert gt.num_frames == 50 and int(np.sum(gt.name == "DontCare")) == 72
    assert max_ap_difference(evaluate(gt, dt), reference) <= 1e-9
    # and mixed with the OpenPCDet formats
    dt_pcdet = load_detections(SMALL / "result.pkl")
    assert max_ap_difference(evaluate(gt, dt_pcdet), reference) <= 1e-9


def test_mmdet3d_formats_are_detected_and_overridable(tmp_path):
    infos, results = golden()
    mm_infos, mm_results = to_mmdet3d_infos(infos), to_mmdet3d_results(results)
    a = annotations_from_object(mm_infos, "ground_truth", source="x", fmt="mmdet3d_infos")
    assert a.frame_ids[:2] == ("000000", "000001")
    b = annotations_from_object(mm_results, "detections", source="x", fmt="mmdet3d_results")
    assert b.num_boxes == 790
    with pytest.raises(InputError, match="expects a dict"):
        annotations_from_object(mm_results, "detections", source="x", fmt="mmdet3d_infos")
    with pytest.raises(InputError, match="not detections"):
        annotations_from_object(mm_infos, "detections", source="x")
    with pytest.raises(InputError, match="empty data_list"):
        annotations_from_object({"metainfo": {"categories": {}}, "data_list": []}, "ground_truth", source="x")
    with pytest.raises(InputError, match="unknown format"):
        load_ground_truth(SMALL / "kitti_infos_val.pkl", fmt="nope")


def test_mmdet3d_bad_label_names_the_frame():
    infos, _ = golden()
    mm = to_mmdet3d_infos(infos)
    mm["data_list"][3]["instances"][0]["bbox_label"] = 42
    with pytest.raises(InputError, match="bbox_label 42") as err:
        annotations_from_object(mm, "ground_truth", source="x")
    assert err.value.frame == "000003"


def test_mmdet3d_pickle_with_torch_is_refused(tmp_path):
    # what mmdet3d's generic --out dump holds: a global of torch, refused without importing it
    data = b"\x80\x04\x95\x1e\x00\x00\x00\x00\x00\x00\x00\x8c\x0ctorch._utils\x8c\x12_rebuild_tensor_v2\x93."
    path = tmp_path / "results.pkl"
    path.write_bytes(data)
    with pytest.raises(InputError, match="torch"):
        load_detections(path)
    assert main(["describe", str(path)]) == 1


# ------------------------------------------------------------------------------------------- archives


def test_zip_and_tar_archives_equal_the_txt_route(tmp_path):
    label_dir, pred_dir = txt_folders(tmp_path)
    txt = evaluate(load_ground_truth(label_dir), load_detections(pred_dir))
    label_zip = zip_folder(label_dir, tmp_path / "label_2.zip", "training/label_2")
    pred_zip = zip_folder(pred_dir, tmp_path / "pred.zip", "pred")
    for gt_path, pred_path in ((label_zip, pred_zip), (SMALL / "label_2.tar.gz", SMALL / "pred.tar.gz")):
        gt, dt = load_ground_truth(gt_path), load_detections(pred_path)
        assert gt.source == str(gt_path)
        assert max_ap_difference(evaluate(gt, dt), txt) <= 1e-9


def test_archive_prefers_label_2_or_data(tmp_path):
    both = zip_of(
        {"training/label_2/000000.txt": GOOD_LINE[:-5] + b"\n", "training/calib/000000.txt": b"P0: 1\n"},
        tmp_path / "a.zip",
    )
    assert load_ground_truth(both).num_boxes == 1
    result = tar_of(
        {"final_result/data/000007.txt": GOOD_LINE, "final_result/x/000001.txt": GOOD_LINE}, tmp_path / "r.tar.gz"
    )
    assert load_detections(result).frame_ids == ("000007",)
    two = zip_of({"a/000000.txt": GOOD_LINE, "b/000001.txt": GOOD_LINE}, tmp_path / "two.zip")
    with pytest.raises(InputError, match="several folders"):
        load_detections(two)


@pytest.mark.parametrize(
    "members, message",
    [
        ({"../000000.txt": GOOD_LINE}, "outside"),
        ({"/etc/000000.txt": GOOD_LINE}, "absolute"),
        ({"pred/0\x1b.txt": GOOD_LINE}, "control characters"),
        ({"pred/readme.md": b"x"}, "no .txt files"),
    ],
)
@pytest.mark.parametrize("container", ["zip", "tar"])
def test_unsafe_archives_are_refused(tmp_path, members, message, container):
    path = zip_of(members, tmp_path / "p.zip") if container == "zip" else tar_of(members, tmp_path / "p.tar.gz")
    with pytest.raises(InputError, match=message):
        load_detections(path)


@pytest.mark.parametrize("kind", [tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.CHRTYPE, tarfile.FIFOTYPE])
def test_tar_links_and_devices_are_refused(tmp_path, kind):
    special = tarfile.TarInfo("pred/000001.txt")
    special.type = kind
    special.linkname = "/etc/passwd"
    path = tar_of({"pred/000000.txt": GOOD_LINE}, tmp_path / "p.tar.gz", special)
    with pytest.raises(InputError, match="link|device"):
        load_detections(path)


def test_zip_symlink_and_limits(tmp_path):
    path = tmp_path / "s.zip"
    with zipfile.ZipFile(path, "w") as zf:
        info = zipfile.ZipInfo("pred/000000.txt")
        info.external_attr = 0o120777 << 16
        zf.writestr(info, "/etc/passwd")
    with pytest.raises(InputError, match="link"):
        load_detections(path)
    from kitti_eval.io.loaders import ArchiveLimits

    many = zip_of({f"pred/{i:06d}.txt": GOOD_LINE for i in range(20)}, tmp_path / "m.zip")
    (tmp_path / "out").mkdir()
    with pytest.raises(InputError, match="more than 10 members"):
        extract_txt_archive(many, tmp_path / "out", limits=ArchiveLimits(max_members=10))
    (tmp_path / "out2").mkdir()
    with pytest.raises(InputError, match="unpacks to more than"):
        extract_txt_archive(many, tmp_path / "out2", limits=ArchiveLimits(max_unpacked_bytes=100))
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"PK\x03\x04" + b"garbage" * 10)
    with pytest.raises(InputError, match="not a readable"):
        load_detections(bad)


# ---------------------------------------------------------------------------------------------- split


def test_split_subsets_ground_truth_and_drops_other_predictions(tmp_path, capsys):
    infos, results = golden()
    ids = [f"{i:06d}" for i in range(0, 50, 2)]
    split = tmp_path / "val.txt"
    split.write_text("\n".join(str(int(i)) for i in ids) + "\n\n")
    assert read_split(split) == ids
    warnings: list[str] = []
    gt, dt = load_pair(SMALL / "kitti_infos_val.pkl", SMALL / "result.pkl", split=split, warnings=warnings)
    assert gt.frame_ids == tuple(ids) and set(dt.frame_ids) <= set(ids)
    assert any("25 frames outside the split" in w for w in warnings)
    want = evaluate(
        annotations_from_object([infos[i] for i in range(0, 50, 2)], "ground_truth", source="g"),
        annotations_from_object([results[i] for i in range(0, 50, 2)], "detections", source="p"),
    )
    assert max_ap_difference(evaluate(gt, dt), want) == 0.0
    out = tmp_path / "r.json"
    code = main(
        [
            "--gt",
            str(SMALL / "kitti_infos_val.pkl"),
            "--pred",
            str(SMALL / "result.pkl"),
            "--split",
            str(split),
            "--format",
            "json",
            "--output",
            str(out),
        ]
    )
    assert code == 0
    assert "25 frames outside the split" in capsys.readouterr().err
    split.write_text("000000\n999999\n")
    assert (
        main(["--gt", str(SMALL / "kitti_infos_val.pkl"), "--pred", str(SMALL / "result.pkl"), "--split", str(split)])
        == 1
    )


# -------------------------------------------------------------------------------------- LiDAR-only boxes


def test_lidar_to_camera_reproduces_the_synthetic_camera_fields():
    infos, results = generate(30, seed=3, pred_decimals=None)
    calibs = calibs_from_object(infos)
    n = 0
    for r in results:
        if not len(r["score"]):
            continue
        conv = lidar_to_camera(r["boxes_lidar"], calibs[str(r["frame_id"])])
        for k in ("location", "dimensions", "bbox", "alpha"):
            np.testing.assert_allclose(conv[k], r[k], atol=1e-3, rtol=0, err_msg=k)
        assert np.abs(wrap_angle(conv["rotation_y"] - r["rotation_y"])).max() <= 1e-3
        assert np.all(np.abs(conv["rotation_y"]) <= np.pi)
        n += len(r["score"])
    assert n > 100


def test_lidar_only_predictions_evaluate_like_their_camera_fields(reference, tmp_path):
    infos, results = golden()
    path = dump(tmp_path / "lidar.pkl", lidar_only(results))
    gt, dt = load_pair(SMALL / "kitti_infos_val.pkl", path)
    original = annotations_from_object(results, "detections", source="p")
    assert dt.num_boxes == original.num_boxes
    assert np.abs(dt.location - original.location).max() < 1e-3
    assert np.abs(dt.dimensions - original.dimensions).max() < 1e-5
    assert np.abs(wrap_angle(dt.rotation_y - original.rotation_y)).max() < 1e-5
    assert np.abs(dt.bbox - original.bbox).max() < 0.05
    # not float-precision equal: result.pkl's alpha is OpenPCDet's (from the LiDAR origin), the conversion's
    # is ry - arctan2(x, z) (camera origin), up to 0.048 rad apart here, and its 2D boxes differ by up to
    # 0.03 px. Measured: bbox, BEV and 3D AP within 1e-6 (equal), AOS within 0.0054 AP points.
    got, want = flat_ap(evaluate(gt, dt)), flat_ap(reference)
    for key, value in want.items():
        if value is None:
            assert got[key] is None, key
        else:
            assert abs(got[key] - value) <= (0.01 if key[3] == "aos" else 1e-6), key
    with pytest.raises(InputError, match="calibration"):
        load_detections(path)
    # through the CLI, and with mmdetection3d infos as the source of calibration
    assert (
        main(
            [
                "--gt",
                str(SMALL / "kitti_infos_val.pkl"),
                "--pred",
                str(path),
                "--quiet",
                "--output",
                str(tmp_path / "o.txt"),
            ]
        )
        == 0
    )
    # the subcommands that evaluate load the pair the same way
    assert (
        main(
            [
                "frames",
                "--gt",
                str(SMALL / "kitti_infos_val.pkl"),
                "--pred",
                str(path),
                "--output",
                str(tmp_path / "f.txt"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "compare",
                str(SMALL / "result.pkl"),
                str(path),
                "--gt",
                str(SMALL / "kitti_infos_val.pkl"),
                "--output",
                str(tmp_path / "c.txt"),
            ]
        )
        == 0
    )
    inspect_out = tmp_path / "i.txt"
    assert (
        main(
            [
                "inspect",
                "--gt",
                str(SMALL / "kitti_infos_val.pkl"),
                "--pred",
                str(path),
                "--frame",
                gt.frame_ids[0],
                "--output",
                str(inspect_out),
            ]
        )
        == 0
    )
    mm = dump(tmp_path / "mm.pkl", to_mmdet3d_infos(infos))
    gt2, dt2 = load_pair(mm, path)
    assert np.abs(dt2.location - dt.location).max() < 1e-9


def test_camera_lidar_disagreement_warns(tmp_path, capsys):
    _, results = golden()
    bad = [dict(r) for r in results]
    for r in bad:  # a conversion that is off everywhere, as a broken one is
        r["location"] = r["location"] + np.float32(0.5)
    path = dump(tmp_path / "bad.pkl", bad)
    warnings: list[str] = []
    load_pair(SMALL / "kitti_infos_val.pkl", path, warnings=warnings)
    # every 10th frame that has both is checked: frames 0, 10, 20, 30 and 40 of the 50
    checked = sum(len(r["score"]) for r in results[::10])
    assert len(warnings) == 1 and "disagree" in warnings[0] and "every 10th frame" in warnings[0]
    assert f"for {checked} of {checked} boxes" in warnings[0] and "in 5 frames" in warnings[0]
    clean: list[str] = []
    load_pair(SMALL / "kitti_infos_val.pkl", SMALL / "result.pkl", warnings=clean)
    assert clean == []
    assert main(["describe", str(path), "--gt", str(SMALL / "kitti_infos_val.pkl")]) == 0
    assert "DISAGREE" in capsys.readouterr().out


# ----------------------------------------------------------------------------------------- the CLI


def test_cli_format_options(tmp_path):
    infos, results = golden()
    gt_path = dump(tmp_path / "gt.pkl", to_mmdet3d_infos(infos))
    pred_path = dump(tmp_path / "pred.pkl", to_mmdet3d_results(results))
    out = tmp_path / "o.json"
    assert (
        main(
            [
                "--gt",
                str(gt_path),
                "--pred",
                str(pred_path),
                "--gt-format",
                "mmdet3d_infos",
                "--pred-format",
                "mmdet3d_results",
                "--format",
                "json",
                "--output",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    assert main(["--gt", str(gt_path), "--pred", str(pred_path), "--gt-format", "openpcdet_infos"]) == 1
    assert main(["--gt", str(gt_path), "--pred", str(pred_path), "--gt-format", "bogus"]) == 2
    assert (
        main(["--gt", str(SMALL / "label_2.tar.gz"), "--pred", str(SMALL / "pred.tar.gz"), "-q", "--output", str(out)])
        == 0
    )


def test_describe_reports(tmp_path, capsys):
    infos, results = golden()
    text = describe(SMALL / "result.pkl")
    assert "format: annos_list" in text and "kind: predictions" in text and "frames: 50 (1 empty)" in text
    assert "Car 545" in text and "float32" in text and "looks like (l, h, w)" in text
    text = describe(dump(tmp_path / "mm.pkl", to_mmdet3d_infos(infos)))
    assert "format: mmdet3d_infos" in text and "DontCare 72" in text
    text = describe(dump(tmp_path / "lidar.pkl", lidar_only(results)))
    assert "LiDAR-only frames" in text
    assert "kitti_txt archive" in describe(SMALL / "label_2.tar.gz", "gt")
    swapped = [dict(r, dimensions=r["dimensions"][:, [1, 2, 0]]) for r in results]
    assert "look like" in describe(dump(tmp_path / "swapped.pkl", swapped))
    assert main(["describe", str(SMALL / "kitti_infos_val.pkl")]) == 0
    assert "kind: ground truth" in capsys.readouterr().out
    assert main(["describe", str(tmp_path / "missing.pkl")]) == 1
    (tmp_path / "junk.pkl").write_bytes(b"not a pickle at all")
    assert main(["describe", str(tmp_path / "junk.pkl")]) == 1
    assert main(["describe", str(SMALL / "result.pkl"), "--kind", "bogus"]) == 2


def test_pointpillars_dicts_keyed_by_frame_give_the_golden_ap(reference, tmp_path):
    """PointPillars writes {int frame id: info} infos and {int frame id: annos} results."""
    infos, results = golden()
    gt_path = dump(tmp_path / "infos.pkl", {int(i["image"]["image_idx"]): i for i in infos})
    pred_path = dump(
        tmp_path / "results.pkl", {int(r["frame_id"]): {k: v for k, v in r.items() if k != "frame_id"} for r in results}
    )
    assert max_ap_difference(evaluate(load_ground_truth(gt_path), load_detections(pred_path)), reference) <= 1e-9


# ------------------------------------------------------------------- one test of what a file is, CLI and service


def _same_file_cases(tmp_path: Path) -> dict[str, tuple[str, bytes]]:
    import gzip as gz
    import zipfile

    from kitti_eval.synth import write_result_dir

    pred_dir = tmp_path / "pred"
    write_result_dir(pred_dir, generate(3, seed=1)[1])
    zipped = io.BytesIO()
    with zipfile.ZipFile(zipped, "w") as zf:
        for f in sorted(pred_dir.iterdir()):
            zf.writestr(f"data/{f.name}", f.read_bytes())
    results = pickle.dumps(generate(3, seed=1)[1], protocol=4)
    return {
        "a zip named like a pickle": ("result.pkl", zipped.getvalue()),
        "a pickle named like a zip": ("pred.zip", results),
        "a gzipped pickle named like a tar": ("pred.tar.gz", gz.compress(results)),
        "a single KITTI txt file": ("000000", (pred_dir / "000000.txt").read_bytes()),
        "something else": ("result.pkl", b"%PDF-1.4 not a pickle"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "a zip named like a pickle",
        "a pickle named like a zip",
        "a gzipped pickle named like a tar",
        "a single KITTI txt file",
        "something else",
    ],
)
def test_a_file_loads_the_same_way_through_the_cli_and_the_service(tmp_path: Path, case: str) -> None:
    """The CLI's loader and the upload reader the service calls decide what a file is by the same test of its
    content, whatever its name: the same boxes, or the same refusal."""
    from kitti_eval.io.upload import read_upload

    name, data = _same_file_cases(tmp_path)[case]
    path = tmp_path / "in" / name
    path.parent.mkdir()
    path.write_bytes(data)
    outcomes = []
    for load in (
        lambda: load_detections(path),
        lambda: read_upload(io.BytesIO(data), "detections", source=name, scratch=tmp_path / "scratch").annotations,
    ):
        try:
            dt = load()
            outcomes.append(("loaded", dt.frame_ids, dt.num_boxes, dt.score.tolist()))
        except InputError as e:
            outcomes.append((type(e).__name__, e.message))
    assert outcomes[0] == outcomes[1]
    if case in ("a single KITTI txt file", "something else"):
        assert outcomes[0][0] == "UnknownFormatError"
    else:
        assert outcomes[0][0] == "loaded" and outcomes[0][1] == ("000000", "000001", "000002")


def test_class_names_of_bytes_that_are_not_utf8_are_names_no_class_has(tmp_path: Path, capsys) -> None:
    """The references read any name: a name array of bytes with a byte that is not UTF-8 (once a traceback,
    then a refusal) is evaluated like any unknown name, the byte shown as U+FFFD; ASCII bytes are the names
    they spell."""
    import json

    infos, results = generate(3, seed=1)
    gt = tmp_path / "infos.pkl"
    gt.write_bytes(pickle.dumps(infos, protocol=4))
    n = len(results[1]["score"])

    def run(names: np.ndarray) -> dict:
        results[1]["name"] = names
        path = tmp_path / "result.pkl"
        path.write_bytes(pickle.dumps(results, protocol=4))
        assert main(["--gt", str(gt), "--pred", str(path), "--format", "json", "--quiet"]) == 0
        return json.loads(capsys.readouterr().out)["ap"]

    assert run(np.array([b"Car\xff"] * n)) == run(np.array(["Unknown"] * n))
    assert run(np.array([b"Car"] * n)) == run(np.array(["Car"] * n))
    results[1]["name"] = np.array([b"Car\xff"] * n)
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps(results, protocol=4))
    dt = load_detections(path)
    assert dt.name[dt.offsets[1] : dt.offsets[2]].tolist() == ["Car\ufffd"] * n


def test_a_label_file_that_is_not_utf8_is_read(tmp_path: Path) -> None:
    """A latin-1 class name in a label file: the devkit reads its bytes, an unknown class; so does kitti-eval."""
    folder = tmp_path / "label_2"
    folder.mkdir()
    line = " 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"
    (folder / "000000.txt").write_bytes(b"Caf\xe9" + line.encode() + b"Car" + line.encode())
    gt = load_ground_truth(folder)
    assert gt.name.tolist() == ["Caf\ufffd", "Car"]
