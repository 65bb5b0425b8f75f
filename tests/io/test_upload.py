"""One file as a user sends it, read in one call (:func:`kitti_eval.io.upload.read_upload`): identified by its
content, unpacked, loaded and, for a submission, checked, every refusal a class of the library's one tree."""

from __future__ import annotations

import io
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.errors import (
    ArchiveError,
    InputError,
    InvalidSubmissionError,
    UnknownFormatError,
    UnsafePickleError,
)
from kitti_eval.io.loaders import load_detections
from kitti_eval.io.submission import SubmissionRules, validate_submission
from kitti_eval.io.upload import UploadLimits, read_upload
from kitti_eval.synth import generate, write_result_dir

FRAMES = tuple(f"{i:06d}" for i in range(8))


@pytest.fixture(scope="module")
def results() -> list[dict]:
    return generate(len(FRAMES), seed=11)[1]


def _zip(folder: Path, *, extra: dict[str, str] | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for f in sorted(folder.iterdir()):
            zf.write(f, f"label/{f.name}")
        for name, text in (extra or {}).items():
            zf.writestr(name, text)
    return buffer.getvalue()


def _read(data: bytes, scratch: Path, **kw):
    return read_upload(io.BytesIO(data), "detections", source="upload.bin", scratch=scratch, **kw)


def test_a_pickle_and_a_zip_of_the_same_results_read_as_the_files_do(tmp_path: Path, results: list[dict]) -> None:
    folder = tmp_path / "pred"
    write_result_dir(folder, results)
    pkl = pickle.dumps(results, protocol=4)
    from_pickle = _read(pkl, tmp_path / "s1")
    from_zip = _read(_zip(folder), tmp_path / "s2")
    assert (from_pickle.kind, from_pickle.folder) == ("pickle", None)
    assert from_zip.kind == "zip" and from_zip.folder is not None and from_zip.folder.is_relative_to(tmp_path / "s2")
    for read, path in ((from_pickle, None), (from_zip, folder)):
        assert read.annotations.source == "upload.bin"
        assert read.annotations.frame_ids == FRAMES
        if path is not None:  # the same numbers as the folder read by the path's loader (bit for bit: one parser)
            expected = load_detections(path)
            for column in ("score", "bbox", "dimensions", "location", "rotation_y"):
                assert np.array_equal(getattr(read.annotations, column), getattr(expected, column)), column
    assert np.allclose(from_pickle.annotations.score, from_zip.annotations.score, atol=1e-4)  # txt keeps 4 digits
    assert from_pickle.validation is None


def test_a_submission_is_checked_with_the_validators_sentences(tmp_path: Path, results: list[dict]) -> None:
    rules = SubmissionRules(FRAMES)
    entries = [dict(r) for r in results[:-1]]  # the last test frame missing
    entries[0]["name"] = np.array(["Bus"] * len(entries[0]["name"]))
    data = pickle.dumps(entries, protocol=4)
    with pytest.raises(InvalidSubmissionError) as refused:
        _read(data, tmp_path / "s", rules=rules)
    path = tmp_path / "result.pkl"
    path.write_bytes(data)
    assert refused.value.lines() == validate_submission(path, rules).lines()
    assert refused.value.problems[0] == "1 test frames are missing: 000007"
    assert refused.value.problems[1].startswith("frame 000000, box 1: unknown class 'Bus'")
    valid = _read(pickle.dumps(results, protocol=4), tmp_path / "v", rules=rules)
    assert valid.validation is not None and valid.validation.ok
    assert (valid.validation.frames, valid.validation.boxes) == (len(FRAMES), sum(len(r["name"]) for r in results))


def test_an_archive_that_breaks_the_rules_names_its_members(tmp_path: Path, results: list[dict]) -> None:
    folder = tmp_path / "pred"
    write_result_dir(folder, results)
    (folder / "000003.txt").write_text("Car 0 0 0.1 10 20 110 120 1.5 1.6 3.9 1.0 1.5 20 0.1\n")  # no score
    with pytest.raises(InvalidSubmissionError) as refused:
        _read(_zip(folder), tmp_path / "s", rules=SubmissionRules(FRAMES))
    assert refused.value.problems == [
        "000003.txt: line 1: expected 16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score), "
        "got 15"
    ]
    # without rules the same file is refused by the loader, naming the upload and the member, not the scratch path
    with pytest.raises(InputError) as unreadable:
        _read(_zip(folder), tmp_path / "t")
    assert type(unreadable.value) is InputError
    assert unreadable.value.source == "upload.bin:label/000003.txt" and str(tmp_path) not in str(unreadable.value)


def test_every_refusal_is_a_class_of_the_one_tree(tmp_path: Path, results: list[dict]) -> None:
    rules = SubmissionRules(FRAMES)
    folder = tmp_path / "pred"
    write_result_dir(folder, results)
    escaping = _zip(folder, extra={"../evil.txt": "Car 0 0 0 0 0 1 1 1 1 1 0 0 0 0 1\n"})
    with pytest.raises(ArchiveError) as archive:
        _read(escaping, tmp_path / "a", rules=rules)  # the archive itself: refused, not one of the problems
    assert archive.value.source == "upload.bin" and "evil.txt" in archive.value.message
    too_many = UploadLimits(max_members=3, members_setting="MEMBERS")
    with pytest.raises(ArchiveError, match=r"more than 3 members \(MEMBERS\)"):
        _read(_zip(folder), tmp_path / "b", limits=too_many)

    class Evil:
        def __reduce__(self):
            return (print, ("owned",))

    with pytest.raises(UnsafePickleError):
        _read(pickle.dumps([Evil()]), tmp_path / "c", rules=rules)
    with pytest.raises(UnknownFormatError):
        _read(b"Car 0 0 0 0 0 1 1 1 1 1 0 0 0 0 1\n", tmp_path / "d", rules=rules)
    with pytest.raises(InvalidSubmissionError) as cut:  # a pickle that cannot be read: a problem, as validate says
        _read(pickle.dumps(results, protocol=4)[:-200], tmp_path / "e", rules=rules)
    assert len(cut.value.problems) == 1 and cut.value.problems[0].startswith("upload.bin: ")
    for error in (ArchiveError, InvalidSubmissionError, UnsafePickleError, UnknownFormatError):
        assert issubclass(error, InputError)


def test_the_frames_limit_refuses_a_pickle_before_it_is_built(tmp_path: Path, results: list[dict]) -> None:
    with pytest.raises(InputError, match="frames") as refused:
        _read(pickle.dumps(results, protocol=4), tmp_path / "s", limits=UploadLimits(max_frames=5))
    assert refused.value.source == "upload.bin"
