"""Benchmark submissions checked before they count: every problem listed, one sentence each, the same from the
library and from ``kitti-eval validate``."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.cli import main
from kitti_eval.errors import UnsafePickleError
from kitti_eval.io.submission import SubmissionRules, validate_submission
from kitti_eval.synth import generate, write_result_dir

FRAMES = tuple(f"{i:06d}" for i in range(12))


@pytest.fixture(scope="module")
def results() -> list[dict]:
    return generate(len(FRAMES), seed=4)[1]


def zipped(folder: Path, dest: Path, *, at_root: bool = True) -> Path:
    with zipfile.ZipFile(dest, "w") as zf:
        for f in sorted(folder.iterdir()):
            zf.write(f, f.name if at_root else f"data/{f.name}")
    return dest


def result_folder(tmp_path: Path, results: list[dict]) -> Path:
    folder = tmp_path / "pred"
    write_result_dir(folder, results)
    return folder


def test_a_complete_submission_is_valid_in_every_form(tmp_path: Path, results: list[dict]) -> None:
    folder = result_folder(tmp_path, results)
    boxes = sum(len(r["name"]) for r in results)
    pkl = tmp_path / "result.pkl"
    pkl.write_bytes(pickle.dumps(results, protocol=4))
    for path in (folder, zipped(folder, tmp_path / "a.zip"), zipped(folder, tmp_path / "b.zip", at_root=False), pkl):
        outcome = validate_submission(path, SubmissionRules(FRAMES))
        assert outcome.ok, (path, outcome.problems)
        assert (outcome.frames, outcome.boxes) == (12, boxes)


def test_every_problem_is_listed_once(tmp_path: Path, results: list[dict]) -> None:
    folder = result_folder(tmp_path, results)
    (folder / "000003.txt").unlink()
    (folder / "000004.txt").unlink()
    (folder / "000777.txt").write_text("")
    (folder / "notes.txt").write_text("hello\n")
    (folder / "5.txt").write_text("")  # frame 000005 a second time
    (folder / "000006.txt").write_text("Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1\n")  # 15 fields
    (folder / "000007.txt").write_text("Bus 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1 0.9\n")
    (folder / "000008.txt").write_text("Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 nan 1.5 20 0.1 0.9\n")
    (folder / "000009.txt").write_text("Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1 high\n")
    line = "Car 0 0 0.1 10 20 110 120 -1 -1 -1 -1000 -1000 -1000 -10 0.5\n"  # 2D-only, sizes -1: valid
    (folder / "000010.txt").write_text(line * 101)
    outcome = validate_submission(folder, SubmissionRules(FRAMES, max_boxes_per_frame=100))
    assert outcome.problems == [
        "5.txt: frame 000005 is also in 000005.txt",
        "2 test frames are missing: 000003, 000004",
        "2 frames are not in the test set: 000777, notes",
        "000006.txt: line 1: expected 16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score), "
        "got 15",
        "000007.txt, box 1: unknown class 'Bus'; a result names one of Car, Van, Truck, Pedestrian, "
        "Person_sitting, Cyclist, Tram, Misc",
        "000008.txt: line 1: x is nan, a non-finite value (every value must be a finite number)",
        "000009.txt: line 1: score is not a number: 'high'",
        "000010.txt: 101 boxes; a frame may hold at most 100",
    ]
    assert not outcome.ok and outcome.more == 0


def test_problems_past_the_limit_are_counted(tmp_path: Path, results: list[dict]) -> None:
    folder = result_folder(tmp_path, results)
    for fid in FRAMES[:5]:
        (folder / f"{fid}.txt").write_text("Bus 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1 0.9\n")
    outcome = validate_submission(folder, SubmissionRules(FRAMES, max_problems=2))
    assert len(outcome.problems) == 2 and outcome.more == 3
    assert outcome.lines()[-1] == "... and 3 more problems"


def test_a_pickle_names_frames_and_classes(tmp_path: Path, results: list[dict]) -> None:
    entries = [dict(r) for r in results[:-1]]  # the last test frame missing
    entries[0]["name"] = np.array(["Bus"] * len(entries[0]["name"]))
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps(entries, protocol=4))
    outcome = validate_submission(path, SubmissionRules(FRAMES))
    assert outcome.problems[0] == "1 test frames are missing: 000011"
    assert outcome.problems[1].startswith("frame 000000, box 1: unknown class 'Bus'")
    entries[1]["location"] = np.full((len(entries[1]["name"]), 3), np.inf)
    path.write_bytes(pickle.dumps(entries, protocol=4))
    (problem,) = validate_submission(path, SubmissionRules(FRAMES)).problems
    assert "frame 000001, field 'location': non-finite value" in problem


def test_an_unsafe_pickle_is_refused_not_listed(tmp_path: Path) -> None:
    import os

    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps(os.system, protocol=4))
    with pytest.raises(UnsafePickleError):
        validate_submission(path, SubmissionRules(FRAMES))


def test_kitti_eval_validate(tmp_path: Path, results: list[dict], capsys: pytest.CaptureFixture[str]) -> None:
    folder = result_folder(tmp_path, results)
    ids = tmp_path / "test.txt"
    ids.write_text("\n".join(FRAMES) + "\n")
    archive = zipped(folder, tmp_path / "submission.zip")
    assert main(["validate", str(archive), "--frames", str(ids)]) == 0
    boxes = sum(len(r["name"]) for r in results)
    assert capsys.readouterr().out == f"{archive}: valid: 12 frames, {boxes} boxes\n"
    (folder / "000000.txt").unlink()
    archive = zipped(folder, tmp_path / "bad.zip")
    assert main(["validate", str(archive), "--frames", str(ids), "--max-boxes", "1"]) == 1
    err = capsys.readouterr().err.splitlines()
    want = validate_submission(archive, SubmissionRules(FRAMES, max_boxes_per_frame=1)).lines()
    assert err == want and err[0] == "1 test frames are missing: 000000"
    assert main(["validate", str(archive), "--frames", str(ids), "--max-boxes", "0"]) == 2
    assert main(["validate", str(tmp_path / "absent.zip"), "--frames", str(ids)]) == 1
