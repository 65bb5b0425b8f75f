"""A slow twin of how the official devkit reads a KITTI txt file: glibc's ``fscanf`` in the C locale, one
byte at a time, with the devkit's formats and loop (``while (!feof(fp)) if (fscanf(...) == N) keep``).

* ground truth: ``%s %lf %d`` and 12 ``%lf`` (15 conversions); detections: ``%s`` and 15 ``%lf``;
* every conversion skips the six C whitespace bytes first; ``%s`` takes the run of other bytes (the name
  ends at a NUL, as ``std::string`` makes of the ``char[]``); ``%d`` and ``%lf`` take the longest
  prefix that can still become a number, pushing back only the byte that stops them: if what they took is
  no number, the conversion fails, those bytes are lost, and the record is dropped;
* the next record starts where the last conversion stopped, whatever the lines.

Returns the records as ``(name, numbers)``: the name's bytes, and the numbers after it as floats (``%d`` as
the ``int`` glibc stores). Only the tests use it: it is the reference the reader is tested against.
Hexadecimal floats are not modelled (read as ``0`` and a next field here; the reader refuses them).
"""

from __future__ import annotations

WHITESPACE = b" \t\n\v\f\r"
DIGITS = b"0123456789"


class _Eof(Exception):
    pass


class _Fail(Exception):
    pass


class _Stream:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0
        self.eof = False  # feof(): set once a read found the end

    def peek(self) -> int | None:
        if self.pos >= len(self.data):
            self.eof = True
            return None
        return self.data[self.pos]

    def skip_whitespace(self) -> None:
        while (c := self.peek()) is not None and c in WHITESPACE:
            self.pos += 1

    def take_if(self, allowed: bytes) -> bool:
        c = self.peek()
        if c is not None and c in allowed:
            self.pos += 1
            return True
        return False

    def take_digits(self) -> int:
        n = 0
        while self.take_if(DIGITS):
            n += 1
        return n


def _string(s: _Stream) -> bytes:
    s.skip_whitespace()
    if s.peek() is None:
        raise _Eof
    start = s.pos
    while (c := s.peek()) is not None and c not in WHITESPACE:
        s.pos += 1
    return s.data[start : s.pos]


def _integer(s: _Stream) -> int:
    s.skip_whitespace()
    if s.peek() is None:
        raise _Eof
    start = s.pos
    s.take_if(b"+-")
    if not s.take_digits():
        raise _Fail
    value = int(s.data[start : s.pos])
    value = max(-(2**63), min(2**63 - 1, value))  # strtol's long, saturated ...
    return (value + 2**31) % 2**32 - 2**31  # ... stored into an int


def _word(s: _Stream, word: bytes) -> None:
    for ch in word:
        if not s.take_if(bytes([ch, ord(chr(ch).upper())])):
            raise _Fail


def _double(s: _Stream) -> float:
    s.skip_whitespace()
    if s.peek() is None:
        raise _Eof
    start = s.pos
    negative = s.data[s.pos : s.pos + 1] == b"-"
    s.take_if(b"+-")
    if s.take_if(b"nN"):
        _word(s, b"an")
        return float("nan")
    if s.take_if(b"iI"):
        _word(s, b"nf")
        if s.take_if(b"iI"):
            _word(s, b"nity")
        return float("-inf" if negative else "inf")
    mantissa = s.take_digits()
    if s.take_if(b"."):
        mantissa += s.take_digits()
    if not mantissa:
        raise _Fail
    if s.take_if(b"eE"):
        s.take_if(b"+-")
        if not s.take_digits():
            raise _Fail
    return float(s.data[start : s.pos])


def read_records(data: bytes, kind: str) -> list[tuple[bytes, list[float]]]:
    """The records the devkit keeps of a file's bytes (``kind``: ``ground_truth`` or ``detections``)."""
    numbers = [_double, _integer, *[_double] * 12] if kind == "ground_truth" else [_double] * 15
    s = _Stream(data)
    records = []
    while not s.eof:
        try:
            name = _string(s)
            values = [float(convert(s)) for convert in numbers]
        except (_Eof, _Fail):
            continue
        records.append((name.split(b"\x00", 1)[0], values))
    return records
