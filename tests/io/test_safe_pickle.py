"""The restricted unpickler: hostile pickles are refused without running anything, numpy data round-trips."""

from __future__ import annotations

import builtins
import codecs
import collections
import functools
import gzip
import importlib
import io
import math
import os
import pickle
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import kitti_eval.io._pickle_scan as _pickle_scan
import kitti_eval.io.safe_pickle as safe_pickle
from kitti_eval.errors import InputError, UnsafePickleError
from kitti_eval.io.safe_pickle import ALLOWED_GLOBALS, load_pickle

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # pragma: no cover - numpy < 2
    from numpy.core.multiarray import _reconstruct

PROTOCOLS = [0, 1, 2, 3, 4, 5]


def loads(data: bytes, **kw) -> object:
    return load_pickle(io.BytesIO(data), source="upload.pkl", **kw)


class Reducer:
    """Pickles as ``func(*args)``: the shape of every code-execution payload."""

    def __init__(self, func, args, state=None):
        self.func, self.args, self.state = func, args, state

    def __reduce__(self):
        if self.state is None:
            return self.func, self.args
        return self.func, self.args, self.state


# ------------------------------------------------------------------------------------------- hostile


def _payloads(canary: Path) -> dict[str, object]:
    cmd = f"touch {canary}"
    return {
        "os.system": Reducer(os.system, (cmd,)),
        "eval": Reducer(eval, (f"open({str(canary)!r}, 'w').close()",)),
        "exec": Reducer(exec, (f"open({str(canary)!r}, 'w').close()",)),
        "subprocess.call": Reducer(subprocess.call, (["touch", str(canary)],)),
        "subprocess.Popen": Reducer(subprocess.Popen, (["touch", str(canary)],)),
        "functools.partial": Reducer(functools.partial(os.system, cmd), ()),
        "importlib.import_module": Reducer(importlib.import_module, ("antigravity",)),
        "builtins.open": Reducer(builtins.open, (str(canary), "w")),
        "nested in list in dict": {
            "frames": [{"name": np.array(["Car"]), "score": np.ones(1), "extra": [1, Reducer(os.system, (cmd,))]}]
        },
        "as the state of an array": Reducer(
            _reconstruct, (np.ndarray, (0,), b"b"), (1, (1,), np.dtype("O"), False, [Reducer(os.system, (cmd,))])
        ),
    }


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
@pytest.mark.parametrize("payload", list(_payloads(Path("x"))))
def test_code_execution_payloads_are_refused(tmp_path: Path, protocol: int, payload: str) -> None:
    canary = tmp_path / "CANARY"
    data = pickle.dumps(_payloads(canary)[payload], protocol=protocol)
    with pytest.raises(UnsafePickleError) as err:
        loads(data)
    assert "only numpy arrays and plain containers" in str(err.value)
    assert err.value.source == "upload.pkl"
    assert not canary.exists()


def test_hand_written_protocol0_global_is_refused_naming_it(tmp_path: Path) -> None:
    canary = tmp_path / "CANARY"
    data = f"cos\nsystem\n(S'touch {canary}'\ntR.".encode()
    with pytest.raises(UnsafePickleError, match=r"os\.system"):
        loads(data)
    assert not canary.exists()


def test_getattr_chain_through_builtins_is_refused(tmp_path: Path) -> None:
    canary = tmp_path / "CANARY"
    # getattr(__import__('os'), 'system')('touch CANARY'), written by hand at protocol 0
    data = (f"cbuiltins\ngetattr\n(cbuiltins\n__import__\n(S'os'\ntRS'system'\ntR(S'touch {canary}'\ntR.").encode()
    with pytest.raises(UnsafePickleError, match=r"builtins\.getattr"):
        loads(data)
    assert not canary.exists()


def test_nothing_is_imported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    canary = tmp_path / "CANARY"
    (tmp_path / "kitti_eval_canary_mod.py").write_text(f"open({str(canary)!r}, 'w').close()\ndef run():\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = b"kitti_eval_canary_mod"
    stack_global = b"\x80\x04\x8c" + bytes([len(mod)]) + mod + b"\x8c\x03run\x93)R."
    for data in (b"ckitti_eval_canary_mod\nrun\n)R.", stack_global):
        with pytest.raises(UnsafePickleError, match="kitti_eval_canary_mod.run"):
            loads(data)
    assert "kitti_eval_canary_mod" not in sys.modules
    assert not canary.exists()


def test_torch_tensor_pickle_gets_the_torch_message() -> None:
    data = b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\nq\x00)Rq\x01."
    with pytest.raises(UnsafePickleError) as err:
        loads(data)
    msg = str(err.value)
    assert "torch tensors" in msg and ".numpy()" in msg and "not loaded" in msg
    assert "torch._utils._rebuild_tensor_v2" in msg


def test_torch_storage_inside_a_result_list_gets_the_torch_message() -> None:
    # [{'frame_id': '000001', 'score': torch.FloatStorage...}] as a protocol-2 pickle
    data = (
        b"\x80\x02]q\x00}q\x01(X\x08\x00\x00\x00frame_idq\x02X\x06\x00\x00\x00000001q\x03"
        b"X\x05\x00\x00\x00scoreq\x04ctorch\nFloatStorage\nq\x05)Rq\x06ua."
    )
    with pytest.raises(UnsafePickleError, match="torch tensors"):
        loads(data)


def test_mmdet3d_boxes_get_the_mmdet3d_message() -> None:
    data = b"\x80\x02cmmdet3d.structures.bbox_3d.cam_box3d\nCameraInstance3DBoxes\nq\x00)R."
    with pytest.raises(UnsafePickleError) as err:
        loads(data)
    assert "mmdet3d box objects" in str(err.value) and "numpy" in str(err.value)


def test_legacy_torch_save_and_zip_files_are_recognised() -> None:
    with pytest.raises(UnsafePickleError, match="torch"):
        loads(pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2))
    with pytest.raises(InputError, match="zip archive"):
        loads(b"PK\x03\x04" + b"\0" * 100)


@pytest.mark.parametrize(
    "data",
    [
        b"\x80\x02cnumpy\nmemmap\nq\x00.",
        b"\x80\x02cnumpy.ma.core\n_mareconstruct\nq\x00.",
        b"\x80\x02cnumpy.lib.npyio\nNpzFile\nq\x00.",
        b"\x80\x02cnumpy.testing\nassert_equal\nq\x00.",
    ],
)
def test_other_numpy_globals_are_refused(data: bytes) -> None:
    with pytest.raises(UnsafePickleError, match="numpy"):
        loads(data)


def test_masked_array_and_numpy_classes_are_refused() -> None:
    for obj in (np.ma.masked_array([1.0, 2.0], mask=[0, 1]), np.memmap):
        with pytest.raises(UnsafePickleError):
            loads(pickle.dumps(obj, protocol=2))


# -------------------------------------------------- numpy-level attacks on the allowlisted callables


def test_structured_dtype_with_fields_outside_the_item_is_refused() -> None:
    # numpy itself accepts this state and then reads 1000 bytes past each element
    state = (3, "<", None, ("a",), {"a": (np.dtype("<f8"), 1000)}, 8, 1, 16)
    evil = Reducer(np.dtype, ("f8", False, True), state)
    with pytest.raises(UnsafePickleError, match="dtype"):
        loads(pickle.dumps(evil, protocol=2))


def test_object_flags_on_a_plain_dtype_are_refused() -> None:
    evil = Reducer(np.dtype, ("i8", False, True), (3, "<", None, None, None, -1, -1, 63))
    with pytest.raises(UnsafePickleError, match="dtype"):
        loads(pickle.dumps(evil, protocol=2))


@pytest.mark.parametrize(
    "dtype", [np.dtype([("a", "<f8"), ("b", "<i4")]), np.dtype("V8"), np.dtype("M8[s]"), np.dtype([("a", "<f8", (2,))])]
)
def test_structured_void_and_datetime_arrays_are_refused(dtype: np.dtype) -> None:
    with pytest.raises(UnsafePickleError):
        loads(pickle.dumps(np.zeros(2, dtype=dtype), protocol=2))


def test_huge_shape_with_a_tiny_buffer_is_an_input_error() -> None:
    for shape in [(10**9, 10**9), (2**62, 4), (10**6,)]:
        evil = Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, shape, np.dtype("f8"), False, b"\0" * 8))
        with pytest.raises(InputError, match="needs .* bytes") as err:
            loads(pickle.dumps(evil, protocol=2))
        assert not isinstance(err.value, UnsafePickleError)


def test_huge_shape_in_the_array_header_is_an_input_error() -> None:
    evil = Reducer(_reconstruct, (np.ndarray, (10**12,), b"b"))
    with pytest.raises(InputError, match="array header"):
        loads(pickle.dumps(evil, protocol=2))


def test_object_array_with_a_short_list_is_an_input_error() -> None:
    evil = Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, (10**9,), np.dtype("O"), False, [1, 2]))
    with pytest.raises(InputError, match="list of"):
        loads(pickle.dumps(evil, protocol=2))


def test_protocol5_buffer_of_the_wrong_size_is_an_input_error() -> None:
    data = pickle.dumps(np.arange(4.0), protocol=5)
    # shrink the shape (4,) written after the buffer to (400,)
    evil = data.replace(b"K\x04\x85", b"M\x90\x01\x85")
    assert evil != data
    with pytest.raises(InputError, match="needs 3200 bytes"):
        loads(evil)


def test_ndarray_cannot_be_called_directly() -> None:
    with pytest.raises(UnsafePickleError, match="ndarray"):
        loads(pickle.dumps(Reducer(np.ndarray, ((10**10,), "f8")), protocol=2))


def test_codecs_encode_only_does_latin1() -> None:
    with pytest.raises(UnsafePickleError, match="latin-1"):
        loads(pickle.dumps(Reducer(codecs.encode, (b"abc", "hex")), protocol=2))


def test_object_arrays_may_hold_only_plain_items() -> None:
    assert loads(pickle.dumps(np.array(["Car", 1, 2.5, None], dtype=object), protocol=2)).tolist() == [
        "Car",
        1,
        2.5,
        None,
    ]
    nested = np.empty(1, dtype=object)
    nested[0] = np.zeros(2)
    for obj in (np.array([{"a": 1}, 2], dtype=object), nested):
        with pytest.raises(UnsafePickleError, match="object arrays"):
            loads(pickle.dumps(obj, protocol=2))


def test_constructors_with_arguments_are_refused() -> None:
    with pytest.raises(UnsafePickleError, match="OrderedDict"):
        loads(pickle.dumps(Reducer(collections.OrderedDict, ([("a", 1)],)), protocol=2))
    with pytest.raises(UnsafePickleError, match="bytes"):
        loads(pickle.dumps(Reducer(bytes, (10**12,)), protocol=2).replace(b"builtins", b"__builtin__"))
    with pytest.raises(UnsafePickleError, match="NEWOBJ"):
        loads(b"\x80\x02ccollections\nOrderedDict\n)\x81.")


def test_state_of_other_objects_cannot_be_set() -> None:
    with pytest.raises(UnsafePickleError, match="state"):
        loads(b"\x80\x02ccollections\nOrderedDict\n)R}X\x01\x00\x00\x00aK\x01sb.")


def test_extension_codes_and_persistent_ids_are_refused() -> None:
    with pytest.raises(UnsafePickleError, match="extension"):
        loads(b"\x80\x02\x82\x01.")
    with pytest.raises(UnsafePickleError, match="persistent"):
        loads(b"\x80\x02X\x01\x00\x00\x00aQ.")


def test_deeply_nested_tuple_keys_are_refused() -> None:
    # CPython's tuple hash recurses without a guard: ~1e6 levels crash the process
    data = b"\x80\x02}K\x01" + b"\x85" * 1000 + b"K\x02s."
    with pytest.raises(InputError, match="nested too deeply"):
        loads(data)
    assert loads(b"\x80\x02}K\x01" + b"\x85" * 50 + b"K\x02s.")  # moderate nesting is fine


def test_a_small_pickle_cannot_build_a_lot_of_data() -> None:
    big = "x" * (1 << 20)
    data = pickle.dumps([Reducer(codecs.encode, (big, "latin1")) for _ in range(100)], protocol=2)
    assert len(data) < 2 << 20
    with pytest.raises(InputError, match="far more array data"):
        loads(data)


# --------------------------------------------------------------------------------------------- legit

LEGIT = {
    "float32": np.array([[1.5, -2.25, 3.0]], dtype=np.float32),
    "float64": np.linspace(-1, 1, 7),
    "int32": np.arange(12, dtype=np.int32).reshape(3, 4),
    "uint8": np.array([0, 255], dtype=np.uint8),
    "bool": np.array([True, False]),
    "str": np.array(["Car", "Pedestrian", "DontCare"], dtype="<U10"),
    "bytes": np.array([b"Car"], dtype="S3"),
    "empty2d": np.zeros((0, 4)),
    "empty str": np.zeros(0, dtype="<U1"),
    "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
    "big endian": np.array([1.0, 2.0], dtype=">f8"),
    "object str": np.array(["Car", "Van"], dtype=object),
    "0-d": np.array(3.5),
}
SCALARS = {
    "float32": np.float32(1.5),
    "str_": np.str_("000001"),
    "int64": np.int64(-7),
    "bool_": np.bool_(True),
    "float64": np.float64(0.1),
}


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("name", list(LEGIT))
def test_arrays_round_trip(protocol: int, name: str) -> None:
    arr = LEGIT[name]
    out = loads(pickle.dumps(arr, protocol=protocol))
    assert type(out) is np.ndarray
    assert out.shape == arr.shape
    assert out.dtype.kind == arr.dtype.kind and out.dtype.itemsize == arr.dtype.itemsize
    np.testing.assert_array_equal(out, arr)


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("name", list(SCALARS))
def test_numpy_scalars_round_trip(protocol: int, name: str) -> None:
    value = SCALARS[name]
    out = loads(pickle.dumps(value, protocol=protocol))
    assert type(out) is type(value) and out == value


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_containers_round_trip(protocol: int) -> None:
    obj = {
        "frames": [
            {"frame_id": np.str_("000001"), "name": np.array(["Car"]), "score": np.float32([0.9])},
            {"frame_id": 2, "name": np.zeros(0), "bbox": np.zeros((0, 4))},
        ],
        "meta": ("kitti", 1, 2.5, None, True, b"raw", b""),
        "ordered": collections.OrderedDict([("b", 1), ("a", [1, 2, 3])]),
        (1, "key"): {"nested": [[{"x": -1.0}]]},
    }
    if protocol >= 4:  # below 4, sets pickle as builtins.set(list), which is not on the allowlist
        obj.update({"set": {1, 2}, "frozen": frozenset({"a"})})
    out = loads(pickle.dumps(obj, protocol=protocol))
    assert isinstance(out, dict) and isinstance(out["ordered"], collections.OrderedDict)
    assert list(out["ordered"].items()) == [("b", 1), ("a", [1, 2, 3])]
    assert out["meta"] == obj["meta"] and out[(1, "key")] == obj[(1, "key")]
    if protocol >= 4:
        assert out["set"] == {1, 2} and out["frozen"] == frozenset({"a"})
    f0, f1 = out["frames"]
    assert type(f0["frame_id"]) is np.str_ and f0["frame_id"] == "000001"
    np.testing.assert_array_equal(f0["score"], obj["frames"][0]["score"])
    assert f1["frame_id"] == 2 and f1["bbox"].shape == (0, 4)


def test_shared_arrays_stay_shared() -> None:
    a = np.arange(3.0)
    out = loads(pickle.dumps({"x": a, "y": a}, protocol=4))
    assert out["x"] is out["y"]


@pytest.mark.parametrize("protocol", [2, 5])
def test_gzip_round_trip_from_path_and_file_object(tmp_path: Path, protocol: int) -> None:
    obj = [{"frame_id": "000000", "location": np.ones((2, 3), dtype=np.float32)}]
    path = tmp_path / "result.pkl.gz"
    path.write_bytes(gzip.compress(pickle.dumps(obj, protocol=protocol)))
    for src in (path, str(path), io.BytesIO(path.read_bytes())):
        out = load_pickle(src, source="r")
        np.testing.assert_array_equal(out[0]["location"], obj[0]["location"])
    # gzip is recognised by its magic bytes, not by the name
    (tmp_path / "plain_name.pkl").write_bytes(path.read_bytes())
    assert load_pickle(tmp_path / "plain_name.pkl", source="r")[0]["frame_id"] == "000000"


def test_allowlist_is_what_the_docs_say() -> None:
    assert {f"{m}.{n}" for m, n in ALLOWED_GLOBALS} == {
        "numpy.core.multiarray._reconstruct",
        "numpy._core.multiarray._reconstruct",
        "numpy.core.numeric._frombuffer",
        "numpy._core.numeric._frombuffer",
        "numpy.ndarray",
        "numpy.dtype",
        "numpy.core.multiarray.scalar",
        "numpy._core.multiarray.scalar",
        "_codecs.encode",
        "collections.OrderedDict",
        "builtins.bytes",
        "__builtin__.bytes",
    }


def test_numpy1_module_names_are_accepted() -> None:
    data = pickle.dumps({"a": np.arange(3.0), "s": np.float32(2.0)}, protocol=2)
    old = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    assert old != data
    out = loads(old)
    np.testing.assert_array_equal(out["a"], np.arange(3.0))
    assert out["s"] == np.float32(2.0)


# ------------------------------------------------------------------------------------------- corrupt

CORRUPT = {
    "empty": b"",
    "truncated": pickle.dumps({"a": np.zeros(100)}, protocol=4)[:-30],
    "truncated at the start": pickle.dumps([1, 2, 3], protocol=2)[:3],
    "random bytes": bytes((i * 197 + 13) % 256 for i in range(1000)),
    "text": b"Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n",
    "truncated gzip": gzip.compress(pickle.dumps(np.zeros(1000), protocol=2))[:-20],
    "gzip of garbage": gzip.compress(b"\xff\xfe not a pickle"),
    "gzip header only": b"\x1f\x8b",
    "stop on empty stack": b".",
    "bad memo": b"\x80\x02h\x05.",
    "huge bytearray8": b"\x80\x05\x96" + (10**12).to_bytes(8, "little") + b"ab.",
    "tar archive": b"\0" * 257 + b"ustar\x0000" + b"\0" * 300,
}


@pytest.mark.parametrize("name", list(CORRUPT))
def test_corrupt_input_is_an_input_error(name: str) -> None:
    with pytest.raises(InputError) as err:
        loads(CORRUPT[name])
    assert not isinstance(err.value, UnsafePickleError)
    assert str(err.value).startswith("upload.pkl: not a readable")


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        load_pickle(tmp_path / "nope.pkl", source="nope.pkl")
    with pytest.raises(InputError, match="directory"):
        load_pickle(tmp_path, source="dir")


def test_text_mode_file_object_is_an_input_error() -> None:
    with pytest.raises(InputError, match="binary"):
        load_pickle(io.StringIO("abc"), source="s")


def test_max_bytes_bounds_decompressed_and_plain_input(tmp_path: Path) -> None:
    bomb = gzip.compress(b"\0" * (8 << 20))
    assert len(bomb) < 100_000
    with pytest.raises(InputError, match="decompressed gzip data is larger than the limit of 1048576 bytes"):
        loads(bomb, max_bytes=1 << 20)
    data = pickle.dumps(np.zeros(1000), protocol=2)
    with pytest.raises(InputError, match="larger than the limit"):
        loads(data, max_bytes=100)
    assert loads(data, max_bytes=len(data)).shape == (1000,)
    assert loads(gzip.compress(data), max_bytes=len(data)).shape == (1000,)


# =============================================================================== the scan (_pickle_scan)
#
# load_pickle runs the C unpickler only on bytes that kitti_eval.io._pickle_scan.scan has checked. These
# tests cover the scan's model of _pickle.c opcode by opcode, its limits, and (by truncation and random
# mutation) that nothing it accepts can crash the interpreter or yield anything but plain data.


@pytest.fixture(params=["compiled", "python"])
def scan_mode(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test with the compiled scan and with its main loop as plain Python (the same checks)."""
    if request.param == "python":
        if not hasattr(_pickle_scan.scan, "py_func"):
            pytest.skip("NUMBA_DISABLE_JIT: the scan is plain Python in the other run already")
        monkeypatch.setattr(_pickle_scan, "scan", _pickle_scan.scan.py_func)
    return request.param


def same(a: object, b: object, strides: bool = False) -> bool:
    """Deep equality that also compares numpy arrays, dtypes and scalars by type and bytes (and array
    strides if ``strides``: below protocol 5 numpy pickles every array as a contiguous copy)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        if a.dtype != b.dtype or a.shape != b.shape or (strides and a.strides != b.strides):
            return False
        if a.dtype.kind == "O":
            return all(same(x, y, strides) for x, y in zip(a.ravel(), b.ravel()))
        return a.tobytes() == b.tobytes()
    if isinstance(a, np.generic):
        return a.dtype == b.dtype and a.tobytes() == b.tobytes()
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same(x, y, strides) for x, y in zip(a, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k], strides) for k in a)
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b)


_PLAIN = (str, int, float, bool, bytes, bytearray, type(None))


def post_check(obj: object, depth: int = 0) -> None:
    """What load_pickle may return: plain containers (at most ~100 deep), plain numpy arrays whose memory
    is all there, object arrays of plain items, numpy scalars and dtypes."""
    assert depth <= 101
    if isinstance(obj, _PLAIN) or isinstance(obj, np.generic):
        return
    if isinstance(obj, np.dtype):
        assert obj.kind in "biufcUSO" and obj.names is None and obj.subdtype is None
        return
    if type(obj) is np.ndarray:
        dt = obj.dtype
        assert dt.kind in "biufcUSO" and dt.names is None and dt.subdtype is None
        assert dt.hasobject == (dt.kind == "O")
        if dt.kind == "O":
            for x in obj.ravel():
                assert isinstance(x, _PLAIN) or isinstance(x, np.generic), type(x)
        else:
            assert len(obj.tobytes()) == obj.size * dt.itemsize  # reads every element
        return
    if type(obj) in (list, tuple, set, frozenset):
        for x in obj:  # type: ignore[attr-defined]
            post_check(x, depth + 1)
        return
    assert type(obj) in (dict, collections.OrderedDict), type(obj)
    for k, v in obj.items():  # type: ignore[attr-defined]
        post_check(k, depth + 1)
        post_check(v, depth + 1)


def _dtypes() -> list[np.dtype]:
    out = [
        np.dtype(c)
        for c in (
            "?",
            "i1",
            "i2",
            "i4",
            "i8",
            "u1",
            "u2",
            "u4",
            "u8",
            "f2",
            "f4",
            "f8",
            "c8",
            "c16",
            "U1",
            "U7",
            "S1",
            "S5",
            ">i4",
            ">f8",
            ">c16",
            ">U3",
            "O",
        )
    ]
    out += [np.dtype(np.longdouble), np.dtype(np.clongdouble)]
    return out


def _rich(protocol: int) -> dict[str, object]:
    """Every kind of value load_pickle accepts, as pickle writes it at ``protocol``."""
    arrays = [
        np.zeros((2, 3), dtype=dt) + (np.array("ab", dtype=dt) if dt.kind in "US" else 1)
        for dt in _dtypes()
        if dt.kind != "O"
    ]
    arrays += [
        np.array(["Car", 1, 2.5, None, b"x", np.float32(3)], dtype=object),
        np.frombuffer(bytes(range(256)) * 2, np.uint8),  # every byte value (escapes at protocol 0)
        np.array(7.25),
        np.zeros((0, 7)),
        np.zeros(0, "U1"),
        np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        np.arange(24.0).reshape(2, 3, 4).transpose(1, 0, 2),
    ]  # neither C nor F (axis order at protocol 5)
    scalars = [np.dtype(dt).type(1) for dt in _dtypes() if dt.kind not in "USO"]
    scalars += [np.str_("000001"), np.bytes_(b"ab\x00c"), np.float64("nan")]
    strings = [str(i) for i in range(300)]
    obj: dict[str, object] = {
        "arrays": arrays,
        "scalars": scalars,
        "dtypes": [np.dtype("f4"), np.dtype(">U5")],
        "nested": [[{"a": (1, (2, (3,)))}], (), [], {}, ((),)],
        "str": ["", "plain", "ünïcødé \u20ac \U0001f600", "back\\slash\nnew line\r\x1a\x00", "'\""],
        "bytes": [b"", b"raw\x00\xff\\\n", bytes(range(256)) * 2],
        "ints": [0, 1, -1, 255, 256, 65535, 65536, 2**31 - 1, -(2**31), 2**63, -(2**63) - 1, 2**70, -(2**3000)],
        "floats": [0.0, -0.0, 1.5, 1e308, float("inf"), float("nan")],
        "consts": [None, True, False],
        "od": collections.OrderedDict([("b", 1), ("a", [1, 2, 3])]),
        (1, "tuple key"): "v",
        "memo": strings + strings,  # > 256 memo entries, each fetched again (LONG_BINGET)
        "shared": [arrays[0], arrays[0]],
    }
    if protocol >= 4:  # below 4 sets pickle as builtins.set(list), which is not on the allowlist
        obj.update({"set": {1, "a", (2, 3)}, "frozenset": frozenset({frozenset({1}), "b"})})
    if protocol >= 5:
        obj["bytearray"] = bytearray(b"ba\x00")
    return obj


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_every_kind_of_value_round_trips(protocol: int, scan_mode: str) -> None:
    obj = _rich(protocol)
    data = pickle.dumps(obj, protocol=protocol)
    out = loads(data)
    post_check(out)
    assert same(out, obj) and same(out, pickle.loads(data), strides=True)
    assert out["shared"][0] is out["shared"][1]  # type: ignore[index]


@pytest.mark.parametrize(
    "data, expected",
    [
        (b"S'abc'\n.", "abc"),  # STRING (protocol 0, quoted)
        (b'S"a\\x41\\n"\n.', "aA\n"),  # STRING with escapes
        (b"U\x03abc.", "abc"),  # SHORT_BINSTRING
        (b"T\x03\x00\x00\x00abc.", "abc"),  # BINSTRING
        (b"\x8d\x02\x00\x00\x00\x00\x00\x00\x00\xc3\xa9.", "\xe9"),  # BINUNICODE8
        (b"\x8e\x02\x00\x00\x00\x00\x00\x00\x00ab.", b"ab"),  # BINBYTES8
        (b"B\x02\x00\x00\x00ab.", b"ab"),  # BINBYTES
        (b"Vab\\u00e9\\x\n.", "ab\xe9\\x"),  # UNICODE with an escape and a lone backslash
        (b"I01\n.", True),
        (b"I00\n.", False),
        (b"I7\n.", 7),
        (b"I-12\n.", -12),
        (b"I010\n.", 8),  # INT
        (b"L123L\n.", 123),
        (b"L99999999999999999999999\n.", 99999999999999999999999),  # LONG
        (b"F1.5\n.", 1.5),  # FLOAT
        (b"\x8b\x02\x00\x00\x00\xff\x7f.", 32767),  # LONG4
        (b"\x8a\x01\xff.", -1),
        (b"\x8a\x00.", 0),  # LONG1
        (b"K\x012\x86.", (1, 1)),  # DUP
        (b"K\x01K\x020\x85.", (1,)),  # POP of an object
        (b"K\x01(0\x85.", (1,)),  # POP of a MARK
        (b"K\x01(K\x02K\x031\x85.", (1,)),  # POP_MARK
        (b"(K\x01K\x02l.", [1, 2]),
        (b"(K\x01K\x02d.", {1: 2}),  # LIST, DICT
        (b"(K\x01\x91.", frozenset({1})),
        (b"\x8f(K\x01\x90.", {1}),  # FROZENSET, ADDITEMS
        (b"K\x01p5\n0g5\n.", 1),  # PUT / GET (protocol 0)
        (b"K\x01r\x00\x01\x00\x000j\x00\x01\x00\x00.", 1),  # LONG_BINPUT / LONG_BINGET
        (b"K\x01q\x07\x94\x94h\x07\x85.", (1,)),  # MEMOIZE after an explicit PUT
        (b"\x80\x05\x95\x03\x00\x00\x00\x00\x00\x00\x00K\x01.", 1),  # FRAME
        (b"\x80\x02K\x01.trailing bytes are ignored", 1),
    ],
)
def test_hand_written_opcodes(data: bytes, expected: object) -> None:
    out = loads(data)
    assert same(out, expected) and same(out, pickle.loads(data), strides=True)


@pytest.mark.parametrize(
    "data, match",
    [
        (b"(i__builtin__\nbytes\n.", "INST"),
        (b"\x80\x02ccollections\nOrderedDict\n)o.", "INST"),
        (b"Pfoo\n.", "persistent"),
        (b"\x80\x02\x83\x01\x00.", "extension"),
        (b"\x80\x02\x84\x01\x00\x00\x00.", "extension"),
        (b"\x80\x04ccollections\nOrderedDict\n)}\x92.", "NEWOBJ"),
        (b"\x80\x04]ccollections\nOrderedDict\na.", "as a value"),  # a global is never a value
        (b"\x80\x04ccollections\nOrderedDict\n.", "as a value"),
        (b"\x80\x04cnumpy\nndarray\n)R.", "calls numpy.ndarray"),
        (b"\x80\x04\x8c\x01aK\x01\x85R.", "calls 'a'"),
        (b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00f8K\x00K\x01\x87R.", "dtype"),  # align/copy as int, not bool
        (b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00f8\x89\x89\x87R.", "dtype"),  # copy=False: numpy's shared dtype
        (
            b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87RK\x01K\x02s.",
            "adds items to a numpy array",
        ),
        (b"\x80\x02K\x01K\x02K\x03(u.", "adds items to a int"),  # a no-op for _pickle.c, never written
    ],
)
def test_scan_refusals(data: bytes, match: str, scan_mode: str) -> None:
    with pytest.raises(UnsafePickleError, match=match):
        loads(data)


@pytest.mark.parametrize(
    "data, match",
    [
        (b"\x80\x02}]Ns.", "cannot be hashed"),  # a list as a dict key
        (b"\x80\x02]q\x00h\x00a.", "recursive"),  # l.append(l)
        (b"\x80\x02]q\x00\x85h\x00K\x02a.", "recursive"),  # a list changed inside a tuple
        (b"\x80\x02Nr\xff\xff\xff\x7f.", "memo index"),  # the C memo would take 16 GB
        (b"\x80\x05\x97.", "out-of-band"),
        (b"\x80\x05C\x01a\x98.", "out-of-band"),
        (b"\x80\x02(u.", "underflow"),
        (b"\x80\x02(K\x01\x85(\x86.", "underflow"),
        (b"\x80\x02K\x01t.", "MARK"),
        (b"\x80\x02\x8c.", "ends before"),
        (b"\x80\x06N.", "malformed"),
        (b"\x80\x02\x8b\xff\xff\xff\xffN.", "malformed"),
        (b"\x80\x02g1x\n.", "malformed"),
        (b"\x80\x02}(K\x01d.", "odd"),
        (
            b"\x80\x05cnumpy._core.numeric\n_frombuffer\n(C\x00cnumpy\ndtype\nX\x02\x00\x00\x00O8\x89\x88\x87R"
            b"(K\x03X\x01\x00\x00\x00|NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK?tbK\x00\x85X\x01\x00\x00\x00CtR.",
            "raw buffer",
        ),
    ],
)
def test_scan_rejects_malformed_input(data: bytes, match: str, scan_mode: str) -> None:
    with pytest.raises(InputError, match=match) as err:
        loads(data)
    assert not isinstance(err.value, UnsafePickleError)
    assert str(err.value).startswith("upload.pkl: not a readable pickle: ")


def test_protocol5_axis_order_is_checked() -> None:
    arr = np.arange(24.0).reshape(2, 3, 4).transpose(1, 0, 2)
    data = pickle.dumps(arr, protocol=5)
    assert same(loads(data), arr, strides=True)
    axes = b"K\x01K\x00K\x02\x87"
    assert data.count(axes) == 1
    for bad in (b"K\x01K\x01K\x02\x87", b"K\x01K\x00K\x03\x87", b"K\x01K\x00\x86\x94\x94"):
        with pytest.raises(InputError, match="order"):
            loads(data.replace(axes, bad))


def test_dtype_states_are_the_ones_numpy_writes() -> None:
    """The scan's table of canonical dtype states agrees with numpy for every dtype and byte order."""
    for dt in _dtypes() + [np.dtype(f"U{n}") for n in (0, 1, 9, 1000)] + [np.dtype(f"S{n}") for n in (0, 2, 333)]:
        for order in "<>":
            d = dt.newbyteorder(order) if dt.byteorder != "|" else dt
            assert loads(pickle.dumps(d, protocol=2)) == d
            for protocol in (2, 5):  # below 5, numpy itself loads swapped arrays in native order
                data = pickle.dumps(np.ones(2, d), protocol=protocol)
                assert same(loads(data), pickle.loads(data), strides=True)
                np.testing.assert_array_equal(loads(data), np.ones(2, d))
    for state in [
        (3, "|", None, None, None, -1, -1, 0),  # a multi-byte number with no byte order
        (3, "<", None, None, None, 8, -1, 0),  # explicit size on a fixed-size dtype
        (3, "<", None, None, None, -1, -1, 16),  # custom flags
        (4, "<", None, None, None, -1, -1, 0),
    ]:  # another version
        with pytest.raises(UnsafePickleError, match="dtype"):
            loads(pickle.dumps(Reducer(np.dtype, ("f8", False, True), state), protocol=2))
    with pytest.raises(InputError, match="string size 6"):
        loads(pickle.dumps(Reducer(np.dtype, ("U1", False, True), (3, "<", None, None, None, 6, 4, 8)), protocol=2))


def _nested(opener: bytes, closer: bytes, n: int) -> bytes:
    return b"\x80\x04" + opener * n + closer * n + b"."


@pytest.mark.parametrize("n", [99, 1000, pytest.param(1_000_000, marks=pytest.mark.slow)])
def test_deep_nesting_is_refused_before_anything_is_built(n: int, scan_mode: str) -> None:
    lists = b"\x80\x04" + b"]" * n + b"a" * (n - 1) + b"."  # [[[...]]]
    frozensets = _nested(b"(", b"\x91", n)  # frozenset({frozenset({...})})
    tuples = _nested(b"(", b"t", n)
    dicts = b"\x80\x04" + b"}K\x00" * (n - 1) + b"}" + b"s" * (n - 1) + b"."  # {0: {0: {...}}}
    for data in (lists, frozensets, tuples, dicts):
        if n < 100:
            post_check(loads(data))
        else:
            with pytest.raises(InputError, match="nested too deeply"):
                loads(data)


def test_a_million_deep_tuple_key_is_refused_in_process() -> None:
    # pickle.loads of this segfaults CPython: hashing the key recurses 1e6 deep in C
    data = b"\x80\x02}N" + b"\x85" * 1_000_000 + b"Ns."
    with pytest.raises(InputError, match="nested too deeply"):
        loads(data)
    # ... and the same as a set item, a frozenset item and a nested key
    for data in (
        b"\x80\x04\x8f(N" + b"\x85" * 1_000_000 + b"\x90.",
        b"\x80\x04(N" + b"\x85" * 1_000_000 + b"\x91.",
        b"\x80\x04}N" + b"\x85" * 1_000_000 + b"K\x01\x86Ns.",
    ):
        with pytest.raises(InputError, match="nested too deeply"):
            loads(data)


def test_a_tuple_key_that_would_hash_for_ever_is_refused() -> None:
    # t[i] = (t[i-1], t[i-1]): 60 levels, 2**60 elements to hash, 400 bytes of pickle
    # each level: BINGET i, BINGET i, TUPLE2, MEMOIZE, POP
    level = b"".join(b"h" + bytes([i]) + b"h" + bytes([i]) + b"\x86\x940" for i in range(60))
    data = b"\x80\x04})\x940" + level + b"h<Ns."  # {t[60]: None}
    start = time.perf_counter()
    with pytest.raises(InputError, match="nested too deeply"):
        loads(data)
    assert time.perf_counter() - start < 5


def _small_pickles() -> list[bytes]:
    frame = {
        "frame_id": "000001",
        "name": np.array(["Car", "Pedestrian"]),
        "score": np.float32([0.9, 0.1]),
        "bbox": np.zeros((2, 4)),
        "s": np.float32(2.5),
        "od": collections.OrderedDict(a=(1, b"x")),
        "big": 2**70,
        "obj": np.array(["Car", None], dtype=object),
    }
    return [pickle.dumps(frame, protocol=p) for p in PROTOCOLS]


def test_every_truncation_is_an_input_error(scan_mode: str) -> None:
    for data in _small_pickles():
        for cut in range(len(data)):
            with pytest.raises(InputError) as err:
                loads(data[:cut])
            assert not isinstance(err.value, UnsafePickleError), (cut, data[:cut])


def test_random_mutations_never_crash_and_yield_only_plain_data(scan_mode: str) -> None:
    """Seeded byte flips, deletions, insertions and copies: whatever load_pickle accepts is plain data and
    exactly what pickle.loads makes of the same bytes (safe to call once the scan accepted them)."""
    rng = random.Random(20240611)
    base = _small_pickles()
    counts = collections.Counter()
    for _ in range(3000 if scan_mode == "inline" else 1000):
        data = bytearray(rng.choice(base))
        for _ in range(rng.choice((1, 1, 2, 3, 6))):
            k = rng.randrange(len(data))
            r = rng.random()
            if r < 0.6:
                data[k] = rng.randrange(256)
            elif r < 0.75:
                del data[k]
            elif r < 0.9:
                data.insert(k, rng.randrange(256))
            else:
                data[k:k] = data[rng.randrange(len(data)) :][: rng.randrange(1, 12)]
        try:
            out = loads(bytes(data))
        except UnsafePickleError:
            counts["refused"] += 1
            continue
        except InputError:
            counts["malformed"] += 1
            continue
        counts["loaded"] += 1
        post_check(out)
        assert same(out, pickle.loads(bytes(data)), strides=True)
    assert min(counts.values()) > 20, counts  # all three outcomes happen


def test_the_c_unpickler_never_runs_on_a_refused_pickle(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A big pickle whose payload comes first, in the middle or last: the scan refuses it before the C
    unpickler has built anything or asked for a single global."""
    asked: list[tuple[str, str]] = []
    find_class = safe_pickle._Unpickler.find_class

    def spy(self: safe_pickle._Unpickler, module: str, name: str) -> object:
        asked.append((module, name))
        return find_class(self, module, name)

    monkeypatch.setattr(safe_pickle._Unpickler, "find_class", spy)
    canary = tmp_path / "CANARY"
    frames = [{"name": np.array(["Car"] * 3), "score": np.float32([0.5, 0.25, 0.125]), "i": i} for i in range(12000)]
    for protocol in (2, 4):
        for at in (0, len(frames) // 2, len(frames)):
            payload = frames[:at] + [Reducer(os.system, (f"touch {canary}",))] + frames[at:]
            with pytest.raises(UnsafePickleError, match="system"):
                loads(pickle.dumps(payload, protocol=protocol))
            assert asked == []
            assert not canary.exists()
        big = pickle.dumps(frames, protocol=protocol)
        assert same(loads(big), frames)
        assert set(asked) <= ALLOWED_GLOBALS and len(asked) > 0
        asked.clear()
        for cut in (len(big) - 1, len(big) // 2, 2):
            with pytest.raises(InputError, match="ends before"):
                loads(big[:cut])
            assert asked == []


def test_load_pickles_builds_in_order_and_raises_where_a_file_is_bad(tmp_path: Path) -> None:
    """Several files: each is checked in a helper thread ahead of the caller, built in order; a refused
    file raises (naming it) when its turn comes, after the good ones before it."""
    frames = [{"frame_id": f"{i:06d}", "score": np.float32([0.5, 0.25])} for i in range(3)]
    paths = []
    for name, obj in (("a.pkl", frames), ("b.pkl", Reducer(os.system, ("true",))), ("c.pkl", frames[:1])):
        paths.append(tmp_path / name)
        paths[-1].write_bytes(pickle.dumps(obj, protocol=4))
    loaded = safe_pickle.load_pickles(paths, sources=["a", "b", "c"])
    assert same(next(loaded), frames)
    with pytest.raises(UnsafePickleError, match="system") as err:
        next(loaded)
    assert err.value.source == "b"
    good = safe_pickle.load_pickles([paths[2], paths[0]], sources=["c", "a"])
    assert [len(x) for x in good] == [1, 3]  # type: ignore[arg-type]


@pytest.mark.parametrize("flood", [b"}", b"]", b"\x8f"])
def test_a_pickle_of_millions_of_tiny_objects_is_refused_before_they_are_built(flood: bytes) -> None:
    """Empty dicts, lists or sets: one byte each in the pickle, 60-220 in memory; the budget counts them
    and refuses before the C unpickler makes any."""
    data = b"\x80\x04" + flood * (3_000_000 // len(flood)) + b"."
    with pytest.raises(InputError, match="far more array data or objects") as err:
        loads(data)
    assert not isinstance(err.value, UnsafePickleError)
    assert safe_pickle._budget(len(data)) < 96 << 20
    loads(b"\x80\x04" + flood * 1000 + b".")  # a thousand are fine


def test_only_tuple_keys_count_against_the_hashing_budget(monkeypatch: pytest.MonkeyPatch, scan_mode: str) -> None:
    """Hashing a str or int key is cheap (and cached for str); only tuple keys, whose hash walks every element,
    count. A set of 300k frames of 15 keys each hashes 4.5M plain keys and must load."""
    monkeypatch.setattr(safe_pickle, "_KEY_BUDGET", 100)
    frames = [{"frame_id": f"{i:06d}", "score": 0.5, "name": "Car"} for i in range(200)]  # 600 str keys
    assert loads(pickle.dumps(frames, protocol=4)) == frames
    keys = {(i, i + 1, i + 2): None for i in range(40)}  # 120 tuple elements hashed
    with pytest.raises(InputError, match="too many elements to hash"):
        loads(pickle.dumps(keys, protocol=4))
    assert loads(pickle.dumps(dict(list(keys.items())[:30]), protocol=4)) == dict(list(keys.items())[:30])


def test_items_put_into_containers_count_against_the_budget() -> None:
    """A dict entry takes 30-50 bytes in CPython however short its pickle (a memoized key and True: 3 bytes).
    Frames of ten such entries: 330 KB of pickle that builds 7.5 MB, within the budget (32 MiB + 8x); a
    million empty frames with an id each (56 MB of pickle, 700 MB built) is refused before it is built."""
    frame = {f"k{j}": True for j in range(10)}
    small = pickle.dumps([dict(frame) for _ in range(10_000)], protocol=4)
    assert len(loads(small)) == 10_000  # type: ignore[arg-type]
    big = pickle.dumps([dict(frame) for _ in range(400_000)], protocol=4)  # 13 MB, ~140 MB of dicts
    with pytest.raises(InputError, match="far more array data or objects"):
        loads(big)


# ---------------------------------------------------------------------------------- what a pickle expands to


def _shared_frames(frames: int, boxes: int) -> list[dict[str, object]]:
    """A result.pkl whose frames all hold the same arrays (one object each: pickle writes them once, then
    reads them from its memo): ``frames`` x ``boxes`` boxes from a file of one frame's bytes."""
    rng = np.random.default_rng(0)
    arrays = {
        "name": np.array(["Car"] * boxes),
        "truncated": np.zeros(boxes, np.float32),
        "occluded": np.zeros(boxes, np.int8),
        "alpha": rng.random(boxes, np.float32),
        "bbox": rng.random((boxes, 4), np.float32),
        "dimensions": rng.random((boxes, 3), np.float32),
        "location": rng.random((boxes, 3), np.float32),
        "rotation_y": rng.random(boxes, np.float32),
        "score": rng.random(boxes, np.float32),
    }
    return [{"frame_id": f"{i:06d}", **arrays} for i in range(frames)]


def test_arrays_a_pickle_shares_between_frames_are_charged_each_time_and_refused_before_they_are_built(
    scan_mode: str,
) -> None:
    """200 frames that all use the same 10,000-box arrays: a 0.7 MB file that reads into 2 million boxes (about
    340 MB of float64 columns). Each use of an array is charged its bytes again; the file is refused by the
    check, before anything is built, naming the limit."""
    data = pickle.dumps(_shared_frames(200, 10_000), protocol=4)
    assert len(data) < 1 << 20
    with pytest.raises(InputError) as err:
        safe_pickle.check_pickle(io.BytesIO(data), source="r.pkl")
    message = str(err.value)
    limit, size = safe_pickle._budget(len(data)) / (1 << 20), len(data) / (1 << 20)
    assert f"more than the limit of {limit:.1f} MB for a pickle of {size:.1f} MB (8 times its size" in message
    assert "are arrays it uses more than once (through its memo), counted each time" in message
    assert not isinstance(err.value, UnsafePickleError)
    assert len(loads(pickle.dumps(_shared_frames(20, 1_000), protocol=4))) == 20  # type: ignore[arg-type]


def test_an_array_put_twice_into_one_list_is_charged_twice_at_eight_bytes_a_value(scan_mode: str) -> None:
    """One int8 array of 2 M values (2 MB; 16 MB as float64) in a list 3 times is within the budget of its 2 MB
    pickle (48 MB); 4 times (64 MB) is not. Counted at its own bytes, 4 would be 8 MB."""
    a = np.zeros(2_000_000, np.int8)
    assert len(loads(pickle.dumps([a, a, a], protocol=4))) == 3  # type: ignore[arg-type]
    with pytest.raises(InputError, match="uses more than once"):
        loads(pickle.dumps([a, a, a, a], protocol=4))
    with pytest.raises(InputError, match="uses more than once"):
        loads(pickle.dumps([(a, a), (a, a)], protocol=4))  # in tuples, the tuple again: 4 uses


def test_the_state_of_an_array_already_in_a_container_is_refused() -> None:
    """pickle.loads sets an array's state whenever BUILD comes; the check only on a fresh array not yet put into
    a container (what numpy writes), so that what a container holds is final when it is charged."""
    shell = (
        b"\x80\x04\x8c\x15numpy.core.multiarray\x8c\x0c_reconstruct\x93\x8c\x05numpy\x8c\x07ndarray\x93K\x00\x85"
        b"C\x01b\x87R\x94"
    )
    dtype = b"\x8c\x05numpy\x8c\x05dtype\x93\x8c\x02f8\x89\x88\x87R"
    dtype += b"(K\x03\x8c\x01<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"  # numpy.dtype("f8") and its state
    state = b"(K\x01K\x02\x85" + dtype + b"\x89C\x10" + bytes(16) + b"t"  # (1, (2,), float64, False, data)
    fresh = shell + state + b"b."
    assert loads(fresh).shape == (2,)  # type: ignore[attr-defined]
    placed = shell + b"\x85h\x00" + state + b"b0."  # a tuple holding the shell, then its state
    assert pickle.loads(placed)[0].shape == (2,)
    with pytest.raises(UnsafePickleError, match="sets the state of a numpy array"):
        loads(placed)


def test_str_arrays_are_charged_at_the_widest_ones_width(scan_mode: str) -> None:
    """A reader joins the frames' class names into one array as wide as the widest name: 3,000 frames of ten
    3-character names and one name of 2,000 characters (a 0.5 MB pickle) would be 30,001 names of 8,000 bytes,
    240 MB, past the budget (36 MB); counted at their own width they are 0.4 MB. The same names shared by every
    frame through the memo count once a frame, as they are copied."""
    names = [np.array([f"C{i % 10:02d}"] * 10) for i in range(3000)]
    data = pickle.dumps([*names, np.array(["x" * 2000])], protocol=4)
    with pytest.raises(InputError, match=r"str arrays \(class names\) hold 30001 strings or more, which read toget"):
        loads(data)
    assert len(loads(pickle.dumps(names, protocol=4))) == 3000  # type: ignore[arg-type]
    shared = np.array(["Car"] * 10)
    with pytest.raises(InputError, match="at the widest one's width .2000 characters."):
        loads(pickle.dumps([np.array(["x" * 2000]), *[shared] * 3000], protocol=4))
