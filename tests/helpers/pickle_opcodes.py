"""A pickle writer by opcodes, for differential tests of the pickle readers: the values a result.pkl or infos
holds (dicts, lists, tuples, str, ints, numpy arrays and scalars) written with every choice ``pickle`` could
make or a hand could write -- protocols 0-5, each opcode of a value's family, memo writes (PUT, BINPUT,
LONG_BINPUT, MEMOIZE) and reads (GET, BINGET, LONG_BINGET), DUP, dicts by SETITEM, SETITEMS or DICT, lists by
APPEND, APPENDS or LIST, arrays as numpy 1.x or 2.x writes them (``_reconstruct`` and a state, or
``_frombuffer`` at protocol 5) in either byte order and in Fortran order -- each choice taken by ``choose``.

The values to write are plain Python values and numpy arrays, and the wrappers below: :class:`Dict` (pairs, so
that a key may be there twice), :class:`Key` (a dict key written as a numpy.str_, or with escapes),
:class:`NpScalar`. One object given twice (the same Python object) is written once and then read from the memo,
as pickle shares it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: ``choose(options)``: one of them (a hypothesis draw, or a seeded generator's choice)
Choose = Callable[[Sequence[Any]], Any]


@dataclass(eq=False)
class Dict:
    """A dict written pair by pair (a key may come twice: pickle keeps the last value)."""

    pairs: list[tuple[Any, Any]] = field(default_factory=list)


@dataclass(eq=False)
class Key:
    """A str key written as ``form``: 'str' (a str opcode), 'numpy' (a numpy.str_), 'escaped' (UNICODE with its
    first character as a \\u escape, so that its raw bytes are not its text)."""

    text: str
    form: str = "str"


@dataclass(eq=False)
class NpScalar:
    """A numpy scalar (``numpy.str_``, ``numpy.int64``, ...) written as numpy writes it: scalar(dtype, bytes)."""

    value: Any


class Writer:
    """Writes one value as a pickle of ``protocol``; every free choice is ``choose``'s."""

    def __init__(self, protocol: int, choose: Choose, rare: Callable[[], bool] | None = None) -> None:
        self.protocol, self.choose = protocol, choose
        #: a choice that makes a layout numpy's pickles do not have (big-endian, Fortran order): rarer
        self.rare = rare if rare is not None else lambda: bool(choose([True, False, False, False]))
        self.out = bytearray()
        self.memo: dict[Any, int] = {}  # what was written (by identity or a key) -> its memo index
        self.next_index = 0  # above every slot filled
        self.memo_slots: set[int] = set()
        self.numpy2 = choose([False, True])  # numpy._core (2.x) or numpy.core (1.x) module names

    # ------------------------------------------------------------------------ the stream
    def dumps(self, obj: Any) -> bytes:
        self.value(obj)
        self.out += b"."
        if self.protocol >= 4 and self.choose([True, False]):  # one frame of it all, as pickle writes small ones
            self.out[:0] = b"\x95" + struct.pack("<Q", len(self.out))
        if self.protocol >= 2:
            self.out[:0] = b"\x80" + bytes([self.protocol])
        return bytes(self.out)

    def op(self, code: bytes, arg: bytes = b"") -> None:
        self.out += code + arg

    def line(self, code: bytes, text: str) -> None:
        self.out += code + text.encode("ascii") + b"\n"

    # ------------------------------------------------------------------------ the memo
    def put(self, key: Any) -> None:
        """Memoize the value on top of the stack (or not: then it is written again where it comes again)."""
        if key is None or not self.choose([True, True, False]):
            return
        if self.protocol >= 4 and len(self.memo_slots) not in self.memo_slots and self.choose([True, False]):
            index = len(self.memo_slots)  # MEMOIZE writes at the number of filled slots
            self.op(b"\x94")
        else:
            index = self.next_index + self.choose([0, 0, 0, 1, 7])  # sparse indices are read as well
            if self.protocol == 0:
                self.line(b"p", str(index))
            elif index < 256 and self.choose([True, False]):
                self.op(b"q", bytes([index]))
            else:
                self.op(b"r", struct.pack("<I", index))
        self.next_index = max(self.next_index, index + 1)
        self.memo_slots.add(index)
        self.memo[key] = index

    def get(self, key: Any) -> bool:
        """Read the value of ``key`` from the memo, if it is there (and the choice is to share it)."""
        if key not in self.memo or not self.choose([True, True, False]):
            return False
        index = self.memo[key]
        if self.protocol == 0:
            self.line(b"g", str(index))
        elif index < 256 and self.choose([True, False]):
            self.op(b"h", bytes([index]))
        else:
            self.op(b"j", struct.pack("<I", index))
        if self.choose([False, False, False, True]):  # DUP, then POP the copy: the stack as before
            self.op(b"20")
        return True

    # ------------------------------------------------------------------------ values
    def value(self, obj: Any) -> None:
        if isinstance(obj, Key):
            self.key(obj)
        elif isinstance(obj, (np.generic, NpScalar)):
            self.scalar(obj.value if isinstance(obj, NpScalar) else obj)
        elif isinstance(obj, str):
            self.text(obj, memo_key=("str", obj))
        elif isinstance(obj, bool) or obj is None:
            self.constant(obj)
        elif isinstance(obj, int):
            self.integer(obj)
        elif isinstance(obj, np.ndarray):
            self.array(obj)
        elif isinstance(obj, (dict, Dict)):
            self.dict_(obj)
        elif isinstance(obj, list):
            self.list_(obj)
        elif isinstance(obj, tuple):
            self.tuple_(obj)
        elif isinstance(obj, bytes):
            self.raw_bytes(obj)
        else:  # pragma: no cover - a value the tests do not write
            raise TypeError(type(obj))

    def constant(self, obj: bool | None) -> None:
        if obj is None:
            self.op(b"N")
        elif self.protocol >= 2:
            self.op(b"\x88" if obj else b"\x89")
        else:
            self.line(b"I", "01" if obj else "00")

    def integer(self, v: int) -> None:
        if self.protocol == 0 or self.choose([False, False, False, True]):
            self.line(b"I", str(v))
        elif 0 <= v < 256 and self.choose([True, False]):
            self.op(b"K", bytes([v]))
        elif 0 <= v < 65536 and self.choose([True, False]):
            self.op(b"M", struct.pack("<H", v))
        elif -(1 << 31) <= v < 1 << 31 and (self.protocol < 2 or self.choose([True, False])):
            self.op(b"J", struct.pack("<i", v))
        else:
            raw = v.to_bytes((v.bit_length() + 8) // 8, "little", signed=True)
            self.op(b"\x8a", bytes([len(raw)]) + raw)

    def text(self, s: str, memo_key: Any = None, escaped: bool = False) -> None:
        if memo_key is not None and self.get(memo_key):
            return
        forms = ["V"] if self.protocol == 0 or escaped else ["X"] + (["\x8c", "\x8d"] if self.protocol >= 4 else [])
        form = self.choose(forms)
        if form == "V":
            body = s.replace("\\", "\\u005c").replace("\0", "\\u0000").replace("\n", "\\u000a")
            body = body.replace("\r", "\\u000d").replace("\x1a", "\\u001a")
            if escaped and s:
                body = f"\\u{ord(s[0]):04x}" + body[1:]
            self.out += b"V" + body.encode("raw_unicode_escape") + b"\n"
        else:
            raw = s.encode("utf-8", "surrogatepass")
            if form == "\x8c" and len(raw) < 256:
                self.op(b"\x8c", bytes([len(raw)]) + raw)
            elif form == "\x8d":
                self.op(b"\x8d", struct.pack("<Q", len(raw)) + raw)
            else:
                self.op(b"X", struct.pack("<I", len(raw)) + raw)
        self.put(memo_key)

    def key(self, key: Key) -> None:
        if key.form == "numpy":
            self.scalar(np.str_(key.text))
        else:
            self.text(
                key.text, memo_key=None if key.form == "escaped" else ("str", key.text), escaped=key.form == "escaped"
            )

    def raw_bytes(self, b: bytes, bytearray_: bool = False) -> None:
        if bytearray_:
            self.op(b"\x96", struct.pack("<Q", len(b)) + b)
        elif self.protocol >= 3:
            if len(b) < 256 and self.choose([True, False]):
                self.op(b"C", bytes([len(b)]) + b)
            elif self.protocol >= 4 and self.choose([False, True]):
                self.op(b"\x8e", struct.pack("<Q", len(b)) + b)
            else:
                self.op(b"B", struct.pack("<I", len(b)) + b)
        elif not b and self.choose([True, False]):  # how protocols 0-2 write b""
            self.global_("builtins" if self.protocol else "__builtin__", "bytes")
            self.tuple_(())
            self.op(b"R")
        else:  # _codecs.encode(the latin-1 text, 'latin1'), as protocols 0-2 write bytes
            self.global_("_codecs", "encode")
            self.op(b"(")
            self.text(b.decode("latin-1"))
            self.text(self.choose(["latin1", "latin-1"]), memo_key=("str", "latin1"))
            self.op(b"t")
            self.op(b"R")

    def global_(self, module: str, name: str) -> None:
        key = ("global", module, name)
        if self.get(key):
            return
        if self.protocol >= 4 and self.choose([True, False]):
            self.text(module, memo_key=("str", module))
            self.text(name, memo_key=("str", name))
            self.op(b"\x93")
        else:
            self.out += b"c" + module.encode() + b"\n" + name.encode() + b"\n"
        self.put(key)

    def tuple_(self, items: tuple[Any, ...]) -> None:
        if not items:
            self.op(b")" if self.protocol >= 1 else b"(t")
            return
        short = self.protocol >= 2 and len(items) <= 3 and self.choose([True, False])
        if not short:
            self.op(b"(")
        for item in items:
            self.value(item)
        self.op(bytes([0x84 + len(items)]) if short else b"t")

    def list_(self, items: list[Any]) -> None:
        if self.get(("id", id(items))):
            return
        style = self.choose(["APPENDS", "APPEND", "LIST"] if self.protocol >= 1 else ["APPEND", "LIST"])
        if style == "LIST":
            self.op(b"(")
            for item in items:
                self.value(item)
            self.op(b"l")
            self.put(("id", id(items)))
            return
        self.op(b"]" if self.protocol >= 1 else b"(l")
        self.put(("id", id(items)))
        if style == "APPEND":
            for item in items:
                self.value(item)
                self.op(b"a")
            return
        for start in range(0, len(items), 3):  # batches, as pickle writes them (of 1000)
            self.op(b"(")
            for item in items[start : start + 3]:
                self.value(item)
            self.op(b"e")

    def dict_(self, d: dict[Any, Any] | Dict) -> None:
        if self.get(("id", id(d))):
            return
        pairs = list(d.pairs) if isinstance(d, Dict) else list(d.items())
        style = self.choose(["SETITEMS", "SETITEM", "DICT"] if self.protocol >= 1 else ["SETITEM", "DICT"])
        if style == "DICT":
            self.op(b"(")
            for k, v in pairs:
                self.value(k)
                self.value(v)
            self.op(b"d")
            self.put(("id", id(d)))
            return
        self.op(b"}" if self.protocol >= 1 else b"(d")
        self.put(("id", id(d)))
        if style == "SETITEM":
            for k, v in pairs:
                self.value(k)
                self.value(v)
                self.op(b"s")
            return
        for start in range(0, len(pairs), 4):
            self.op(b"(")
            for k, v in pairs[start : start + 4]:
                self.value(k)
                self.value(v)
            self.op(b"u")

    # ------------------------------------------------------------------------ numpy
    def _module(self, which: str) -> str:
        return f"numpy.{'_core' if self.numpy2 else 'core'}.{which}"

    def dtype(self, dt: np.dtype) -> None:
        key = ("dtype", dt.str)
        if self.get(key):
            return
        _, (code, align, copy), state = dt.__reduce__()
        self.global_("numpy", "dtype")
        self.tuple_((code, align, copy))
        self.op(b"R")
        self.tuple_(state)
        self.op(b"b")
        self.put(key)

    def scalar(self, value: np.generic) -> None:
        dt = value.dtype
        if dt.itemsize > 1 and dt.kind in "iuf" and self.rare():
            dt = dt.newbyteorder(">")
        self.global_(self._module("multiarray"), "scalar")
        self.op(b"(")
        self.dtype(dt)
        self.raw_bytes(np.asarray(value, dt).tobytes())
        self.op(b"t")
        self.op(b"R")

    def array(self, arr: np.ndarray) -> None:
        if self.get(("id", id(arr))):
            return
        dt = arr.dtype
        if dt.itemsize > 1 and dt.kind in "iufU" and self.rare():
            dt = dt.newbyteorder(">")
        fortran = arr.ndim == 2 and self.rare()
        data = np.asarray(arr, dt).tobytes("F" if fortran else "C")
        if self.protocol == 5 and dt.kind != "O" and self.choose([False, True]):
            self.global_(self._module("numeric"), "_frombuffer")
            self.op(b"(")
            self.raw_bytes(data, bytearray_=self.choose([True, False]))
            self.dtype(dt)
            self.tuple_(tuple(arr.shape))
            self.text("F" if fortran else "C", memo_key=("str", "F" if fortran else "C"))
            self.op(b"t")
            self.op(b"R")
            self.put(("id", id(arr)))
            return
        self.global_(self._module("multiarray"), "_reconstruct")
        self.op(b"(")
        self.global_("numpy", "ndarray")
        self.tuple_((0,))
        self.raw_bytes(b"b")
        self.op(b"t")
        self.op(b"R")
        self.op(b"(")
        self.integer(1)
        self.tuple_(tuple(arr.shape))
        self.dtype(dt)
        self.constant(fortran)
        self.raw_bytes(data)
        self.op(b"t")
        self.op(b"b")
        self.put(("id", id(arr)))


def dumps(obj: Any, protocol: int, choose: Choose, rare: Callable[[], bool] | None = None) -> bytes:
    """``obj`` as a pickle of ``protocol``, written with ``choose``'s choices (``rare``: whether to take a rare
    one, a layout numpy does not write)."""
    return Writer(protocol, choose, rare).dumps(obj)
