"""The one place kitti_eval unpickles: a restricted unpickler for numpy arrays and plain containers.

Ground truth and predictions arrive as pickles (OpenPCDet's ``kitti_infos_val.pkl`` and ``result.pkl``),
often uploaded by someone else. ``pickle.load`` on such a file runs whatever callables it names, and even
numpy's own reconstructors trust their input (a dtype state can declare structured fields outside the item,
or object fields over raw bytes, which reads or frees arbitrary memory later). So :func:`load_pickle`
imports nothing and calls only numpy's reconstructors, with the arguments numpy itself writes:

* ``numpy.core.multiarray._reconstruct`` / ``numpy._core.multiarray._reconstruct`` with ``numpy.ndarray``
  (the empty shell numpy pickles every array as; its data arrive by ``BUILD``),
* ``numpy.core.numeric._frombuffer`` / ``numpy._core.numeric._frombuffer`` (arrays at protocol 5),
* ``numpy.dtype`` (plain numeric, bool, str, bytes and object dtypes; no structured or datetime dtypes),
* ``numpy.core.multiarray.scalar`` / ``numpy._core.multiarray.scalar`` (``np.float32(1.5)``, ``np.str_``),
* ``_codecs.encode`` (latin-1 only: how protocols 0-2 store bytes),
* ``collections.OrderedDict`` without arguments (its items come by ``SETITEMS``),
* ``builtins.bytes`` without arguments (how protocols 0-2 store ``b""``, e.g. an empty array's data).

How: :func:`kitti_eval.io._pickle_scan.scan` (numba) first runs the whole opcode stream through a model of
CPython's C unpickler and refuses the pickle unless every call and every ``BUILD`` is one of the above with
checked arguments and states, nesting, hashing, the memo and the bytes built stay bounded (see its
docstring); only then does the C unpickler (:class:`pickle.Unpickler`) build the objects from the same
bytes, with ``find_class`` handing out exactly the globals the scan saw, in the same order. The scan takes
about 10 ms on a KITTI-val-sized result.pkl (22 MB, 41k arrays).
"""

from __future__ import annotations

import codecs
import collections
import gzip
import io
import os
import pickle
import zlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import IO, Any, cast

import numpy as np

from ..core.budget import setting_name
from ..errors import InputError, UnsafePickleError
from . import _pickle_scan as _ps

__all__ = [
    "load_pickle",
    "load_pickles",
    "check_pickle",
    "check_pickles",
    "CheckedPickle",
    "ALLOWED_GLOBALS",
    "GZIP_MAGIC",
]

try:  # numpy >= 2 (numpy 1.26 also ships the numpy._core aliases)
    from numpy._core import multiarray as _np_multiarray
    from numpy._core import numeric as _np_numeric
except ImportError:  # pragma: no cover - old numpy
    from numpy.core import multiarray as _np_multiarray  # type: ignore[no-redef]
    from numpy.core import numeric as _np_numeric  # type: ignore[no-redef]

GZIP_MAGIC = b"\x1f\x8b"
_ZIP_MAGIC = b"PK\x03\x04"
_NPY_MAGIC = b"\x93NUMPY"
#: what ``torch.save`` writes first in its legacy (non-zip) format: a pickled int
_TORCH_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_MAX_DEPTH = 100
Buffer = bytes | bytearray  # a pickle's bytes: as read, or gathered from a decompressing reader
_KEY_BUDGET = 1 << 22  # elements of tuples hashed as dict keys and set members, in all


# ------------------------------------------------------------------------------------------ allowlist

#: (module, name, what the scan lets it do, what ``find_class`` returns), in the order the scan numbers them
_GLOBALS: tuple[tuple[str, str, int, object], ...] = (
    ("numpy.core.multiarray", "_reconstruct", _ps.FN_RECONSTRUCT, _np_multiarray._reconstruct),
    ("numpy._core.multiarray", "_reconstruct", _ps.FN_RECONSTRUCT, _np_multiarray._reconstruct),
    ("numpy.core.numeric", "_frombuffer", _ps.FN_FROMBUFFER, _np_numeric._frombuffer),  # type: ignore[attr-defined]
    ("numpy._core.numeric", "_frombuffer", _ps.FN_FROMBUFFER, _np_numeric._frombuffer),  # type: ignore[attr-defined]
    ("numpy", "ndarray", _ps.FN_NDARRAY, np.ndarray),  # only ever the subtype argument of _reconstruct
    ("numpy", "dtype", _ps.FN_DTYPE, np.dtype),
    ("numpy.core.multiarray", "scalar", _ps.FN_SCALAR, _np_multiarray.scalar),
    ("numpy._core.multiarray", "scalar", _ps.FN_SCALAR, _np_multiarray.scalar),
    ("_codecs", "encode", _ps.FN_ENCODE, codecs.encode),
    ("collections", "OrderedDict", _ps.FN_ODICT, collections.OrderedDict),
    ("builtins", "bytes", _ps.FN_BYTES, bytes),  # b"" at protocols 0-2 is bytes()
    ("__builtin__", "bytes", _ps.FN_BYTES, bytes),
)

#: every global a pickle may name, as (module, name); anything else raises UnsafePickleError
ALLOWED_GLOBALS: frozenset[tuple[str, str]] = frozenset((m, n) for m, n, _, _ in _GLOBALS)
_GLOBAL_ROW = {(m, n): i for i, (m, n, _, _) in enumerate(_GLOBALS)}
_GLOBAL_OBJ = tuple(obj for _, _, _, obj in _GLOBALS)


def _globals_table() -> tuple[np.ndarray, np.ndarray]:
    blob = bytearray()
    rows = []
    for module, name, fn, _ in _GLOBALS:
        m, n = module.encode("ascii"), name.encode("ascii")
        rows.append((len(blob), len(m), len(blob) + len(m), len(n), fn))
        blob += m + n
    return np.frombuffer(bytes(blob), np.uint8), np.array(rows, np.int64)


def _canonical_state(dt: np.dtype, byteorder: str) -> tuple[Any, ...]:
    """The state numpy writes for a plain dtype like ``dt`` stored in ``byteorder``."""
    if byteorder in "<>" and dt.byteorder != "|":
        dt = dt.newbyteorder("<" if byteorder == "<" else ">")
    return cast(tuple[Any, ...], dt.__reduce__()[2])


def _dtype_table() -> tuple[np.ndarray, np.ndarray]:
    """The dtype codes ``numpy.dtype`` may be called with and the states their BUILD must carry, from
    numpy itself: every plain numeric code numpy writes (``f8``, ``b1``, ``c16``, ``O8``, ...) and the
    ``U<n>`` / ``S<n>`` families (one row each, the size comes from the state)."""
    blob = bytearray()
    rows = []

    def add(code: str, dt: np.dtype, itemsize: int, sample_sizes: tuple[int, ...]) -> None:
        mask = 0
        fields: set[tuple[int, int, int]] = set()
        for bit, bo in enumerate("<>|"):
            for size in sample_sizes:
                want = np.dtype(f"{dt.kind}{size}") if itemsize < 0 else dt
                state = _canonical_state(want, bo)
                if state[1] != bo:
                    continue
                assert state[0] == 3 and state[2:5] == (None, None, None)
                assert itemsize >= 0 or state[5] == want.itemsize  # U/S: the state gives the size
                fields.add((state[5] if itemsize >= 0 else -1, state[6], state[7]))
                mask |= 1 << bit
        assert len(fields) == 1, (code, fields)  # the same canonical fields for every size and order
        ((elsize, align, flags),) = fields
        c = code.encode("ascii")
        rows.append((len(blob), len(c), ord(dt.kind), itemsize, mask, elsize, align, flags))
        blob.extend(c)

    for kind, sizes in (
        ("b", (1,)),
        ("i", (1, 2, 4, 8)),
        ("u", (1, 2, 4, 8)),
        ("f", (2, 4, 8, 16)),
        ("c", (8, 16, 32)),
    ):
        for size in sizes:
            code = f"{kind}{size}"
            try:
                dt = np.dtype(code)
            except TypeError:  # pragma: no cover - platform without this long double
                continue
            if dt.kind == kind and dt.itemsize == size and dt.__reduce__()[1][0] == code:
                add(code, dt, size, (size,))
    obj = np.dtype("O")
    add(obj.__reduce__()[1][0], obj, obj.itemsize, (obj.itemsize,))
    add("U", np.dtype("U1"), -1, (0, 1, 7, 40))
    add("S", np.dtype("S1"), -1, (0, 1, 7, 40))
    return np.frombuffer(bytes(blob), np.uint8), np.array(rows, np.int64)


_GBLOB, _GTAB = _globals_table()
_DBLOB, _DTAB = _dtype_table()


def _unsafe(source: str, module: str, name: str) -> UnsafePickleError:
    qual = f"{module}.{name}"
    top = module.split(".", 1)[0]
    if top == "torch":
        return UnsafePickleError(
            f"the pickle holds torch tensors (it refers to {qual}); it was not loaded. Export predictions "
            "as plain numpy arrays (e.g. call .numpy() on each tensor, or .cpu().numpy() on GPU tensors) "
            "and pickle the list of per-frame dicts",
            source=source,
        )
    if top in ("mmdet3d", "mmdet", "mmengine", "mmcv"):
        return UnsafePickleError(
            f"the pickle holds mmdet3d box objects or other OpenMMLab classes (it refers to {qual}); it was "
            "not loaded. Export predictions as plain numpy arrays (e.g. boxes.tensor.numpy(), and .numpy() "
            "on each tensor) in KITTI annos dicts (name, bbox, dimensions, location, rotation_y, score)",
            source=source,
        )
    if top == "numpy":
        return UnsafePickleError(
            f"the pickle refers to {qual}, which is not accepted; only numpy arrays of numbers or "
            "fixed-width strings, numpy scalars and plain containers are accepted (nothing was imported "
            "or called)",
            source=source,
        )
    return UnsafePickleError(
        f"the pickle refers to {qual}; only numpy arrays and plain containers (dict, list, tuple, str, "
        "numbers) are accepted. Nothing was imported or called",
        source=source,
    )


# ------------------------------------------------------------------------------- scan errors to messages


class _Nodes:
    """Read access to the scan's nodes, for messages."""

    def __init__(self, data: Buffer, nodes: np.ndarray, ch: np.ndarray) -> None:
        self.data, self.nodes, self.ch = data, nodes, ch

    def kind(self, n: int) -> int:
        return int(self.nodes[n, _ps.W]) & _ps.KIND_MASK if 0 <= n < len(self.nodes) else 0

    def text(self, n: int) -> str:
        """A str node as the C unpickler decodes it (best effort: only for messages)."""
        w, a, b = (int(self.nodes[n, c]) for c in (_ps.W, _ps.A, _ps.B))
        raw = bytes(self.data[a : a + b])
        op = (w >> _ps.OP_SHIFT) & 0xFF
        try:
            if op == ord("V"):
                return raw.decode("raw_unicode_escape")
            if op == ord("S"):
                return codecs.escape_decode(raw)[0].decode("ascii", "replace")
            return raw.decode("utf-8", "replace")
        except (UnicodeError, ValueError):
            return raw.decode("latin-1")

    def describe(self, n: int) -> str:
        k = self.kind(n)
        if k == _ps.K_GLOBAL:
            module, name, _, _ = _GLOBALS[int(self.nodes[n, _ps.V])]
            return f"{module}.{name}"
        if k == _ps.K_STR:
            return repr(self.text(n))
        return _ps.KIND_NAMES.get(k, "object")

    def shape(self, n: int) -> tuple[int, ...]:
        a, b = int(self.nodes[n, _ps.A]), int(self.nodes[n, _ps.B])
        return tuple(int(self.nodes[c, _ps.V]) for c in self.ch[a : a + b])

    def dtype(self, n: int) -> np.dtype:
        kind, size = chr(int(self.nodes[n, _ps.A])), int(self.nodes[n, _ps.V])
        return np.dtype(f"{kind}{size // 4 if kind == 'U' else size}")


def _mb(n: int) -> str:
    return f"{n / (1 << 20):.1f} MB"


def _budget_message(size: int, again: int) -> str:
    """Why a pickle of ``size`` bytes was refused for building more than its budget (``again`` bytes of what it
    would build, counted up to the refusal, are arrays charged again: values put into containers more than once)."""
    msg = (
        "the pickle builds far more array data or objects than it contains (a corrupt or hostile size): more than "
        f"the limit of {_mb(_budget(size))} for a pickle of {_mb(size)} (8 times its size + 32 MB, arrays of numbers "
        "counted at 8 bytes a value, as they are read)"
    )
    if again:
        msg += (
            f"; {_mb(again)} of what it would build, counted up to the refusal, are arrays it uses more than once "
            "(through its memo), counted each time, as each frame that uses one gets a copy"
        )
    return msg


def _line(data: Buffer, start: int) -> str:
    line = bytes(data[start : start + 4096])
    end = line.find(b"\n")
    return line[: end if end >= 0 else len(line)].decode("utf-8", "replace")


def _scan_error(res: tuple[Any, ...], data: Buffer, source: str) -> InputError:
    code, pos, i0, i1, i2, nodes, ch = (int(res[0]), int(res[1]), int(res[2]), int(res[3]), int(res[4]), res[5], res[6])
    nd = _Nodes(data, nodes, ch)
    if code == _ps.E_GLOBAL:
        if i0 == 0:
            return _unsafe(source, _line(data, i1), _line(data, i2))
        return _unsafe(source, nd.text(i1), nd.text(i2))
    refused = {
        _ps.E_NEWOBJ: "the pickle instantiates a class (NEWOBJ), which is not allowed",
        _ps.E_INST: "the pickle instantiates a class (INST/OBJ), which is not allowed",
        _ps.E_EXT: "the pickle uses copyreg extension codes, which are not accepted",
        _ps.E_PERSID: "the pickle refers to external (persistent) objects, e.g. torch storages; they are not accepted",
        _ps.E_CALL: f"the pickle calls {nd.describe(i0)}, which is not allowed",
        _ps.E_BUILD: f"the pickle sets the state of a {nd.describe(i0)}, which is not allowed (only fresh "
        "numpy arrays and dtypes)",
        _ps.E_GLOBAL_VALUE: f"the pickle uses {nd.describe(i0)} as a value, which is not allowed",
        _ps.E_DTYPE_CODE: f"numpy dtype {nd.describe(i0)} is not accepted (only plain numeric, str, bytes and "
        "object dtypes; structured, datetime and void dtypes are refused)",
        _ps.E_DTYPE_ARGS: "numpy.dtype is accepted only as numpy calls it: (code, align, copy=True)",
        _ps.E_DTYPE_STATE: "unsupported numpy dtype state: only the plain state numpy writes is accepted "
        "(structured dtypes and custom flags are refused)",
        _ps.E_SUBTYPE: f"arrays of type {nd.describe(i0)} are not accepted, only numpy.ndarray",
        _ps.E_OBJ_ITEMS: "object arrays may hold only str, numbers, bytes and None",
        _ps.E_ENCODE: "_codecs.encode is accepted only to turn a str into latin-1 bytes",
        _ps.E_ODICT_ARGS: "OrderedDict is accepted only without arguments (as pickle writes it)",
        _ps.E_BYTES_ARGS: "bytes() is accepted only without arguments (an empty bytes object)",
        _ps.E_SCALAR_OBJ: "numpy scalars of object dtype are not accepted",
        _ps.E_NOT_DTYPE: "numpy expects a dtype there, the pickle gives something else",
        _ps.E_TARGET: f"the pickle adds items to a {nd.describe(i0)}, which is not allowed",
    }
    if code in refused:
        return UnsafePickleError(
            f"{refused[code]}; it was not loaded (only numpy arrays and plain containers are accepted)", source=source
        )
    if code == _ps.E_BUDGET:
        msg = _budget_message(len(data), i1)
    elif code == _ps.E_WIDE:
        msg = (
            f"its str arrays (class names) hold {i0} strings or more, which read together at the widest one's width "
            f"({i1 // 4} characters) take over {_mb(i0 * i1)}, more than the limit of {_mb(_budget(len(data)))} "
            f"for a pickle of {_mb(len(data))} (8 times its size + 32 MB)"
        )
    elif code == _ps.E_SIZE:
        shape, dt = nd.shape(i0), nd.dtype(i1)
        need = int(np.prod(shape, dtype=object)) * dt.itemsize
        msg = f"array of shape {shape} and dtype {dt} needs {need} bytes, the pickle holds {i2}"
    elif code == _ps.E_LIST:
        shape = nd.shape(i1)
        msg = f"object array of shape {shape} needs a list of {int(np.prod(shape, dtype=object))} items"
    else:
        msg = {
            _ps.E_TRUNC: "the pickle ends before its STOP opcode (truncated?)",
            _ps.E_OPCODE: f"invalid opcode 0x{i0:02x}",
            _ps.E_UNDERFLOW: "unpickling stack underflow",
            _ps.E_NOMARK: "an opcode needs a MARK that is not there",
            _ps.E_BADARG: "malformed opcode argument",
            _ps.E_MEMO: f"memo value not found at index {i0}",
            _ps.E_MEMO_RANGE: f"memo index {i0} is far beyond the number of memo entries",
            _ps.E_ODD: "odd number of items for a dict",
            _ps.E_DEPTH: f"containers nested too deeply (more than {_MAX_DEPTH} levels)",
            _ps.E_KEYS: "dict keys or set items are tuples nested too deeply (too many elements to hash)",
            _ps.E_UNHASHABLE: f"a dict key or set item is a {nd.describe(i0)}, which cannot be hashed",
            _ps.E_CHANGED: "a container is changed after it was put into another one (recursive structures "
            "are not accepted)",
            _ps.E_OOB: "the pickle refers to out-of-band buffers, which are not supported",
            _ps.E_NOT_TUPLE: "call arguments must be a tuple",
            _ps.E_HEADER: "malformed numpy array header (numpy writes an empty int8 shell)",
            _ps.E_SHAPE: "array: shape must be a tuple of at most 64 sizes >= 0",
            _ps.E_ARRSTATE: "unsupported numpy array state",
            _ps.E_INCOMPLETE: "array or scalar of an incomplete dtype (no state)",
            _ps.E_RAWTYPE: "array data must be bytes (of a size the pickle states)",
            _ps.E_ORDER: "bad array order",
            _ps.E_SCALAR: "numpy scalar data must be bytes of the dtype's itemsize",
            _ps.E_FROMBUF_OBJ: "an object array cannot come from a raw buffer",
            _ps.E_DTYPE_SIZE: f"bad string size {i1} in a numpy dtype",
            _ps.E_ARGS: "malformed call arguments for a numpy reconstructor",
        }.get(code, f"rejected by the check (code {code})")
        if code in (_ps.E_OPCODE, _ps.E_UNDERFLOW, _ps.E_NOMARK, _ps.E_BADARG, _ps.E_MEMO, _ps.E_MEMO_RANGE, _ps.E_ODD):
            msg += f" (at byte {pos})"
    return InputError(f"not a readable pickle: {msg}", source=source)


# --------------------------------------------------------------------------------------------- loading


class _Reader:
    """The checked bytes as a file for the C unpickler: ``peek`` hands out all of them at once, so it parses
    from one buffer (as ``pickle.loads`` does) without copies."""

    __slots__ = ("_view", "_pos")

    def __init__(self, data: Buffer) -> None:
        self._view = memoryview(data).cast("B")
        self._pos = 0

    def peek(self, n: int = 0) -> memoryview:
        return self._view[self._pos :]

    def read(self, n: int = -1) -> memoryview:
        start = self._pos
        self._pos = len(self._view) if n is None or n < 0 else min(len(self._view), start + n)
        return self._view[start : self._pos]

    def readinto(self, buf: Any) -> int:
        chunk = self.read(len(buf))
        buf[: len(chunk)] = chunk
        return len(chunk)

    def readline(self) -> bytes:
        rest = bytes(self._view[self._pos : self._pos + (1 << 20)])
        end = rest.find(b"\n")
        return bytes(self.read(len(rest) if end < 0 else end + 1))


class _Unpickler(pickle.Unpickler):
    """The C unpickler, handing out the allowlisted globals (the scan has seen every one it will ask for)."""

    def __init__(self, data: Buffer) -> None:
        # the C unpickler reads any buffer (memoryviews, without copies), not only bytes
        super().__init__(_Reader(data), fix_imports=False, encoding="ASCII", errors="strict")  # type: ignore[arg-type]

    def find_class(self, module: str, name: str) -> Any:
        row = _GLOBAL_ROW.get((module, name))
        if row is None:  # pragma: no cover - the scan refuses every other global first
            raise UnsafePickleError(f"the pickle refers to {module}.{name}; it was not loaded")
        return _GLOBAL_OBJ[row]


#: what each kind of scan node is in Python, to check the loaded result against the scan
_RESULT_TYPES: dict[int, tuple[type, ...]] = {
    _ps.K_NONE: (type(None),),
    _ps.K_INT: (int,),
    _ps.K_BIGINT: (int,),
    _ps.K_FLOAT: (float,),
    _ps.K_STR: (str,),
    _ps.K_BYTES: (bytes,),
    _ps.K_BYTEARRAY: (bytearray,),
    _ps.K_TUPLE: (tuple,),
    _ps.K_LIST: (list,),
    _ps.K_DICT: (dict,),
    _ps.K_SET: (set,),
    _ps.K_FROZENSET: (frozenset,),
    _ps.K_ODICT: (collections.OrderedDict,),
    _ps.K_SHELL: (np.ndarray,),
    _ps.K_ARRAY: (np.ndarray,),
    _ps.K_DTYPE: (np.dtype,),
    _ps.K_SCALAR: (np.generic,),
}


def _budget(n: int) -> int:
    """Bytes the objects of an ``n``-byte pickle, and what a reader makes of them, may take (array data, an
    array of numbers at 8 bytes a value, charged again each time the pickle puts it into a container; Python
    objects, the unpickler's stack, dict entries and list items, as the scan counts them). The val-sized
    pickles use 25% (result.pkl: 50 of 200 MB) and 41% (the golden infos: 41 of 102 MB), an mmdetection3d-style
    infos of the same frames (22 MB, lists of Python floats) 56%; a pickle of a million empty dicts (1 MB) would
    need 40 MB, a result.pkl of 200 frames that all use one frame's 10,000 boxes (0.7 MB) 340 MB."""
    return 8 * n + (32 << 20)


def _scan(data: Buffer, source: str) -> tuple[Any, ...]:
    """Run the scan, with work arrays sized for common pickles and grown (by rerunning it) when too small."""
    u8 = np.frombuffer(data, np.uint8)
    if u8.flags.writeable:  # one compiled specialization (read-only input) whatever the source
        u8 = u8.view()
        u8.flags.writeable = False
    n = len(u8)
    # by _ps.ROOM_*: nodes, children, stack (pickle appends in batches of 1000), marks, memo, container items
    sizes = [n // 8 + 1024, n // 8 + 1024, 1 << 16, 1 << 10, n // 16 + 1024, n // 64 + 1024]
    try:
        while True:
            work = [np.empty((sizes[0], _ps.COLUMNS), np.int64)] + [np.empty(k, np.int64) for k in sizes[1:-1]]
            work.append(np.empty((sizes[-1], 3), np.int64))
            work[_ps.ROOM_MEMO] = np.zeros(sizes[_ps.ROOM_MEMO], np.int64)  # pages zeroed as they are touched
            work[_ps.ROOM_NODES][: len(_ps.BASE_NODES)] = _ps.BASE_NODES
            res = _ps.scan(u8, _GBLOB, _GTAB, _DBLOB, _DTAB, _budget(n), _MAX_DEPTH, _KEY_BUDGET, *work)
            if res[0] != _ps.E_ROOM:
                break
            sizes[int(res[2])] = int(res[3])
    except MemoryError:
        raise InputError("not a readable pickle: it needs more memory than is available", source=source) from None
    nn, nch, ni = int(res[5]), int(res[6]), int(res[8])
    return (*res[:5], work[_ps.ROOM_NODES][:nn], work[_ps.ROOM_CH][:nch], int(res[7]), work[_ps.ROOM_ITEMS][:ni])


def _build(data: Buffer, res: tuple[Any, ...], source: str) -> object:
    """The objects of a pickle the scan accepted (``res``), built by the C unpickler."""
    nodes, result = res[5], int(res[7])
    unpickler = _Unpickler(data)
    try:
        obj = unpickler.load()
    except MemoryError:
        raise InputError(
            "not a readable pickle: it needs more memory than is available (corrupt sizes?)", source=source
        ) from None
    except UnsafePickleError:  # pragma: no cover - find_class disagreeing with the scan
        raise
    except Exception as e:  # noqa: BLE001 - only allowlisted code ran on checked arguments; bad input
        raise InputError(f"not a readable pickle: {type(e).__name__}: {e}", source=source) from None
    kind = int(nodes[result, _ps.W]) & _ps.KIND_MASK
    if not isinstance(obj, _RESULT_TYPES[kind]):  # pragma: no cover - the scan models what pickle builds
        raise InputError(
            f"not a readable pickle: the loaded {type(obj).__name__} is not the {_ps.KIND_NAMES[kind]} the check saw",
            source=source,
        )
    if isinstance(obj, int) and not isinstance(obj, bool) and obj == _TORCH_LEGACY_MAGIC:
        raise UnsafePickleError(
            "this is a torch.save() file (legacy format) holding torch tensors; it was "
            "not loaded. Export predictions as plain numpy arrays (e.g. .numpy() on each "
            "tensor) and pickle the list of per-frame dicts",
            source=source,
        )
    return obj


# ---------------------------------------------------------------------------------------------- input


_READ_CHUNK = 64 << 20


def _read_limited(
    read: Callable[..., bytes], max_bytes: int | None, what: str, source: str, chunk: int | None = None
) -> Buffer:
    """Everything ``read`` gives, up to ``max_bytes`` (InputError past it). ``chunk``: read that much at a
    time into one growing buffer (a decompressing reader would otherwise hold a second copy of it all)."""
    parts: list[bytes] = []
    buf = bytearray()
    total = 0
    while max_bytes is None or total <= max_bytes:
        want = -1 if max_bytes is None else max_bytes + 1 - total
        if chunk is not None:
            want = chunk if want < 0 else min(want, chunk)
        data = read(want) if want >= 0 else read()
        if not data:
            break
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InputError(
                f"expected binary data, got {type(data).__name__} (open the file in 'rb' mode)", source=source
            )
        total += len(data)
        if chunk is not None:
            buf += data
        else:
            parts.append(data if type(data) is bytes else bytes(data))
    if max_bytes is not None and total > max_bytes:
        raise InputError(f"{what} is larger than the limit of {max_bytes} bytes", source=source)
    if chunk is not None:
        return buf
    return parts[0] if len(parts) == 1 else b"".join(parts)


def _read_input(path_or_fileobj: str | os.PathLike[str] | IO[bytes], source: str, max_bytes: int | None) -> Buffer:
    if hasattr(path_or_fileobj, "read"):
        try:
            read = path_or_fileobj.read
            data = _read_limited(read, max_bytes, "the upload", source)
        except OSError as e:
            raise InputError(f"cannot read: {e}", source=source) from None
    else:
        path = os.fspath(path_or_fileobj)
        try:
            with open(path, "rb") as fh:
                data = _read_limited(fh.read, max_bytes, "the file", source)
        except FileNotFoundError:
            raise InputError(f"no such file: {path}", source=source) from None
        except IsADirectoryError:
            raise InputError(f"{path} is a directory, not a pickle", source=source) from None
        except OSError as e:
            raise InputError(f"cannot read {path}: {e.strerror or e}", source=source) from None
    if bytes(data[:2]) == GZIP_MAGIC:
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(data), mode="rb") as gz:
                data = _read_limited(gz.read, max_bytes, "the decompressed gzip data", source, _READ_CHUNK)
        except InputError:
            raise
        except (OSError, EOFError, zlib.error, ValueError, MemoryError) as e:
            raise InputError(f"not a readable gzip file: {e or type(e).__name__}", source=source) from None
    return data


def _sniff(data: Buffer, source: str) -> None:
    if not len(data):
        raise InputError("not a readable pickle: the file is empty", source=source)
    data = bytes(data[:262])
    if data[:4] == _ZIP_MAGIC:
        raise InputError(
            "not a readable pickle: this is a zip archive (a torch.save() file or a numpy "
            ".npz?). "
            "Export predictions as plain numpy arrays and pickle the list of per-frame dicts",
            source=source,
        )
    if data[257:262] == b"ustar":
        raise InputError(
            "not a readable pickle: this is a tar archive; extract it (KITTI txt folders are read as folders)",
            source=source,
        )
    if data[:6] == _NPY_MAGIC:
        raise InputError(
            "not a readable pickle: this is a numpy .npy file; pickle the list of per-frame dicts", source=source
        )


def load_pickle(
    path_or_fileobj: str | os.PathLike[str] | IO[bytes],
    *,
    source: str,
    max_bytes: int | None = None,
    max_entries: int | None = None,
) -> object:
    """Unpickle a file that may only hold numpy arrays, numpy scalars and plain containers.

    Parameters
    ----------
    path_or_fileobj : a path, or a binary file object (read to its end)
    source : a name for messages (usually the path or the upload's name)
    max_bytes : refuse input (after gzip decompression) larger than this; ``None``: no limit
    max_entries : refuse a pickle of a list or tuple with more items than this (a set of more frames than
        the limit), before anything is built; ``None``: no limit

    gzip input (magic ``1f 8b``) is decompressed transparently, whatever the file name.

    Raises
    ------
    UnsafePickleError : the pickle refers to anything outside the allowlist (e.g. ``os.system``, torch
        tensors, mmdet3d boxes) or sets state that numpy would not write; nothing was imported or called
    InputError : missing, empty, truncated or corrupt input, or input over ``max_bytes``
    """
    return _build(*_checked(path_or_fileobj, source, max_bytes, max_entries), source)


def _checked(
    path_or_fileobj: str | os.PathLike[str] | IO[bytes], source: str, max_bytes: int | None, max_entries: int | None
) -> tuple[Buffer, tuple[Any, ...]]:
    """The input's bytes and the scan's verdict on them (raises if it refused them)."""
    data = _read_input(path_or_fileobj, source, max_bytes)
    _sniff(data, source)
    res = _scan(data, source)
    if res[0] != _ps.OK:
        raise _scan_error(res, data, source)
    if max_entries is not None:
        root = res[5][res[7]]
        kind = int(root[_ps.W]) & _ps.KIND_MASK
        n = int(root[_ps.V]) if kind == _ps.K_LIST else int(root[_ps.B]) if kind == _ps.K_TUPLE else 0
        if n > max_entries:
            raise InputError(
                f"the pickle is a {_ps.KIND_NAMES[kind]} of {n} entries, more than the limit of {max_entries} "
                f"frames ({setting_name('KITTI_EVAL_MAX_FRAMES')})",
                source=source,
            )
    return data, res


class CheckedPickle:
    """A pickle's bytes that the scan accepted, and what the scan recorded of them (:func:`check_pickle`).

    :meth:`load` builds its objects with the C unpickler (what :func:`load_pickle` returns);
    :mod:`kitti_eval.io.pickle_columns` reads the usual layouts' arrays from the bytes instead, through the
    record, without building an object.
    """

    __slots__ = ("data", "scan", "source")

    def __init__(self, data: Buffer, scan: tuple[Any, ...], source: str) -> None:
        self.data, self.scan, self.source = data, scan, source

    def load(self) -> object:
        """The objects of the pickle, as :func:`load_pickle` returns them."""
        return _build(self.data, self.scan, self.source)


def check_pickle(
    path_or_fileobj: str | os.PathLike[str] | IO[bytes],
    *,
    source: str,
    max_bytes: int | None = None,
    max_entries: int | None = None,
) -> CheckedPickle:
    """The first half of :func:`load_pickle`: the input read (gzip or not) and scanned, nothing built; the same
    arguments, and the same errors for anything the scan refuses."""
    return CheckedPickle(*_checked(path_or_fileobj, source, max_bytes, max_entries), source)


def check_pickles(
    paths: Sequence[str | os.PathLike[str]],
    *,
    sources: Sequence[str],
    max_bytes: int | None = None,
    max_entries: int | None = None,
) -> Iterator[CheckedPickle]:
    """:func:`check_pickle` of several files, in order; while the caller works on one, the next file is read
    and checked in a helper thread (the scan needs no GIL). Errors are raised where that file would be."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="kitti-eval pickle check") as pool:
        pending = [pool.submit(_checked, p, s, max_bytes, max_entries) for p, s in zip(paths, sources)]
        for future, source in zip(pending, sources):
            yield CheckedPickle(*future.result(), source)


def load_pickles(
    paths: Sequence[str | os.PathLike[str]],
    *,
    sources: Sequence[str],
    max_bytes: int | None = None,
    max_entries: int | None = None,
) -> Iterator[object]:
    """:func:`load_pickle` of several files, in order; while the caller works on one object, the next file
    is read and checked in a helper thread (the scan needs no GIL). Errors are raised where that file's
    object would be."""
    for checked in check_pickles(paths, sources=sources, max_bytes=max_bytes, max_entries=max_entries):
        yield checked.load()
