"""The one place kitti_eval unpickles: a restricted unpickler for numpy arrays and plain containers.

Ground truth and predictions arrive as pickles (OpenPCDet's ``kitti_infos_val.pkl`` and ``result.pkl``),
often uploaded by someone else. ``pickle.load`` on such a file runs whatever callables it names, so
:func:`load_pickle` never imports anything and calls only a short allowlist of numpy reconstructors,
each through a wrapper that checks its arguments:

* ``numpy.core.multiarray._reconstruct`` / ``numpy._core.multiarray._reconstruct`` with ``numpy.ndarray``
  (the empty shell numpy pickles every array as; its data arrive by ``__setstate__``),
* ``numpy.core.numeric._frombuffer`` / ``numpy._core.numeric._frombuffer`` (arrays at protocol 5),
* ``numpy.dtype`` (plain numeric, bool, str, bytes and object dtypes; no structured or datetime dtypes),
* ``numpy.core.multiarray.scalar`` / ``numpy._core.multiarray.scalar`` (``np.float32(1.5)``, ``np.str_``),
* ``_codecs.encode`` (latin-1 only: how protocols 0-2 store bytes),
* ``collections.OrderedDict`` without arguments (its items come by ``SETITEMS``),
* ``builtins.bytes`` without arguments (how protocols 0-2 store ``b""``, e.g. an empty array's data).

numpy 2 does not pickle the ``numpy.dtypes.*DType`` classes for these dtypes (a ``dtype`` pickles as
``numpy.dtype(code)`` plus a state tuple), so they are not on the list.

The unpickler is the pure-Python one (:class:`pickle._Unpickler`) because numpy's own ``__setstate__``
trusts its input: a dtype state can declare structured fields at offsets outside the item, or object
fields over raw bytes, which reads or frees arbitrary memory later. So every ``BUILD`` is checked here:
a dtype state must be exactly the canonical state of a plain dtype, an array state must carry a plain
dtype and a buffer of exactly ``prod(shape) * itemsize`` bytes. ``REDUCE`` may call only the
allowlist; ``NEWOBJ``, extension codes and persistent ids are refused; object arrays may hold only str,
numbers and None (so nothing nests through them); tuples used as dict keys may nest at most 100 deep
(CPython's tuple hash recurses in C without a guard); and the bytes that reconstructors produce are
budgeted (a few times the input size), so a small pickle cannot claim a huge array.

Cost: KITTI-val-sized files (3769 frames) load in ~0.43 s (result.pkl.gz, 22 MB, 41k arrays) and ~0.58 s
(kitti_infos_val.pkl.gz, 9 MB, 64k arrays), about 3x the unchecked C unpickler, which cannot be hooked.
"""

from __future__ import annotations

import collections
import gzip
import io
import math
import os
import pickle
import re
import struct
import zlib
from collections.abc import Callable
from typing import IO, Any

import numpy as np

from .errors import InputError, UnsafePickleError

__all__ = ["load_pickle", "ALLOWED_GLOBALS", "GZIP_MAGIC"]

try:  # numpy >= 2 (numpy 1.26 also ships the numpy._core aliases)
    from numpy._core import multiarray as _np_multiarray
except ImportError:  # pragma: no cover - old numpy
    from numpy.core import multiarray as _np_multiarray  # type: ignore[no-redef]

_np_scalar = _np_multiarray.scalar

GZIP_MAGIC = b"\x1f\x8b"
_ZIP_MAGIC = b"PK\x03\x04"
_NPY_MAGIC = b"\x93NUMPY"
#: what ``torch.save`` writes first in its legacy (non-zip) format: a pickled int
_TORCH_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
#: array element kinds accepted: bool, signed/unsigned int, float, complex, str, bytes, object
_PLAIN_KINDS = frozenset("biufcUSO")
_DTYPE_CODE = re.compile(r"[biufcUSO][0-9]{0,10}")
_READ_CHUNK = 1 << 20
_MAX_KEY_DEPTH = 100
#: what an object array may hold (numpy scalars too): nothing that nests, so nothing that deallocates
#: recursively (an object array of object arrays 1e5 deep overflows the C stack when freed)
_PLAIN_ITEM_TYPES = frozenset({str, int, float, bool, complex, bytes, type(None)})

#: every global a pickle may name, as (module, name); anything else raises UnsafePickleError
ALLOWED_GLOBALS: frozenset[tuple[str, str]] = frozenset({
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("_codecs", "encode"), ("collections", "OrderedDict"),
    ("builtins", "bytes"), ("__builtin__", "bytes"),  # b"" at protocols 0-2 is bytes(); only bytes() allowed
})


# --------------------------------------------------------------------------------------------- errors

def _unsafe(source: str, module: str, name: str) -> UnsafePickleError:
    qual = f"{module}.{name}"
    top = module.split(".", 1)[0]
    if top == "torch":
        return UnsafePickleError(
            f"the pickle holds torch tensors (it refers to {qual}); it was not loaded. Export predictions "
            "as plain numpy arrays (e.g. call .numpy() on each tensor, or .cpu().numpy() on GPU tensors) "
            "and pickle the list of per-frame dicts", source=source)
    if top in ("mmdet3d", "mmdet", "mmengine", "mmcv"):
        return UnsafePickleError(
            f"the pickle holds mmdet3d box objects or other OpenMMLab classes (it refers to {qual}); it was "
            "not loaded. Export predictions as plain numpy arrays (e.g. boxes.tensor.numpy(), and .numpy() "
            "on each tensor) in KITTI annos dicts (name, bbox, dimensions, location, rotation_y, score)",
            source=source)
    if top == "numpy":
        return UnsafePickleError(
            f"the pickle refers to {qual}, which is not accepted; only numpy arrays of numbers or "
            "fixed-width strings, numpy scalars and plain containers are accepted (nothing was imported "
            "or called)", source=source)
    return UnsafePickleError(
        f"the pickle refers to {qual}; only numpy arrays and plain containers (dict, list, tuple, str, "
        "numbers) are accepted. Nothing was imported or called", source=source)


class _Refused(Exception):
    """Raised inside the unpickler for hostile-looking structure; turned into UnsafePickleError."""


class _Malformed(Exception):
    """Raised inside the unpickler for inconsistent numpy data; turned into InputError."""


# ------------------------------------------------------------------------------------------ unpickler

def _shape(value: object, what: str) -> tuple[int, ...]:
    if type(value) is tuple and len(value) <= 64:
        for v in value:
            if type(v) is not int or v < 0:
                break
        else:
            return value
    if not isinstance(value, tuple) or len(value) > 64:
        raise _Malformed(f"{what}: shape must be a tuple of at most 64 sizes, got {type(value).__name__}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise _Malformed(f"{what}: bad dimension {v!r} in shape")
        out.append(int(v))
    return tuple(out)


def _plain_dtype(dt: object, what: str) -> np.dtype:
    if not isinstance(dt, np.dtype):
        raise _Refused(f"{what}: expected a numpy dtype, got {type(dt).__name__}")
    if dt.kind not in _PLAIN_KINDS or dt.names is not None or dt.subdtype is not None or \
            dt.hasobject != (dt.kind == "O"):
        raise _Refused(f"{what}: numpy dtype {dt!r} is not accepted (structured, datetime and void dtypes "
                       "are refused)")
    return dt


class _RestrictedUnpickler(pickle._Unpickler):  # type: ignore[name-defined,misc]
    dispatch = dict(pickle._Unpickler.dispatch)  # type: ignore[attr-defined]

    def __init__(self, file: IO[bytes], *, source: str, budget: int) -> None:
        super().__init__(file, fix_imports=False, encoding="ASCII", errors="strict")
        self._input = file
        self._source = source
        self._budget = budget
        # objects made by the wrappers that still await their one BUILD, by id (holding them alive)
        self._fresh: dict[int, object] = {}
        self._globals: dict[tuple[str, str], object] = {
            ("numpy.core.multiarray", "_reconstruct"): self._reconstruct,
            ("numpy._core.multiarray", "_reconstruct"): self._reconstruct,
            ("numpy.core.numeric", "_frombuffer"): self._frombuffer,
            ("numpy._core.numeric", "_frombuffer"): self._frombuffer,
            ("numpy", "ndarray"): np.ndarray,  # only ever an argument of _reconstruct, never called
            ("numpy", "dtype"): self._dtype,
            ("numpy.core.multiarray", "scalar"): self._scalar,
            ("numpy._core.multiarray", "scalar"): self._scalar,
            ("_codecs", "encode"): self._encode,
            ("collections", "OrderedDict"): self._ordered_dict,
            ("builtins", "bytes"): self._empty_bytes,
            ("__builtin__", "bytes"): self._empty_bytes,
        }
        assert set(self._globals) == ALLOWED_GLOBALS
        self._key_nodes = 1 << 22  # tuple elements walked when checking dict keys, in all
        self._plain: dict[int, np.dtype] = {}  # dtypes already checked and complete, by id
        self._callables = {id(f): f for k, f in self._globals.items() if k != ("numpy", "ndarray")}

    def load(self) -> object:
        """The stdlib loop, reading straight from the in-memory input: frames (protocol 4+) are only a
        buffering hint, so FRAME is skipped instead of routed through pickle's Python-level _Unframer."""
        self.read = self._input.read
        self.readline = self._input.readline
        self.readinto = self._input.readinto
        self.metastack = []
        self.stack: list[Any] = []
        self.append = self.stack.append
        self.proto = 0
        read = self.read
        dispatch = self.dispatch
        try:
            while True:
                key = read(1)
                if not key:
                    raise EOFError("the pickle ends before its STOP opcode (truncated?)")
                dispatch[key[0]](self)
        except pickle._Stop as stop:  # type: ignore[attr-defined]
            return stop.value

    def _load_frame(self) -> None:
        if len(self.read(8)) != 8:
            raise EOFError("truncated frame header")

    dispatch[pickle.FRAME[0]] = _load_frame

    def _load_bytearray8(self) -> None:  # the stdlib allocates the claimed size before reading
        (size,) = struct.unpack("<Q", self.read(8))
        data = self.read(size)
        if len(data) != size:
            raise EOFError("the pickle ends inside a byte array (truncated?)")
        self.append(bytearray(data))

    dispatch[pickle.BYTEARRAY8[0]] = _load_bytearray8

    # -- the allowlist -----------------------------------------------------------------------------
    def find_class(self, module: str, name: str) -> Any:
        obj = self._globals.get((module, name))
        if obj is None:
            raise _unsafe(self._source, module, name)
        return obj

    def _spend(self, nbytes: int) -> None:
        self._budget -= nbytes
        if self._budget < 0:
            raise _Malformed("the pickle builds far more array data than it contains (a corrupt or "
                             "hostile size)")

    def _complete_dtype(self, dtype: object, what: str) -> np.dtype:
        """A dtype made and built (BUILD done) by this unpickler, checked once per object."""
        dt = self._plain.get(id(dtype))
        if dt is dtype:
            return dt
        dt = _plain_dtype(dtype, what)
        if id(dt) in self._fresh:
            raise _Malformed(f"{what} of an incomplete dtype (no state)")
        self._plain[id(dt)] = dt
        return dt

    def _reconstruct(self, subtype: object, shape: object, code: object) -> np.ndarray:
        if subtype is not np.ndarray:
            raise _Refused(f"arrays of type {getattr(subtype, '__name__', type(subtype).__name__)} are not "
                           "accepted, only numpy.ndarray")
        if math.prod(_shape(shape, "array header")) != 0 or type(code) not in (bytes, str) or \
                code not in (b"b", "b"):
            raise _Malformed("malformed numpy array header (numpy writes an empty int8 shell)")
        arr = np.ndarray((0,), np.int8)
        self._fresh[id(arr)] = arr
        return arr

    def _frombuffer(self, buf: object, dtype: object, shape: object, order: object = "C") -> np.ndarray:
        dt = self._complete_dtype(dtype, "array")
        if dt.hasobject:
            raise _Malformed("an object array cannot come from a raw buffer")
        shp = _shape(shape, "array")
        if not isinstance(buf, (bytes, bytearray)):
            raise _Malformed(f"array buffer must be bytes, got {type(buf).__name__}")
        if order not in ("C", "F"):
            raise _Malformed(f"bad array order {order!r}")
        need = math.prod(shp) * dt.itemsize
        if len(buf) != need:
            raise _Malformed(f"array of shape {shp} and dtype {dt} needs {need} bytes, the pickle holds "
                             f"{len(buf)}")
        self._spend(need)
        return np.frombuffer(buf, dtype=dt).reshape(shp, order=order)

    def _dtype(self, code: object, align: object = False, copy: object = True) -> np.dtype:
        if isinstance(code, bytes):
            code = code.decode("ascii", "replace")
        if not isinstance(code, str) or not _DTYPE_CODE.fullmatch(code):
            raise _Refused(f"numpy dtype {code!r} is not accepted (only plain numeric, str, bytes and object "
                           "dtypes)")
        dt = np.dtype(code, bool(align), True)  # copy=True: never the shared builtin instance
        _plain_dtype(dt, "dtype")
        self._fresh[id(dt)] = dt
        return dt

    def _scalar(self, dtype: object, data: object = None) -> object:
        dt = self._complete_dtype(dtype, "numpy scalar")
        if dt.kind == "O":
            return data  # what numpy does: an object scalar is the object itself
        if not isinstance(data, bytes) or len(data) != dt.itemsize:
            raise _Malformed(f"numpy scalar of dtype {dt} needs {dt.itemsize} bytes")
        self._spend(len(data))
        return _np_scalar(dt, data)

    def _encode(self, obj: object, encoding: object = "utf-8", errors: object = "strict") -> bytes:
        if not isinstance(obj, str) or not isinstance(encoding, str) or \
                encoding.lower().replace("_", "-") not in ("latin1", "latin-1", "iso-8859-1"):
            raise _Refused("_codecs.encode is accepted only to turn a str into latin-1 bytes")
        self._spend(len(obj))
        return obj.encode("latin-1")

    @staticmethod
    def _ordered_dict(*args: object) -> collections.OrderedDict[Any, Any]:
        if args:  # items arrive by SETITEMS, where keys are checked
            raise _Refused("OrderedDict is accepted only without arguments (as pickle writes it)")
        return collections.OrderedDict()

    @staticmethod
    def _empty_bytes(*args: object) -> bytes:
        if args:
            raise _Refused("bytes() is accepted only without arguments (an empty bytes object)")
        return b""

    # -- opcodes that call or mutate ---------------------------------------------------------------
    def _call(self, func: object, args: object) -> object:
        if id(func) not in self._callables or self._callables[id(func)] is not func:
            raise _Refused(f"the pickle calls {getattr(func, '__name__', type(func).__name__)}, which is not "
                           "allowed")
        if not isinstance(args, tuple):
            raise _Malformed("call arguments must be a tuple")
        return func(*args)  # type: ignore[operator]

    def load_reduce(self) -> None:
        stack = self.stack
        args = stack.pop()
        stack[-1] = self._call(stack[-1], args)

    dispatch[pickle.REDUCE[0]] = load_reduce

    def _instantiate(self, klass: object, args: object) -> None:  # INST and OBJ (protocols 0/1)
        self.append(self._call(klass, tuple(args) if isinstance(args, list) else args))

    def _refuse_newobj(self) -> None:
        raise _Refused("the pickle instantiates a class (NEWOBJ), which is not allowed")

    dispatch[pickle.NEWOBJ[0]] = _refuse_newobj
    dispatch[pickle.NEWOBJ_EX[0]] = _refuse_newobj

    # -- opcodes that hash: a tuple nested ~1e6 deep crashes CPython's tuple hash (no recursion guard) ----
    def _check_keys(self, keys: list[Any]) -> None:
        for key in keys:
            if type(key) is tuple:
                todo = [(key, 1)]
                while todo:
                    t, depth = todo.pop()
                    self._key_nodes -= len(t)
                    if depth > _MAX_KEY_DEPTH or self._key_nodes < 0:
                        raise _Malformed("a dict key or set item is a tuple nested too deeply")
                    todo.extend((x, depth + 1) for x in t if type(x) is tuple)

    def load_dict(self) -> None:
        self._check_keys(self.stack[0::2])
        pickle._Unpickler.load_dict(self)  # type: ignore[attr-defined]

    dispatch[pickle.DICT[0]] = load_dict

    def load_setitem(self) -> None:
        self._check_keys(self.stack[-2:-1])
        pickle._Unpickler.load_setitem(self)  # type: ignore[attr-defined]

    dispatch[pickle.SETITEM[0]] = load_setitem

    def load_setitems(self) -> None:
        self._check_keys(self.stack[0::2])
        pickle._Unpickler.load_setitems(self)  # type: ignore[attr-defined]

    dispatch[pickle.SETITEMS[0]] = load_setitems

    def load_additems(self) -> None:
        self._check_keys(self.stack)
        pickle._Unpickler.load_additems(self)  # type: ignore[attr-defined]

    dispatch[pickle.ADDITEMS[0]] = load_additems

    def load_frozenset(self) -> None:
        self._check_keys(self.stack)
        pickle._Unpickler.load_frozenset(self)  # type: ignore[attr-defined]

    dispatch[pickle.FROZENSET[0]] = load_frozenset

    def _refuse_ext(self) -> None:
        raise _Refused("the pickle uses copyreg extension codes, which are not accepted")

    for _op in (pickle.EXT1, pickle.EXT2, pickle.EXT4):
        dispatch[_op[0]] = _refuse_ext
    del _op

    def persistent_load(self, pid: object) -> object:
        raise _Refused("the pickle refers to external (persistent) objects, e.g. torch storages; they are "
                       "not accepted")

    def load_build(self) -> None:
        stack = self.stack
        state = stack.pop()
        inst = stack[-1]
        if self._fresh.pop(id(inst), None) is not inst:
            raise _Refused(f"the pickle sets the state of a {type(inst).__name__}, which is not allowed")
        if isinstance(inst, np.dtype):
            self._build_dtype(inst, state)
        else:
            self._build_array(inst, state)

    dispatch[pickle.BUILD[0]] = load_build

    def _build_dtype(self, dt: np.dtype, state: object) -> None:
        """Accept exactly the state numpy itself writes for a plain dtype of this kind."""
        if not isinstance(state, tuple) or len(state) != 8 or state[0] != 3:
            raise _Refused("unsupported numpy dtype state")
        byteorder, elsize = state[1], state[5]
        if byteorder not in ("<", ">", "|", "=") or isinstance(elsize, bool) or not isinstance(elsize, int):
            raise _Refused("unsupported numpy dtype state")
        if dt.kind in "US":
            per_char = 4 if dt.kind == "U" else 1
            if elsize < 0 or elsize % per_char or elsize > (1 << 31):
                raise _Malformed(f"bad string size {elsize} in a numpy dtype")
            want = np.dtype(f"{dt.kind}{elsize // per_char}")
        else:
            want = np.dtype(dt.str[1:])
        if byteorder in "<>" and want.byteorder != "|":
            want = want.newbyteorder(byteorder)
        canonical = want.__reduce__()[2]
        if state != canonical:
            raise _Refused(f"numpy dtype state {state!r} is not the plain state of {want} (structured "
                           "dtypes and custom flags are refused)")
        dt.__setstate__(state)
        if dt != want or dt.itemsize != want.itemsize:  # pragma: no cover - belt and braces
            raise _Refused("numpy dtype state did not produce a plain dtype")

    def _build_array(self, arr: np.ndarray, state: object) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _Malformed("unsupported numpy array state")
        if len(state) == 5:
            if state[0] != 1:
                raise _Malformed(f"unsupported numpy array state version {state[0]!r}")
            state = state[1:]
        shape, dtype, fortran, raw = state
        shp = _shape(shape, "array")
        dt = self._complete_dtype(dtype, "array")
        if not isinstance(fortran, (bool, int)):
            raise _Malformed("bad array order flag")
        count = math.prod(shp)
        if dt.hasobject:
            if not isinstance(raw, list) or len(raw) != count:
                raise _Malformed(f"object array of shape {shp} needs a list of {count} items")
            for item in raw:
                if type(item) not in _PLAIN_ITEM_TYPES and not isinstance(item, np.generic):
                    raise _Refused(f"object arrays may hold only str, numbers and None, not "
                                   f"{type(item).__name__}")
        else:
            if not isinstance(raw, (bytes, bytearray)):
                raise _Malformed(f"array data must be bytes, got {type(raw).__name__}")
            need = count * dt.itemsize
            if len(raw) != need:
                raise _Malformed(f"array of shape {shp} and dtype {dt} needs {need} bytes, the pickle "
                                 f"holds {len(raw)}")
            self._spend(need)
        arr.__setstate__((1, shp, dt, bool(fortran), raw))


# ---------------------------------------------------------------------------------------------- input

def _read_limited(read: Callable[[int], bytes], max_bytes: int | None, what: str, source: str) -> bytes:
    chunks: list[bytes] = []
    total = 0
    while max_bytes is None or total <= max_bytes:
        want = _READ_CHUNK * 16 if max_bytes is None else min(_READ_CHUNK * 16, max_bytes + 1 - total)
        chunk = read(want)
        if not chunk:
            break
        if not isinstance(chunk, (bytes, bytearray)):
            raise InputError(f"expected binary data, got {type(chunk).__name__} (open the file in 'rb' mode)",
                             source=source)
        chunks.append(bytes(chunk))
        total += len(chunk)
    if max_bytes is not None and total > max_bytes:
        raise InputError(f"{what} is larger than the limit of {max_bytes} bytes", source=source)
    return b"".join(chunks)


def _read_input(path_or_fileobj: str | os.PathLike[str] | IO[bytes], source: str,
                max_bytes: int | None) -> bytes:
    if hasattr(path_or_fileobj, "read"):
        try:
            read = path_or_fileobj.read  # type: ignore[union-attr]
            data = _read_limited(read, max_bytes, "the upload", source)
        except OSError as e:
            raise InputError(f"cannot read: {e}", source=source) from None
    else:
        path = os.fspath(path_or_fileobj)  # type: ignore[arg-type]
        try:
            with open(path, "rb") as fh:
                data = _read_limited(fh.read, max_bytes, "the file", source)
        except FileNotFoundError:
            raise InputError(f"no such file: {path}", source=source) from None
        except IsADirectoryError:
            raise InputError(f"{path} is a directory, not a pickle", source=source) from None
        except OSError as e:
            raise InputError(f"cannot read {path}: {e.strerror or e}", source=source) from None
    if data[:2] == GZIP_MAGIC:
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(data), mode="rb") as gz:
                data = _read_limited(gz.read, max_bytes, "the decompressed gzip data", source)
        except InputError:
            raise
        except (OSError, EOFError, zlib.error, ValueError, MemoryError) as e:
            raise InputError(f"not a readable gzip file: {e or type(e).__name__}", source=source) from None
    return data


def _sniff(data: bytes, source: str) -> None:
    if not data:
        raise InputError("not a readable pickle: the file is empty", source=source)
    if data[:4] == _ZIP_MAGIC:
        raise InputError("not a readable pickle: this is a zip archive (a torch.save() file or a numpy "
                         ".npz?). "
                         "Export predictions as plain numpy arrays and pickle the list of per-frame dicts",
                         source=source)
    if data[257:262] == b"ustar":
        raise InputError("not a readable pickle: this is a tar archive; extract it (KITTI txt folders are "
                         "read as folders)", source=source)
    if data[:6] == _NPY_MAGIC:
        raise InputError("not a readable pickle: this is a numpy .npy file; pickle the list of per-frame "
                         "dicts", source=source)


def load_pickle(path_or_fileobj: str | os.PathLike[str] | IO[bytes], *, source: str,
                max_bytes: int | None = None) -> object:
    """Unpickle a file that may only hold numpy arrays, numpy scalars and plain containers.

    Parameters
    ----------
    path_or_fileobj : a path, or a binary file object (read to its end)
    source : a name for messages (usually the path or the upload's name)
    max_bytes : refuse input (after gzip decompression) larger than this; ``None``: no limit

    gzip input (magic ``1f 8b``) is decompressed transparently, whatever the file name.

    Raises
    ------
    UnsafePickleError : the pickle refers to anything outside the allowlist (e.g. ``os.system``, torch
        tensors, mmdet3d boxes) or sets state that numpy would not write; nothing was imported or called
    InputError : missing, empty, truncated or corrupt input, or input over ``max_bytes``
    """
    data = _read_input(path_or_fileobj, source, max_bytes)
    _sniff(data, source)
    unpickler = _RestrictedUnpickler(io.BytesIO(data), source=source, budget=4 * len(data) + (16 << 20))
    try:
        obj = unpickler.load()
    except InputError:
        raise
    except _Refused as e:
        raise UnsafePickleError(f"{e}; it was not loaded (only numpy arrays and plain containers are "
                                "accepted)", source=source) from None
    except _Malformed as e:
        raise InputError(f"not a readable pickle: {e}", source=source) from None
    except MemoryError:
        raise InputError("not a readable pickle: it needs more memory than is available (corrupt sizes?)",
                         source=source) from None
    except RecursionError:
        raise InputError("not a readable pickle: nested too deeply", source=source) from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError, AttributeError,
            OverflowError, UnicodeError, struct.error, OSError, zlib.error) as e:
        raise InputError(f"not a readable pickle: {type(e).__name__}: {e}", source=source) from None
    except Exception as e:  # noqa: BLE001 - only allowlisted code ran; any failure means bad input
        raise InputError(f"not a readable pickle: {type(e).__name__}: {e}", source=source) from None
    finally:
        unpickler._fresh.clear()
        unpickler._plain.clear()
    if isinstance(obj, int) and not isinstance(obj, bool) and obj == _TORCH_LEGACY_MAGIC:
        raise UnsafePickleError("this is a torch.save() file (legacy format) holding torch tensors; it was "
                                "not loaded. Export predictions as plain numpy arrays (e.g. .numpy() on each "
                                "tensor) and pickle the list of per-frame dicts", source=source)
    return obj
