"""A KITTI txt file is read as the official devkit reads it, or refused naming the line and field.

The reference is a slow twin of the devkit's ``fscanf`` (tests/helpers/devkit_fscanf.py): a property test
writes label and result files from a grammar of separators, number spellings, names and encodings, and
the reader either reads exactly the records the twin reads or refuses the file; a file spelled only the
ways the devkit reads normally is never refused. The examples are the inputs on which the two used to
disagree, each now refused with the reason.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from devkit_fscanf import read_records
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kitti_eval.core.frames import Annotations
from kitti_eval.errors import InputError
from kitti_eval.io.formats.kitti_txt import load_kitti_txt_dir, parse_kitti_txt

GT_LINE = "Car 0.00 0 -1.58 587.01 173.33 614.12 240.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"
DET_LINE = "Car -1 -1 -1.58 587.01 173.33 614.12 240.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59 0.95"


def _load(tmp_path: Path, data: bytes, kind: str) -> Annotations:
    folder = tmp_path / kind
    folder.mkdir(exist_ok=True)
    (folder / "000000.txt").write_bytes(data)
    return load_kitti_txt_dir(folder, kind)  # type: ignore[arg-type]


def _refused(tmp_path: Path, data: bytes, kind: str) -> InputError:
    with pytest.raises(InputError) as err:
        _load(tmp_path, data, kind)
    assert err.value.frame == "000000" and err.value.source is not None
    assert err.value.source.endswith("000000.txt")
    return err.value


def _field(line: str, k: int, value: str) -> str:
    parts = line.split(" ")
    parts[k] = value
    return " ".join(parts)


# ---------------------------------------------------------------------- what the devkit reads otherwise


@pytest.mark.parametrize(("spelling", "rest"), [("0.0", ".0"), ("0.", "."), ("0e0", "e0"), ("-0.00", ".00")])
def test_a_ground_truth_occluded_written_as_a_float_is_refused(tmp_path: Path, spelling: str, rest: str) -> None:
    data = f"{GT_LINE}\n{_field(GT_LINE, 2, spelling)}\n".encode()
    err = _refused(tmp_path, data, "ground_truth")
    assert err.field == "occluded"
    assert err.message == (
        f"line 2: occluded is not an integer: {spelling!r}; the official devkit reads occluded as an integer: "
        f"it would read 0, then take {rest!r} as alpha and shift every later field"
    )


def test_a_result_occluded_written_as_a_float_is_read_as_the_devkit_reads_it(tmp_path: Path) -> None:
    """The devkit reads a detection's truncated and occluded with %lf (and throws them away)."""
    dt = _load(tmp_path, (_field(_field(DET_LINE, 2, "0.0"), 1, "0.5") + "\n").encode(), "detections")
    assert dt.occluded.tolist() == [0.0] and dt.truncated.tolist() == [0.5]


@pytest.mark.parametrize(("spelling", "value"), [("3", 3), ("+1", 1), ("-0", 0), ("007", 7), ("-2147483648", -(2**31))])
def test_a_ground_truth_occluded_of_d_grammar_is_read(tmp_path: Path, spelling: str, value: int) -> None:
    gt = _load(tmp_path, (_field(GT_LINE, 2, spelling) + "\n").encode(), "ground_truth")
    assert gt.occluded.tolist() == [value]


def test_a_ground_truth_occluded_past_32_bits_is_refused(tmp_path: Path) -> None:
    err = _refused(tmp_path, (_field(GT_LINE, 2, "4294967296") + "\n").encode(), "ground_truth")
    assert err.field == "occluded"
    assert err.message == "line 1: occluded 4294967296 does not fit in the devkit's 32-bit integer"


@pytest.mark.parametrize("kind", ["ground_truth", "detections"])
def test_a_byte_order_mark_is_refused(tmp_path: Path, kind: str) -> None:
    line = GT_LINE if kind == "ground_truth" else DET_LINE
    err = _refused(tmp_path, f"\ufeff{line}\n{line}\n".encode(), kind)
    assert err.field == "type"
    assert err.message == (
        "line 1: the file starts with a UTF-8 byte order mark; the devkit reads it as part of the first class "
        "name and ignores that line: save the file without one"
    )


@pytest.mark.parametrize("spelling", ["٠.٩٥", "５００.００", "0.9５"])
def test_digits_that_are_not_ascii_are_refused(tmp_path: Path, spelling: str) -> None:
    err = _refused(tmp_path, f"{DET_LINE}\n{_field(DET_LINE, 15, spelling)}\n".encode(), "detections")
    assert err.field == "score"
    assert err.message.startswith(
        f"line 2: score is not a number: {spelling!r}; it has non-ASCII characters, and the devkit reads numbers "
        "of ASCII digits only; the devkit would "
    )


def test_an_underscore_in_a_number_is_refused(tmp_path: Path) -> None:
    err = _refused(tmp_path, f"{DET_LINE}\n{_field(DET_LINE, 15, '5_00.00')}\n".encode(), "detections")
    assert err.field == "score"
    assert err.message == (
        "line 2: score is not a number: '5_00.00'; the devkit would read 5, then take '_00.00' as the next "
        "field and shift every later field"
    )


@pytest.mark.parametrize("kind", ["ground_truth", "detections"])
@pytest.mark.parametrize(("sep", "code"), [("\u00a0", "U+00A0"), ("\u3000", "U+3000"), ("\x1f", "U+001F")])
def test_a_separator_the_devkit_does_not_know_is_refused(tmp_path: Path, kind: str, sep: str, code: str) -> None:
    line = GT_LINE if kind == "ground_truth" else DET_LINE
    bad = line.replace(" ", sep, 1)
    err = _refused(tmp_path, f"{line}\n{bad}\n".encode(), kind)
    n = 15 if kind == "ground_truth" else 16
    assert err.message.startswith(f"line 2: expected {n} fields")
    assert err.message.endswith(
        f", got {n - 1}; {code} is not a field separator for the devkit (only space, tab, CR, LF, VT and FF "
        "are), and reads the characters around it as one field"
    )


@pytest.mark.parametrize(("kind", "name"), [("ground_truth", "Car\xa00.00"), ("detections", "Car\xa0-1")])
def test_a_separator_the_devkit_does_not_know_in_a_class_name_is_refused(tmp_path: Path, kind: str, name: str) -> None:
    """A line of one field too many with U+00A0 after the name has the right count of C fields: the devkit
    reads the name and the next field as one name, and every later field one place early."""
    line = GT_LINE + " 0.9" if kind == "ground_truth" else DET_LINE + " 0"
    err = _refused(tmp_path, (line.replace(" ", "\u00a0", 1) + "\n").encode(), kind)
    assert err.field == "type"
    assert err.message == (
        f"line 1: the class name {name!r} holds U+00A0, which is not a field separator for the devkit (only "
        "space, tab, CR, LF, VT and FF are): it reads the whole as one class name, of no class"
    )


def test_a_foreign_separator_at_the_end_of_a_number_is_refused(tmp_path: Path) -> None:
    err = _refused(tmp_path, (DET_LINE + "\u00a0\n").encode(), "detections")
    assert err.message == (
        "line 1: score is not a number: '0.95\\xa0'; U+00A0 is not a field separator for the devkit (only "
        "space, tab, CR, LF, VT and FF are); the devkit would read 0.95, then take '\\xa0' as the next field "
        "and shift every later field"
    )


@pytest.mark.parametrize("kind", ["ground_truth", "detections"])
def test_a_nul_in_a_class_name_is_refused(tmp_path: Path, kind: str) -> None:
    line = GT_LINE if kind == "ground_truth" else DET_LINE
    bad = line.replace("Car", "Car\x00x", 1)
    err = _refused(tmp_path, f"{line}\n{bad}\n".encode(), kind)
    assert err.field == "type"
    assert err.message == "line 2: the class name 'Car\\x00x' holds a NUL byte; the devkit's name ends there ('Car')"


def test_a_detection_taller_than_32_bits_is_refused(tmp_path: Path) -> None:
    tall = _field(DET_LINE, 7, "2147483821.33")  # y2 - y1 = 2**31 + 0.00...: int32_t overflows
    err = _refused(tmp_path, f"{DET_LINE}\n\n{tall}\n".encode(), "detections")
    assert err.field == "y2"
    assert err.message.startswith("line 3: the 2D box's height |y2 - y1| = 2.14748e+09 px does not fit in 32 bits")
    ok = _field(DET_LINE, 7, "2147483820.33")  # just under 2**31
    assert _load(tmp_path, f"{ok}\n".encode(), "detections").num_boxes == 1
    gt = _load(tmp_path, (_field(GT_LINE, 7, "2147483821.33") + "\n").encode(), "ground_truth")
    assert gt.bbox[0, 3] == 2147483821.33  # the devkit keeps a ground-truth height as a double


def test_a_class_name_longer_than_the_devkits_buffer_is_refused(tmp_path: Path) -> None:
    assert _load(tmp_path, (DET_LINE.replace("Car", "C" * 254, 1) + "\n").encode(), "detections").num_boxes == 1
    err = _refused(tmp_path, (DET_LINE.replace("Car", "C" * 255, 1) + "\n").encode(), "detections")
    assert (
        err.message
        == "line 1: a class name of 255 bytes; the devkit reads a name into a buffer of 255 bytes (its NUL included)"
    )


def test_a_name_that_lower_cases_to_ascii_only_in_python_is_refused(tmp_path: Path) -> None:
    err = _refused(tmp_path, (GT_LINE.replace("Car", "Truc\u212a", 1) + "\n").encode(), "ground_truth")
    assert "has non-ASCII letters that lower-case to 'truck'" in err.message
    gt = _load(tmp_path, (GT_LINE.replace("Car", "Cär", 1) + "\n").encode(), "ground_truth")
    assert gt.name.tolist() == ["Cär"]  # an unknown class, as in the devkit


def test_ground_truth_with_a_16th_field_before_a_name_that_starts_like_a_number(tmp_path: Path) -> None:
    line16 = GT_LINE + " 0.9"
    gt = _load(tmp_path, f"{line16}\n{line16}\n".encode(), "ground_truth")
    assert gt.num_boxes == 2
    err = _refused(tmp_path, f"{line16}\n{line16.replace('Car', 'nancy', 1)}\n".encode(), "ground_truth")
    assert err.message.startswith("line 2: the class name 'nancy' starts like a number after a line of 16 fields")
    # the devkit: "0.9" is a record's name, "nan" its truncated, "cy" no integer; then "cy" is a name
    twin = read_records(f"{line16}\n{line16.replace('Car', 'nancy', 1)}\n".encode(), "ground_truth")
    assert [name for name, _ in twin] == [b"Car", b"cy"]


def test_parse_kitti_txt_applies_the_same_grammar() -> None:
    with pytest.raises(InputError, match="line 1: occluded is not an integer: '0.0'"):
        parse_kitti_txt(_field(GT_LINE, 2, "0.0").encode(), "ground_truth", frame="1", source="s")
    with pytest.raises(InputError, match="does not fit in 32 bits"):
        parse_kitti_txt(_field(DET_LINE, 5, "-3e9"), "detections", frame="1", source="s")
    names, values = parse_kitti_txt(
        b"Car\t0 +1 .5 1e2 2 3 5. -0 1 1 1 1 1 1\r\n", "ground_truth", frame="1", source="s"
    )
    assert names == ["Car"] and values[:4] == [0.0, 1.0, 0.5, 100.0]


# ---------------------------------------------------------------------------- against the devkit's twin

#: number spellings the devkit reads whole, as float() does
NORMAL_FLOATS = {
    "fixed": lambda v: f"{v:.2f}",
    "repr": repr,
    "exp": lambda v: f"{v:e}",
    "EXP": lambda v: f"{v:E}",
    "plus": lambda v: f"{v:+.3f}",
    "dot first": lambda v: f"{v:.3f}".replace("0.", ".", 1) if abs(v) < 1 else f"{v:.1f}",
    "dot last": lambda v: f"{round(v):d}.",
    "general": lambda v: f"{v:g}",
}
NORMAL_INTS = {"plain": str, "plus": lambda i: f"{i:+d}", "padded": lambda i: f"{i:03d}"}
#: spellings the devkit reads otherwise than float() (or not at all)
ODD_NUMBERS = [
    "0.0",
    "1e",
    "-",
    ".",
    "5_00.00",
    "٠.٩٥",
    "５",
    "1.5abc",
    "0x1p3",
    "nan",
    "inf",
    "-Infinity",
    "1.2.3",
    "+-1",
    "1e+",
    "\x00",
    "1\x1f2",
    "2147483648",
    "-0",
    "1e999",
]
NAMES = ["Car", "car", "CAR", "Pedestrian", "Cyclist", "DontCare", "Van", "Person_sitting", "Misc", "x", "3d"]
ODD_NAMES = ["Car\x00x", "Cär", "\ufeffCar", "nancy", "Infantry", "+5", ".x", "Car\u00a0", "Truc\u212a", "\xe9t\xe9"]
SEPARATORS = [" ", "  ", "\t", " \t ", "\v", "\f"]
ODD_SEPARATORS = ["\u00a0", "\u3000", "\x1f", "\x1c", "\x85", "\u2028"]
LINE_ENDS = ["\n", "\r\n", "\r"]


@st.composite
def kitti_file(draw: st.DrawFn, kind: str, normal: bool) -> bytes:
    """A label (``ground_truth``) or result file: records of a name and numbers, each spelled one of the
    ways above; ``normal`` keeps to the ways the devkit reads as float() does, one record a line."""

    budget = [0 if normal else draw(st.integers(1, 2))]  # decisions that stray from the normal ways

    def odd(rate: int = 40) -> bool:
        if budget[0] and draw(st.integers(1, rate)) == 1:
            budget[0] -= 1
            return True
        return False

    def value() -> float:
        return round(draw(st.floats(-2000, 2000, allow_nan=False)), draw(st.integers(0, 6)))

    n_numbers = 15 if kind == "detections" else draw(st.sampled_from([14, 14, 15]))
    out = []
    if odd(10):
        out.append("\ufeff")
    for _ in range(draw(st.integers(0, 5))):
        name = draw(st.sampled_from(ODD_NAMES if odd() else NAMES))
        if normal and n_numbers == 15 and kind == "ground_truth" and name == "3d":
            name = "Car"  # after a 16th field, a name that starts like a number is read as a number
        fields = [name]
        for k in range(1, n_numbers + 1):
            if odd():
                fields.append(draw(st.sampled_from(ODD_NUMBERS)))
            elif k == 2 and kind == "ground_truth" and odd(4):
                fields.append(f"{draw(st.integers(0, 3))}{draw(st.sampled_from(['.0', '.', 'e0', '.00']))}")
            elif k == 2 and kind == "ground_truth":
                fields.append(NORMAL_INTS[draw(st.sampled_from(sorted(NORMAL_INTS)))](draw(st.integers(-3, 5))))
            else:
                fields.append(NORMAL_FLOATS[draw(st.sampled_from(sorted(NORMAL_FLOATS)))](value()))
        if odd():
            del fields[draw(st.integers(0, len(fields) - 1))]
        line = fields[0]
        for f in fields[1:]:
            line += draw(st.sampled_from(ODD_SEPARATORS if odd() else SEPARATORS)) + f
        out.append(draw(st.sampled_from(["", " ", "\t"])) + line + draw(st.sampled_from(["", " "])))
        out.append(draw(st.sampled_from(LINE_ENDS)) * draw(st.integers(1, 2)))
    if out and draw(st.booleans()):
        out.pop()  # no line end after the last line
    text = "".join(out)
    if not normal and draw(st.integers(0, 4)) == 0:
        return text.encode("latin-1", "replace")
    return text.encode("utf-8")


def _records(annos: Annotations) -> list[tuple[str, list[float]]]:
    l, h, w = annos.dimensions.T
    columns = [annos.truncated, annos.occluded, annos.alpha, *annos.bbox.T, h, w, l, *annos.location.T]
    columns.append(annos.rotation_y)
    if annos.kind == "detections":
        columns.append(annos.score)
    table = np.stack(columns, axis=1) if annos.num_boxes else np.zeros((0, len(columns)))
    return [(str(n), row.tolist()) for n, row in zip(annos.name, table, strict=True)]


#: ``KITTI_EVAL_FUZZ_EXAMPLES=5000 pytest tests/io/test_txt_grammar.py`` runs longer (and with a random seed)
EXAMPLES = int(os.environ.get("KITTI_EVAL_FUZZ_EXAMPLES", "100"))
GRAMMAR = settings(
    max_examples=EXAMPLES, deadline=None, derandomize=EXAMPLES <= 100, suppress_health_check=list(HealthCheck)
)


def _read_or_refuse(data: bytes, kind: str) -> list[tuple[str, list[float]]] | None:
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp, "000000.txt").write_bytes(data)
        try:
            return _records(load_kitti_txt_dir(tmp, kind))  # type: ignore[arg-type]
        except InputError:
            return None


def _twin(data: bytes, kind: str) -> list[tuple[str, list[float]]]:
    n = 15 if kind == "detections" else 14
    return [(name.decode("utf-8", "replace"), values[:n]) for name, values in read_records(data, kind)]


@pytest.mark.parametrize("kind", ["ground_truth", "detections"])
def test_the_reader_reads_what_the_devkit_reads_or_refuses(kind: str) -> None:
    @GRAMMAR
    @given(kitti_file(kind, normal=False))
    def run(data: bytes) -> None:
        got = _read_or_refuse(data, kind)
        if got is not None:
            assert got == _twin(data, kind)

    run()


@pytest.mark.parametrize("kind", ["ground_truth", "detections"])
def test_a_file_the_devkit_reads_normally_is_read_and_not_refused(kind: str) -> None:
    @GRAMMAR
    @given(kitti_file(kind, normal=True))
    def run(data: bytes) -> None:
        got = _read_or_refuse(data, kind)
        assert got is not None, data
        assert got == _twin(data, kind)

    run()


SECOND = b"\nCar 0 0 0 0 0 10 10 1 1 1 1 1 1 0 1\n"


@pytest.mark.parametrize(
    ("data", "names", "last_score"),
    [
        (b"Car 0 0 0 0 0 10 10 1 1 1 1 1 1 0 0.9" + SECOND, [b"Car", b"Car"], 1.0),
        # %lf takes "1e", which is no number: dropped; the next record's name is "0", and its 15th number
        # would be the next line's "Car": dropped too; the second line is read
        (b"Car 1e 0 0 0 0 10 10 1 1 1 1 1 1 0 0.9" + SECOND, [b"Car"], 1.0),
        # 5, then "_00.00" fails as occluded: dropped; "_00.00" is the next record's name, and so on
        (b"Car 5_00.00 0 0 0 0 10 10 1 1 1 1 1 1 0 0.9" + SECOND, [b"Car"], 1.0),
        # the same one field further: "_00.00" is the name of a record of the 15 fields that follow
        (b"Car 0 5_00.00 0 0 0 10 10 1 1 1 1 1 1 0 0.9 1 2" + SECOND, [b"_00.00", b"Car"], 1.0),
        (b"\xef\xbb\xbfCar 0 0 0 0 0 10 10 1 1 1 1 1 1 0 0.9", [b"\xef\xbb\xbfCar"], 0.9),
        (b"Car\x00x 0 0 0 0 0 10 10 1 1 1 1 1 1 0 0.9", [b"Car"], 0.9),
        (
            b"Car 0 0 0 0 0 10 10 1 1 1 1 1 1 0 .9\x0b\x0cVan\t+0 -0 0 0 0 10 10 1 1 1 1 1 1 0 9e-1",
            [b"Car", b"Van"],
            0.9,
        ),
    ],
)
def test_the_twin_reads_as_fscanf_does(data: bytes, names: list[bytes], last_score: float) -> None:
    """The twin itself, on cases worked by hand from the C standard and glibc."""
    records = read_records(data, "detections")
    assert [name for name, _ in records] == names
    assert records[-1][1][-1] == last_score
