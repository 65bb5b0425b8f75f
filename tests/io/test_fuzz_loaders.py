"""A fuzz target over the loaders: valid pickles, txt folders and archives, mutated by hypothesis.

Whatever the bytes, a loader either returns validated annotations or raises one of the project's own
errors (never another exception, never a crash). A few seconds in the suite;
``KITTI_EVAL_FUZZ_EXAMPLES=20000 pytest tests/io/test_fuzz_loaders.py`` runs longer.
"""

from __future__ import annotations

import io
import os
import pickle
import tarfile
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_loaders import DET, GT, _txt_line, infos, results

from kitti_eval.core.frames import Annotations
from kitti_eval.errors import KittiEvalError
from kitti_eval.io.archives import ArchiveLimits, extract_txt_folder
from kitti_eval.io.loaders import annotations_from_object, load_kitti_txt_dir
from kitti_eval.io.safe_pickle import load_pickle

EXAMPLES = int(os.environ.get("KITTI_EVAL_FUZZ_EXAMPLES", "120"))
FUZZ = settings(
    max_examples=EXAMPLES, deadline=None, derandomize=EXAMPLES <= 120, suppress_health_check=list(HealthCheck)
)
LIMITS = ArchiveLimits(max_members=50, max_unpacked_bytes=1 << 20)


def _txt(frames: dict, with_score: bool) -> dict[str, bytes]:
    return {
        f"{fid}.txt": "".join(_txt_line(o, with_score) + "\n" for o in objs).encode() for fid, objs in frames.items()
    }


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(f"pred/{name}", data)
    return buf.getvalue()


def _tar(files: dict[str, bytes], mode: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for name, data in files.items():
            info = tarfile.TarInfo(f"pred/{name}")
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


SEEDS = {
    "result.pkl": pickle.dumps(results(), protocol=4),
    "result-p2.pkl": pickle.dumps(results(), protocol=2),
    "infos.pkl": pickle.dumps(infos(), protocol=5),
    "pred.zip": _zip(_txt(DET, True)),
    "pred.tar": _tar(_txt(DET, True), "w"),
    "pred.tar.gz": _tar(_txt(DET, True), "w:gz"),
}
TXT_SEEDS = {"gt": _txt(GT, False), "pred": _txt(DET, True)}


@st.composite
def mutated(draw: st.DrawFn, seed: bytes) -> bytes:
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 6))):
        if not data:
            break
        k = draw(st.integers(0, len(data) - 1))
        op = draw(st.sampled_from(["flip", "set", "delete", "insert", "splice", "cut"]))
        if op == "flip":
            data[k] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            data[k] = draw(st.sampled_from([0, 1, 0x7F, 0x80, 0xFF, ord("-"), ord("9"), ord("\n"), ord(".")]))
        elif op == "delete":
            del data[k : k + draw(st.integers(1, 16))]
        elif op == "insert":
            data[k:k] = draw(st.binary(min_size=1, max_size=16))
        elif op == "splice":
            j = draw(st.integers(0, len(data) - 1))
            data[k:k] = data[j : j + draw(st.integers(1, 64))]
        else:
            del data[k:]
    return bytes(data)


def _check(annos: Annotations) -> None:
    n = annos.num_boxes
    assert annos.offsets[-1] == n and len(annos.name) == n
    for f in ("bbox", "dimensions", "location", "rotation_y", "score", "alpha"):
        arr = getattr(annos, f)
        assert len(arr) == n and arr.dtype == np.float64 and np.isfinite(arr).all(), f


def _load_any(name: str, data: bytes) -> None:
    kind = "ground_truth" if name.startswith("infos") else "detections"
    if name.endswith(".pkl"):
        obj = load_pickle(io.BytesIO(data), source=name, max_bytes=1 << 20)
        _check(annotations_from_object(obj, kind, source=name))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder, _ = extract_txt_folder(
            io.BytesIO(data), "zip" if name.endswith("zip") else "tar", Path(tmp), LIMITS, name
        )
        _check(load_kitti_txt_dir(folder, kind))


@pytest.mark.parametrize("name", list(SEEDS))
def test_fuzzed_inputs_load_or_raise_the_projects_errors(name: str) -> None:
    _load_any(name, SEEDS[name])  # the seed itself loads

    @FUZZ
    @given(mutated(SEEDS[name]))
    def run(data: bytes) -> None:
        try:
            _load_any(name, data)
        except KittiEvalError:
            pass

    run()


@pytest.mark.parametrize("kind", ["gt", "pred"])
def test_fuzzed_txt_files_load_or_raise_the_projects_errors(kind: str) -> None:
    files = TXT_SEEDS[kind]

    @FUZZ
    @given(st.sampled_from(sorted(files)).flatmap(lambda f: st.tuples(st.just(f), mutated(files[f]))))
    def run(case: tuple[str, bytes]) -> None:
        target, data = case
        with tempfile.TemporaryDirectory() as tmp:
            for f, content in files.items():
                Path(tmp, f).write_bytes(data if f == target else content)
            try:
                _check(load_kitti_txt_dir(tmp, "ground_truth" if kind == "gt" else "detections"))
            except KittiEvalError:
                pass

    run()


@pytest.mark.parametrize("kind", ["zip", "tar"])
@pytest.mark.parametrize(
    ("code", "passes_through"), [(28, True), (122, True), (13, False)], ids=["ENOSPC", "EDQUOT", "EACCES"]
)
def test_a_full_disk_while_unpacking_is_not_the_archives_fault(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str, code: int, passes_through: bool
) -> None:
    """Out of space (or quota) while writing the txt files is raised as the OSError it is, for the caller to
    report as the machine's failure; any other write failure stays a refusal of the archive."""
    import errno

    from kitti_eval.io import archives

    assert (errno.ENOSPC, errno.EDQUOT, errno.EACCES) == (28, 122, 13)
    files = {"pred/000001.txt": b"Car -1 -1 0 0 0 10 10 1 1 1 1 1 1 0 0.9\n"}
    buf = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buf, "w") as zf:
            for name, data in files.items():
                zf.writestr(name, data)
    else:
        with tarfile.open(fileobj=buf, mode="w") as tf:
            for name, data in files.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))

    class Full(io.BytesIO):
        def write(self, data: object) -> int:
            raise OSError(code, os.strerror(code))

    monkeypatch.setattr(archives, "open", lambda *a, **k: Full(), raising=False)
    with pytest.raises((OSError, KittiEvalError)) as caught:
        extract_txt_folder(buf, kind, tmp_path, LIMITS, "pred.archive")  # type: ignore[arg-type]
    if passes_through:
        assert isinstance(caught.value, OSError) and caught.value.errno == code
    else:
        assert isinstance(caught.value, KittiEvalError) and "pred.archive" in str(caught.value)
