"""The service reads an uploaded KITTI txt archive as the official devkit reads it, or answers 422 naming the
file, the frame, the line and the field (the rules: kitti_eval/io/formats/txt_grammar.py)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from server_helpers import assert_error, golden_bytes, golden_txt, register, upload, zip_of


@pytest.fixture(scope="module")
def client(service_client: Any) -> Iterator[Any]:
    with service_client() as c:
        assert register(c, "small", golden_bytes("kitti_infos_val.pkl"), "kitti_infos_val.pkl").status_code == 201
        yield c


def _with(archive: str, member: str, change: Any) -> bytes:
    files = golden_txt(archive)
    files[member] = change(files[member])
    return zip_of(files)


def test_a_result_file_with_a_byte_order_mark_is_422(client: Any) -> None:
    data = _with("pred.tar.gz", "pred/000001.txt", lambda b: b"\xef\xbb\xbf" + b)
    err = assert_error(upload(client, data, "pred.zip", gt="small"), 422, "pred.zip:pred/000001.txt", "byte order mark")
    assert err["frame"] == "000001" and err["field"] == "type"
    assert upload(client, golden_bytes("pred.tar.gz"), "pred.tar.gz", gt="small").status_code == 201


def test_ground_truth_with_occluded_written_as_a_float_is_422(client: Any) -> None:
    def occluded_as_float(b: bytes) -> bytes:
        first, rest = b.split(b"\n", 1)
        parts = first.split(b" ")
        parts[2] += b".0"
        return b" ".join(parts) + b"\n" + rest

    data = _with("label_2.tar.gz", "label_2/000002.txt", occluded_as_float)
    err = assert_error(
        register(client, "floats", data, "label_2.zip"),
        422,
        "line 1: occluded is not an integer",
        "the official devkit reads occluded as an integer",
    )
    assert err["frame"] == "000002" and err["field"] == "occluded"
    assert register(client, "ints", golden_bytes("label_2.tar.gz"), "label_2.tar.gz").status_code == 201
