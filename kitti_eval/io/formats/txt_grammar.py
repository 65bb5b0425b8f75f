"""How the official devkit reads a KITTI txt file, in one place: the txt reader checks every file against
these rules and refuses, naming the line and the field, what the devkit would read otherwise.

The devkit (``evaluate_object.cpp``) reads a file with ``fscanf``: ground truth as ``%s %lf %d %lf ...``
(15 conversions; ``occluded`` is ``%d``), detections as ``%s`` and 15 ``%lf`` (``truncated`` and
``occluded`` are read as floats and thrown away). So, in the C locale:

* fields are separated by the six C whitespace bytes only (space, ``\\t``, ``\\n``, ``\\v``, ``\\f``,
  ``\\r``); a U+00A0, a U+3000 or a ``\\x1f`` is part of a field;
* a float field is an ASCII number of ``strtod``'s grammar, an integer field one of ``%d``'s (into 32
  bits); a field that only begins as one is read up to where it stops, and the rest is the next field;
* a class name is any run of other bytes, into a 255-byte buffer, and ends at a NUL;
* the file is one stream of fields, not of lines: a record whose conversion fails is dropped and reading
  resumes at the failing field, so every later field of that line shifts;
* a detection's 2D height ``|y2 - y1|`` is taken as an ``int32_t``.

kitti-eval reads one record per line; a file is read exactly as the devkit reads it when every non-blank
line holds one record whose fields are all spelled in this grammar, which is what is checked here. The
fast checks work on a whole file at once (a byte-set test of its number fields, then ``float``, which
agrees with ``strtod`` on those bytes); only a file that fails them is walked field by field
(:func:`explain_numbers`) to say where and why.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ...core.frames import Kind
from ...errors import InputError

__all__ = [
    "BOM",
    "C_WHITESPACE",
    "KITTI_TXT_FIELDS",
    "NAME_MAX_BYTES",
    "check_start",
    "check_names",
    "check_number_bytes",
    "explain_numbers",
    "foreign_separator",
    "not_a_separator",
    "table_problem",
    "values_problem",
]

#: the bytes ``isspace`` is true of in the C locale: the only field separators of ``fscanf``
C_WHITESPACE = b" \t\n\v\f\r"
#: a UTF-8 byte order mark, which the devkit reads as the start of the first class name
BOM = b"\xef\xbb\xbf"
#: the longest class name the devkit's ``char str[255]`` holds (and its NUL)
NAME_MAX_BYTES = 254
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

#: ``strtod``'s decimal numbers (what ``float`` reads of ASCII bytes without ``_`` too)
_FLOAT = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
#: C's hexadecimal floats (``0x1p3``), which ``strtod`` reads and ``float`` does not
_HEX_FLOAT = re.compile(rb"[+-]?0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?")
#: ``%d``'s integers
_INT = re.compile(rb"[+-]?[0-9]+")
#: spellings ``strtod`` and ``float`` both read as non-finite: left to the finiteness check of the frames
_NON_FINITE = re.compile(rb"[+-]?(?:inf(?:inity)?|nan)", re.IGNORECASE)
#: the bytes a float field or an integer field of the fast path may hold; with these, ``float`` accepts
#: exactly the tokens ``strtod`` reads whole
FLOAT_BYTES = b"0123456789+-.eE"
INT_BYTES = b"0123456789+-"
_NUMBER_OR_SPACE = FLOAT_BYTES + C_WHITESPACE

_SEPARATORS = "space, tab, CR, LF, VT and FF"
#: the fields of a KITTI label line, in file order (``score`` only in detections)
KITTI_TXT_FIELDS = (
    "type",
    "truncated",
    "occluded",
    "alpha",
    "x1",
    "y1",
    "x2",
    "y2",
    "h",
    "w",
    "l",
    "x",
    "y",
    "z",
    "ry",
    "score",
)


def _shown(token: bytes) -> str:
    return repr(token.decode("utf-8", "replace"))


def check_start(raw: bytes, frame: str, source: str) -> None:
    """A file that starts with a UTF-8 byte order mark is refused: the devkit reads it as part of the first
    class name, which then is no class's, and so ignores that line."""
    if raw.startswith(BOM):
        raise InputError(
            "line 1: the file starts with a UTF-8 byte order mark; the devkit reads it as part of the first "
            "class name and ignores that line: save the file without one",
            source=source,
            frame=frame,
            field="type",
        )


def foreign_separator(line: bytes) -> str | None:
    """The first character of ``line`` that Python's ``str.split`` would take as a separator and the devkit
    does not (U+00A0, U+3000, ``\\x1c``-``\\x1f``, ...), as ``U+XXXX``; None if there is none."""
    if line.isascii() and not any(b in line for b in (b"\x1c", b"\x1d", b"\x1e", b"\x1f")):
        return None
    for ch in line.decode("utf-8", "replace"):
        if ch.isspace() and ch not in " \t\n\v\f\r":
            return f"U+{ord(ch):04X}"
    return None


def not_a_separator(sep: str) -> str:
    return f"{sep} is not a field separator for the devkit (only {_SEPARATORS} are)"


def check_names(
    raw: bytes, lines: Sequence[bytes], names: Sequence[bytes], width: int, kind: Kind, frame: str, source: str
) -> None:
    """The class names of one file (``names``, in line order, of the non-blank ``lines``) as the devkit
    reads them: without a NUL (the devkit's name ends there), without a character that looks like a
    separator and is not one (:func:`foreign_separator`), at most :data:`NAME_MAX_BYTES` long, and, in
    ground truth written with a 16th field, not starting like a number (the devkit reads that 16th field as
    the next record's name and the next line's name as its ``truncated``)."""
    nul = b"\x00" in raw
    long = bool(names) and max(map(len, names)) > NAME_MAX_BYTES
    gt16 = kind == "ground_truth" and width == 16 and len(names) > 1
    folding = not raw.isascii()
    separator = foreign_separator(b" ".join(names)) is not None
    if not (nul or long or gt16 or folding or separator):
        return
    records = [i for i, line in enumerate(lines, 1) if line.split()]
    for lineno, name, previous in zip(records, names, [None, *names[:-1]], strict=True):
        where = f"line {lineno}: the class name {_shown(name)}"
        if b"\x00" in name:
            cut = name.split(b"\x00", 1)[0]
            raise InputError(
                f"{where} holds a NUL byte; the devkit's name ends there ({_shown(cut)})",
                source=source,
                frame=frame,
                field="type",
            )
        sep = foreign_separator(name)
        if sep is not None:
            raise InputError(
                f"{where} holds {sep}, which {not_a_separator(sep)[len(sep) + 1 :]}: it reads the whole as one "
                "class name, of no class",
                source=source,
                frame=frame,
                field="type",
            )
        if len(name) > NAME_MAX_BYTES:
            raise InputError(
                f"line {lineno}: a class name of {len(name)} bytes; the devkit reads a name into a buffer of "
                f"{NAME_MAX_BYTES + 1} bytes (its NUL included)",
                source=source,
                frame=frame,
                field="type",
            )
        if gt16 and previous is not None and name[:1] and name[:1] in b"0123456789+-.iInN":
            raise InputError(
                f"{where} starts like a number after a line of 16 fields; the devkit reads a ground-truth "
                "line's 16th field as the next record's class name and this name as its truncated: write "
                "15 fields",
                source=source,
                frame=frame,
                field="type",
            )
        if folding and not name.isascii():
            text = name.decode("utf-8", "replace")
            if text.lower().isascii():
                raise InputError(
                    f"{where} has non-ASCII letters that lower-case to {text.lower()!r}; the devkit compares "
                    "names by their ASCII letters only",
                    source=source,
                    frame=frame,
                    field="type",
                )


def check_number_bytes(raw: bytes, names: Sequence[bytes], tokens: Sequence[bytes], n_numbers: int, kind: Kind) -> bool:
    """The fast test of one file's number fields (``tokens``, ``n_numbers`` a record, flat, in file order):
    True when each holds only the bytes of a float (of an integer, for ground truth's ``occluded``), so
    that ``float`` reads it exactly when ``strtod`` reads it whole. Counted on the whole file: every byte
    that is neither whitespace nor a number's is in a class name. False sends the file to
    :func:`explain_numbers`."""
    if len(raw.translate(None, _NUMBER_OR_SPACE)) != len(b"".join(names).translate(None, _NUMBER_OR_SPACE)):
        return False
    if kind == "ground_truth" and tokens:
        return not b"".join(tokens[1::n_numbers]).translate(None, INT_BYTES)
    return True


def _float_problem(token: bytes) -> str | None:
    """None for a token the devkit reads whole as ``float`` reads it; else how the devkit reads it, or ""
    for a token ``float`` does not read either (refused as not a number, as it always was)."""
    if _FLOAT.fullmatch(token) or _NON_FINITE.fullmatch(token):
        return None
    if _HEX_FLOAT.fullmatch(token):
        value = float.fromhex(token.decode())
        return (
            f"it is a hexadecimal float, which the official devkit reads (C's strtod) as {value!r}, and kitti-eval "
            "reads decimal numbers only: write it as one"
        )
    sep = foreign_separator(token)
    try:
        float(token.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        if sep is None:
            return ""
    detail = []
    if sep is not None:
        detail.append(not_a_separator(sep))
    elif not token.isascii():
        detail.append("it has non-ASCII characters, and the devkit reads numbers of ASCII digits only")
    prefix = _FLOAT.match(token)
    if prefix and token[prefix.end() : prefix.end() + 1] not in (b"e", b"E"):
        detail.append(
            f"the devkit would read {prefix.group().decode()}, then take {_shown(token[prefix.end() :])} as the "
            "next field and shift every later field"
        )
    else:
        detail.append("the devkit would not read this line as a box")
    return "; ".join(detail)


def _int_problem(token: bytes) -> str | None:
    if _INT.fullmatch(token):
        return None
    prefix = _INT.match(token)
    how = "the official devkit reads occluded as an integer"
    if prefix:
        rest = token[prefix.end() :]
        return (
            f"{how}: it would read {int(prefix.group())}, then take {_shown(rest)} as alpha and shift every later field"
        )
    sep = foreign_separator(token)
    first = f"{not_a_separator(sep)}; " if sep else ""
    return f"{first}{how} and would not read this line as a box"


def explain_numbers(lines: Sequence[bytes], width: int, kind: Kind, frame: str, source: str) -> None:
    """Walk one file's number fields (``width`` fields a non-blank line, the type first) and raise for the
    first the devkit reads otherwise than as the number ``float`` makes of it. Returns when there is none
    (then each field is a decimal number, or a non-finite one, for the frames' own check to refuse)."""
    n_fields = 16 if kind == "detections" else 15  # a ground-truth 16th field is the next record's name
    for lineno, line in enumerate(lines, 1):
        parts = line.split()
        for k, tok in enumerate(parts[1 : min(width, n_fields)], 1):
            field = KITTI_TXT_FIELDS[k]
            integer = kind == "ground_truth" and field == "occluded"
            problem = _int_problem(tok) if integer else _float_problem(tok)
            if problem is None:
                continue
            what = "an integer" if integer else "a number"
            message = f"line {lineno}: {field} is not {what}: {_shown(tok)}"
            raise InputError(f"{message}; {problem}" if problem else message, source=source, frame=frame, field=field)


def values_problem(values: list[float], kind: Kind) -> tuple[int, str, str] | None:
    """:func:`table_problem` of one file's numbers, flat (14 a record in ground truth, 15 in detections),
    with a plain test first: most files have none."""
    n = 14 if kind == "ground_truth" else 15
    if all(map(math.isfinite, values)):
        if kind == "ground_truth":
            occ = values[1::n]
            if not occ or INT32_MIN <= min(occ) and max(occ) <= INT32_MAX:
                return None
        elif sum(map(abs, map(operator.sub, values[4::n], values[6::n]))) < 2.0**31:
            return None
    return table_problem(np.array(values, dtype=np.float64).reshape(-1, n), kind)


def table_problem(table: npt.NDArray[np.float64], kind: Kind) -> tuple[int, str, str] | None:
    """The first record (row of ``table``: the numbers after the type, as read) whose value the devkit
    holds otherwise: ``(row, field, message)``, or None. Ground truth's ``occluded`` must fit in the
    ``int`` it is read into; a detection's height ``|y2 - y1|`` in the ``int32_t`` it is taken as."""
    if not len(table):
        return None
    finite = np.isfinite(table)
    if not finite.all():
        row, col = (int(i) for i in np.argwhere(~finite)[0])
        field = KITTI_TXT_FIELDS[col + 1]
        return row, field, f"{field} is {table[row, col]:g}, a non-finite value (every value must be a finite number)"
    if kind == "ground_truth":
        occ = table[:, 1]
        bad = np.flatnonzero((occ < INT32_MIN) | (occ > INT32_MAX))
        if len(bad):
            return int(bad[0]), "occluded", f"occluded {occ[bad[0]]:.0f} does not fit in the devkit's 32-bit integer"
        return None
    y1, y2 = table[:, 4], table[:, 6]
    height = np.abs(y1 - y2)
    bad = np.flatnonzero(np.isfinite(y1) & np.isfinite(y2) & ~(height < 2.0**31))
    if len(bad):
        return (
            int(bad[0]),
            "y2",
            f"the 2D box's height |y2 - y1| = {height[bad[0]]:g} px does not fit in 32 bits; the devkit takes a "
            "detection's height as an int32_t, which would overflow (and ignore the box as too small)",
        )
    return None
