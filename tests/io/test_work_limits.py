"""The work limits of one input: boxes per frame and boxes in all, refused as the frames are read (every format,
the frame, the count and the limit named), before anything that grows with them."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path

import numpy as np
import pytest
from test_loaders import DET, GT, dump, infos, results, write_txt

from kitti_eval.core.frames import Annotations, BoxLimits
from kitti_eval.errors import InputError, WorkLimitError
from kitti_eval.io import limits
from kitti_eval.io.loaders import annotations_from_object, load_detections, load_ground_truth, load_pair
from kitti_eval.io.upload import read_upload

CAR = DET["000000"][0]
LABEL = GT["000000"][0]


@pytest.fixture(autouse=True)
def _no_limits_from_outside(monkeypatch: pytest.MonkeyPatch) -> None:
    for env in (limits.MAX_FRAME_BOXES_ENV, limits.MAX_BOXES_ENV):
        monkeypatch.delenv(env, raising=False)


def _crowded(counts: dict[str, int], box: tuple = CAR) -> dict[str, list[tuple]]:
    return {fid: [box] * n for fid, n in counts.items()}


def test_the_defaults_and_the_settings() -> None:
    assert limits.box_limits() == BoxLimits(10_000, 5_000_000)
    assert limits.box_limits(per_frame=3).per_frame == 3


def test_a_setting_that_is_not_a_number_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    from kitti_eval.errors import ConfigError

    monkeypatch.setenv(limits.MAX_FRAME_BOXES_ENV, "many")
    with pytest.raises(ConfigError, match="KITTI_EVAL_MAX_BOXES_PER_FRAME='many': expected a number > 0"):
        limits.box_limits()


def test_a_txt_frame_past_the_limit_is_refused_before_the_next_file_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = write_txt(tmp_path / "pred", _crowded({"000000": 3, "000001": 5, "000002": 1}), with_score=True)
    (folder / "000003.txt").write_text("not a KITTI line\n")  # never read: the refusal comes before it
    monkeypatch.setenv(limits.MAX_FRAME_BOXES_ENV, "4")
    with pytest.raises(WorkLimitError, match=r"5 boxes in one frame, more than the limit of 4 \(KITTI_EVAL_MAX_BOX"):
        load_detections(folder)
    try:
        load_detections(folder)
    except WorkLimitError as e:
        assert e.frame == "000001"
        assert e.source == str(folder / "000001.txt")


def test_a_txt_folder_past_the_limit_in_all_is_refused_at_the_frame_that_passes_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = write_txt(tmp_path / "gt", _crowded({"000000": 3, "000001": 3, "000002": 3}, LABEL), with_score=False)
    monkeypatch.setenv(limits.MAX_BOXES_ENV, "8")
    with pytest.raises(WorkLimitError, match=r"9 boxes up to this frame, more than the limit of 8 in one input") as e:
        load_ground_truth(folder)
    assert e.value.frame == "000002"
    monkeypatch.setenv(limits.MAX_BOXES_ENV, "9")
    assert load_ground_truth(folder).num_boxes == 9


def test_pickles_are_held_to_the_same_limits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    crowded = _crowded({"000000": 1, "000001": 6, "000002": 2})
    pred = dump(tmp_path / "result.pkl", results(crowded))  # OpenPCDet's layout: read from its bytes
    gt = dump(tmp_path / "infos.pkl", infos(_crowded({"000000": 1, "000001": 1, "000002": 7}, LABEL)))
    assert load_detections(pred).num_boxes == 9
    monkeypatch.setenv(limits.MAX_FRAME_BOXES_ENV, "5")
    with pytest.raises(WorkLimitError, match="6 boxes in one frame, more than the limit of 5") as e:
        load_detections(pred)
    assert (e.value.frame, e.value.source) == ("000001", str(pred))
    with pytest.raises(WorkLimitError, match="7 boxes in one frame, more than the limit of 5") as e:
        load_pair(gt, pred)
    assert e.value.frame == "000002"
    by_frame = dict(zip(crowded, results(crowded), strict=True))  # another layout: frame by frame
    with pytest.raises(WorkLimitError, match="6 boxes in one frame") as e:
        annotations_from_object(by_frame, "detections", source="d")
    assert e.value.frame == "000001"


class _Poison(dict):  # type: ignore[type-arg]
    """A frame that fails the test if its fields are read."""

    def __getitem__(self, key: object) -> object:
        raise AssertionError("a frame after the refused one was converted")

    get = __getitem__  # type: ignore[assignment]


def test_frames_given_one_by_one_stop_at_the_first_past_the_limit() -> None:
    frames = [(f"{i:06d}", r) for i, r in enumerate(results(_crowded({"a": 2, "b": 3})))]
    frames.append(("000009", _Poison()))
    with pytest.raises(WorkLimitError, match="3 boxes in one frame, more than the limit of 2") as e:
        Annotations.from_frames("detections", "d", iter(frames), box_limits=BoxLimits(per_frame=2))
    assert e.value.frame == "000001"
    with pytest.raises(WorkLimitError, match="5 boxes up to this frame, more than the limit of 4 in one input"):
        Annotations.from_frames("detections", "d", frames[:2], box_limits=BoxLimits(per_input=4))
    assert Annotations.from_frames("detections", "d", frames[:2], box_limits=BoxLimits(3, 5)).num_boxes == 5


def test_an_archive_of_one_line_repeated_is_refused_at_its_first_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Many boxes in few bytes: a tar.gz of frames of one line repeated, inside every byte limit."""
    line = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59 0.95\n"
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for i in range(4):
            data = (line * 3000).encode()
            info = tarfile.TarInfo(f"pred/{i:06d}.txt")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    monkeypatch.setenv(limits.MAX_FRAME_BOXES_ENV, "2000")
    buf.seek(0)
    with pytest.raises(WorkLimitError, match="3000 boxes in one frame, more than the limit of 2000") as e:
        read_upload(buf, "detections", source="pred.tar.gz", scratch=tmp_path)
    assert (e.value.source, e.value.frame) == ("pred.tar.gz:pred/000000.txt", "000000")
    assert isinstance(e.value, InputError)  # the CLI's exit 1, the service's 4xx
    monkeypatch.delenv(limits.MAX_FRAME_BOXES_ENV)
    buf.seek(0)
    loaded = read_upload(buf, "detections", source="pred.tar.gz", scratch=tmp_path / "again")
    assert np.array_equal(loaded.annotations.counts, [3000] * 4)


def test_the_cli_refuses_past_its_flags_with_exit_code_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    from kitti_eval.cli import main

    for env in ("KITTI_EVAL_MAX_FRAME_PAIRS", "KITTI_EVAL_MAX_PAIRS"):
        monkeypatch.delenv(env, raising=False)
    gt = write_txt(tmp_path / "gt", _crowded({"000000": 3, "000001": 2}, LABEL), with_score=False)
    pred = write_txt(tmp_path / "pred", _crowded({"000000": 4, "000001": 1}), with_score=True)
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-boxes-per-frame", "3"]) == 1
    err = capsys.readouterr().err
    # a limit set by a flag is named by its flag, one set by the environment by its variable
    assert "frame 000000: 4 boxes in one frame, more than the limit of 3 (--max-boxes-per-frame)" in err
    assert "Traceback" not in err
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-frame-pairs", "11"]) == 1
    assert "12 overlaps in one frame, more than the limit of 11 (--max-frame-pairs)" in capsys.readouterr().err
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-pairs", "13"]) == 1
    err = capsys.readouterr().err
    assert (
        "14 detection x ground-truth overlaps in all, more than the limit of 13 for one evaluation (--max-pairs)" in err
    )
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-boxes", "4"]) == 1
    assert "5 boxes up to this frame, more than the limit of 4 in one input (--max-boxes)" in capsys.readouterr().err
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-frames", "1"]) == 1
    assert "more than the limit of 1 frames (--max-frames)" in capsys.readouterr().err
    monkeypatch.setenv("KITTI_EVAL_MAX_BOXES_PER_FRAME", "3")
    assert main(["--gt", str(gt), "--pred", str(pred)]) == 1
    assert "more than the limit of 3 (KITTI_EVAL_MAX_BOXES_PER_FRAME)" in capsys.readouterr().err
    monkeypatch.delenv("KITTI_EVAL_MAX_BOXES_PER_FRAME")
    assert main(["--gt", str(gt), "--pred", str(pred), "--max-pairs", "14", "--max-boxes-per-frame", "4"]) == 0
    assert "KITTI_EVAL_MAX_PAIRS" not in os.environ  # the flags hold for the command only
