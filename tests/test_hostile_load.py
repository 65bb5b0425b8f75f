"""Bad input refused early, naming the frame and field: shapes before arithmetic, boxes without volume,
frame-count claims, byte limits of the CLI, archive members charged before they are written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_loaders import DET, GT, dump, infos, results, write_txt

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


# ------------------------------------------------------------------------------- boxes without volume


def _with_dims(frames: dict, fid: str, k: int, dims: tuple[float, float, float]) -> dict:
    out = {f: list(objs) for f, objs in frames.items()}
    o = list(out[fid][k])
    o[5] = dims
    out[fid][k] = tuple(o)
    return out


@pytest.mark.parametrize("dims", [(0.0, 1.5, 1.6), (3.9, -0.5, 1.6), (3.9, 1.5, -2.0), (-1.0, -1.0, -1.0)])
def test_ground_truth_boxes_need_a_volume(tmp_path: Path, dims: tuple[float, float, float]) -> None:
    frames = _with_dims(GT, "000000", 1, dims)
    for load in (
        lambda: load_ground_truth(write_txt(tmp_path / "label_2", frames, with_score=False)),
        lambda: annotations_from_object(infos(frames), "ground_truth", source="infos"),
    ):
        with pytest.raises(InputError, match=r"box 1 \(Car\) has dimensions .* l, h and w must be > 0") as err:
            load()
        assert (err.value.frame, err.value.field) == ("000000", "dimensions")


def test_dontcare_regions_keep_their_minus_one_dimensions() -> None:
    gt = annotations_from_object(infos(), "ground_truth", source="infos")  # DontCare: -1 -1 -1
    assert (gt.dimensions[gt.name == "DontCare"] == -1).all()


@pytest.mark.parametrize("dims", [(0.0, 1.5, 1.6), (3.9, -0.5, 1.6), (3.9, 1.5, 0.0), (-2.0, -1.0, -1.0)])
def test_detections_need_a_volume_or_the_not_given_marker(tmp_path: Path, dims: tuple[float, float, float]) -> None:
    frames = _with_dims(DET, "000000", 1, dims)
    for load in (
        lambda: load_detections(write_txt(tmp_path / "pred", frames, with_score=True)),
        lambda: load_detections(dump(tmp_path / "result.pkl", results(frames))),
    ):
        with pytest.raises(InputError, match=r"box 1 \(Pedestrian\) has dimensions .* > 0, or -1") as err:
            load()
        assert (err.value.frame, err.value.field) == ("000000", "dimensions")


@pytest.mark.parametrize("dims", [(3.9, -1.0, 1.6), (-1.0, -1.0, -1.0)])
def test_detections_may_mark_sizes_as_not_given(tmp_path: Path, dims: tuple[float, float, float]) -> None:
    """KITTI's -1 means 'not given': BEV-only (h) or 2D-only (all three) results, as the devkit reads them."""
    dt = load_detections(write_txt(tmp_path / "pred", _with_dims(DET, "000000", 1, dims), with_score=True))
    np.testing.assert_array_equal(dt.dimensions[1], dims)


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
