"""The restricted unpickler: hostile pickles are refused without running anything, numpy data round-trips."""

from __future__ import annotations

import builtins
import codecs
import collections
import functools
import gzip
import importlib
import io
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kitti_eval.errors import InputError, UnsafePickleError
from kitti_eval.safe_pickle import ALLOWED_GLOBALS, load_pickle

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
        "nested in list in dict": {"frames": [{"name": np.array(["Car"]), "score": np.ones(1),
                                               "extra": [1, Reducer(os.system, (cmd,))]}]},
        "as the state of an array": Reducer(_reconstruct, (np.ndarray, (0,), b"b"),
                                            (1, (1,), np.dtype("O"), False, [Reducer(os.system, (cmd,))])),
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
    data = (f"cbuiltins\ngetattr\n(cbuiltins\n__import__\n(S'os'\ntRS'system'\ntR(S'touch {canary}'\ntR."
            ).encode()
    with pytest.raises(UnsafePickleError, match=r"builtins\.getattr"):
        loads(data)
    assert not canary.exists()


def test_nothing_is_imported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    canary = tmp_path / "CANARY"
    (tmp_path / "kitti_eval_canary_mod.py").write_text(
        f"open({str(canary)!r}, 'w').close()\ndef run():\n    pass\n")
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
    data = (b"\x80\x02]q\x00}q\x01(X\x08\x00\x00\x00frame_idq\x02X\x06\x00\x00\x00000001q\x03"
            b"X\x05\x00\x00\x00scoreq\x04ctorch\nFloatStorage\nq\x05)Rq\x06ua.")
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


@pytest.mark.parametrize("data", [
    b"\x80\x02cnumpy\nmemmap\nq\x00.",
    b"\x80\x02cnumpy.ma.core\n_mareconstruct\nq\x00.",
    b"\x80\x02cnumpy.lib.npyio\nNpzFile\nq\x00.",
    b"\x80\x02cnumpy.testing\nassert_equal\nq\x00.",
])
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


@pytest.mark.parametrize("dtype", [np.dtype([("a", "<f8"), ("b", "<i4")]), np.dtype("V8"), np.dtype("M8[s]"),
                                   np.dtype([("a", "<f8", (2,))])])
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
    assert loads(pickle.dumps(np.array(["Car", 1, 2.5, None], dtype=object), protocol=2)).tolist() == \
        ["Car", 1, 2.5, None]
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
SCALARS = {"float32": np.float32(1.5), "str_": np.str_("000001"), "int64": np.int64(-7),
           "bool_": np.bool_(True), "float64": np.float64(0.1)}


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
        "frames": [{"frame_id": np.str_("000001"), "name": np.array(["Car"]), "score": np.float32([0.9])},
                   {"frame_id": 2, "name": np.zeros(0), "bbox": np.zeros((0, 4))}],
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
        "numpy.core.multiarray._reconstruct", "numpy._core.multiarray._reconstruct",
        "numpy.core.numeric._frombuffer", "numpy._core.numeric._frombuffer",
        "numpy.ndarray", "numpy.dtype", "numpy.core.multiarray.scalar", "numpy._core.multiarray.scalar",
        "_codecs.encode", "collections.OrderedDict", "builtins.bytes", "__builtin__.bytes"}


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
