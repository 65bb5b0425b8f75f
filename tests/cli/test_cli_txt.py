"""The command line on KITTI txt folders the official devkit reads otherwise than their authors meant: each
used to be evaluated (exit 0, other numbers than the devkit's); it is refused, exit 1, naming the file,
the line and the reason. The case: two ground-truth Cars, two exact detections and one far false positive."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from kitti_eval.cli import main

GT = [
    "Car 0.00 0 0.00 100.00 100.00 200.00 200.00 1.50 1.60 3.90 0.00 1.50 20.00 0.00",
    "Car 0.00 0 0.00 300.00 100.00 400.00 200.00 1.50 1.60 3.90 5.00 1.50 20.00 0.00",
]
PRED = [
    "Car -1 -1 0.00 100.00 100.00 200.00 200.00 1.50 1.60 3.90 0.00 1.50 20.00 0.00 0.90",
    "Car -1 -1 0.00 300.00 100.00 400.00 200.00 1.50 1.60 3.90 5.00 1.50 20.00 0.00 0.80",
    "Car -1 -1 0.00 800.00 100.00 900.00 200.00 1.50 1.60 3.90 30.00 1.50 60.00 0.00 0.95",
]


def _field(line: str, k: int, value: str) -> str:
    parts = line.split(" ")
    parts[k] = value
    return " ".join(parts)


def _write(tmp_path: Path, gt: list[str], pred: list[str], gt_bom: bool = False, pred_bom: bool = False) -> None:
    for name, lines, bom in (("label_2", gt, gt_bom), ("pred", pred, pred_bom)):
        (tmp_path / name).mkdir()
        text = ("\ufeff" if bom else "") + "".join(line + "\n" for line in lines)
        (tmp_path / name / "000000.txt").write_bytes(text.encode())


def _run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["--gt", str(tmp_path / "label_2"), "--pred", str(tmp_path / "pred"), "--format", "json"])
    out, err = capsys.readouterr()
    return code, out, err


def test_the_case_itself_is_evaluated(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write(tmp_path, GT, PRED)
    code, out, _ = _run(tmp_path, capsys)
    assert code == 0
    ap = json.loads(out)["ap"]["strict"]["R40"]["Car"]
    # two score thresholds (recall 1/2, 1), precision 2/3 at both once interpolated; R40 takes sample 1 of 40
    assert ap["bbox"]["easy"] == pytest.approx(100 * (2 / 3) / 40, abs=1e-9)
    assert ap["3d"]["hard"] == pytest.approx(100 * (2 / 3) / 40, abs=1e-9)


ROWS: dict[str, tuple[Callable[[Path], None], str, str]] = {
    "occluded 0.0 in a label": (
        lambda t: _write(t, [_field(GT[0], 2, "0.0"), GT[1]], PRED),
        "label_2/000000.txt",
        "line 1: occluded is not an integer: '0.0'; the official devkit reads occluded as an integer: it would "
        "read 0, then take '.0' as alpha and shift every later field",
    ),
    "a byte order mark in a label": (
        lambda t: _write(t, GT, PRED, gt_bom=True),
        "label_2/000000.txt",
        "line 1: the file starts with a UTF-8 byte order mark; the devkit reads it as part of the first class "
        "name and ignores that line",
    ),
    "a byte order mark in a result": (
        lambda t: _write(t, GT, PRED, pred_bom=True),
        "pred/000000.txt",
        "line 1: the file starts with a UTF-8 byte order mark",
    ),
    "digits that are not ASCII": (
        lambda t: _write(t, GT, [*PRED[:2], _field(PRED[2], 15, "٠.٩٥")]),
        "pred/000000.txt",
        "line 3: score is not a number: '٠.٩٥'; it has non-ASCII characters",
    ),
    "5_00.00": (
        lambda t: _write(t, GT, [*PRED[:2], _field(PRED[2], 4, "8_00.00")]),
        "pred/000000.txt",
        "line 3: x1 is not a number: '8_00.00'; the devkit would read 8, then take '_00.00' as the next field",
    ),
    "U+00A0 between fields": (
        lambda t: _write(t, GT, [*PRED[:2], PRED[2].replace(" ", "\u00a0", 1)]),
        "pred/000000.txt",
        "line 3: expected 16 fields (type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry score), got 15; "
        "U+00A0 is not a field separator for the devkit",
    ),
    "a NUL in a class name": (
        lambda t: _write(t, GT, [*PRED[:2], PRED[2].replace("Car", "Car\x00x", 1)]),
        "pred/000000.txt",
        "line 3: the class name 'Car\\x00x' holds a NUL byte; the devkit's name ends there ('Car')",
    ),
    "a 2D box taller than 2**31 px": (
        lambda t: _write(t, GT, [*PRED[:2], _field(PRED[2], 7, "3000000000.00")]),
        "pred/000000.txt",
        "line 3: the 2D box's height |y2 - y1| = 3e+09 px does not fit in 32 bits",
    ),
}


@pytest.mark.parametrize("row", list(ROWS))
def test_a_file_the_devkit_reads_otherwise_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], row: str
) -> None:
    write, path, reason = ROWS[row]
    write(tmp_path)
    code, out, err = _run(tmp_path, capsys)
    assert code == 1 and out == ""
    assert f"{tmp_path / path}, frame 000000" in err
    assert reason in err
    assert "Traceback" not in err
