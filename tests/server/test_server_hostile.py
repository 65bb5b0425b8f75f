"""Hostile pickles and malformed uploads: each gets a 4xx with a clear message, nothing runs, the server goes on.

Every hostile pickle tries to create a canary file (or import a module that would); the test proves the
file is not there after the request. Every case is followed by a valid upload that must succeed.
"""

from __future__ import annotations

import copy
import io
import os
import pickle
import sys
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from server_helpers import (
    ADMIN,
    GOLDEN,
    assert_error,
    golden_bytes,
    golden_txt,
    register,
    tar_of,
    upload,
    zip_of,
)
from server_payloads import CANARY_MOD, Reducer, hostile_pickles

from kitti_eval.io.safe_pickle import load_pickle
from kitti_eval.synth import generate

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # pragma: no cover - numpy < 2
    from numpy.core.multiarray import _reconstruct


@pytest.fixture(scope="module")
def canary_env(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    canary = root / "CANARY"
    (root / f"{CANARY_MOD}.py").write_text(f"open({str(canary)!r}, 'w').close()\ndef run():\n    pass\n")
    evil_npy = root / "evil.npy"
    np.save(evil_npy, np.array([Reducer(os.system, (f"touch {canary}",))], dtype=object), allow_pickle=True)
    sys.path.insert(0, str(root))
    try:
        yield canary, evil_npy
    finally:
        sys.path.remove(str(root))


@pytest.fixture(scope="module")
def client(service_client):
    with service_client(max_upload_mb=2, max_unpacked_mb=4, max_archive_members=200) as c:
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        yield c


def still_serving(client) -> None:
    r = upload(client, golden_bytes("result.pkl"), gt="small")
    assert r.status_code == 201, r.text


HOSTILE = list(hostile_pickles(Path("/nonexistent/CANARY"), Path("/nonexistent/evil.npy")))


def test_there_are_enough_hostile_pickles() -> None:
    assert len(HOSTILE) >= 20


@pytest.mark.parametrize("name", HOSTILE)
def test_hostile_pickle_is_refused_and_nothing_runs(client, canary_env, name) -> None:
    canary, evil_npy = canary_env
    data = hostile_pickles(canary, evil_npy)[name]
    err = assert_error(upload(client, data, "result.pkl", gt="small"), 422)
    assert err["code"] in ("unsafe_pickle", "invalid_input"), err
    assert "result.pkl" in err["message"]
    assert not canary.exists(), name
    assert CANARY_MOD not in sys.modules
    still_serving(client)


@pytest.mark.parametrize(
    "name",
    [
        "os.system, protocol 2",
        "builtins.getattr(__import__('os'), 'system') chain",
        "GLOBAL of a module that writes the canary on import",
        "gzip-wrapped os.system",
    ],
)
def test_hostile_ground_truth_is_refused_too(client, canary_env, name) -> None:
    canary, evil_npy = canary_env
    data = hostile_pickles(canary, evil_npy)[name]
    err = assert_error(register(client, "evil", data, "kitti_infos_val.pkl"), 422)
    assert err["code"] == "unsafe_pickle"
    err = assert_error(upload(client, golden_bytes("result.pkl"), gt=None, gt_file=("infos.pkl", data)), 422)
    assert err["code"] == "unsafe_pickle"
    assert not canary.exists()
    assert client.get("/v1/ground-truths/evil").status_code == 404
    still_serving(client)


# ------------------------------------------------------------------------------------------- malformed


def _golden_results() -> list[dict]:
    return load_pickle(GOLDEN / "result.pkl", source="golden")  # type: ignore[return-value]


def results_with(change: Callable[[list[dict]], object]) -> bytes:
    results = copy.deepcopy(_golden_results())
    change(results)
    return pickle.dumps(results, protocol=4)


def _set(i: int, key: str, value: object) -> Callable[[list[dict]], object]:
    return lambda r: r[i].__setitem__(key, value)


def _tar_special(kind: bytes, name: str = "pred/000000.txt", linkname: str = "") -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        info = tarfile.TarInfo(name)
        info.type = kind
        info.linkname = linkname
        if kind == tarfile.CHRTYPE:
            info.devmajor, info.devminor = 1, 3
        tf.addfile(info)
    return buf.getvalue()


def _zip_symlink() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        info = zipfile.ZipInfo("pred/000000.txt")
        info.create_system = 3
        info.external_attr = 0o120777 << 16
        zf.writestr(info, "/etc/passwd")
    return buf.getvalue()


def _zip_bomb() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        with zf.open("pred/000000.txt", "w", force_zip64=True) as member:
            chunk = b"\0" * (1 << 20)
            for _ in range(64):
                member.write(chunk)
    return buf.getvalue()


def _tar_bomb() -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        info = tarfile.TarInfo("pred/000000.txt")
        info.size = 64 << 20
        tf.addfile(info, io.BytesIO(b"\0" * info.size))
    return buf.getvalue()


def _tar_negative_size() -> bytes:
    data = bytearray(tar_of({"pred/000000.txt": b""}, compression=""))
    size_field = b"\xff" * 12  # base-256, all ones: -1
    data[124:136] = size_field
    chksum = sum(data[:148]) + 8 * 32 + sum(data[156:512])
    data[148:156] = b"%06o\0 " % chksum
    return bytes(data)


def _pred_files() -> dict[str, bytes]:
    return golden_txt("pred.tar.gz")


def _txt_with(frame: str, text: bytes) -> bytes:
    files = _pred_files()
    files[f"pred/{frame}.txt"] = text
    return zip_of(files)


def _good_line() -> bytes:
    return _pred_files()["pred/000000.txt"].splitlines()[0]


def _zip_duplicate() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("pred/000000.txt", _good_line())
        with pytest.warns(UserWarning):
            zf.writestr("pred/000000.txt", _good_line())
    return buf.getvalue()


def _infos_dict() -> bytes:
    infos = load_pickle(GOLDEN / "kitti_infos_val.pkl", source="golden")
    return pickle.dumps(infos, protocol=4)


def malformed_cases() -> dict[str, tuple[str, Callable[[], bytes], tuple[str, ...]]]:
    """name -> (upload file name, bytes factory, words the message must contain)."""
    good = lambda: golden_bytes("result.pkl")  # noqa: E731
    return {
        "truncated pickle": ("result.pkl", lambda: good()[: len(good()) // 2], ("not a readable pickle",)),
        "empty file": ("result.pkl", lambda: b"", ("empty",)),
        "a pickled int": ("result.pkl", lambda: pickle.dumps(42), ("expected",)),
        "a list of strings": ("result.pkl", lambda: pickle.dumps(["a", "b"]), ("entry #0", "expected a dict")),
        "an empty list": ("result.pkl", lambda: pickle.dumps([]), ("no frames",)),
        "missing key score": (
            "result.pkl",
            lambda: results_with(lambda r: r[2].pop("score")),
            ("frame 000002", "score", "missing"),
        ),
        "missing frame_id": ("result.pkl", lambda: results_with(lambda r: r[2].pop("frame_id")), ("frame_id",)),
        "wrong type: score as strings": (
            "result.pkl",
            lambda: results_with(_set(2, "score", np.array(["high"] * 14))),
            ("frame 000002", "score"),
        ),
        "wrong type: frame_id a float": (
            "result.pkl",
            lambda: results_with(_set(3, "frame_id", 3.5)),
            ("frame_id", "float"),
        ),
        "NaN location": (
            "result.pkl",
            lambda: results_with(lambda r: r[1]["location"].__setitem__((0, 0), np.nan)),
            ("frame 000001", "location", "non-finite"),
        ),
        "inf dimensions": (
            "result.pkl",
            lambda: results_with(lambda r: r[1]["dimensions"].__setitem__((0, 1), np.inf)),
            ("frame 000001", "dimensions", "non-finite"),
        ),
        "negative array size in a pickle": (
            "result.pkl",
            lambda: pickle.dumps(
                Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, (-5,), np.dtype("f8"), False, b"")), protocol=2
            ),
            ("result.pkl",),
        ),
        "negative member size in a tar": ("pred.tar", _tar_negative_size, ("negative size",)),
        "bbox of the wrong shape": (
            "result.pkl",
            lambda: results_with(lambda r: r[2].__setitem__("bbox", r[2]["bbox"][:, :3])),
            ("frame 000002", "bbox", "shape"),
        ),
        "field lengths disagree": (
            "result.pkl",
            lambda: results_with(lambda r: r[2].__setitem__("name", np.append(r[2]["name"], "Car"))),
            ("frame 000002", "shape"),
        ),
        "a frame listed twice": (
            "result.pkl",
            lambda: results_with(_set(3, "frame_id", "000002")),
            ("000002", "twice"),
        ),
        "a frame the ground truth does not have": (
            "result.pkl",
            lambda: results_with(_set(4, "frame_id", "999999")),
            ("999999",),
        ),
        "the infos file uploaded as predictions": ("kitti_infos_val.pkl", _infos_dict, ("infos",)),
        "an mmdetection3d 1.x info dict": (
            "result.pkl",
            lambda: pickle.dumps({"metainfo": {}, "data_list": []}),
            ("mmdetection3d",),
        ),
        "gzip magic then garbage": ("result.pkl.gz", lambda: b"\x1f\x8b\x08\x00garbage-not-deflate" * 3, ("gzip",)),
        "zip with ../": ("pred.zip", lambda: zip_of({"../../etc/000000.txt": _good_line()}), ("outside",)),
        "zip with an absolute path": ("pred.zip", lambda: zip_of({"/etc/000000.txt": _good_line()}), ("absolute",)),
        "zip with a windows drive path": ("pred.zip", lambda: zip_of({"C:/x/000000.txt": _good_line()}), ("absolute",)),
        "zip with a symlink member": ("pred.zip", _zip_symlink, ("symbolic link",)),
        "zip bomb": ("pred.zip", _zip_bomb, ("unpacks to more than",)),
        "zip with too many members": (
            "pred.zip",
            lambda: zip_of({f"pred/{i:06d}.txt": b"" for i in range(500)}),
            ("more than 200 members",),
        ),
        "zip with a duplicate member": ("pred.zip", _zip_duplicate, ("listed twice",)),
        "zip with a control character in a name": (
            "pred.zip",
            lambda: zip_of({"pred/0\x1b[2J.txt": b""}),
            ("control characters",),
        ),
        "corrupt zip": ("pred.zip", lambda: b"PK\x03\x04" + b"\x00garbage" * 10, ("not a readable zip",)),
        "zip without txt files (a torch.save file?)": (
            "model.pt",
            lambda: zip_of({"archive/data.pkl": b"\x80\x02."}),
            ("no .txt files", "torch.save"),
        ),
        "zip with txt files in two folders": (
            "pred.zip",
            lambda: zip_of({"a/000000.txt": _good_line(), "b/000001.txt": _good_line()}),
            ("several folders",),
        ),
        "tar with a character device": ("pred.tar.gz", lambda: _tar_special(tarfile.CHRTYPE), ("device",)),
        "tar with a fifo": ("pred.tar.gz", lambda: _tar_special(tarfile.FIFOTYPE), ("device or fifo",)),
        "tar with a symlink": ("pred.tar.gz", lambda: _tar_special(tarfile.SYMTYPE, linkname="/etc/passwd"), ("link",)),
        "tar with a hard link": (
            "pred.tar.gz",
            lambda: _tar_special(tarfile.LNKTYPE, linkname="/etc/passwd"),
            ("link",),
        ),
        "tar with ../": ("pred.tar.gz", lambda: tar_of({"../000000.txt": _good_line()}), ("outside",)),
        "tar with an absolute path": ("pred.tar.gz", lambda: tar_of({"/etc/000000.txt": _good_line()}), ("absolute",)),
        "tar bomb": ("pred.tar.gz", _tar_bomb, ("unpacks to more than",)),
        "truncated tar.gz": ("pred.tar.gz", lambda: golden_bytes("pred.tar.gz")[:5000], ("truncated",)),
        "bzip2 data that is not a tar": ("pred.tar.bz2", lambda: __import__("bz2").compress(b"hello" * 100), ("tar",)),
        "txt line with the wrong number of fields": (
            "pred.zip",
            lambda: _txt_with("000003", b"Car 0 0 0 1 2 3\n"),
            ("000003", "16 fields"),
        ),
        "txt with a field that is not a number": (
            "pred.zip",
            lambda: _txt_with(
                "000004", _good_line().replace(b" ", b" x", 1).replace(b" x", b" ", 1).rsplit(b" ", 1)[0] + b" high\n"
            ),
            ("000004", "score"),
        ),
        "txt with nan coordinates": (
            "pred.zip",
            lambda: _txt_with("000005", b"Car -1 -1 0.1 10 20 110 120 1.5 1.6 3.9 nan 1.5 20 0.1 0.9\n"),
            ("000005", "non-finite"),
        ),
        "txt that is not UTF-8": ("pred.zip", lambda: _txt_with("000006", b"\xff\xfe\x00binary"), ("000006",)),
        "unknown format (a PNG)": ("result.pkl", lambda: b"\x89PNG\r\n\x1a\n" + b"\0" * 100, ("unknown format",)),
        "a single KITTI txt file": ("000000.txt", _good_line, ("single KITTI txt file",)),
        "a numpy .npy file": ("result.npy", lambda: _npy_bytes(), (".npy",)),
    }


def _npy_bytes() -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.zeros(3))
    return buf.getvalue()


MALFORMED = list(malformed_cases())


def test_there_are_enough_malformed_inputs() -> None:
    assert len(MALFORMED) >= 30


@pytest.mark.parametrize("name", MALFORMED)
def test_malformed_upload_is_a_clear_4xx_and_the_server_goes_on(client, name) -> None:
    filename, make, needles = malformed_cases()[name]
    r = upload(client, make(), filename, gt="small")
    err = assert_error(r, (400, 404, 413, 422), *needles)
    assert err["code"] in ("invalid_input", "unsafe_pickle", "invalid_archive", "unknown_format"), err
    assert str(client.app.state.service.data_dir) not in r.text and "/tmp/" not in r.text  # no server paths
    still_serving(client)


def test_input_errors_name_frame_and_field(client) -> None:
    r = upload(client, results_with(lambda r: r[1]["location"].__setitem__((0, 0), np.nan)), gt="small")
    err = assert_error(r, 422)
    assert err["frame"] == "000001" and err["field"] == "location"
    r = upload(client, _txt_with("000004", _good_line().rsplit(b" ", 1)[0] + b" high\n"), "pred.zip", gt="small")
    err = assert_error(r, 422, "pred.zip:pred/000004.txt")
    assert err["frame"] == "000004" and err["field"] == "score"


def test_oversized_upload_is_413(client) -> None:
    err = assert_error(upload(client, b"\x80\x04" + b"\0" * (3 << 20), gt="small"), 413, "upload limit")
    assert err["code"] == "payload_too_large"
    still_serving(client)


def test_missing_or_broken_form_is_422(client) -> None:
    assert_error(client.post("/v1/evaluations", data={"gt": "small"}), 422, "predictions")
    assert_error(client.post("/v1/evaluations", content=b"not a form", headers={"content-type": "text/plain"}), 422)
    assert_error(
        client.post(
            "/v1/evaluations", content=b"--x\r\ngarbage", headers={"content-type": "multipart/form-data; boundary=x"}
        ),
        (400, 422),
    )
    still_serving(client)


def test_scratch_space_is_empty_after_all_of_it(client) -> None:
    service = client.app.state.service
    assert list((service.data_dir / "tmp").iterdir()) == []
    assert client.get("/v1/ground-truths").json()["items"][0]["name"] in ("demo", "small")
    assert client.get("/readyz").status_code == 200
    assert ADMIN  # the admin token fixture is shared with the other modules


def _zip_with_lying_entry_count(n: int) -> bytes:
    """n members, but the end record claims 1: zipfile trusts the directory size, not the count."""
    data = bytearray(zip_of({f"pred/{i:06d}.txt": b"" for i in range(n)}))
    at = data.rfind(b"PK\x05\x06")
    data[at + 8 : at + 12] = (1).to_bytes(2, "little") * 2
    return bytes(data)


def test_a_huge_zip_directory_is_refused_before_it_is_read(client) -> None:
    # 5000 members against a cap of 200, with the count in the end record forged to 1
    err = assert_error(upload(client, _zip_with_lying_entry_count(5000), "pred.zip", gt="small"), 422, "members")
    assert err["code"] == "invalid_archive"
    still_serving(client)


def test_class_names_of_bytes_that_are_not_utf8_are_evaluated_not_a_500(client) -> None:
    """As every reference reads them: a name no class has (it was a 500, then a 422)."""
    results = generate(3, seed=1)[1]
    n = len(results[0]["score"])
    results[0]["name"] = np.array([b"Car\xff"] * n)
    response = upload(client, pickle.dumps(results, protocol=4), "result.pkl")
    assert response.status_code == 201, response.text
    results[0]["name"] = np.array(["Unknown"] * n)
    same = upload(client, pickle.dumps(results, protocol=4), "result.pkl")
    assert same.status_code == 201 and same.json()["ap"] == response.json()["ap"]


def test_a_prediction_frame_outside_the_ground_truth_is_refused_where_it_is_read(client) -> None:
    def add_unknown(results: list) -> None:
        results.insert(1, dict(results[0], frame_id="777777"))

    err = assert_error(upload(client, results_with(add_unknown), gt="small"), 422, "not in the ground truth")
    assert err["frame"] == "777777"
    txt = golden_txt("pred.tar.gz")
    txt["pred/777777.txt"] = _good_line()
    err = assert_error(upload(client, zip_of(txt), "pred.zip", gt="small"), 422, "not in the ground truth")
    assert err["frame"] == "777777"
    still_serving(client)
