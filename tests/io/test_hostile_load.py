"""Bad input refused early, naming the frame and field: shapes before arithmetic, frame-count claims, byte
limits of the CLI, archive members charged before they are written; and what is not refused because every
reference reads it: boxes whose size is not positive, read as written and reported once per input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from test_loaders import DET, GT, dump, infos, results, write_txt

from kitti_eval.core.frames import UnsizedBoxes, size_warnings, unsized_boxes
from kitti_eval.errors import InputError
from kitti_eval.io.loaders import (
    annotations_from_object,
    calibs_from_object,
    load_detections,
    load_ground_truth,
    load_pair,
)

# ------------------------------------------------------------------------------ shapes before arithmetic


def test_a_location_of_the_wrong_shape_is_named_before_the_lidar_check() -> None:
    calibs = calibs_from_object(infos())
    entries = results()
    entries[0]["location"] = np.zeros((2, 2), np.float32)  # 4 numbers: no (N, 3) reading of them
    with pytest.raises(InputError, match=r"expected shape \(2, 3\), got \(2, 2\)") as err:
        annotations_from_object(entries, "detections", source="r", calibs=calibs, warnings=[])
    assert (err.value.frame, err.value.field) == ("000000", "location")
    entries = results()
    entries[0]["rotation_y"] = np.array(["a", "b"])
    with pytest.raises(InputError, match="expected numbers") as err:
        annotations_from_object(entries, "detections", source="r", calibs=calibs, warnings=[])
    assert (err.value.frame, err.value.field) == ("000000", "rotation_y")


# --------------------------------------------------------------------- boxes whose size is not positive


def _with_dims(frames: dict, fid: str, k: int, dims: tuple[float, float, float]) -> dict:
    out = {f: list(objs) for f, objs in frames.items()}
    o = list(out[fid][k])
    o[5] = dims
    out[fid][k] = tuple(o)
    return out


SIZES = [(0.0, 1.5, 1.6), (3.9, -0.5, 1.6), (3.9, 1.5, 0.0), (-1.0, -1.0, -1.0), (0.0, 0.0, 0.0), (-2.0, -1.0, -1.0)]


@pytest.mark.parametrize("dims", SIZES)
def test_ground_truth_of_any_size_is_read_as_written(tmp_path: Path, dims: tuple[float, float, float]) -> None:
    """The devkit, OpenPCDet and mmdetection3d read every box (mmdetection3d's own test data has Cars of size
    -1 -1 -1): both routes keep the size as written, and the evaluation says how many there are."""
    frames = _with_dims(GT, "000000", 1, dims)
    for gt in (
        load_ground_truth(write_txt(tmp_path / "label_2", frames, with_score=False)),
        annotations_from_object(infos(frames), "ground_truth", source="infos"),
    ):
        np.testing.assert_allclose(gt.dimensions[1], dims, rtol=1e-6)  # the pickle holds float32
        (warning,) = size_warnings(gt)
        assert warning.startswith(
            f"{gt.source}: 1 ground-truth box (DontCare aside) has a size that is not positive (the first: frame "
            f"000000, box 1 (Car), (l, h, w) = {tuple(float(v) for v in gt.dimensions[1])}); evaluated as the "
            "KITTI devkit reads them"
        )


@pytest.mark.parametrize("dims", SIZES)
def test_detections_of_any_size_are_read_as_written(tmp_path: Path, dims: tuple[float, float, float]) -> None:
    frames = _with_dims(DET, "000000", 1, dims)
    for dt in (
        load_detections(write_txt(tmp_path / "pred", frames, with_score=True)),
        load_detections(dump(tmp_path / "result.pkl", results(frames))),
    ):
        np.testing.assert_allclose(dt.dimensions[1], dims, rtol=1e-6)
        (warning,) = size_warnings(dt)
        assert "1 predicted box (DontCare aside) has a size that is not positive (the first: frame 000000, box 1 " in (
            warning
        )


def test_dontcare_regions_keep_their_minus_one_dimensions_and_are_not_counted() -> None:
    gt = annotations_from_object(infos(), "ground_truth", source="infos")  # DontCare: -1 -1 -1
    assert (gt.dimensions[gt.name == "DontCare"] == -1).all()
    assert unsized_boxes(gt) == UnsizedBoxes() and size_warnings(gt) == []


def test_the_size_warning_counts_every_box_and_names_the_first(tmp_path: Path) -> None:
    frames = _with_dims(_with_dims(GT, "000002", 0, (0.0, 0.0, 0.0)), "000000", 2, (1.2, -1.0, 0.5))
    gt = load_ground_truth(write_txt(tmp_path / "label_2", frames, with_score=False))
    assert unsized_boxes(gt) == UnsizedBoxes(2, ("000000", 2, "Pedestrian", (1.2, -1.0, 0.5)))
    (warning,) = size_warnings(gt)
    assert ": 2 ground-truth boxes (DontCare aside) have a size that is not positive (the first: frame 000000, " in (
        warning
    )
    # the parts of a set in shards add up to the whole, the first part's first box first
    parts = [unsized_boxes(gt.subset([f])) for f in gt.frame_ids]
    assert parts[0].merged(parts[1]).merged(parts[2]) == unsized_boxes(gt)
    assert UnsizedBoxes().merged(parts[1]) == parts[1]


def test_the_warning_reaches_stderr_and_the_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from kitti_eval.cli import main

    gt = write_txt(tmp_path / "label_2", _with_dims(GT, "000000", 0, (-1.0, -1.0, -1.0)), with_score=False)
    pred = write_txt(tmp_path / "pred", _with_dims(DET, "000001", 0, (0.0, 0.0, 0.0)), with_score=True)
    assert main(["--gt", str(gt), "--pred", str(pred), "--format", "json"]) == 0
    out, err = capsys.readouterr()
    warnings = [w for w in json.loads(out)["warnings"] if "not positive" in w]
    assert [w.split(": ", 1)[0] for w in warnings] == [str(gt), str(pred)]
    assert "frame 000000, box 0 (Car), (l, h, w) = (-1.0, -1.0, -1.0)" in warnings[0]
    assert "frame 000001, box 0 (Car), (l, h, w) = (0.0, 0.0, 0.0)" in warnings[1]
    shown = [line for line in err.splitlines() if "not positive" in line]
    assert shown == [f"kitti-eval: warning: {w}" for w in warnings]


# -------------------------------------------------------------------------------------- frame ids


def test_a_frame_id_taken_from_lidar_idx_is_reported() -> None:
    entries = infos()
    del entries[0]["image"]
    del entries[2]["image"]
    warnings: list[str] = []
    gt = annotations_from_object(entries, "ground_truth", source="infos", warnings=warnings)
    assert gt.frame_ids == ("000000", "000001", "000002")
    assert warnings == [
        "infos: 2 entries have no image.image_idx; their point_cloud.lidar_idx is used as the frame id "
        "(the first: entry #0, frame 000000)"
    ]
    warnings.clear()
    annotations_from_object(infos(), "ground_truth", source="infos", warnings=warnings)
    assert warnings == []


def test_load_pair_reports_the_lidar_idx_fallback(tmp_path: Path) -> None:
    entries = infos()
    del entries[1]["image"]
    warnings: list[str] = []
    gt, dt = load_pair(
        dump(tmp_path / "infos.pkl", entries), dump(tmp_path / "result.pkl", results()), warnings=warnings
    )
    assert gt.frame_ids == dt.frame_ids == ("000000", "000001", "000002")
    fallback = [w for w in warnings if "image_idx" in w]
    assert fallback == [
        f"{tmp_path / 'infos.pkl'}: 1 entries have no image.image_idx; their point_cloud.lidar_idx is used as the "
        "frame id (the first: entry #1, frame 000001)"
    ]


# ------------------------------------------------------------------------------------------- archives


def _tar_gz(path: Path, members: dict[str, bytes]) -> Path:
    import io
    import tarfile

    with tarfile.open(path, "w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return path


def _written(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def test_a_tar_member_is_charged_its_declared_size_before_it_is_written(tmp_path: Path) -> None:
    from kitti_eval.io.archives import ArchiveLimits, extract_txt_folder

    bomb = _tar_gz(tmp_path / "pred.tar.gz", {"pred/000000.txt": b"0" * (3 << 20)})  # 3 MB of zeros, 3 KB packed
    dest = tmp_path / "out"
    with open(bomb, "rb") as fh, pytest.raises(InputError, match="unpacks to more than 1 MB"):
        extract_txt_folder(fh, "tar", dest, ArchiveLimits(max_unpacked_bytes=1 << 20), "pred.tar.gz")
    assert not dest.exists() or _written(dest) == 0
    ok = _tar_gz(tmp_path / "ok.tar.gz", {"pred/000000.txt": b"x" * 600_000, "pred/000001.txt": b"y" * 400_000})
    with open(ok, "rb") as fh:  # exactly what is declared fits: 1,000,000 bytes of a 1 MiB cap, counted once
        folder, _ = extract_txt_folder(fh, "tar", tmp_path / "ok", ArchiveLimits(max_unpacked_bytes=1 << 20), "ok")
    assert _written(folder) == 1_000_000


def test_a_txt_file_larger_than_any_kitti_frame_is_refused_unread(tmp_path: Path) -> None:
    from kitti_eval.io.archives import MAX_TXT_FILE_BYTES, ArchiveLimits, extract_txt_folder

    big = b"Car 0 0 0 0 0 1 1 1 1 1 1 1 1 1 0.5\n" * (MAX_TXT_FILE_BYTES // 36 + 1)
    folder = tmp_path / "pred"
    folder.mkdir()
    (folder / "000000.txt").write_bytes(big)
    with pytest.raises(InputError, match=r"larger than 16 MB; a KITTI txt file holds one frame") as err:
        load_detections(folder)
    assert err.value.frame == "000000"
    archive = _tar_gz(tmp_path / "pred.tar.gz", {"pred/000000.txt": big})
    with open(archive, "rb") as fh, pytest.raises(InputError, match=r"larger than 16 MB; a KITTI txt file"):
        extract_txt_folder(fh, "tar", tmp_path / "out", ArchiveLimits(), "pred.tar.gz")


# -------------------------------------------------------------------------------------- frame claims


def test_a_pickle_claiming_more_frames_than_the_limit_is_refused_before_it_is_built(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kitti_eval.io import safe_pickle

    build = safe_pickle._build

    def never(data: bytes, res: tuple, source: str) -> object:
        assert not source.endswith("result.pkl"), "the C unpickler ran on the predictions"
        return build(data, res, source)

    empty = results({"000002": []})[0]
    path = dump(tmp_path / "result.pkl", [dict(empty, frame_id=f"{i:06d}") for i in range(101)])
    monkeypatch.setenv("KITTI_EVAL_MAX_FRAMES", "100")
    monkeypatch.setattr(safe_pickle, "_build", never)
    with pytest.raises(InputError, match="the pickle is a list of 101 entries, more than the limit of 100 frames"):
        load_detections(path)
    with pytest.raises(InputError, match="a list of 101 entries"):
        load_detections(path, max_frames=100)
    monkeypatch.delenv("KITTI_EVAL_MAX_FRAMES")
    with pytest.raises(InputError, match="a list of 101 entries"):
        load_pair(dump(tmp_path / "infos.pkl", infos()), path, max_frames=100)


class _Poison(dict):  # type: ignore[type-arg]
    """A frame that fails the test if its fields are read."""

    def __getitem__(self, key: object) -> object:
        raise AssertionError("a frame after the refused one was converted")

    get = __getitem__  # type: ignore[assignment]


def test_other_layouts_are_refused_at_the_first_frame_past_the_limit(tmp_path: Path) -> None:
    by_frame = {f"{i:06d}": annos for i, annos in enumerate(r for r in results() for _ in range(2))}
    by_frame["999999"] = _Poison()
    with pytest.raises(InputError, match="more than the limit of 6 frames") as err:
        annotations_from_object(by_frame, "detections", source="d", max_frames=6)
    assert err.value.frame == "999999"
    write_txt(tmp_path / "pred", {f"{i:06d}": [] for i in range(7)}, with_score=True)
    with pytest.raises(InputError, match="7 txt files, more than the limit of 6 frames"):
        load_detections(tmp_path / "pred", max_frames=6)


def test_predictions_of_frames_not_in_the_ground_truth_stop_at_the_first(tmp_path: Path) -> None:
    entries = results() + [dict(results()[0], frame_id="777777")] + [_Poison(frame_id=f"8{i:05d}") for i in range(3)]
    with pytest.raises(InputError, match="predictions for a frame that is not in the ground truth") as err:
        annotations_from_object(entries, "detections", source="r", known_frames={"000000", "000001", "000002"})
    assert err.value.frame == "777777"
    pred = write_txt(tmp_path / "pred", {**DET, "000003": []}, with_score=True)
    with pytest.raises(InputError, match="not in the ground truth") as err:
        load_pair(dump(tmp_path / "infos.pkl", infos()), pred)
    assert err.value.frame == "000003"


# ------------------------------------------------------------------------------------- CLI byte limits


def test_the_cli_has_default_input_limits_that_flags_and_the_environment_change(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import gzip
    import pickle

    from kitti_eval.cli import main
    from kitti_eval.io.loaders import input_limits

    monkeypatch.delenv("KITTI_EVAL_MAX_UNPACKED_MB", raising=False)
    monkeypatch.delenv("KITTI_EVAL_MAX_FRAMES", raising=False)
    assert input_limits() == (512 << 20, 200_000)
    gt = dump(tmp_path / "infos.pkl", infos())
    bomb = tmp_path / "result.pkl.gz"  # 3 MB of pickle in 3 KB
    bomb.write_bytes(gzip.compress(pickle.dumps([b"\0" * (3 << 20)], protocol=4)))
    assert main(["--gt", str(gt), "--pred", str(bomb), "--max-input-mb", "2"]) == 1
    assert "decompressed gzip data is larger than the limit of 2097152 bytes" in capsys.readouterr().err
    monkeypatch.setenv("KITTI_EVAL_MAX_UNPACKED_MB", "1")
    assert main(["--gt", str(gt), "--pred", str(bomb)]) == 1
    assert "larger than the limit of 1048576 bytes" in capsys.readouterr().err
    monkeypatch.setenv("KITTI_EVAL_MAX_UNPACKED_MB", "lots")
    assert main(["--gt", str(gt), "--pred", str(bomb)]) == 2
    assert "KITTI_EVAL_MAX_UNPACKED_MB='lots': expected a number > 0" in capsys.readouterr().err
    monkeypatch.delenv("KITTI_EVAL_MAX_UNPACKED_MB")
    assert main(["--gt", str(gt), "--pred", str(bomb), "--max-frames", "0"]) == 2
    assert main(["--gt", str(gt), "--pred", str(dump(tmp_path / "r.pkl", results())), "--max-frames", "2"]) == 1
    assert "a list of 3 entries, more than the limit of 2 frames" in capsys.readouterr().err
    assert "KITTI_EVAL_MAX_FRAMES" not in os.environ  # the flags hold for the command only


# -------------------------------------------------------------------------------------- text


def test_numpy_strings_that_are_not_text_are_refused(tmp_path: Path) -> None:
    """numpy builds str arrays and scalars from raw bytes without checking; a code point above U+10FFFF makes
    every later use of the string raise SystemError (found by the loader fuzz target)."""
    bad = np.frombuffer(b"C\x00\x00\x00a\x00\x7f\x00r\x00\x00\x00", dtype="<U3")
    entries = results()
    entries[2]["name"] = bad
    entries[2]["score"] = np.float32([0.5])
    for f in ("truncated", "occluded", "alpha", "rotation_y"):
        entries[2][f] = np.zeros(1)
    entries[2].update(bbox=np.zeros((1, 4)), dimensions=np.ones((1, 3)), location=np.zeros((1, 3)))
    with pytest.raises(InputError, match="class names must be text; a name holds a code point above") as err:
        load_detections(dump(tmp_path / "result.pkl", entries))
    assert (err.value.frame, err.value.field) == ("000002", "name")
    # names are checked once for all frames: the first frame holding one is named, whatever the array's layout
    for later in (bad, bad.byteswap().view(">U3")):
        entries = results()
        for k, names in ((1, later), (2, bad)):
            entries[k]["name"] = names
            entries[k]["score"] = np.float32([0.5])
            for f in ("truncated", "occluded", "alpha", "rotation_y"):
                entries[k][f] = np.zeros(1)
            entries[k].update(bbox=np.zeros((1, 4)), dimensions=np.ones((1, 3)), location=np.zeros((1, 3)))
        with pytest.raises(InputError, match="class names must be text") as err:
            load_detections(dump(tmp_path / "result.pkl", entries))
        assert (err.value.frame, err.value.field) == ("000001", "name")
    entries = results()
    entries[1]["frame_id"] = bad.byteswap().view(">U3")[0]  # a non-native byte order, too
    with pytest.raises(InputError, match=r"bad frame id <not text>: it is not text") as err:
        load_detections(dump(tmp_path / "result.pkl", entries))
    assert err.value.frame == "#1"
